"""fit() and smooth(): the structured Newton (Levenberg–Marquardt) maximisation of the ELBO.

Decision vector, objective and the reduced Newton system: :class:`vsidgen.estimator.problem.Problem`
(shared s = [z (free θ, unconstrained), noise parameters] and, per record, the state means μ
(N×n) and assumed-density parameters r = (d, strict-lower L, C)). Each iteration
(:func:`_optimize`)

1. measures the iterate (:func:`_lm_measure`): value, gradient and Hessian blocks of −ELBO per
   record (exact sigma-point assembly, one jit per record shape), relative gradient and Newton
   decrement;
2. stops (:func:`_lm_terminate`) on the Newton decrement with a positive-definite Hessian or the
   relative gradient (see :class:`FitOptions` ``decrement_tol``, ``gtol``): converged; or on a
   limit;
3. otherwise (:func:`_lm_step`) solves (H + λ D) Δ = −∇ with D = Marquardt diagonal scaling: μ is
   eliminated record by record with an O(N) block-tridiagonal Cholesky, the border (all r and s)
   through its Schur complement; accepts the step when the actual / predicted reduction ratio
   ρ > ACCEPT_RATIO and updates λ (Nielsen's rule); a failed Cholesky (indefinite H + λD) or a
   rejected step increases λ. No progress (step below ``xtol``, λ overflow, predicted reduction
   below rounding) stops, not converged, with a status saying so.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import time
from collections.abc import Mapping, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from scipy.stats import chi2

from ..errors import FitError, VsidgenError
from .core import diff_scale
from .problem import Gradient, Problem
from .results import (FitOptions, FitPhase, FitResult, PhaseKind, SmootherPath, StdErrorFlag, StdErrorIssue,
                      StopReason, announce)

from .. import precision  # noqa: F401  (float64, set once)


def _relgrad(P: Problem, f, s, recs, gs, gmus, grs):
    """max_i |∂f/∂v_i| · max(|v_i|, 1) / max(|f|, 1), with v and f in coherent units
    (:meth:`CoherentScale.reference`, :attr:`Problem.elbo_shift`: the same number for a model
    in degrees as in radians)."""
    cs = P.coherent
    scale = max(abs(f - P.elbo_shift), 1.0)        # |ELBO| in coherent units
    vals = [np.abs(gs) * cs.reference(s, cs.shared, cs.shared_shift)]
    for (m, r), gm, gr in zip(recs, gmus, grs):
        vals.append((np.abs(gm) * cs.reference(m, cs.state, 0.0)).ravel())
        vals.append(np.abs(gr) * cs.reference(r, cs.r, cs.r_shift))
    return float(max((v.max() if v.size else 0.0) for v in vals)) / scale


def _stalled(P: "Problem", history, ws, window: int, rtol: float, remaining: int) -> bool:
    """Is this start creeping without a prospect of converging within the iteration budget?

    True when (i) the ELBO rose by less than ``rtol · max(|ELBO|, 1)`` over the last ``window``
    iterations and (ii) no noise parameter is on its way to an active floor within the
    ``remaining`` iterations. (ii) keeps a start whose last step to convergence is a
    std sliding onto its floor (σ = floor + e^w, the floor counts as active once
    e^w ≤ 0.01·floor): with w falling by δ per iteration (its mean over the window) the
    floor is reached after (w − log(0.01·floor))/δ iterations. A std creeping towards a
    floor of 0, or towards a floor too far away for its rate, does not count.
    """
    if window <= 0 or len(history) <= window or len(ws) <= window:
        return False
    e1, e0 = history[-1]["elbo"], history[-1 - window]["elbo"]
    if e1 - e0 >= rtol * max(abs(e1 + P.elbo_shift), 1.0):      # |ELBO| in coherent units
        return False
    nm = P.nm
    floors = [(a, nm.proc_floor[i]) for a, i in enumerate(nm.proc_est_idx)]
    floors += [(nm.n_proc + a, nm.meas_floor[j]) for a, j in enumerate(nm.meas_est_idx)]
    w1, w0 = ws[-1], ws[-1 - window]
    for k, fl in floors:
        rate = (w0[k] - w1[k]) / window
        if fl > 0 and rate > 0 and (w1[k] - math.log(0.01 * fl)) / rate <= remaining:
            return False
    return True


#: Levenberg–Marquardt constants (Nielsen's damping rule; :func:`_optimize`)
#: a step is accepted when the actual reduction of −ELBO is more than this share of the predicted one
ACCEPT_RATIO = 1e-4
#: smallest damping after an accepted step: the Marquardt scaling stays in the system
LAMBDA_MIN = 1e-12
#: damping beyond which no acceptable step is left (the step is a vanishing gradient step)
LAMBDA_MAX = 1e16
#: floor of the Marquardt diagonal, relative to its largest entry (a zero diagonal of H still damps)
DIAG_FLOOR = 1e-10
#: a predicted reduction below this share of max(|f|, 1) is rounding: no progress possible
PRED_RTOL = 1e-15


@dataclasses.dataclass(frozen=True)
class _Measured:
    """What the optimizer knows at one iterate: blocks, −ELBO ``f``, the gradient split by parts
    (``grad``), the gathered border Hessian ``Hg``, the active floors, the relative gradient and
    half the Newton decrement (NaN: H not positive definite on the free subspace)."""

    blks: list
    f: float
    grad: Gradient
    Hg: np.ndarray
    active: np.ndarray
    relgrad: float
    decrement: float
    n_held: int = 0


@dataclasses.dataclass(frozen=True)
class _Stop:
    """Why the iterations end (``converged``: at an optimum)."""

    reason: StopReason
    status: str
    converged: bool = False


def _lm_init(P: Problem, options: FitOptions, start: str, resume):
    """(s, recs, λ, history, first iteration) from the noise start ``start`` or a previous output."""
    if resume is None:
        s, recs = P.initial(options, start)
        f0 = P.value(s, recs)
        if not math.isfinite(f0):
            s, recs, f0 = _narrower_start(P, s, recs)
        if not math.isfinite(f0):
            raise FitError("the negative ELBO is not finite at the initial point"
                           + _nonfinite_where(P, s, recs))
        return s, recs, float(options.lambda0), [], 0
    # the last point of a resumed history is evaluated again
    return resume["s"], resume["recs"], resume["lam"], list(resume["history"])[:-1], resume["iterations"]


#: factors by which :func:`_narrower_start` shrinks the assumed density's initial variances
NARROWER_START = (1e-2, 1e-4, 1e-6, 1e-8)


def _narrower_start(P: Problem, s, recs):
    """The initial point with the assumed density's variances shrunk until −ELBO is finite.

    The density starts at Σ = I in coherent units, so its sigma points lie ±√(2n) state
    units from the means — ±2 rad for an angle. A model finite near the data but not that
    far from it (``sqrt(alpha + 1)``, ``log(alpha)``, ``asin`` of a ratio) made every start
    fail with a message about large initial values (red team, session 47). Σ × 10⁻², 10⁻⁴, …
    brings the sigma points to the means, where the model is finite; the estimator then
    widens Σ as the evidence asks. Returns the first finite point, or the input unchanged."""
    nx = P.model.nx
    f = math.nan
    for k in NARROWER_START:
        trial = []
        for mu, r in recs:
            r = np.array(r, float)
            r[:nx] += math.log(k)
            trial.append((mu, r))
        f = P.value(s, trial)
        if math.isfinite(f):
            return s, trial, f
    return s, recs, f


def _nonfinite_where(P: Problem, s, recs) -> str:
    """Where the model is not finite at the initial point: the first equation (drift or
    output) and sample of each record at the initial θ and state means, for the message."""
    m = P.model
    theta = jnp.asarray(P.tm.theta(jnp.asarray(s[:P.tm.n_free])))
    parts = []
    for rec, (mu, _) in zip(P.records, recs):
        u = jnp.asarray(np.asarray(rec.u, float))
        x = jnp.asarray(mu)
        for what, fn, names in (("drift", m.drift, m.state_names),
                                ("output", m.output, m.output_names)):
            try:
                v = np.asarray(jax.vmap(lambda a, b: fn(a, b, theta))(x, u))
            except Exception:  # noqa: BLE001 - only for the message
                continue
            bad = np.argwhere(~np.isfinite(v))
            if len(bad):
                k, j = (int(i) for i in bad[0])
                parts.append(f"{what} of `{names[j]}` at sample {k} of "
                             f"{getattr(rec, 'name', 'the record')}")
                break
        if parts:
            break
    th = np.asarray(theta, float)
    vals = ", ".join(f"{n} = {float(v):.6g}" for n, v in zip(m.parameter_names, th))
    if parts:
        return (f": {parts[0]} is not finite (initial parameter values {vals[:300]}; the "
                "states start at their direct measurements, else solved from the outputs, else 0)\n  hint: check divisions, "
                "log, sqrt and exp in that equation at these values, and --fix/--init values")
    big = [f"{n} = {float(v):.3g}" for n, v in zip(m.parameter_names, th) if abs(v) > 1e10]
    if big:
        return (": the drift and outputs are finite there, but their squared residuals overflow"
                f" ({', '.join(big)})\n  hint: check for very large initial values, --fix or "
                "--init values")
    return (": the drift and outputs are finite at the initial state means, but not at the "
            "sigma points of the assumed state density around them, even with its variances "
            f"shrunk to {NARROWER_START[-1]:g} of their start\n  hint: an equation leaves its "
            "domain right next to the data (sqrt or log of a quantity that is zero there, asin "
            "of a ratio at ±1, a division by a state that crosses zero); write it so that it is "
            "defined a little beyond the data, or check --fix/--init values")


def _lm_measure(P: Problem, s, recs) -> _Measured:
    """Blocks, gradient, relative gradient and Newton decrement at (s, recs)."""
    blks = P.blocks(s, recs)
    f = P.total(blks)
    gg, Hg = P.gather(blks)
    grad = P.gradient(blks, gg)
    gs, gmus, grs = grad.shared, list(grad.records_mu), list(grad.records_r)
    active = P.floor_active(s, gs)
    rg = _relgrad(P, f, s, recs, np.where(active, 0.0, gs), gmus, grs)
    dec = newton_decrement(P, blks, gs, gmus, grs, active)
    return _Measured(blks=blks, f=f, grad=grad, Hg=Hg, active=active, relgrad=rg, decrement=dec,
                     n_held=int(P.held.sum()))


def _lm_detail(m: _Measured) -> str:
    if not math.isfinite(m.decrement):
        return f"Hessian not positive definite, relative gradient {m.relgrad:.3g}"
    return f"Newton decrement λ²/2 = {m.decrement:.3g} nats, relative gradient {m.relgrad:.3g}"


def _lm_terminate(m: _Measured, options: FitOptions, it: int, elapsed: float) -> _Stop | None:
    """Stop at the measured iterate? Convergence (Newton decrement with a positive-definite Hessian,
    or the relative gradient), a non-finite gradient, the iteration or the time limit."""
    rg, dec = m.relgrad, m.decrement
    pd = math.isfinite(dec)
    detail = _lm_detail(m)
    if not np.isfinite(rg):
        return _Stop(StopReason.NONFINITE, "stopped: gradient is not finite")
    stop = None
    if pd and dec < options.decrement_tol:
        stop = _Stop(StopReason.NEWTON_DECREMENT,
                     f"converged: Newton decrement λ²/2 = {dec:.3g} nats < {options.decrement_tol:g} "
                     f"(positive-definite Hessian; relative gradient {rg:.3g})", True)
    elif rg < options.gtol:
        stop = _Stop(StopReason.GRADIENT, f"converged: relative gradient {rg:.3g} < gtol {options.gtol:g}", True)
    if stop is not None:
        n_floor = int(m.active.sum()) - m.n_held
        if n_floor > 0:
            stop = dataclasses.replace(stop, status=stop.status + (
                f" (projected: {n_floor} noise parameter(s) at their floor "
                "treated as active bounds)"))
        if m.n_held:
            stop = dataclasses.replace(stop, status=stop.status + (
                f" ({m.n_held} parameter(s) held at their start)"))
        return stop
    if it == options.max_iter:
        return _Stop(StopReason.ITERATION_LIMIT, f"stopped: iteration limit {options.max_iter} reached ({detail})")
    if options.time_limit is not None and elapsed > options.time_limit:
        return _Stop(StopReason.TIME_LIMIT, f"stopped: time limit {options.time_limit:g} s reached ({detail})")
    return None


def _marquardt_diagonal(P: Problem, m: _Measured):
    """Marquardt scaling: |diag H| per state mean and over the border, floored at DIAG_FLOOR of its largest entry.

    The floor is taken in coherent units (:attr:`Problem.coherent`: a variable v = c·v' in
    them has the curvature H'/c²), so the damping, like the undamped Newton step, does not
    depend on whether the model is written in degrees or radians."""
    cs = P.coherent
    cm2 = cs.state ** 2
    cb2 = cs.border(P.nrec) ** 2
    dmus = [np.abs(np.diagonal(np.asarray(b["D"]), axis1=1, axis2=2)) for b in m.blks]
    dglob = np.abs(np.diag(m.Hg))
    # the largest entry over the records' own samples (a padded sample's block is the identity
    # in declared units, which is not the same curvature in every unit system)
    big = max([1.0] + [float((d[:n] / cm2).max()) for d, n in zip(dmus, P.lengths) if n]
              + ([float((dglob / cb2).max())] if dglob.size else []))
    floor = DIAG_FLOOR * big
    return [np.maximum(d, floor * cm2) for d in dmus], np.maximum(dglob, floor * cb2)


#: relative size (to the largest entry) below which a gradient component or a Hessian entry
#: counts as exactly zero (:func:`_saddle_step`: parameters no equation depends on)
ZERO_RTOL = 1e-14
#: an eigenvalue below −SADDLE_RTOL · (largest |eigenvalue|) is negative curvature
SADDLE_RTOL = 1e-8


def _saddle_step(P: Problem, s, recs, m: _Measured):
    """Leave a saddle along negative curvature of −ELBO in parameters nothing else depends on.

    A set Z of free parameters that no equation depends on at the iterate (two factors of a
    product both at 0; ``wn`` and ``zeta`` of ``wn**2*(u - x) - 2*zeta*wn*v`` both at 0) has a
    zero gradient and Hessian rows that vanish outside Z (no coupling to the state means, the
    assumed density, the noise or the other parameters): no damped Newton step
    (H + λD)Δ = −g moves it. When the block H_ZZ has a negative eigenvalue e, −ELBO falls along
    its eigenvector v (either sign); the step α v with the lowest −ELBO over
    α = α₀·4⁻ᵏ, k = 0…11, α₀ = √(2 max(|f|, 1)/|e|), is taken when it lowers −ELBO. Only such
    exactly decoupled sets qualify (a parameter of an unmeasured state that starts at zero has
    a zero gradient but couples to the state means: the ordinary step handles it). Returns the
    new (s, recs), or None. Held parameters are not moved.
    """
    nt = P.tm.n_free
    gs = np.asarray(m.grad.shared, float)
    if nt == 0 or not gs.size:
        return None
    scale = max(float(np.max(np.abs(gs))), 1e-300)
    zero = np.array([j for j in range(nt)
                     if abs(gs[j]) <= ZERO_RTOL * scale and not P.held[j]], int)
    if not zero.size:
        return None
    nq = P.layout.nq
    off = P.nrec * nq
    kz = off + zero
    Hzz = m.Hg[np.ix_(kz, kz)]
    hmax = max(float(np.max(np.abs(m.Hg))), 1e-300)
    if not np.any(np.abs(Hzz) > ZERO_RTOL * hmax):
        return None     # no curvature among them (an unused parameter, a break point whose
        #                 slope is still 0): nothing to leave along
    others = np.setdiff1d(np.arange(P.nglob), kz)
    if np.any(np.abs(m.Hg[np.ix_(kz, others)]) > ZERO_RTOL * hmax):
        return None
    for b in m.blks:
        W = np.asarray(b["W"])
        if np.any(np.abs(W[..., nq + zero]) > ZERO_RTOL * hmax):
            return None
    # the eigenproblem in coherent units (H → C⁻¹HC⁻¹, v → C⁻¹v: the same direction and
    # step for a parameter in deg/s² as in rad/s²)
    cz = P.coherent.shared[zero]
    w, V = np.linalg.eigh(0.5 * (Hzz + Hzz.T) / np.outer(cz, cz))
    if not w[0] < -SADDLE_RTOL * max(float(np.max(np.abs(w))), 1e-300):
        return None
    v0 = V[:, 0] / cz

    def point(a):
        s_new = np.array(s, float)
        s_new[zero] += a * v0
        return s_new, recs

    best = _along_negative_curvature(P, m, point, float(w[0]), early=False)
    return None if best is None else best[1]


def _along_negative_curvature(P: Problem, m: _Measured, point, e: float, *, early: bool):
    """(f, (s, recs)) of the lowest −ELBO below ``m.f`` at ``point(α)``, α = α₀·4⁻ᵏ, k = 0…11,
    α₀ = √(2 max(|f|, 1)/|e|) (where the quadratic model along a direction of curvature e < 0
    predicts a fall of max(|f|, 1)); ``early``: stop once a shorter step is no better. None
    when no step lowers −ELBO."""
    a0 = math.sqrt(2.0 * max(abs(m.f - P.elbo_shift), 1.0) / abs(e))
    best = None
    for k in range(12):
        x = point(a0 * 4.0 ** -k)
        f_new = P.value(*x)
        if not math.isfinite(f_new):
            continue
        if early and best is not None and f_new >= best[0]:
            break
        if f_new < m.f and (best is None or f_new < best[0]):
            best = (f_new, x)
    return best


def _dot(gs, gmus, grs, ds, dmu, dr) -> float:
    """gᵀΔ over the whole decision: shared part, and state means and densities of every record."""
    return float(gs @ ds + sum(float(np.sum(g * d)) for g, d in zip(gmus, dmu))
                 + sum(float(g @ d) for g, d in zip(grs, dr)))


def _curvature_step(P: Problem, s, recs, m: _Measured):
    """Leave a saddle along the most negative curvature of −ELBO, the state means included.

    With the state means μ eliminated (A_i = H_μ_iμ_i positive definite, the usual case: for
    fixed θ and density the ELBO is close to concave in μ), the inertia of the Hessian is that
    of A plus the inertia of the Schur complement S = H_bb − Σ W_iᵀA_i⁻¹W_i over the border b
    (all r and s; Haynsworth). So H is indefinite exactly when S is, and for an eigenvector v
    of the Marquardt-scaled pencil S v = e D v with e < 0 (D = :func:`_marquardt_diagonal`:
    the direction does not depend on the parameters' units) the full direction

        d = (Δb = v,  Δμ_i = −A_i⁻¹ W_i v)

    has curvature dᵀ H d = vᵀ S v = e vᵀ D v < 0: −ELBO falls along ±d to second order
    whatever the gradient. The sign with gᵀd ≤ 0 is taken and the step α d with the lowest
    −ELBO over α = α₀·4⁻ᵏ (α₀ = √(2 max(|f|, 1)/|e|), the length at which the quadratic model
    predicts a fall of max(|f|, 1); k = 0…11, stopping once a shorter step is no better) is
    returned. :func:`_optimize` takes it where the relative-gradient test would end the
    iterations at an indefinite Hessian: a stationary point that is not a maximum of the ELBO.

    This is the general case of :func:`_saddle_step` (there the zero-gradient set couples to
    nothing; here it may couple to the state means, e.g. an added unmeasured state whose
    couplings into and out of the model all start at zero: a symmetric saddle (the state's
    sign flipped with the couplings') whose gradient vanishes, so that damped Newton steps
    only crawl away from it). Held parameters and noise parameters at an active floor are not
    moved. Returns (s, recs, fall of −ELBO) or None (A not positive definite, S positive
    semi-definite, or no decrease).
    """
    found = _curvature_direction(P, m)
    if found is None:
        return None
    e, ds, dmu, dr = found
    g = m.grad
    sign = -1.0 if _dot(g.shared, g.records_mu, g.records_r, ds, dmu, dr) > 0 else 1.0

    def point(a):
        a *= sign
        return (np.asarray(s, float) + a * ds,
                [(mu + a * d1, r + a * d2) for (mu, r), d1, d2 in zip(recs, dmu, dr)])

    best = _along_negative_curvature(P, m, point, e, early=True)
    return None if best is None else (*best[1], m.f - best[0])


def _curvature_direction(P: Problem, m: _Measured):
    """(e, Δs, [Δμ_i], [Δr_i]) of :func:`_curvature_step`: the direction d of the most negative
    eigenvalue e of S v = e D v (vᵀ D v = 1), or None (some A_i not positive definite, or S
    positive semi-definite on the free border).

    The state means are eliminated with A_i + λD_i (:meth:`Problem.damped_reduced_system`,
    λ = ``SCORE_DAMPING`` relative to |diag A_i|, as for score statistics): A_i is singular where an unmeasured state couples to nothing
    (its initial value is free). With Δμ = −(A + λD)⁻¹ W v the curvature is
    dᵀ H d = vᵀ S_λ v − λ Δμᵀ D Δμ ≤ e: still negative, equal to e where A is regular."""
    if not P.nglob:
        return None
    red = P.damped_reduced_system(m.blks)
    if red is None:
        return None
    nq = P.layout.nq
    off = P.nrec * nq
    keep = np.ones(P.nglob, bool)
    keep[off + np.nonzero(m.active)[0]] = False
    if not keep.any():
        return None
    _, dglob = _marquardt_diagonal(P, m)
    isd = 1.0 / np.sqrt(dglob[keep])
    St = red.S[np.ix_(keep, keep)] * isd[:, None] * isd[None, :]
    w, V = np.linalg.eigh(0.5 * (St + St.T))
    if not w[0] < -SADDLE_RTOL * max(float(np.max(np.abs(w))), 1e-300):
        return None
    v = np.zeros(P.nglob)
    v[keep] = isd * V[:, 0]
    _, mu0, _ = P.back_substitute(red, np.zeros(P.nglob))   # −A⁻¹ g_μ
    ds, mu1, dr = P.back_substitute(red, v)                  # −A⁻¹ (g_μ + W v)
    dmu = [b - a for a, b in zip(mu0, mu1)]
    return float(w[0]), ds, dmu, dr


def _lm_step(P: Problem, options: FitOptions, s, recs, m: _Measured, lam: float):
    """One accepted Levenberg–Marquardt step from the measured iterate.

    Solves (H + λD) Δ = −g (:meth:`Problem.newton_step`, active floors held), predicts the
    reduction pred = −½ gᵀΔ + ½ λ ΔᵀDΔ of the local quadratic model and accepts the step when
    ρ = (f − f(x + Δ)) / pred > ACCEPT_RATIO; then λ ← λ max(1/3, 1 − (2ρ − 1)³) (Nielsen), at
    least LAMBDA_MIN. A failed factorisation or a rejected step multiplies λ by ν (ν doubling
    each time). Returns (s, recs, λ, stop): stop is None after an accepted step, else why no step
    is possible (predicted reduction at rounding level or relative step below ``xtol``: no
    progress; λ beyond LAMBDA_MAX: damping overflow).
    """
    nq = P.layout.nq
    gs, gmus, grs = m.grad.shared, list(m.grad.records_mu), list(m.grad.records_r)
    pd = math.isfinite(m.decrement)
    f = m.f
    dmus, dglob = _marquardt_diagonal(P, m)
    nu = 2.0
    while True:
        sol = P.newton_step(m.blks, lam, dmus, dglob, frozen=m.active)
        if sol is None:
            lam *= nu
            nu *= 2.0
        else:
            ds, dmu, dr, _ = sol
            gdot = _dot(gs, gmus, grs, ds, dmu, dr)
            dDd = float(dglob[P.nrec * nq:] @ ds ** 2 + sum(float(np.sum(dm[:len(d)] * d ** 2)) for dm, d in zip(dmus, dmu))
                        + sum(float(dglob[i * nq:(i + 1) * nq] @ d ** 2) for i, d in enumerate(dr)))
            pred = -0.5 * gdot + 0.5 * lam * dDd
            s_new = s + ds
            recs_new = [(mu + d1, r + d2) for (mu, r), d1, d2 in zip(recs, dmu, dr)]
            cs = P.coherent       # the relative step in coherent units, as the gradient test
            step = max([float(np.max(np.abs(ds) / cs.reference(s, cs.shared, cs.shared_shift))) if ds.size else 0.0]
                       + [float(np.max(np.abs(d1) / cs.reference(mu, cs.state, 0.0))) for (mu, _), d1 in zip(recs, dmu)]
                       + [float(np.max(np.abs(d2) / cs.reference(r, cs.r, cs.r_shift))) for (_, r), d2 in zip(recs, dr)])
            if pred <= PRED_RTOL * max(abs(f), 1.0) or step < options.xtol:
                return s, recs, lam, _Stop(
                    StopReason.NO_PROGRESS if pd else StopReason.INDEFINITE_HESSIAN,
                    f"stopped: no further progress possible (relative step {step:.2g}, predicted "
                    f"reduction {pred:.2g}; {_lm_detail(m)})")
            f_new = P.value(s_new, recs_new)
            rho = (f - f_new) / pred
            if math.isfinite(f_new) and rho > ACCEPT_RATIO:
                lam *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
                return s_new, recs_new, max(lam, LAMBDA_MIN), None
            lam *= nu
            nu *= 2.0
        if lam > LAMBDA_MAX:
            return s, recs, lam, _Stop(StopReason.DAMPING_OVERFLOW if pd else StopReason.INDEFINITE_HESSIAN,
                                       f"stopped: damping overflow, no acceptable step ({_lm_detail(m)})")


class _Cancelled(Exception):
    """A start of a concurrent multi-start stopped because another start failed or the run
    was interrupted (:func:`_multistart`); never leaves this module."""


def _optimize(P: Problem, options: FitOptions, start: str = "data", t0=None, *, resume=None,
              stall=False, phase: FitPhase | None = None, cancel=None):
    """Levenberg–Marquardt iterations from the noise start ``start`` (or ``resume``: a previous output).

    Each iteration measures the iterate (:func:`_lm_measure`), asks whether to stop
    (:func:`_lm_terminate`; with ``stall`` also when the ELBO rose by less than
    ``options.stall_rtol`` (relative) over ``options.stall_window`` iterations without meeting the
    convergence criteria, reason :attr:`StopReason.STALLED`, resumable; used while other noise
    starts remain to be tried) and otherwise takes one damped step (:func:`_lm_step`).
    ``phase`` (what these iterations are part of) is announced to the progress callback
    (:func:`~vsidgen.estimator.results.announce`) and its label kept in each history entry.
    ``stall`` may also be a callable, asked when the stall test fires whether this start may be
    abandoned (the last start of a concurrent multi-start: only when an earlier one converged).
    ``cancel`` (a ``threading.Event``): when set, the iterations end with :class:`_Cancelled`.
    """
    t0 = time.perf_counter() if t0 is None else t0
    s, recs, lam, history, it0 = _lm_init(P, options, start, resume)
    label = None if phase is None else str(phase)
    if phase is not None and options.progress is not None:
        announce(options.progress, phase)
    ws = []  # noise parameters per iteration (stall test)
    it, stop, m = it0, None, None
    for it in range(it0, options.max_iter + 1):
        if cancel is not None and cancel.is_set():
            raise _Cancelled(start)
        m = _lm_measure(P, s, recs)
        elapsed = time.perf_counter() - t0
        history.append({"iteration": it, "elbo": -m.f, "grad_norm": m.relgrad, "lambda": lam, "elapsed_s": elapsed,
                        "decrement": m.decrement, **({"phase": label} if label else {})})
        if options.progress is not None:
            options.progress(it, -m.f, m.relgrad, elapsed)
        if options.verbose:
            print(f"iter {it:4d}  elbo {-m.f: .10e}  relgrad {m.relgrad:.3e}  decrement/2 {m.decrement:.3e}  "
                  f"lambda {lam:.2e}  {elapsed:7.2f} s")
        stop = _lm_terminate(m, options, it, elapsed)
        if not math.isfinite(m.decrement) and (stop is None or stop.converged):
            # a saddle: parameters with a zero gradient along which −ELBO curves down
            moved = _saddle_step(P, s, recs, m)
            if moved is not None:
                s, recs = moved
                history[-1]["saddle_step"] = True
                continue
            if stop is not None and options.negative_curvature:
                # "converged" by the relative gradient at an indefinite Hessian: a saddle
                # whose directions of descent couple to the state means
                moved = _curvature_step(P, s, recs, m)
                if moved is not None:
                    s, recs = moved[0], moved[1]
                    history[-1]["curvature_step"] = True
                    continue
        if stop is not None:
            break
        ws.append(np.asarray(s[P.tm.n_free:], float).copy())
        if stall and _stalled(P, history, ws, options.stall_window, options.stall_rtol, options.max_iter - it) \
                and (not callable(stall) or stall()):
            stop = _Stop(StopReason.STALLED, f"stalled: ELBO rose by less than {options.stall_rtol:g} (relative) "
                                             f"over {options.stall_window} iterations ({_lm_detail(m)})")
            break
        s, recs, lam, stop = _lm_step(P, options, s, recs, m, lam)
        if stop is not None:
            break
    return dict(s=s, recs=recs, blks=None if m is None else m.blks, converged=stop is not None and stop.converged,
                status="" if stop is None else stop.status, iterations=it, history=tuple(history),
                reason=None if stop is None else stop.reason, t0=t0, lam=lam,
                decrement=float("nan") if m is None else m.decrement)


def newton_decrement(P: "Problem", blks, gs, gmus, grs, active) -> float:
    """Half the Newton decrement, λ²/2 = ½ gᵀH⁻¹g (nats), on the free subspace; NaN if H is not PD there.

    H and g are the exact Hessian and gradient of −ELBO over every decision variable (θ,
    noise, assumed-density parameters, state means); variables of active noise floors are
    held fixed (projected out). λ²/2 is the ELBO gain of a full Newton step on the local
    quadratic model, invariant to any affine change of variables (parameter units).
    """
    zero_mu = [np.zeros((np.asarray(b["D"]).shape[0], P.model.nx)) for b in blks]
    sol = P.newton_step(blks, 0.0, zero_mu, np.zeros(P.nglob), frozen=active)
    if sol is None:
        return float("nan")
    ds, dmu, dr, _ = sol
    lam2 = -_dot(gs, gmus, grs, ds, dmu, dr)
    if not math.isfinite(lam2) or lam2 < -1e-8 * max(1.0, abs(float(np.sum(gs ** 2)))):
        return float("nan")
    return 0.5 * max(lam2, 0.0)


AUTO_STARTS = ("release", "data", "data-meas", "unit")
NOISE_STARTS = ("release", "data", "data-meas", "unit")


def _negelbo(out) -> float:
    return float(sum(float(b["f"]) for b in out["blks"]))


#: a bounded θ whose transform derivative dθ/dz has fallen below this share of its scale
#: (the bound range, or the one-sided scale) sits at its bound: the bounding transform
#: saturates there, so the gradient in z vanishes whichever way the ELBO slopes in θ
SATURATION = 1e-8
#: where a saturated θ is probed: this share of its scale inside the bound
RELEASE_SHARE = 0.01
#: releases per start (each followed by more iterations)
MAX_RELEASES = 3


def saturated(P: Problem, s, share: float = SATURATION) -> np.ndarray:
    """Mask over the free θ of parameters at a bound: |dθ/dz| (the bounding transform's
    derivative, :meth:`ThetaMap.dtheta_dz`) below ``share`` of its scale (the interval for
    two-sided bounds, the one-sided scale, 1 unbounded)."""
    tm = P.tm
    scale = np.where(tm.kind == 3, tm.hi - tm.lo, np.where(tm.kind == 0, 1.0, tm.sc))
    with np.errstate(over="ignore", under="ignore"):
        d = np.abs(tm.dtheta_dz(np.asarray(s, float)[:tm.n_free]))
    return d < share * scale


def _release_saturated(P: Problem, s, recs) -> np.ndarray | None:
    """A start off the bounds for the saturated θ, or None when every bound holds.

    At a saturated bound the optimizer's gradient in z vanishes, so "converged" there says
    nothing about the slope in θ (a parameter started at one bound of a two-sided interval
    overshot to the other and stopped at ELBO 6669, below the interior optimum). Each saturated
    θ is moved :data:`RELEASE_SHARE` of its scale inside its bound, one at a time, and kept
    there when that raises the ELBO: the bound is then not active (the ELBO rises into the
    interior), and the iterations continue from there. Bounds where the ELBO falls
    inwards are active constraints and stay."""
    nt = P.tm.n_free
    # every θ closer to its bound than the probe point is probed: there the gradient in z is
    # the θ-gradient times a small dθ/dz, so a "converged" stop says nothing about the
    # slope in θ (ATTAS yaw model of a new user: N_r stopped at its bound −5 with
    # dθ/dz ≈ 1e-7 of the interval and an indefinite Hessian). Held parameters
    # (FitOptions.held_parameters: a staged refit's base parameters, a candidate's lag held
    # at its nesting bound) stay where they are.
    near = saturated(P, s, RELEASE_SHARE * (1.0 - RELEASE_SHARE))
    sat = np.nonzero(near & ~np.asarray(P.held[:nt], bool))[0]
    if not len(sat):
        return None
    f0 = P.value(s, recs)
    s_new, moved = np.array(s, float), False
    inner = math.log(RELEASE_SHARE / (1.0 - RELEASE_SHARE))
    for i in sat:
        trial = s_new.copy()
        if P.tm.kind[i] == 3:
            trial[i] = inner if trial[i] < 0 else -inner
        else:
            trial[i] = math.log(RELEASE_SHARE)
        f1 = P.value(trial, recs)
        if math.isfinite(f1) and f1 < f0:
            s_new, f0, moved = trial, f1, True
    return s_new if moved else None


def _starts(options: FitOptions):
    if options.warm_start is not None:
        return ["data"]
    st = options.noise_start
    if st == "auto":
        return list(AUTO_STARTS)
    if st not in NOISE_STARTS:
        raise FitError(f"noise_start must be 'auto', 'release', 'data', 'data-meas' or 'unit', got '{st}'")
    return [st]


def _optimize_trust_constr(P: Problem, options: FitOptions, start: str = "data"):
    """Reference path (the paper's code): scipy.optimize.minimize(method="trust-constr").

    Same problem and decision vector as the structured optimizer, flattened to
    v = [μ of every record, r of every record, s]; JAX value-and-gradient and
    Hessian–vector products (forward-over-reverse), each jitted once per problem
    shape. Stops when the same (projected) relative-gradient criterion as the
    structured optimizer is met (checked in the callback), or on scipy's own
    termination; the iteration limit is ``50 * max_iter`` trust-region (truncated
    CG) iterations.
    """
    import scipy.optimize

    t0 = time.perf_counter()
    s0, recs0 = P.initial(options, start)
    if options.progress is not None:
        announce(options.progress, FitPhase(PhaseKind.NOISE_START, start=start))
    lay = P.layout
    total = P.flat_value
    vg = jax.jit(jax.value_and_grad(total))
    hvp = jax.jit(lambda v, w, cfg, data: jax.jvp(lambda x: jax.grad(total)(x, cfg, data), (v,), (w,))[1])
    v0 = lay.pack(s0, recs0)
    cfg, data = P.cfg, P.data  # unpadded records
    history = []
    state = {"it": 0, "converged": False, "rg": float("nan")}

    def split(v):
        return lay.unpack(np.asarray(v))

    def fun(v):
        f, g = vg(jnp.asarray(v), cfg, data)
        return float(f), np.asarray(g, float)

    def hessp(v, w):
        return np.asarray(hvp(jnp.asarray(v, float), jnp.asarray(w, float), cfg, data), float)

    def relgrad(v, f, g):
        ss, recs = split(v)
        gs, grecs = lay.unpack(np.asarray(g))
        gmus, grs = [gm for gm, _ in grecs], [gr for _, gr in grecs]
        active = P.floor_active(ss, gs)
        return _relgrad(P, f, ss, recs, np.where(active, 0.0, gs), gmus, grs)

    def callback(intermediate_result):
        res = intermediate_result
        state["it"] = int(res.nit)
        f = float(res.fun)
        rg = relgrad(res.x, f, res.grad)
        state["rg"] = rg
        elapsed = time.perf_counter() - t0
        history.append({"iteration": state["it"], "elbo": -f, "grad_norm": rg, "lambda": float("nan"),
                        "elapsed_s": elapsed})
        if options.progress is not None:
            options.progress(state["it"], -f, rg, elapsed)
        if options.verbose:
            print(f"iter {state['it']:6d}  elbo {-f: .10e}  relgrad {rg:.3e}  {elapsed:7.2f} s")
        if rg < options.gtol:
            state["converged"] = True
            raise StopIteration
        if options.time_limit is not None and elapsed > options.time_limit:
            state["timed_out"] = True
            raise StopIteration

    f0, _ = fun(v0)
    if not math.isfinite(f0):
        raise FitError("the negative ELBO is not finite at the initial point "
                       "(check initial parameter values and the measured-state initialisation)")
    res = scipy.optimize.minimize(fun, v0, jac=True, hessp=hessp, method="trust-constr", callback=callback,
                                  options={"maxiter": 50 * max(options.max_iter, 1), "gtol": 1e-300,
                                           "xtol": 1e-14, "verbose": 0})
    s, recs = split(res.x)
    blks = P.blocks(s, recs)
    if state["converged"]:
        status = f"converged: relative gradient {state['rg']:.3g} < gtol {options.gtol:g} (trust-constr)"
        reason = StopReason.GRADIENT
    elif state.get("timed_out"):
        status = f"stopped: time limit {options.time_limit:g} s reached (trust-constr, relative gradient {state['rg']:.3g})"
        reason = StopReason.TIME_LIMIT
    elif int(res.nit) >= 50 * max(options.max_iter, 1):
        status = f"stopped: trust-constr iteration limit {res.nit} reached (relative gradient {state['rg']:.3g})"
        reason = StopReason.ITERATION_LIMIT
    else:
        status = f"stopped: trust-constr: {res.message} (relative gradient {state['rg']:.3g})"
        reason = StopReason.NO_PROGRESS
    return dict(s=s, recs=recs, blks=blks, converged=state["converged"], status=status,
                iterations=int(res.nit), history=tuple(history), reason=reason, t0=t0,
                decrement=float("nan"))


def _uncertainty(P: Problem, blks, s):
    """cov(θ_free) = J [H⁻¹]_zz J (J = dθ/dz), via the undamped Schur complement.

    θ at a saturated bound (:func:`saturated`) are held, as an active constraint: their
    rows and columns are left out (their s.e. NaN, flagged ``AT_BOUND``), so the others
    keep theirs — the transform's vanishing derivative would otherwise make the whole
    Hessian singular and every s.e. undefined."""
    nt = P.tm.n_free
    info = {"pd": True, "cond": float("nan")}
    if nt == 0:
        return np.zeros((0, 0)), info
    red = P.reduced_system(blks, dglob=np.zeros(P.nglob))
    if red is None:
        info["pd"] = False
        return np.full((nt, nt), np.nan), info
    sat = saturated(P, s)
    tidx = np.asarray(P.theta_idx)
    keep_t = np.nonzero(~sat)[0]          # free θ (positions in z) that are not at a bound
    keep = np.setdiff1d(np.arange(red.S.shape[0]), tidx[sat])
    S = red.S[np.ix_(keep, keep)]
    tidx = np.searchsorted(keep, tidx[keep_t])
    full = np.full((nt, nt), np.nan)
    d = np.diag(S)
    if np.any(d <= 0):
        info["pd"] = False
        info["weak"] = [int(keep_t[i]) for i in np.nonzero(d[tidx] <= 0)[0]]
        return full, info
    Ss = S / np.sqrt(np.outer(d, d))
    ev, V = np.linalg.eigh(Ss)
    v = np.abs(V[tidx, 0])  # θ components of the least-determined direction
    info["weak"] = ([int(keep_t[i]) for i in np.nonzero(v >= 0.3 * v.max())[0]]
                    if v.size and v.max() > 0.1 else [])
    try:
        np.linalg.cholesky(Ss)
    except np.linalg.LinAlgError:
        ev = np.minimum(ev, 0.0)
    if ev[0] <= 0:
        info["pd"] = False
        return full, info
    info["cond"] = float(ev[-1] / ev[0])
    # the inverse from the eigendecomposition above: positive eigenvalues, so it exists even
    # where an LU factorisation of a numerically near-singular Ss gives up (seen with numpy 2.4
    # on a model whose two parameters enter only as their sum: LinAlgError "Singular matrix")
    Sinv = (V / ev[None, :]) @ V.T / np.sqrt(np.outer(d, d))
    cz = Sinv[np.ix_(tidx, tidx)]
    J = P.tm.dtheta_dz(s[:nt])[keep_t]
    cov = cz * np.outer(J, J)
    full[np.ix_(keep_t, keep_t)] = 0.5 * (cov + cov.T)
    return full, info


#: Stated limits of the near-singular-information test (docs/estimator.md): a pair of
#: parameters correlated beyond this, or
CORRELATION_LIMIT = 0.999
#: a smallest eigenvalue of the parameters' correlation matrix below this (the standard
#: error of some combination is 1/√λ ≥ 1000 times what it would be were the others known).
EIGENVALUE_LIMIT = 1e-6
#: a smoothed state this many measurement stds (RMS) from its direct measurement is reported
FAR_FROM_MEASUREMENT = 5.0
#: z value of the two-sided 95 % interval (the bound test).
Z95 = 1.959963984540054


def std_error_flags(names, theta, se, corr, *, kind, lo, hi, positive_definite: bool, weak=(),
                    stop_reason=None, limit=None) -> tuple[StdErrorFlag, ...]:
    """Every reason the standard errors of a fit need attention, each only when its cause is present.

    * ``NOT_CONVERGED``: the stop reason is not an optimum.
    * ``DETERMINISTIC_LIMIT``: ``limit`` (the continuation record of the states without
      process noise) says the limit of vanishing noise was not reached.
    * ``HESSIAN_NOT_PD``: the Schur complement of the Hessian of −ELBO onto the free θ is
      not positive definite; ``weak`` names the θ components of its least-determined direction.
    * ``NEAR_SINGULAR``: with R = corr(θ̂) (unit free), some |R_ij| > ``CORRELATION_LIMIT``
      (the pair is named) or λ_min(R) < ``EIGENVALUE_LIMIT`` (the parameters with
      |v_i| ≥ 0.3 max|v| in its eigenvector v are named). Since λ_min(R) ≤ 1 − |R_ij|, a
      pair beyond 0.999 is one such direction; strongly correlated parameters that are
      not this close (HFB-320: max |R_ij| 0.974, λ_min 4e-5) have large but valid s.e.
    * ``AT_BOUND``: |θ̂_i − bound| < 1.96 s.e._i for a free bounded θ_i: the symmetric 95 %
      interval crosses the bound (the s.e. comes from dθ/dz of the bounding transform and
      shrinks towards zero at the bound).

    Args: names, theta, se, corr: free parameters' names, estimates, s.e., correlation;
    kind/lo/hi: the :class:`~vsidgen.estimator.core.ThetaMap` bound kinds (0 none, 1 lower,
    2 upper, 3 both) and bounds of the free parameters.
    """
    flags = []
    if stop_reason is not None and not stop_reason.converged:
        flags.append(StdErrorFlag(StdErrorIssue.NOT_CONVERGED, (), f"stop reason {stop_reason.value}"))
    if limit is not None and not limit.get("reached", True):
        flags.append(StdErrorFlag(StdErrorIssue.DETERMINISTIC_LIMIT, (),
                                  f"states {', '.join(limit.get('states', ()))}"))
    if not len(names):
        return tuple(flags)
    n = len(names)
    near = []
    for i in range(n):
        bounds = ([lo[i]] if kind[i] in (1, 3) else []) + ([hi[i]] if kind[i] in (2, 3) else [])
        for b in bounds:
            gap = abs(float(theta[i]) - float(b))
            if not np.isfinite(se[i]) or gap < Z95 * se[i] or gap <= 1e-9 * max(abs(float(b)), 1.0):
                near.append(f"{names[i]} = {float(theta[i]):.6g}, bound {float(b):.6g}, s.e. {float(se[i]):.3g}")
                break
    at_bound = ()
    if near:
        at_bound = (StdErrorFlag(StdErrorIssue.AT_BOUND, tuple(x.split(" = ")[0] for x in near),
                                 "; ".join(near)),)
    if not positive_definite:
        flags.append(StdErrorFlag(StdErrorIssue.HESSIAN_NOT_PD, tuple(weak)))
        return tuple(flags) + at_bound
    R = np.asarray(corr, float)
    ok = np.all(np.isfinite(R), axis=0)     # parameters held at a bound have no s.e.
    names = [nm for nm, k in zip(names, ok) if k]
    R = R[np.ix_(ok, ok)]
    n = len(names)
    if n > 1 and np.all(np.isfinite(R)):
        A = np.abs(R - np.diag(np.diag(R)))
        pairs = [(i, j) for i in range(n) for j in range(i + 1, n) if A[i, j] > CORRELATION_LIMIT]
        ev, V = np.linalg.eigh(0.5 * (R + R.T))
        if pairs:
            involved = tuple(dict.fromkeys(names[k] for ij in pairs for k in ij))
            detail = "; ".join(f"corr({names[i]}, {names[j]}) = {R[i, j]:+.4f}" for i, j in pairs)
            flags.append(StdErrorFlag(StdErrorIssue.NEAR_SINGULAR, involved,
                                      f"{detail} (limit {CORRELATION_LIMIT})"))
        elif ev[0] < EIGENVALUE_LIMIT:
            v = np.abs(V[:, 0])
            involved = tuple(names[i] for i in np.nonzero(v >= 0.3 * v.max())[0])
            flags.append(StdErrorFlag(StdErrorIssue.NEAR_SINGULAR, involved,
                                      f"smallest eigenvalue of the correlation matrix {ev[0]:.2g} "
                                      f"(limit {EIGENVALUE_LIMIT:g})"))
    return tuple(flags) + at_bound


def _limit_message(lim: dict) -> str:
    """Why the limit of vanishing process noise was not reached, in numbers that exist."""
    states = ", ".join(lim["states"])
    std = ", ".join(f"{n} {v:.3g}" for n, v in (lim.get("std") or {}).items())
    if not math.isfinite(lim["elbo_change"]):
        tried = max(len(lim.get("stages") or ()) - 1, 0)
        what = (f"no continuation stage after the first converged ({tried} tried with smaller "
                "std)" if tried else "the first stage did not converge")
        return (f"the limit of vanishing process noise on {states} was not reached: {what}; the "
                f"estimates are those of a small process noise on them (std {std}). A state "
                "without process noise needs an equation the data determine from the other "
                "states (a kinematic one, e.g. phi' = p): try more iterations (--max-iter), or "
                "give it process noise (noise.process.states)")
    return (f"the limit of vanishing process noise on {states} was not reached: the last stage "
            f"(std {lim['scale']:.2g} × the first stage's) changed the ELBO by "
            f"{lim['elbo_change']:.3g} nats and the parameters by {lim['theta_change_se']:.3g} s.e.; "
            f"the estimates are those of that small process noise (std {std}; a nonlinear "
            "kinematic equation of a state without process noise, or a model that needs process "
            "noise on it)")


def _finish(P: Problem, out, *, mode: str, options: FitOptions) -> FitResult:
    model = P.model
    s, recs, blks = out["s"], out["recs"], out["blks"]
    nt = P.tm.n_free
    sj = jnp.asarray(s)
    theta = np.asarray(P.tm.theta(sj[:nt]), float)
    w = s[nt:]
    G = P.nm.G_report(w)
    sig = np.asarray(P.nm.sigma(jnp.asarray(w)), float)
    Q1 = G @ G.T
    process_std = {n: float(math.sqrt(Q1[i, i])) for i, n in enumerate(model.state_names) if P.nm.noisy[i]}
    measurement_std = dict(zip(model.output_names, map(float, sig)))
    measurement_floor = dict(zip(model.output_names, map(float, P.nm.meas_floor)))
    f = float(sum(float(b["f"]) for b in blks))
    warnings = []
    npar = model.np
    std_errors = np.full(npar, np.nan)
    corr = np.zeros((nt, nt))
    cov = np.zeros((nt, nt))
    info = {"pd": True}
    if mode == "fit" and nt:
        cov, info = _uncertainty(P, blks, s)
        se = np.sqrt(np.abs(np.diag(cov)))
        std_errors[P.tm.free_idx] = se
        with np.errstate(all="ignore"):
            corr = cov / np.outer(se, se)
    flags = ()
    if mode == "fit":
        free_names = [model.parameter_names[i] for i in P.tm.free_idx]
        flags = std_error_flags(
            free_names, theta[P.tm.free_idx], std_errors[P.tm.free_idx], corr,
            kind=P.tm.kind, lo=P.tm.lo, hi=P.tm.hi, positive_definite=bool(info["pd"]),
            weak=[free_names[i] for i in info.get("weak", [])], stop_reason=out["reason"],
            limit=out.get("limit"))
    for fl in flags:
        # the stop reason and the deterministic limit have their own warnings below
        if fl.issue not in (StdErrorIssue.NOT_CONVERGED, StdErrorIssue.DETERMINISTIC_LIMIT):
            warnings.append({"code": fl.issue.value, "reliable": False, "parameters": list(fl.parameters),
                             "message": f"standard errors: {fl.message}"})
    if out.get("released"):
        rel = ", ".join(out["released"])
        warnings.append({"code": "left_bound", "reliable": True, "parameters": list(out["released"]),
                         "message": f"{rel} stopped at a bound where the ELBO still rose into the "
                                    f"interior (the bounding transform had saturated); the fit "
                                    f"continued from inside the bound"})
    # floors
    for j, o in enumerate(model.output_names):
        fl = P.nm.meas_floor[j]
        if P.nm.meas_est[j] and fl > 0 and sig[j] <= 1.01 * fl:
            warnings.append({"code": "noise_at_floor", "reliable": True, "channel": o, "kind": "measurement",
                             "std": float(sig[j]), "floor": float(fl),
                             "message": f"measurement noise std of '{o}' ({sig[j]:.3g}) is at its floor "
                                        f"({fl:.3g}): the data resolution limits the noise estimate"})
    Gd = np.diag(np.asarray(P.nm.G(jnp.asarray(w))))
    for i in P.nm.proc_est_idx:
        fl = P.nm.proc_floor[i]
        if fl > 0 and Gd[i] <= 1.01 * fl:
            nm = model.state_names[i]
            warnings.append({"code": "noise_at_floor", "reliable": True, "channel": nm, "kind": "process",
                             "std": float(Gd[i]), "floor": float(fl),
                             "message": f"process noise std of '{nm}' ({Gd[i]:.3g}) is at its floor ({fl:.3g})"})
    lim = out.get("limit")
    pinned = [model.state_names[i] for i in np.nonzero(P.nm.pinned)[0]]
    if (mode == "fit" and lim is not None and pinned and not lim["collapsed_directions"]
            and lim["stages"] and lim["stages"][0]["converged"]):
        # likelihood-ratio test of the degenerate constraint: the relaxed first stage is the
        # full factor with G_ii free, the limit the same family at G_ii = 0 (a boundary, so
        # χ²ₖ is conservative)
        lam = 2.0 * (lim["stages"][0]["elbo"] + f)
        thr = float(chi2.isf(0.01, len(pinned)))
        if lam > thr:
            warnings.append({"code": "degenerate_noise_rejected", "reliable": True, "states": pinned,
                             "statistic": lam, "threshold": thr,
                             "message": f"the data contradict `degenerate: [{', '.join(pinned)}]`: the "
                                        f"full factor with independent process noise on "
                                        f"{', '.join(pinned)} fits better by 2ΔELBO = {lam:.4g} > "
                                        f"{thr:.4g} (χ²({len(pinned)}), α = 0.01); remove "
                                        f"them from noise.process.degenerate"})
    if lim is not None and not lim["reached"]:
        warnings.append({"code": "deterministic_limit_not_reached", "reliable": False,
                         "states": list(lim["states"]), "elbo_change": lim["elbo_change"],
                         "theta_change_se": lim["theta_change_se"],
                         "message": _limit_message(lim)})
    reason = out["reason"]
    if reason is not None and not reason.converged:
        code = {StopReason.ITERATION_LIMIT: "iteration_limit", StopReason.TIME_LIMIT: "iteration_limit",
                StopReason.NONFINITE: "nonfinite"}.get(reason, "stopped_on_step_size")
        warnings.append({"code": code, "reliable": False, "stop_reason": reason.value,
                         "message": f"{reason.message}: {out['status']}"})
    # smoothers and state-vs-measurement check
    pairs = P.direct
    smoothers = []
    for rec, (m, r) in zip(P.records, recs):
        Sc, C, Sm, _ = P.obj.cov_factors(jnp.asarray(r))
        Sc, C, Sm = (np.asarray(a) for a in (Sc, C, Sm))
        smoothers.append(SmootherPath(name=str(getattr(rec, "name", "")), mu=np.asarray(m).copy(),
                                      cov_marg=Sm @ Sm.T, cov_cond=Sc @ Sc.T, cross=C))
        y = np.asarray(rec.y, float)
        for i, dm in pairs.items():
            j = dm.output
            res = dm.offset + dm.gain * m[:, i] - y[:, j]
            res = res[np.isfinite(res)]
            if res.size and sig[j] > 0:
                ratio = float(np.sqrt(np.mean(res ** 2)) / sig[j])
                if ratio > FAR_FROM_MEASUREMENT:
                    warnings.append({"code": "state_far_from_measurement", "reliable": True,
                                     "record": str(getattr(rec, "name", "")), "state": model.state_names[i],
                                     "output": model.output_names[j], "ratio": ratio,
                                     "message": f"record '{getattr(rec, 'name', '')}': smoothed state "
                                                f"'{model.state_names[i]}' is {ratio:.1f} measurement std (RMS) "
                                                f"from its direct measurement '{model.output_names[j]}'"})
    reliable = mode == "fit" and not flags
    return FitResult(
        parameter_names=model.parameter_names, theta=theta, std_errors=std_errors, correlation=corr,
        free_mask=P.tm.free_mask.copy(), process_std=process_std, measurement_std=measurement_std,
        measurement_floor=measurement_floor, G=G, R=np.diag(sig ** 2), elbo=-f, converged=out["converged"],
        G_objective=np.array(P.nm.G(jnp.asarray(w)), float),
        status=out["status"], iterations=out["iterations"], wall_time_s=time.perf_counter() - out["t0"],
        smoothers=tuple(smoothers), warnings=tuple(warnings), std_errors_reliable=bool(reliable),
        history=out["history"],
        decision={"s": np.asarray(s).copy(), "records": [{"mu": np.asarray(m).copy(), "r": np.asarray(r).copy()}
                                                          for m, r in recs]},
        covariance=cov, optimizer=options.optimizer, stop_reason=reason,
        newton_decrement=float(out.get("decrement", float("nan"))),
        deterministic_states=tuple(n for n, z in zip(model.state_names, P.nm.noisy) if not z),
        std_error_flags=tuple(flags),
        deterministic_limit=out.get("limit"))


# --------------------------------------------------------------------------- public API
def fit(model, records, *, options: FitOptions = FitOptions()) -> FitResult:
    """Maximise the ELBO over θ (free parameters), noise parameters and one assumed density per record.

    Args:
        model: a :class:`vsidgen.model.Model`.
        records: one record or a sequence (fields t, dt, u (N, nu), y (N, ny; NaN = missing)).
        options: :class:`FitOptions`.

    Returns:
        :class:`FitResult`; ``converged`` False (with ``status``) when the optimiser stopped
        without meeting the gradient criterion. Raises FitError on unusable input.
    """
    P = Problem(model, records, options)
    starts = _starts(options)
    if options.deterministic not in ("limit", "quasi"):
        raise FitError(f"deterministic must be 'limit' or 'quasi', got '{options.deterministic}'")
    limit = (options.deterministic == "limit" and options.optimizer == "structured-newton"
             and bool(P.nm.deterministic.any()))
    if limit:
        t0 = time.perf_counter()
        hold = None
        if options.warm_start is not None:
            out0, P0 = None, None
            eps = _warm_limit_scale(P, options.warm_start)
            hold = _warm_limit_hold(P, options.warm_start)
        else:
            P0 = Problem(model, records, options, relax=True)
            out0 = _multistart(P0, options, starts)
            eps = _first_stage_std(P, P0, out0)
        out = _deterministic_limit(P, P0, out0, eps, options, t0, hold=hold)
        return _finish(P, out, mode="fit", options=options)
    if options.optimizer == "structured-newton":
        out = _multistart(P, options, starts)
    elif options.optimizer == "trust-constr":
        if P.held.any():
            raise FitError("held_parameters need the structured optimizer")
        out = _optimize_trust_constr(P, options, next((st for st in starts if st != "release"), "data"))
    else:
        raise FitError(f"unknown optimizer '{options.optimizer}' (use 'structured-newton' or 'trust-constr')")
    return _finish(P, out, mode="fit", options=options)


def _multistart(P: Problem, options: FitOptions, starts) -> dict:
    """Run every noise start (stalled ones abandoned early) and return the best converged output."""
    t0 = time.perf_counter()
    tried = []
    if "release" in starts:
        starts = [st for st in starts if st != "release"]
        out = _release_start(P, options, t0)
        if out is not None:
            tried.append(("release", out))
        elif not starts:
            starts = ["data"]  # nothing to release: the release start is the data start
    # every start is run: a converged start is a local optimum, and another start may reach
    # a higher one (multi-start, the best converged ELBO is kept). A start that stalls is
    # abandoned early while another start remains or an earlier one has converged.
    if options.parallel_starts and len(starts) > 1:
        tried += _concurrent_starts(P, options, starts, t0, have_optimum=any(o["converged"] for _, o in tried))
    else:
        for i, start in enumerate(starts):
            have_optimum = any(o["converged"] for _, o in tried)
            tried.append((start, _run_start(P, options, start, t0, stall=i < len(starts) - 1 or have_optimum)))
    k = _start_to_continue(tried)
    if k is not None:
        start, o = tried[k]
        # a start stopped at its iteration limit gets another max_iter iterations
        opts = (options if o["iterations"] < options.max_iter
                else dataclasses.replace(options, max_iter=o["iterations"] + options.max_iter))
        tried[k] = (start, _optimize(P, opts, start, t0=t0, resume=o,
                                     phase=FitPhase(PhaseKind.NOISE_START, start=start, continued=True)))
    # the highest ELBO, converged or not (a converged start wins a tie): a point above every
    # converged optimum (continued, still not converged) is reported as not converged rather
    # than a lower optimum as the fit
    out = min((o for _, o in tried), key=lambda o: (_negelbo(o), not o["converged"]))
    label = {StopReason.STALLED: "stalled"}
    out["starts"] = [(st, bool(o["converged"]), -_negelbo(o), o["iterations"]) for st, o in tried]
    if len(tried) > 1:
        out["status"] += "; noise starts tried: " + ", ".join(
            f"{st} ({'converged' if o['converged'] else label.get(o['reason'], 'not converged')}, ELBO {-_negelbo(o):.6g}, {o['iterations']} it.)"
            for st, o in tried)
    out["history"] = tuple(h for _, o in tried for h in o["history"])
    out["iterations"] = sum(o["iterations"] for _, o in tried)
    return out


def _start_to_continue(tried) -> int | None:
    """Which noise start of a multi-start to continue after every start has run, or None.

    The highest start that stopped without an optimum (stalled, or at its iteration limit)
    when its ELBO is above every converged start's (any ELBO when none converged): the ELBO
    is maximised, so a point above a converged local optimum shows that optimum is not the
    best one reachable, and keeping it would report a lower fit as converged. (A new user's
    nonlinear Twin Otter model: two starts at their 200-iteration limit with ELBO 8051.9 and
    8976.4, the one converged start at 4255.2; continued, the highest converges to 11492.8.)"""
    best_conv = max((-_negelbo(o) for _, o in tried if o["converged"]), default=-math.inf)
    open_ = [k for k, (_, o) in enumerate(tried)
             if o["reason"] in (StopReason.STALLED, StopReason.ITERATION_LIMIT)
             and -_negelbo(o) > best_conv]
    return min(open_, key=lambda k: _negelbo(tried[k][1])) if open_ else None


def _diagonal_first(P: Problem, options: FitOptions) -> Problem | None:
    """The problem ``P`` with the off-diagonal entries of a full process-noise factor G held
    at their start (0 unless the spec gives them), or None when there are none to hold (a
    diagonal or fixed G, or a warm start, which keeps its own point).

    A full G nests the diagonal one at zero off-diagonals, so the diagonal optimum is a point
    of the full problem whose ELBO the full optimum can only exceed. Started from the null
    guesses with the off-diagonals free, a new user's Twin Otter lateral model with
    ``structure: full`` (the noise model diagnose advises) stopped at a degenerate optimum
    (an output's noise at its floor, two biases correlated −0.9997) 2750 nats below the same
    physics with diagonal noise; from the diagonal optimum it cannot end below it. The held
    problem shares ``P``'s compiled objective (the held set is a runtime mask)."""
    if options.warm_start is not None or not P.nm.offdiag:
        return None
    _ = P.obj     # built once here, shared by the copy
    nt, ne = P.tm.n_free, len(P.nm.proc_est_idx)
    held = P.held.copy()
    held[nt + ne:nt + P.nm.n_proc] = True
    Pd = copy.copy(P)
    Pd.held = held
    return Pd


def _run_start(P: Problem, options: FitOptions, start: str, t0, *, stall, cancel=None) -> dict:
    """One noise start of :func:`_multistart`: the iterations, then up to ``MAX_RELEASES``
    releases of saturated parameters (each followed by more iterations). With a full
    process-noise factor, the start first converges with its off-diagonal entries held
    (:func:`_diagonal_first`), then goes on with them free from there."""
    phase = FitPhase(PhaseKind.NOISE_START, start=start)
    resume = None
    Pd = _diagonal_first(P, options)
    if Pd is not None:
        resume = _optimize(Pd, options, start, t0=t0, stall=stall, phase=phase, cancel=cancel)
        if resume["reason"] in (StopReason.STALLED, StopReason.TIME_LIMIT, StopReason.NONFINITE):
            return resume
    out = _optimize(P, options, start, t0=t0, stall=stall, phase=phase, cancel=cancel,
                    resume=resume)
    released: list[str] = []
    for _ in range(MAX_RELEASES):
        # released after any stop at a point (an optimum, or no progress: a saturated
        # transform also makes the Hessian singular), not after a limit
        if (out["reason"] in (StopReason.ITERATION_LIMIT, StopReason.TIME_LIMIT,
                              StopReason.NONFINITE, None)
                or out["iterations"] >= options.max_iter):
            break
        s_rel = _release_saturated(P, out["s"], out["recs"])
        if s_rel is None:
            break
        released += [P.free_names[j] for j in np.nonzero(s_rel != out["s"])[0]]
        out = _optimize(P, options, start, t0=t0, stall=stall,
                        resume={**out, "s": s_rel}, phase=phase, cancel=cancel)
        out["released"] = tuple(dict.fromkeys(released))
    return out


class _LeadProgress:
    """The progress callback of a concurrent multi-start: each start reports through its own
    view, and only the first unfinished start (the *lead*) reaches the user's callback, so
    the live line shows one start at a time, in the serial order. When the lead finishes,
    the next start's current phase is announced. The lead's view also opens ``gate`` after
    its first step (every function of an iteration is then compiled once, for all starts)."""

    def __init__(self, progress, n: int, gate):
        import threading

        self.progress, self.n, self.gate = progress, n, gate
        self.lock = threading.Lock()
        self.done: set[int] = set()
        self.phases: dict[int, FitPhase] = {}
        self.last: dict[int, tuple] = {}    # each start's latest iteration report
        self.first_it: int | None = None    # start 0's first iteration

    def lead(self) -> int:
        return next((i for i in range(self.n) if i not in self.done), self.n)

    def finished(self, i: int) -> None:
        """Start ``i`` ended. When it was the lead, the starts after it that ended while they
        waited are shown now, in order (their phase and their last iteration: a start that
        finished before it became the lead would otherwise never reach the user, and its
        summary line was missing from piped output), then the new lead's phase."""
        with self.lock:
            was_lead = self.lead() == i
            self.done.add(i)
            replay = []
            if was_lead:
                j = i + 1
                while j < self.n and j in self.done:
                    replay.append((self.phases.get(j), self.last.get(j)))
                    j += 1
                replay.append((self.phases.get(j), None) if j < self.n else (None, None))
        if i == 0:
            self.gate.set()
        if self.progress is None:
            return
        for ph, last in replay:
            if ph is not None:
                announce(self.progress, ph)
            if last is not None:
                self.progress(*last)

    def view(self, i: int):
        owner = self

        class _View:
            def __call__(self, it, elbo, grad, elapsed):
                owner.last[i] = (it, elbo, grad, elapsed)
                if i == 0:
                    if owner.first_it is None:
                        owner.first_it = it
                    elif it > owner.first_it:
                        owner.gate.set()
                if owner.progress is not None and owner.lead() == i:
                    owner.progress(it, elbo, grad, elapsed)

            def phase(self, ph):
                with owner.lock:
                    owner.phases[i] = ph
                    lead = owner.lead() == i
                if lead and owner.progress is not None:
                    announce(owner.progress, ph)
        return _View()


def _concurrent_starts(P: Problem, options: FitOptions, starts, t0, *, have_optimum: bool) -> list:
    """The noise starts of :func:`_multistart`, one thread each; [(start, output)] in start order.

    The first start runs alone until it has taken one step (its trace and compilation serve
    every start), then the others join. Stall rules as in the serial loop: every start but
    the last may be abandoned as stalled; the last only when an earlier start converged
    (``have_optimum``, or one of the earlier starts, which it then waits for), so the outputs
    are those of the serial run. An exception in one start (or an interrupt of the caller)
    cancels the others at their next iteration and is raised once they have stopped."""
    import concurrent.futures as cf
    import threading

    n = len(starts)
    cancel, gate = threading.Event(), threading.Event()
    lead = _LeadProgress(options.progress, n, gate)
    futures: list = [None] * n

    def earlier_converged() -> bool:
        if have_optimum:
            return True
        cf.wait(futures[:-1])
        return any(not f.cancelled() and f.exception() is None and f.result()["converged"]
                   for f in futures[:-1])

    # the main thread waits on a semaphore, not on ``concurrent.futures.wait``: a Ctrl-C
    # raised while ``wait`` was acquiring the futures' locks one by one left some of them
    # held, and the workers then blocked for ever setting their results (an interrupted fit
    # that never exited, red team, session 48)
    finished = threading.Semaphore(0)
    errors: list = []

    def task(i: int, start: str) -> dict:
        try:
            if i > 0:
                gate.wait()
            if cancel.is_set():
                raise _Cancelled(start)
            opts = dataclasses.replace(options, progress=lead.view(i))
            stall = True if i < n - 1 else earlier_converged
            return _run_start(P, opts, start, t0, stall=stall, cancel=cancel)
        except BaseException as err:
            errors.append(err)
            raise
        finally:
            lead.finished(i)
            finished.release()

    ex = cf.ThreadPoolExecutor(max_workers=n, thread_name_prefix="vsidgen-start")
    pending = 0
    try:
        for i, st in enumerate(starts):
            futures[i] = ex.submit(task, i, st)
            pending += 1
        while pending and not errors:
            finished.acquire()
            pending -= 1
        if errors:
            raise next((e for e in errors if not isinstance(e, _Cancelled)), errors[0])
        return [(st, f.result()) for st, f in zip(starts, futures)]
    except BaseException:
        cancel.set()
        gate.set()
        while pending:
            finished.acquire()
            pending -= 1
        raise
    finally:
        ex.shutdown(wait=True)


# --------------------------------------------------------------------------- deterministic states
LIMIT_RATIO = 0.1       # process-noise std of the deterministic states: factor per continuation stage
LIMIT_MAX_STAGES = 8    # stages after the first (std down to 1e-8 of the first stage's)


def _first_stage_std(P: Problem, P0: Problem, out0) -> np.ndarray:
    """Diagonal std of P's deterministic states (their order) at the end of the first stage ``P0``:
    the std it estimated for a relaxed state, the std it held for a pinned (degenerate) one."""
    nt = P0.tm.n_free
    G = np.abs(np.diagonal(np.asarray(P0.nm.G(jnp.asarray(out0["s"][nt:])))))
    return G[np.nonzero(P.nm.deterministic)[0]]


def _warm_limit_scale(P: Problem, ws) -> np.ndarray:
    """First-stage std of a warm-started limit: the std at which a previous limit fit ended (its decision
    belongs to it), else the data scale of :func:`_smoothing_start_std`."""
    lim = getattr(ws, "deterministic_limit", None)
    if lim is not None and len(lim.get("std", {})) == int(P.nm.deterministic.sum()):
        return np.asarray(list(lim["std"].values()), float)
    return _smoothing_start_std(P)


def _warm_limit_hold(P: Problem, ws) -> np.ndarray | None:
    """Per deterministic state of ``P`` (their order), the std at which a warm-started limit holds
    it instead of taking it to zero (0: taken to the limit), from the warm start's
    ``deterministic_limit["hold"]`` ``{state: std}``; None when it names none.

    For a limit taken in some of the deterministic states only: the diagnose refits take the
    states a candidate adds to their limit while the model's own states without process noise
    stay at the quasi-deterministic std that the refits' common reference has
    (:func:`vsidgen.discrepancy.search.limit_correction`)."""
    lim = getattr(ws, "deterministic_limit", None)
    held = (lim or {}).get("hold") if isinstance(lim, Mapping) else None
    if not held:
        return None
    names = [P.model.state_names[i] for i in np.nonzero(P.nm.deterministic)[0]]
    unknown = set(held) - set(names)
    if unknown:
        raise FitError(f"deterministic_limit hold: {sorted(unknown)} are not deterministic states "
                       f"of {P.model.name} ({', '.join(names) or 'none'})")
    out = np.asarray([float(held.get(n, 0.0)) for n in names], float)
    if not np.all(np.isfinite(out) & (out >= 0.0)):
        raise FitError("deterministic_limit hold: the held stds must be finite and non-negative")
    return out


def _smoothing_start_std(P: Problem) -> np.ndarray:
    """First-stage std of deterministic states when smoothing: the data start of a noisy state.

    A state measured directly by output j gets the robust spread of output j's
    sample-to-sample differences / √T (the random-walk rate the record allows); an
    unmeasured one 1 coherent unit/√s (1 rad/√s for an angle in deg).
    """
    pairs = P.direct
    T = float(np.mean([float(r.dt) for r in P.records]))
    out = []
    for i in np.nonzero(P.nm.deterministic)[0]:
        v = diff_scale(P.records, pairs[i].output) / abs(pairs[i].gain) / math.sqrt(T) if i in pairs else 0.0
        out.append(v if v > 0 else 1.0 / float(P.coherent.state[i]))
    return np.asarray(out, float)


def _scale_cond_rows(obj, r, rho, cross, diag_only=None) -> np.ndarray:
    """Assumed-density parameters r with the rows of S_c (Σ_cond = S_c S_cᵀ) scaled by ``rho`` (per state).

    ``cross`` (per state): scale that state's row of the cross factor C too, so that its
    marginal spread shrinks with its conditional one (a deterministic state whose spread
    collapses with the process noise). ``diag_only`` (per state): scale only the diagonal
    entry of that row — the spread of the state *given the states before it* (S_c is lower
    triangular in state order), which is what vanishes with the diagonal of a degenerate
    (pinned) state's noise factor while its share of the earlier states' noise remains.
    """
    Sc, C, _, _ = obj.cov_factors(jnp.asarray(r))
    rho = np.asarray(rho, float)
    Sc = np.asarray(Sc).copy()
    dmask = np.zeros(len(rho), bool) if diag_only is None else np.asarray(diag_only, bool)
    Sc[~dmask] *= rho[~dmask, None]
    Sc[dmask, dmask] *= rho[dmask]
    dg = np.diagonal(Sc).copy()
    out = np.asarray(r, float).copy()
    n = obj.n
    out[:n] = 2.0 * np.log(dg)
    out[n:n + obj.nl] = (Sc / dg[None, :])[obj._tril]
    out[n + obj.nl:] = (np.asarray(C) * np.where(cross, rho, 1.0)[:, None]).ravel()
    return out


def _stage_start(P: Problem, s, recs, rho):
    """Warm start of the next stage: the rows of S_c of the deterministic states scaled by ``rho``.

    For each deterministic state, its row of C is scaled as well when that raises the ELBO
    at the start (greedy, one state at a time): an integrator such as φ̇ = p keeps its marginal
    spread as the process noise vanishes, a contracting subsystem (output error on a stable
    model) loses it; the start should be consistent with either.
    """
    det = np.nonzero(P.nm.deterministic)[0]
    cross = np.zeros(P.model.nx, bool)

    def start(cr):
        return [(np.asarray(m), _scale_cond_rows(P.obj, r, rho, cr, P.nm.pinned)) for m, r in recs]

    best = P.value(s, start(cross))
    for i in det:
        trial = cross.copy()
        trial[i] = True
        f = P.value(s, start(trial))
        if math.isfinite(f) and (not math.isfinite(best) or f < best):
            best, cross = f, trial
    return start(cross)


def _from_relaxed(P0: Problem, P: Problem, s0) -> np.ndarray:
    """Shared vector of P from the relaxed problem's: the deterministic states' noise parameters dropped."""
    nt = P0.tm.n_free
    w0 = np.asarray(s0[nt:], float)
    keep_states = set(P.nm.proc_est_idx.tolist())
    ne0 = len(P0.nm.proc_est_idx)
    keep = [a for a, i in enumerate(P0.nm.proc_est_idx) if int(i) in keep_states]
    return np.concatenate([np.asarray(s0[:nt], float), w0[keep], w0[ne0:]])


def limit_stage_small(d_elbo: float, d_theta: float, ratio: float, tol: float) -> bool:
    """Whether a converged continuation stage of factor ``ratio`` (ε ← ratio·ε) ends the
    deterministic limit: its ELBO change ``d_elbo`` (nats) and largest parameter change
    ``d_theta`` (standard errors), scaled to a full (1/10) stage, are both below ``tol``.

    In the O(ε²) regime a stage of factor ρ changes them by c ε²(1 − ρ²) and a full stage
    from the same point by c ε²(1 − 1/100), so a milder stage's changes are multiplied by
    (1 − 1/100)/(1 − ρ²); for a full stage the test is |Δ ELBO| < tol and Δθ < tol s.e.
    """
    to_full = (1.0 - LIMIT_RATIO ** 2) / (1.0 - ratio ** 2)
    return abs(d_elbo) * to_full < tol and d_theta * to_full < tol


def _deterministic_limit(P: Problem, P0, out0, eps, options: FitOptions, t0, *, target=None,
                         start_name: str | None = None, smoothing: bool = False,
                         hold=None) -> dict:
    """Fit (or smooth) in the limit of vanishing process noise on the deterministic states.

    A state without process noise has a degenerate transition, x_{k+1,i} = F_i(x_k): the
    ELBO of the model is the limit ε → 0 of the ELBO with process-noise std ε on that
    state (for a linear kinematic equation such as φ̇ = p the assumed density can satisfy
    it exactly and the limit is finite, with ELBO(ε) = ELBO(0) + O(ε²)). Fixing ε tiny at
    once makes the transition term ~1/ε² and the optimisation hopelessly ill-conditioned
    (the optimizer must bring Σ_cond, C and μ of that state onto the constraint from a
    start far from it). This is the quadratic-penalty method with continuation instead:
    the first stage (``P0``/``out0``; for smoothing, the problem at the data scale ``eps``)
    is well conditioned and fixes the scale ε̂; then ε ← ε/10 per stage, warm-started
    (:func:`_stage_start`), each stage converged by the Newton-decrement test. A stage that
    does not converge within its budget is retried from the last optimum with a milder
    factor (√ of the last), and the factor returns to 1/10 after a success. The limit is
    taken as reached when a full (1/10) stage changes the ELBO by less than ``limit_tol``
    nats and every free parameter by less than ``limit_tol`` of its standard error: in the
    O(ε²) regime the remaining distance to the limit is then about 1 % of that change. A
    milder stage (factor ρ) counts its changes as the full stage from the same point would
    have made them in that regime, × (1 − 1/100)/(1 − ρ²): near the precision of float64,
    where a full stage no longer converges, milder ones still end the continuation.

    A contracting deterministic subsystem (every state of an output-error fit of a stable
    model) has a posterior spread that decays along the record, which the time-invariant
    assumed density cannot follow: its spread collapses with ε and the ELBO falls by
    exactly ln 10 per full stage per collapsed direction while the estimates converge.
    Two consecutive stages with the same factor ρ and the same whole number k of ln(1/ρ)
    (within ``limit_tol`` per decade) and converged estimates end the continuation too
    (reported as k collapsed directions: such ELBOs compare only at equal ε).

    ``target`` (validation smoothing of a fit that took the limit; per deterministic state):
    the std at which the estimation's continuation ended. The stages then go from ``eps``
    (the estimation's first-stage std) down to exactly ``target`` and stop there — never
    further, so the smoothing's ELBO belongs to the same noise as the estimation's (a limit
    taken further than the estimation's scores the validation record with a sharper
    constraint than the one fitted; the ELBO of a collapsing direction falls by ln(1/ρ) per
    stage and a constraint the data violate costs ~1/ε²).
    Each stage is announced to the progress callback as a :class:`FitPhase` of kind
    ``LIMIT_STAGE`` (``start_name``: the noise start it belongs to; ``smoothing``: a
    validation smoothing).

    ``hold`` (per deterministic state, or None): a positive entry holds that state's std
    there in every stage (:func:`_warm_limit_hold`): the limit is taken in the others only.
    """
    det_idx = np.nonzero(P.nm.deterministic)[0]
    names = [P.model.state_names[i] for i in det_idx]
    eps = np.asarray(eps, float)
    held = None if hold is None else np.asarray(hold, float) > 0.0
    if held is not None:
        eps = np.where(held, hold, eps)
    if target is not None:
        target = np.asarray(target, float)
        eps = np.maximum(eps, target)
    nt = P.tm.n_free
    history, iterations, stages = [], 0, []
    budget = max(30, int(options.max_iter) // 4)
    stage_opts = dataclasses.replace(options, max_iter=budget)
    max_full = LIMIT_MAX_STAGES
    if target is not None:  # as many full stages as the way down to the target takes
        with np.errstate(divide="ignore", invalid="ignore"):
            need = np.log(eps / target) / math.log(1.0 / LIMIT_RATIO)
        need = need[np.isfinite(need)]
        max_full = max(max_full, int(math.ceil(float(need.max()) - 1e-9)) if need.size else 0)
    max_attempts = max_full + 4  # full stages plus at most four milder retries

    moving = np.ones(len(names), bool) if held is None else ~held   # the states taken to the limit

    def phase(stage, e):
        ref = np.where(eps > 0, eps, 1.0)
        sc = (np.asarray(e, float) / ref)[moving]
        return FitPhase(PhaseKind.LIMIT_STAGE, start=start_name, stage=stage, max_stages=max_attempts,
                        scale=float(np.max(sc)) if sc.size else None,
                        smoothing=smoothing)

    def record(stage, e, o, ratio):
        stages.append({"stage": stage, "std": {n: float(v) for n, v in zip(names, e)}, "elbo": -_negelbo(o),
                       "iterations": int(o["iterations"]), "converged": bool(o["converged"]),
                       "factor": ratio})

    def theta_of(tm, o):
        return np.asarray(tm.theta(jnp.asarray(o["s"][:nt])), float)[P.tm.free_idx]

    if out0 is not None:  # relaxed first stage, mapped onto P
        base = dict(s=_from_relaxed(P0, P, out0["s"]), recs=out0["recs"], elbo=-_negelbo(out0),
                    theta=theta_of(P0.tm, out0), eps=eps, out=None)
        history += list(out0["history"])
        iterations += int(out0["iterations"])
        record(0, eps, out0, None)
        status0 = out0["status"]
    else:  # smoothing or a warm start: the first stage is P itself at ``eps``
        P.set_deterministic_std(eps)
        o = _optimize(P, options, t0=t0, phase=phase(0, eps))
        history += list(o["history"])
        iterations += int(o["iterations"])
        record(0, eps, o, None)
        status0 = ""
        if not o["converged"]:
            o["limit"] = {"states": names, "std": {n: float(v) for n, v in zip(names, eps)}, "stages": stages,
                          "reached": False, "elbo_change": float("nan"), "theta_change_se": float("nan"),
                          "scale": 1.0, "collapsed_directions": 0}
            o["status"] += f"; deterministic state(s) {', '.join(names)}: first stage not converged"
            return o
        base = dict(s=o["s"], recs=o["recs"], elbo=-_negelbo(o), theta=theta_of(P.tm, o), eps=eps, out=o)
    eps_ref = eps.copy()
    reached = False
    d_elbo = d_theta = float("nan")
    collapsed, prev_k = 0, None
    ratio = LIMIT_RATIO
    full = 0
    failed = None
    for attempt in range(1, max_attempts + 1):
        if target is not None and np.all(base["eps"] <= target):
            reached = True  # at the estimation's noise: not a stage further
            break
        e = base["eps"] * ratio
        if target is not None:  # down to the target, and onto it when within rounding of it
            e = np.where(e <= target * (1.0 + 1e-9), target, e)
        if held is not None:    # held at their std: the limit of the others only
            e = np.where(held, base["eps"], e)
        P.set_deterministic_std(e)
        rho = np.ones(P.model.nx)
        rho[det_idx] = e / base["eps"]
        start = _stage_start(P, base["s"], base["recs"], rho)
        o = _optimize(P, stage_opts, t0=t0, resume=dict(s=base["s"], recs=start, lam=float(options.lambda0),
                                                        history=[{}], iterations=0),
                      phase=phase(len(stages), e))
        history += list(o["history"])
        iterations += int(o["iterations"])
        record(len(stages), e, o, ratio)
        if not o["converged"]:
            if ratio < 0.7:  # a milder step from the last optimum
                ratio = math.sqrt(ratio)
                continue
            failed = o
            break
        elbo, theta = -_negelbo(o), theta_of(P.tm, o)
        d_elbo = elbo - base["elbo"]
        d_theta = 0.0
        if nt:
            cov, _ = _uncertainty(P, o["blks"], o["s"])
            se = np.sqrt(np.abs(np.diag(cov)))
            se = np.where(np.isfinite(se) & (se > 0), se, np.nan)
            with np.errstate(invalid="ignore"):
                r_ = np.abs(theta - base["theta"]) / se
            d_theta = float(np.nanmax(r_)) if np.any(np.isfinite(r_)) else 0.0
        base = dict(s=o["s"], recs=o["recs"], elbo=elbo, theta=theta, eps=e, out=o)
        ln_step = math.log(1.0 / ratio)
        k = int(round(-d_elbo / ln_step))
        within = k >= 1 and abs(d_elbo + k * ln_step) < options.limit_tol * ln_step / math.log(10.0)
        steady_k = within and prev_k == (k, ratio)
        prev_k = (k, ratio) if within else None   # both stages within the tolerance
        # with a target the stopping rule is the target (checked before the next stage)
        if target is None and (
                (steady_k and d_theta < options.limit_tol)
                or limit_stage_small(d_elbo, d_theta, ratio, options.limit_tol)):
            reached = True
            collapsed = k if steady_k else 0
            break
        if ratio == LIMIT_RATIO:
            full += 1
            if full >= max_full and not (target is not None and np.all(e <= target)):
                break
        ratio = max(LIMIT_RATIO, ratio * ratio)
    out = base["out"] if base["out"] is not None else failed
    eps = base["eps"] if base["out"] is not None else eps
    sc = (eps / np.where(eps_ref > 0, eps_ref, 1.0))[moving]
    scale = float(np.max(sc)) if sc.size else 1.0
    out["limit"] = {"states": names, "std": {n: float(v) for n, v in zip(names, eps)}, "stages": stages,
                    "reached": reached, "elbo_change": float(d_elbo), "theta_change_se": float(d_theta),
                    "scale": scale, "collapsed_directions": collapsed}
    if target is not None:
        out["limit"]["target_std"] = {n: float(v) for n, v in zip(names, target)}
    if held is not None and held.any():
        out["limit"]["held_std"] = {n: float(v) for n, v, h in zip(names, eps, held) if h}
    pinned = {P.model.state_names[i] for i in np.nonzero(P.nm.pinned)[0]}
    det_names = [n for n in names if n not in pinned]
    parts = ([f"deterministic state(s) {', '.join(det_names)}"] if det_names else []) + \
        ([f"degenerate state(s) {', '.join(sorted(pinned))} (independent process noise)"] if pinned else [])
    if target is not None:
        what = (f"{'; '.join(parts)}: process noise taken to the std at which the estimation's limit "
                f"ended ({', '.join(f'{n} {v:.3g}' for n, v in zip(names, target))}) "
                + (f"in {len(stages) - 1} stage(s)" if reached else
                   f"NOT reached in {len(stages) - 1} stage(s)"))
    else:
        what = (f"{'; '.join(parts)}: limit of vanishing process noise "
                + (f"reached after {len(stages) - 1} stage(s) (last change {d_elbo:.2g} nats, {d_theta:.2g} s.e.)"
                   if reached else f"NOT reached in {len(stages) - 1} stage(s)"))
    if held is not None and held.any():
        what += (f" (held at their std, not taken to the limit: "
                 f"{', '.join(f'{n} {v:.3g}' for n, v, h in zip(names, eps, held) if h)})")
    if collapsed:
        what += (f"; the estimates converged while the ELBO falls by ln(1/ρ) per stage (ρ: the stage's "
                 f"process-noise factor) in {collapsed} "
                 f"direction(s) of a contracting deterministic subsystem (its initial-condition spread "
                 f"collapses): compare ELBOs only at the same process-noise std")
    out["status"] = out["status"] + "; " + what + (f"; first stage: {status0}" if status0 else "")
    out["history"] = tuple(history)
    out["iterations"] = iterations
    return out


def _drift_scale(P: Problem, idx) -> np.ndarray:
    """Data scale of the process-noise std of states ``idx``: √T · rms_k f_i(μ⁰_k, u_k, θ⁰).

    f is the drift at the initial state means μ⁰ (measured states from their outputs,
    unmeasured ones solved from the outputs where these depend on them, else 0:
    :attr:`.problem.Problem.measured_start`), the inputs and the initial θ, over every sample
    of every record:
    the rate at which the model, as given, moves the state along the data. A process noise
    whose increment over one sample (σ√T) equals that movement (f T) has σ = f √T, the same
    construction as a measured state's data start (spread of its sample differences / √T).
    It is in the state's own units (deg/√s for a state in degrees), so a start built on it
    does not depend on them. 0 where the drift of the state vanishes at the start.
    """
    T = float(np.mean([float(r.dt) for r in P.records]))
    p0 = jnp.asarray(P.tm.theta(jnp.asarray(P.tm.z0)))
    drift = jax.vmap(P.model.drift, in_axes=(0, 0, None))
    sq, n = np.zeros(len(idx)), 0
    for rec, mu0 in zip(P.records, P.measured_start):
        f = np.asarray(drift(jnp.asarray(mu0), jnp.asarray(np.asarray(rec.u, float)), p0), float)[:, idx]
        fin = np.all(np.isfinite(f), axis=1)
        sq += np.sum(f[fin] ** 2, axis=0)
        n += int(fin.sum())
    return np.sqrt(sq / max(n, 1)) * math.sqrt(T)


def _release_start(P: Problem, options: FitOptions, t0) -> dict | None:
    """The "release" noise start: unmeasured states with process noise, first held deterministic.

    An unmeasured state i with an estimated process-noise std (measured by no output directly,
    and not determined by the outputs at the start: :attr:`.problem.Problem.output_solved`)
    has no data scale of its own,
    and its noise can absorb any channel it enters: a sideslip with free (or merely large)
    process noise reproduces the lateral accelerometer exactly while that channel's
    measurement std collapses. Its std is therefore reached by a homotopy from the
    deterministic side, in three legs, each warm-started from the previous one:

    1. *Hold, noise fixed.* θ and the assumed densities are fitted with every noise std
       fixed at its "data" start (measurement σ_j = spread of output j's sample
       differences / √2, a measured state's process std = that spread / √T) and the
       unmeasured states held deterministic in the exact limit of vanishing process noise
       (:func:`_deterministic_limit`): the first stage holds their std at the data scale
       ε⁰_i = √T · rms f_i of :func:`_drift_scale` (the assumed density starting at
       Σ_cond = T diag(G Gᵀ), C = 0), then ε ← ε/10 per stage until the limit is reached.
       With the noise fixed no std can collapse, and in the limit the held state cannot
       absorb a channel.
    2. *Hold, noise free.* The other noise parameters are estimated from their data start,
       the held states' std kept where the limit ended.
    3. *Release.* The held states' stds are freed from where the limit ended, and the
       optimizer raises them as far as the data ask.

    Every quantity the path uses is unit free (nats, standard errors, log-stds, Newton
    steps) or in the state's own units (f_i, μ_i, Σ_cond, the stds), so the iterates are
    the same for a state expressed in other units (tests/test_release_start.py).
    Returns the release leg's output (with every leg's iterations and history counted),
    or None when there is no such state or its drift vanishes at the start.
    """
    if P.nm.fixed_G is not None or P.nm.deterministic.any() or P.tm.n_free == 0:
        return None
    pairs = P.direct
    # a state the outputs determine (u, w of a body-axis model through V and α) has the data
    # scale of the outputs it is solved from, like a directly measured one: not held
    held = [int(i) for i in P.nm.proc_est_idx
            if int(i) not in pairs and int(i) not in P.output_solved]
    if not held:
        return None
    eps0 = _drift_scale(P, held)
    if not np.all(np.isfinite(eps0) & (eps0 > 0)):
        return None
    names = P.model.state_names
    Ph = Problem(P.model, P.records, options, relax=P.relax, hold=held)
    w_data = Ph.nm.inits["data"]
    Gd = np.diag(np.diagonal(np.asarray(Ph.nm.G(jnp.asarray(w_data)), float))).copy()
    Gd[held, held] = 0.0
    Rd = np.diag(np.asarray(Ph.nm.sigma(jnp.asarray(w_data)), float) ** 2)
    # leg 1: noise fixed at the data start, held states to the deterministic limit
    Pa = Problem(P.model, P.records, options, fixed_G=Gd, fixed_R=Rd)
    Pa.noise_scaled_start = True
    leg1 = _deterministic_limit(Pa, None, None, eps0, options, t0, start_name="release")
    lim = leg1["limit"]
    end = np.asarray([lim["std"][n] for n in (names[i] for i in np.nonzero(Pa.nm.deterministic)[0])], float)
    # leg 2: the other noise free, held states at the limit's std
    Ph.set_deterministic_std(end)
    nt = P.tm.n_free
    s2 = np.concatenate([np.asarray(leg1["s"], float)[:nt], w_data])
    leg2 = _optimize(Ph, options, t0=t0, resume=dict(s=s2, recs=leg1["recs"], lam=float(options.lambda0),
                                                      history=[{}], iterations=0),
                     phase=FitPhase(PhaseKind.RELEASE_LEG, start="release", leg="other noise free"))
    # leg 3: release; P's process-noise parameters: held ones where the limit ended, new off-diagonal ones 0
    sh = np.asarray(leg2["s"], float)
    wh = {int(i): sh[nt + a] for a, i in enumerate(Ph.nm.proc_est_idx)}
    w = []
    for i in P.nm.proc_est_idx:
        i = int(i)
        if i in wh:
            w.append(wh[i])
        else:
            e = float(Ph.nm.det[i])
            gap = e - P.nm.proc_floor[i]
            w.append(math.log(gap if gap > 0 else e))
    off_h = {ab: sh[nt + len(Ph.nm.proc_est_idx) + k] for k, ab in enumerate(Ph.nm.offdiag)}
    w += [off_h.get(ab, 0.0) for ab in P.nm.offdiag]
    s3 = np.concatenate([sh[:nt], np.asarray(w, float), sh[nt + Ph.nm.n_proc:]])
    out = _optimize(P, options, t0=t0, resume=dict(s=s3, recs=leg2["recs"], lam=float(options.lambda0),
                                                    history=[{}], iterations=0),
                    phase=FitPhase(PhaseKind.RELEASE_LEG, start="release", leg="released"))
    held_names = [names[i] for i in held]
    out["status"] += (f" (release start: {', '.join(held_names)} held deterministic first: noise fixed, "
                      f"{'limit reached' if lim['reached'] else 'limit NOT reached'} after "
                      f"{len(lim['stages']) - 1} stage(s), {leg1['iterations']} it.; noise free, "
                      f"{'converged' if leg2['converged'] else 'not converged'}, ELBO {-_negelbo(leg2):.6g}, "
                      f"{leg2['iterations']} it.)")
    out["history"] = tuple(leg1["history"]) + tuple(leg2["history"]) + tuple(out["history"])
    out["iterations"] = int(out["iterations"]) + int(leg1["iterations"]) + int(leg2["iterations"])
    return out


def _limit_of_estimation(P: Problem, noise):
    """(first-stage std, final std) of the estimation's deterministic-limit continuation for the
    deterministic states of the smoothing problem ``P`` (their order), or (None, None).

    ``noise`` is the estimation's FitResult (or a mapping) with its ``deterministic_limit``
    record; it is used when it names exactly P's deterministic states with positive stds.
    Validation smoothing then follows the estimation's noise path and ends at its noise
    (:func:`_deterministic_limit` ``target``)."""
    lim = noise.get("deterministic_limit") if isinstance(noise, Mapping) else getattr(
        noise, "deterministic_limit", None)
    if not isinstance(lim, Mapping):
        return None, None
    names = [P.model.state_names[i] for i in np.nonzero(P.nm.deterministic)[0]]
    end = lim.get("std") or {}
    first = ((lim.get("stages") or [{}])[0] or {}).get("std") or {}
    if set(end) != set(names):
        return None, None
    target = np.asarray([float(end[n]) for n in names], float)
    if not np.all(np.isfinite(target) & (target > 0)):
        return None, None
    start = (np.asarray([float(first[n]) for n in names], float) if set(first) == set(names) else None)
    if start is None or not np.all(np.isfinite(start) & (start > 0)):
        start = _smoothing_start_std(P)
    return start, target      # _deterministic_limit starts at max(start, target)


def _noise_from(noise, model):
    if hasattr(noise, "G") and hasattr(noise, "R"):
        return np.asarray(noise.G, float), np.asarray(noise.R, float)
    if isinstance(noise, Mapping):
        if "G" in noise and "R" in noise:
            return np.asarray(noise["G"], float), np.asarray(noise["R"], float)
        if "process_std" in noise and "measurement_std" in noise:
            ps, ms = noise["process_std"], noise["measurement_std"]
            G = np.diag([float(ps.get(n, 0.0)) for n in model.state_names])
            R = np.diag([float(ms[n]) ** 2 for n in model.output_names])
            return G, R
    raise FitError("noise must be a FitResult or a mapping with 'G' and 'R' or 'process_std' and 'measurement_std'")


def validate_own_noise(model, records, theta, *, free: Sequence[str] = (),
                       options: FitOptions = FitOptions()) -> FitResult:
    """Validation at the records' own noise: every model parameter fixed at ``theta`` (all
    parameters, model order) except those named in ``free`` (started at ``theta``), the noise
    parameters (process and measurement) and one assumed density per record estimated on
    ``records``.

    ``free`` is for the properties of a flight that are not the aircraft's: its trim
    constants (:meth:`vsidgen.spec.symbolic.SymbolicModel.trim_parameters`: ``Z0``, ``M0``,
    a sensor bias), which the textbook's multi-manoeuvre estimation fits per time segment. A
    constant the estimation record's trim fixed does not carry over to a record flown at
    another trim (Tu-144 ``f20_4d`` → ``f20_4f``, 5 m/s faster: a fitted ``a_z`` bias lost
    on validation with it fixed).

    The ELBO is that of the model's physics at the validation flight's own turbulence and
    sensor noise. :func:`smooth` (θ *and* noise fixed, the paper's validation) also compares
    how well the estimation's noise suits the other flight; noise is a property of a flight,
    not of the physics, so two models are compared on their physics by this ELBO (ATTAS
    ``attas_elv1`` → ``attas_elv2``: the textbook short-period model 6284.7 with the
    estimation's noise — its q measurement std at its floor, 6.6e-6 rad/s, ``elv2``'s own
    7.8e-4 — against 6437.1 for the same model without M_q; at each record's own noise 6861.6
    against 6559.7). Raises FitError as :func:`fit` does."""
    theta = np.asarray(theta, float)
    if theta.shape != (model.np,):
        raise FitError(f"theta has shape {theta.shape}, expected ({model.np},)")
    names = set(free)
    unknown = names - {p.name for p in model.parameters}
    if unknown:
        raise FitError(f"validate_own_noise: free parameters {sorted(unknown)} are not "
                       f"parameters of {model.name}")
    fixed = tuple(dataclasses.replace(p, fixed=p.fixed or p.name not in names,
                                      initial=float(v))
                  for p, v in zip(model.parameters, theta))
    return fit(dataclasses.replace(model, parameters=fixed), records, options=options)


def smooth(model, records, theta, noise, *, options: FitOptions = FitOptions()) -> FitResult:
    """Validation mode: θ and noise fixed, only the assumed densities q (one per record) are fitted.

    ``theta``: all parameters in model order, or a mapping name -> value (missing names:
    the spec's initial values, as :func:`vsidgen.evaluate` and :func:`vsidgen.simulate`
    read it); ``noise``: a FitResult, or a mapping with
    ``G`` (nx×nx) and ``R`` (ny×ny), or ``process_std``/``measurement_std`` dicts.
    The returned FitResult has the maximised ELBO (a lower bound on log p(y | θ)) and the
    smoother paths; std_errors are NaN. States without process noise are smoothed in the
    limit of vanishing noise by the same continuation as the fit; when ``noise`` carries the
    estimation's ``deterministic_limit`` record, the continuation follows its stds from its
    first stage and ends at exactly the std the estimation ended with (never further), so the
    validation ELBO is that of the estimated noise.
    """
    from ..model.runtime import finite_theta

    if not hasattr(model, "parameter_names"):
        raise FitError("the model must be a vsidgen Model\n  hint: model = "
                       "vsidgen.load_model('spec.yaml')")
    try:
        theta = finite_theta(model, theta, who="smooth")
    except VsidgenError as err:
        raise FitError(str(err)) from None
    G, R = _noise_from(noise, model)
    P = Problem(model, records, options, theta_fixed=theta, fixed_G=G, fixed_R=R)
    if options.deterministic == "limit" and P.nm.deterministic.any():
        start, target = _limit_of_estimation(P, noise)
        out = _deterministic_limit(P, None, None, _smoothing_start_std(P) if start is None else start,
                                   options, time.perf_counter(), target=target, smoothing=True)
    else:
        out = _optimize(P, options, phase=FitPhase(PhaseKind.SMOOTHING, smoothing=True))
    return _finish(P, out, mode="smooth", options=options)
