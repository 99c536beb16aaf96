"""The variational objective (negative ELBO) and its structured derivatives.

Model (per record, samples k = 0..N-1, sample period T):

    x_{k+1} ~ N(F(x_k, u_k, θ), Q),   Q = T G Gᵀ          (Euler–Maruyama by default)
    y_k     ~ N(h(x_k, u_k, θ), R),   R = diag(σ_j²)      (NaN samples masked out)

flat (improper) prior on x_0. Assumed density q: a Gaussian Markov chain with
means μ_k and time-invariant ("steady-state") covariances

    Σ_cond = S_c S_cᵀ,  S_c = L diag(exp(d/2)),  L unit lower triangular,
    Σ_marg = S_c S_cᵀ + C Cᵀ = S_m S_mᵀ,

sampled in pairs as x_k = μ_k + S_m z₁, x_{k+1} = μ_{k+1} + C z₁ + S_c z₂.
The ELBO is

    L = Σ_{k<N-1} E_q log N(x_{k+1}; F(x_k), Q) + Σ_k E_q log N_mask(y_k; h(x_k), R) + H[q],
    H[q] = ½ log det Σ_marg + ((N-1)/2) log det Σ_cond + (N n/2)(1 + log 2π).

Expectations use sigma points: pairs (z₁, z₂) = ±√(2n) e_i in R^{2n} (4n points,
weights 1/(4n)); marginals μ_k ± √n S_m e_i (2n points, weights 1/(2n)). They
are exact for quadratic integrands, hence for linear-Gaussian models.

The negative ELBO is a sum of per-pair terms ℓ_k(μ_k, μ_{k+1}, b), per-node
terms m_k(μ_k, b) and −H(b), where b (the "border") holds the record's
assumed-density parameters r = (d, vec L, vec C) and the shared vector s of
free θ (unconstrained coordinates) and noise parameters. Its Hessian over
(μ, b) is therefore block tridiagonal in μ with a dense border; see
:mod:`vsidgen.estimator.linalg`.
"""

from __future__ import annotations

import collections
import functools
import math
import pathlib
import sys
import weakref

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.linalg import block_diag

from ..data import resolution
from ..errors import FitError
from .linalg import btd_solve, btd_solve_parallel, chol_small, tri_solve_small, use_parallel_solve

from .. import precision  # noqa: F401  (float64, set once)

LOG2PI = math.log(2.0 * math.pi)


# --------------------------------------------------------------------------- transition
def step_inputs(F, u):
    """The step inputs of transition ``F`` for the (N, nu) inputs ``u`` (u[:-1] for a bare function)."""
    fn = getattr(F, "step_inputs", None)
    return u[:-1] if fn is None else fn(u)


# --------------------------------------------------------------------------- θ map
def _concrete(*xs) -> bool:
    """No tracer among the arrays: a call on values (after a fit, in set-up), not inside jit."""
    return not any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(xs))


def _theta_of(z, c):
    """θ of the free unconstrained z under the map's arrays ``c`` (:meth:`ThetaMap.theta`)."""
    k, lo, hi, sc = c["kind"], c["lo"], c["hi"], c["sc"]
    ez = jnp.exp(jnp.where((k == 1) | (k == 2), z, 0.0))
    sig = jax.nn.sigmoid(z)
    val = jnp.where(k == 0, z,
          jnp.where(k == 1, lo + sc * ez,
          jnp.where(k == 2, hi - sc * ez,
                    lo + (hi - lo) * sig)))
    return jnp.asarray(c["full0"]).at[c["free_idx"]].set(val)


def _noise_G(w, c, structure):
    """G of :meth:`NoiseMap.G`; ``structure`` = (fixed, estimated indices, off-diagonal
    entries, number of process-noise parameters)."""
    fixed, est_idx, offdiag, n_proc = structure
    if fixed:
        return jnp.asarray(c["fixed_G"])
    est = np.array(est_idx, dtype=int)
    diag = jnp.asarray(c["det_std"])
    ne = len(est)
    diag = diag.at[est].set(jnp.asarray(c["proc_floor"])[est] + jnp.exp(w[:ne]))
    G = jnp.diag(diag)
    if offdiag:
        rows = np.array([a for a, _ in offdiag])
        cols = np.array([b for _, b in offdiag])
        G = G.at[rows, cols].set(w[ne:n_proc])
    return G


def _noise_sigma(w, c, structure):
    """σ of :meth:`NoiseMap.sigma`; ``structure`` = (number of estimated stds, number of
    process-noise parameters, estimated output indices)."""
    n_meas, n_proc, meas_idx = structure
    s = jnp.asarray(c["meas_fixed"])
    if n_meas:
        idx = np.array(meas_idx, dtype=int)
        s = s.at[idx].set(jnp.asarray(c["meas_floor"])[idx] + jnp.exp(w[n_proc:]))
    return s


def cov_factors_of(r, n: int):
    """The assumed density's factors from its parameters r = (d, l, c): Sc = L diag(e^{d/2})
    (the conditional covariance Σ_cond = Sc Scᵀ, L unit lower triangular from l), the cross
    factor C (n × n from c), Sm = chol(Sc Scᵀ + C Cᵀ) (the marginal covariance), and d."""
    nl = n * (n - 1) // 2
    d = r[:n]
    L = jnp.eye(n).at[np.tril_indices(n, -1)].set(r[n:n + nl])
    C = r[n + nl:].reshape(n, n)
    Sc = L * jnp.exp(0.5 * d)[None, :]
    Sm = chol_small(Sc @ Sc.T + C @ C.T)
    return Sc, C, Sm, d


# the same functions compiled once per shape for calls on values (the eager path compiled
# ~70 one-operation programs in every process: ~1 s of a warm HFB-320 fit)
_theta_jit = jax.jit(_theta_of)
_noise_G_jit = jax.jit(_noise_G, static_argnums=2)
_noise_sigma_jit = jax.jit(_noise_sigma, static_argnums=2)
_cov_factors_jit = jax.jit(cov_factors_of, static_argnums=1)


class ThetaMap:
    """Smooth bijection between unconstrained z (free parameters only) and θ (all parameters).

    * unbounded: θ = z (z₀ = initial)
    * lower only: θ = lo + s·exp(z), s = initial − lo (z₀ = 0) or, when initial ≤ lo, 1
      coherent unit of the parameter (:func:`coherent_factors`)
    * upper only: θ = hi − s·exp(z)
    * two-sided: θ = lo + (hi − lo)·sigmoid(z)
    * fixed: θ = initial.
    """

    def __init__(self, parameters, *, fixed_all: bool = False, values=None):
        npar = len(parameters)
        init = np.array([float(p.initial) for p in parameters]) if values is None else np.asarray(values, float)
        self.full0 = init.copy()
        free = np.array([(not p.fixed) and not fixed_all for p in parameters], bool)
        self.free_mask = free
        self.free_idx = np.nonzero(free)[0]
        kind = np.zeros(npar, int)
        lo = np.zeros(npar)
        hi = np.ones(npar)
        sc = np.ones(npar)
        z0 = np.zeros(npar)
        one = 1.0 / coherent_factors(parameters)      # 1 coherent unit in the declared one
        for i, p in enumerate(parameters):
            a, b = p.lower, p.upper
            a = None if a is None or not np.isfinite(a) else float(a)
            b = None if b is None or not np.isfinite(b) else float(b)
            x0 = init[i]
            if a is None and b is None:
                kind[i] = 0
                z0[i] = x0
            elif a is not None and b is None:
                kind[i] = 1
                lo[i] = a
                sc[i] = x0 - a if x0 > a else one[i]
                z0[i] = 0.0
            elif a is None and b is not None:
                kind[i] = 2
                hi[i] = b
                sc[i] = b - x0 if x0 < b else one[i]
                z0[i] = 0.0
            else:
                if not b > a:
                    raise FitError(f"parameter '{p.name}': lower bound {a} is not below upper bound {b}")
                kind[i] = 3
                lo[i], hi[i] = a, b
                frac = np.clip((x0 - a) / (b - a), 1e-3, 1 - 1e-3)
                z0[i] = math.log(frac / (1 - frac))
        fi = self.free_idx
        self.kind, self.lo, self.hi, self.sc = kind[fi], lo[fi], hi[fi], sc[fi]
        self.z0 = z0[fi]
        self.n_free = len(fi)

    def static_key(self):
        """Shape of the map: which parameters are free is a run-time array (``arrays()``), so
        problems of one model that free different parameters of the same count share the
        compiled objective (diagnose's gated refits)."""
        return ("theta", self.n_free, len(self.full0))

    def arrays(self):
        """Numeric configuration passed to the jitted objective (so compiled code is shared)."""
        return {"full0": self.full0, "kind": self.kind.astype(float), "lo": self.lo, "hi": self.hi, "sc": self.sc,
                "free_idx": self.free_idx.astype(np.int32)}

    def theta(self, z, c=None):
        """All parameters θ from the free unconstrained z (``c``: arrays(), default this map's)."""
        c = self.arrays() if c is None else c
        if "free_idx" not in c:
            c = {**c, "free_idx": self.free_idx.astype(np.int32)}
        return (_theta_jit if _concrete(z, c) else _theta_of)(z, c)

    def dtheta_dz(self, z):
        z = np.asarray(z, float)
        k = self.kind
        ez = np.exp(np.where((k == 1) | (k == 2), z, 0.0))
        sig = 1.0 / (1.0 + np.exp(-z))
        return np.where(k == 0, 1.0, np.where(k == 1, self.sc * ez, np.where(k == 2, -self.sc * ez,
                                                                              (self.hi - self.lo) * sig * (1 - sig))))


# --------------------------------------------------------------------------- units
def coherent_factors(variables) -> np.ndarray:
    """Per variable, the factor ``s`` from its declared unit to the coherent unit (SI, rad):
    a value ``x`` in the declared unit is ``s·x`` in the coherent one (``deg`` → π/180,
    ``ft/s`` → 0.3048); 1 for a variable without a unit or with one vsidgen cannot read.

    What the estimator chooses without the data — the "unit" noise start (std 1), the
    assumed density's first covariance (Σ = I), the floor of the Marquardt scaling — is
    chosen in these coherent units and converted to the declared ones, so that a model
    written in degrees or feet is fitted along exactly the path of the same model written
    in radians or metres (the two are one linear change of variables apart).
    """
    return np.asarray([_coherent_factor(getattr(v, "unit", None) or "") for v in variables], float)


@functools.lru_cache(maxsize=1024)
def _coherent_factor(text: str) -> float:
    """:func:`coherent_factors` of one unit text (parsed once per text)."""
    if not text:
        return 1.0
    from ..spec.units import coherent

    try:
        f = float(coherent(text)[0])
    except Exception:       # a unit of a model built in Python that the spec grammar cannot read
        return 1.0
    return f if math.isfinite(f) and f > 0 else 1.0


# --------------------------------------------------------------------------- noise map
def diff_scale(records, j: int) -> float:
    """Robust std (1.4826 · MAD) of the sample-to-sample differences of output j, pooled over records.

    Data-driven starting scale of the noise parameters: for a measured state it bounds
    the random-walk rate of the state (process noise ≲ scale/√T) and the measurement
    noise (σ ≲ scale/√2). 0 when there are no differences.
    """
    d = []
    for r in records:
        col = np.asarray(r.y, float)[:, j]
        dif = np.diff(col)
        d.append(dif[np.isfinite(dif)])
    d = np.concatenate(d) if d else np.zeros(0)
    if d.size == 0:
        return 0.0
    return float(1.4826 * np.median(np.abs(d - np.median(d))))


def input_filter_scales(model, records) -> np.ndarray:
    """Per state (nx,), the std of the input the state carries, pooled over ``records``
    (each record about its own mean); 0 for a state that carries none.

    A state ``z`` *carries* input ``u`` when it has ``u``'s unit and its drift is driven by
    the difference of the two, ``∂f_z/∂u = −∂f_z/∂z ≠ 0`` (in the model's symbolic form): a
    lag ``(u − z)/τ``, a Padé delay ``2(u − z)/τ`` or an actuator state of ``u``, whose values
    are of ``u``'s size. (A flow angle driven by a control, ``α̇ = Z_α α + Z_δe δe``, is not.)
    The std of a quasi-deterministic such state's process noise is then set relative to this scale (``FitOptions.deterministic_input_scale``), so
    that it does not depend on the unit the input is recorded in: an absolute 1e-3 is 7 %
    of an elevator's std in rad per √s but 1e-6 of an engine thrust's in N, which left the
    assumed density of a thrust lag so ill-conditioned that its refit stopped at the
    iteration limit (hfb_thrust_lag_0.5_s0: 800 iterations, 487 s, not converged; scaled,
    converged in 140 s). 0 everywhere for a model without a symbolic form."""
    out = np.zeros(len(model.state_names))
    for i, j in carried_inputs(model):
        cols = [np.asarray(r.u, float)[:, j] for r in records]
        cols = [c[np.isfinite(c)] - np.mean(c[np.isfinite(c)]) for c in cols
                if np.isfinite(c).any()]
        if cols:
            sd = float(np.sqrt(np.mean(np.concatenate(cols) ** 2)))
            if math.isfinite(sd):
                out[i] = max(out[i], sd)
    return out


def quasi_deterministic_stds(model, records, det_std, input_scale: float | None) -> np.ndarray:
    """Per state, the fixed std of a quasi-deterministic state: ``input_scale · std(u)`` for a
    state carrying input ``u`` (:func:`input_filter_scales`) when ``input_scale`` is given,
    ``det_std`` (a scalar or per state) otherwise (``FitOptions.deterministic_input_scale``)."""
    det = np.broadcast_to(np.asarray(det_std, float), (len(model.state_names),))
    if input_scale is None:
        return det.copy()
    sc = input_filter_scales(model, records)
    return np.where(sc > 0, float(input_scale) * sc, det)


#: (state index, input index) pairs of the states that carry an input, per symbolic model
#: (:func:`carried_inputs`; symbolic work done once per model, not per problem): id of the
#: symbolic form → (weak reference to it, pairs); the symbolic form is not hashable
_CARRIED: dict = {}


def carried_inputs(model) -> tuple[tuple[int, int], ...]:
    """(state, input) index pairs where the state carries the input (same unit, drift driven
    by their difference); () for a model without a symbolic form."""
    sym = getattr(model, "symbolic", None)
    if sym is None:
        return ()
    hit = _CARRIED.get(id(sym))
    if hit is not None and hit[0]() is sym:
        return hit[1]
    try:
        drift = sym.drift_expanded()
        u_syms = tuple(sym.input_symbols)
    except (AttributeError, TypeError):
        return ()
    units = {v.name: (v.unit or "").replace(" ", "") for v in model.inputs}
    pairs = []
    for i, st in enumerate(model.states):
        su = (st.unit or "").replace(" ", "")
        if not su or i >= len(drift):
            continue
        free = getattr(drift[i], "free_symbols", set())
        for j, (v, us) in enumerate(zip(model.inputs, u_syms)):
            if units.get(v.name) == su and us in free \
                    and _driven_by_difference(drift[i], us, sym.state_symbols[i]):
                pairs.append((i, j))
    try:
        ref = weakref.ref(sym, lambda _, k=id(sym): _CARRIED.pop(k, None))
        _CARRIED[id(sym)] = (ref, tuple(pairs))
    except TypeError:              # not weakly referenceable: computed again next time
        pass
    return tuple(pairs)


def _driven_by_difference(f, u, z) -> bool:
    """``∂f/∂u = −∂f/∂z ≠ 0``: ``f`` depends on ``u`` and ``z`` through ``u − z`` (sympy).

    The identity ``g = ∂f/∂u + ∂f/∂z ≡ 0`` is decided by evaluating ``g`` at random points
    (:func:`_vanishes_identically`), not by ``sympy.simplify``: on a diagnose screen's gated
    model (≈150 terms in one drift) ``simplify`` took more than a minute per state."""
    import sympy

    try:
        du = sympy.diff(f, u)
        if du == 0:
            return False
        g = du + sympy.diff(f, z)
        return g == 0 or _vanishes_identically(g, du)
    except (TypeError, ValueError, AttributeError):
        return False


#: random points at which :func:`_vanishes_identically` evaluates an expression
IDENTITY_POINTS = 4


def _vanishes_identically(g, scale, *, points: int = IDENTITY_POINTS, seed: int = 0) -> bool:
    """Is the analytic expression ``g`` identically zero? Evaluated at ``points`` random real
    points (every free symbol uniform in [0.3, 1.7], away from 0 and from the integers where
    an expression may be singular), with 30 significant digits: an expression that is not
    identically zero vanishes only on a set of measure zero, so a non-zero value at any
    point decides False (relative to ``|scale|`` there, ``scale`` an expression of the same
    size, e.g. the derivative it is compared with), and zero at every point True (the
    polynomial identity test of Schwartz and Zippel, for analytic functions). Points where
    ``g`` is not finite and real are drawn again (at most 4·``points`` draws); when no point
    evaluates, False."""
    import random

    import sympy

    scale = sympy.sympify(scale)
    syms = sorted(g.free_symbols | scale.free_symbols, key=str)
    rng = random.Random(seed)
    good = 0
    for _ in range(4 * points):
        at = {s: sympy.Float(rng.uniform(0.3, 1.7), 30) for s in syms}
        try:
            gv = complex(g.xreplace(at).evalf(30))
            sv = complex(scale.xreplace(at).evalf(30))
        except (TypeError, ValueError, ZeroDivisionError, OverflowError):
            continue
        if not (math.isfinite(gv.real) and math.isfinite(sv.real)) or gv.imag or sv.imag:
            continue
        if abs(gv.real) > 1e-20 * abs(sv.real) + 1e-280:
            return False
        good += 1
        if good >= points:
            return True
    return False


class NoiseMap:
    """Unconstrained noise parameters → (lower-triangular G, measurement std σ).

    Process: an empty ``ProcessNoiseSpec.states`` means all states (the spec default).
    G is lower triangular on the state order; on the noisy states its
    diagonal is ``floor_i + exp(g_i)`` (estimated) or the fixed std; for
    ``structure: full`` the strictly-lower entries among noisy states are free
    (start at 0). States without process noise (``deterministic``) get the fixed
    diagonal ``deterministic_std`` (a scalar or one value per state; the estimator
    drives it to the deterministic limit, see :mod:`vsidgen.estimator.fit`), or, with
    ``relax``, an estimated one like a noisy state's (the first stage of that limit;
    those states are ``relaxed``). ``hold`` (state indices): noisy states treated as
    deterministic in this problem (the first leg of the release start of an unmeasured
    state, :func:`vsidgen.estimator.fit._release_start`); they are never relaxed.
    Degenerate states (``ProcessNoiseSpec.degenerate``, or a given G whose Cholesky pivot of
    a state with noise is zero: a rank-deficient Q) are ``pinned``: their row keeps its free
    (or given) off-diagonal entries while the diagonal is the fixed ``deterministic_std``,
    driven to the limit G_ii → 0 like a deterministic state's; with ``relax`` their diagonal
    is estimated instead (they are ``relaxed``: the first stage of that limit).
    Measurement: σ_j = floor_j + exp(s_j) (estimated) or the fixed std.
    Starting values (``inits``): the spec's std where given; otherwise "unit": 1 coherent
    unit above the floor (:func:`coherent_factors`: 1 rad/s/√s for a rate in deg/s, 1 rad
    for an angle measured in deg); "data" (:func:`diff_scale`): σ_j =
    max(scale_j/√2, 2·floor_j) and, for a state measured directly by output j,
    G_ii = scale_j/√T; "data-meas": σ from the data, G unit. Floors are honoured by the map, never by clipping.
    """

    def __init__(self, model, records, *, deterministic_std, fixed_G=None, fixed_R=None,
                 state_outputs=None, relax: bool = False, hold=()):
        nx, ny = model.nx, model.ny
        self.nx, self.ny = nx, ny
        states = model.state_names
        sx, sy = coherent_factors(model.states), coherent_factors(model.outputs)
        pn = model.process_noise
        noisy_names = tuple(pn.states) if pn.states else states
        for s in noisy_names:
            if s not in states:
                raise FitError(f"process noise names unknown state '{s}'")
        self.noisy = np.array([s in noisy_names for s in states], bool)
        held = np.zeros(nx, bool)
        held[list(hold)] = True
        self.noisy &= ~held
        self.relaxed = np.zeros(nx, bool)
        self.pinned = np.zeros(nx, bool)
        self.det = np.broadcast_to(np.asarray(deterministic_std, float), (nx,)).copy()
        self.proc_floor = np.array([float(pn.floor.get(s, 0.0)) if self.noisy[i] else 0.0
                                    for i, s in enumerate(states)])
        self.fixed_G = None
        self._G_given = None
        self.proc_est_idx = np.zeros(0, int)
        self.offdiag = []
        init = []
        init_pd = []
        if fixed_G is not None:
            self._G_given = np.array(fixed_G, float).reshape(nx, nx)
            self.noisy = np.array([np.any(self._G_given[i] != 0) for i in range(nx)])
            self.fixed_G = self._fixed_factor()
        elif pn.estimate or relax:
            if not pn.estimate:  # process noise fixed in the spec: its stds stay fixed, on the diagonal
                self._fixed_spec_stds(pn, states)
            est = self.noisy.copy() if pn.estimate else np.zeros(nx, bool)
            degen = np.array([s in tuple(getattr(pn, "degenerate", ()) or ()) for s in states], bool)
            degen &= self.noisy if (pn.estimate and pn.structure == "full") else False
            if relax:
                self.relaxed = (~self.noisy & ~held) | degen
                est |= self.relaxed
            else:
                self.pinned = degen
                est &= ~degen
            self.proc_est_idx = np.nonzero(est)[0]
            for i in self.proc_est_idx:
                s0 = float(pn.std.get(states[i], 0.0) or 0.0)
                # no std in the spec: 1 coherent unit/√s above the floor (1 rad/s/√s for q in deg/s)
                v = math.log(s0 - self.proc_floor[i]) if s0 > self.proc_floor[i] else -math.log(sx[i])
                init.append(v)
                if not s0 > 0 and state_outputs and i in state_outputs:
                    dt = float(np.mean([float(r.dt) for r in records]))
                    sd = diff_scale(records, state_outputs[i].output) / abs(state_outputs[i].gain) / math.sqrt(dt)
                    if sd > self.proc_floor[i]:
                        v = math.log(sd - self.proc_floor[i])
                init_pd.append(v)
            if pn.structure == "full" and pn.estimate:
                idx = np.nonzero(self.noisy)[0]
                self.offdiag = [(int(a), int(b)) for ai, a in enumerate(idx) for b in idx[:ai]]
                init += [0.0] * len(self.offdiag)
                init_pd += [0.0] * len(self.offdiag)
        else:
            self._fixed_spec_stds(pn, states)
            self.fixed_G = np.diag(self.det)
        self.n_proc = len(init)
        # measurement
        specs = {m.output: m for m in model.measurement_noise}
        self.meas_floor = np.zeros(ny)
        self.meas_est = np.zeros(ny, bool)
        self.meas_fixed = np.ones(ny)
        minit = []
        minit_d = []
        for j, o in enumerate(model.output_names):
            sp = specs.get(o)
            est = True if sp is None else bool(sp.estimate)
            fl = "auto" if sp is None else sp.floor
            if fl == "auto":  # vsidgen.data.resolution, smallest non-zero value over the records
                res = [resolution(np.asarray(r.y, float)[:, j]) for r in records]
                fl = min([v for v in res if v > 0], default=0.0)
            self.meas_floor[j] = float(fl or 0.0)
            if fixed_R is not None:
                self.meas_fixed[j] = math.sqrt(float(np.asarray(fixed_R)[j, j]))
                continue
            if est:
                self.meas_est[j] = True
                s0 = None if sp is None else sp.std
                v = (math.log(s0 - self.meas_floor[j]) if s0 and s0 > self.meas_floor[j]
                     else -math.log(sy[j]))          # 1 coherent unit above the floor
                minit.append(v)
                if not s0:
                    sd = max(diff_scale(records, j) / math.sqrt(2.0), 2.0 * self.meas_floor[j])
                    if sd > self.meas_floor[j]:
                        v = math.log(sd - self.meas_floor[j])
                minit_d.append(v)
            else:
                if sp.std is None or not sp.std > 0:
                    raise FitError(f"measurement noise of output '{o}' is fixed but has no positive std")
                self.meas_fixed[j] = float(sp.std)
        self.meas_est_idx = np.nonzero(self.meas_est)[0]
        self.n_meas = len(minit)
        # starting points of the noise parameters (see FitOptions.noise_start)
        self.inits = {"data": np.array(init_pd + minit_d, float), "data-meas": np.array(init + minit_d, float),
                      "unit": np.array(init + minit, float)}
        self.init = self.inits["data"]
        self.n = self.n_proc + self.n_meas

    def _fixed_spec_stds(self, pn, states) -> None:
        """Process noise fixed in the spec: a state's positive std goes on the diagonal; without one it is deterministic."""
        for i, s in enumerate(states):
            v = float(pn.std.get(s, 0.0) or 0.0) if self.noisy[i] else 0.0
            if v > 0:
                self.det[i] = v
            else:
                self.noisy[i] = False

    def _fixed_factor(self):
        """Lower-triangular factor of the given Q = G Gᵀ with every zero pivot replaced by ``det``.

        Cholesky–Banachiewicz on the positive-semidefinite Q: a pivot
        ``d_i = Q_ii − Σ_{k<i} L_ik²`` that vanishes (≤ 1e-12·Q_ii: zero to rounding) marks a
        state whose noise is fully explained by the states before it — no noise at all (a zero
        row, deterministic) or a combination of earlier noise sources (``pinned``, a rank-deficient
        Q). Its column below the pivot is zero (exact for a PSD matrix) and its diagonal is
        ``det[i]``: the limit ``det → 0`` is the given Q.
        """
        Q = self._G_given @ self._G_given.T
        n = Q.shape[0]
        L = np.zeros_like(Q)
        self.pinned = np.zeros(n, bool)
        for i in range(n):
            d = Q[i, i] - float(L[i, :i] @ L[i, :i])
            if not d > 1e-12 * Q[i, i]:
                L[i, i] = self.det[i]
                self.pinned[i] = bool(self.noisy[i])
                continue
            L[i, i] = math.sqrt(d)
            for j in range(i + 1, n):
                L[j, i] = (Q[j, i] - float(L[j, :i] @ L[i, :i])) / L[i, i]
        return L

    @property
    def deterministic(self) -> np.ndarray:
        """Mask of the states whose diagonal std is the fixed ``det`` (driven to the limit ``det → 0``):
        those without process noise (in the spec, zero rows of a given G, or held) that are not
        relaxed, and the ``pinned`` degenerate ones (their row's off-diagonal noise remains)."""
        return (~self.noisy & ~self.relaxed) | self.pinned

    def set_deterministic_std(self, std) -> None:
        """Set the diagonal std of the deterministic states (one value per such state, state order)."""
        std = np.asarray(std, float)
        self.det[self.deterministic] = std
        if self._G_given is not None:
            self.fixed_G = self._fixed_factor()
        elif self.fixed_G is not None:
            self.fixed_G = np.diag(self.det)

    def static_key(self):
        return ("noise", self.fixed_G is None, tuple(self.proc_est_idx.tolist()), tuple(self.offdiag),
                tuple(self.meas_est_idx.tolist()), self.n_proc, self.n_meas)

    def arrays(self):
        """Numeric configuration passed to the jitted objective (so compiled code is shared)."""
        return {"det_std": self.det.copy(), "proc_floor": self.proc_floor,
                "fixed_G": self.fixed_G if self.fixed_G is not None else np.zeros((self.nx, self.nx)),
                "meas_floor": self.meas_floor, "meas_fixed": self.meas_fixed}

    def _g_structure(self):
        return (self.fixed_G is not None, tuple(int(i) for i in self.proc_est_idx),
                tuple((int(a), int(b)) for a, b in self.offdiag), int(self.n_proc))

    def G(self, w, c=None):
        """Lower-triangular factor used in the likelihood (Q = T G Gᵀ)."""
        c = self.arrays() if c is None else c
        return (_noise_G_jit if _concrete(w, c) else _noise_G)(w, c, self._g_structure())

    def sigma(self, w, c=None):
        c = self.arrays() if c is None else c
        st = (int(self.n_meas), int(self.n_proc), tuple(int(i) for i in self.meas_est_idx))
        return (_noise_sigma_jit if _concrete(w, c) else _noise_sigma)(w, c, st)

    def G_report(self, w):
        """G as reported: rows of states without process noise are zero."""
        G = np.array(self.G(jnp.asarray(w)))
        G[~self.noisy, :] = 0.0
        G[self.pinned, self.pinned] = 0.0
        return G



# --------------------------------------------------------------------------- curvature structure
# Primitives whose compositions are real-analytic where defined: a second derivative of such a
# function that vanishes at random points vanishes identically (with probability 1).
_SMOOTH_PRIMS = frozenset("""
add sub mul div neg exp exp2 log log1p expm1 sin cos tan asin acos atan atan2 sinh cosh tanh asinh
acosh atanh sqrt rsqrt cbrt pow integer_pow square logistic erf dot_general broadcast_in_dim reshape
concatenate squeeze expand_dims slice dynamic_slice dynamic_update_slice gather scatter scatter-add
scatter_add convert_element_type transpose reduce_sum iota copy copy_p pad rev cumsum stack split
""".split())


def _smooth_jaxpr(jaxpr) -> bool:
    """True if every primitive of the (closed) jaxpr, recursively, is in _SMOOTH_PRIMS (or a call wrapper)."""
    for eqn in jaxpr.eqns:
        subs = [v for v in eqn.params.values() if hasattr(v, "eqns") or hasattr(v, "jaxpr")]
        if subs and eqn.primitive.name in ("pjit", "jit", "closed_call", "core_call", "remat", "checkpoint"):
            if not all(_smooth_jaxpr(getattr(v, "jaxpr", v)) for v in subs):
                return False
            continue
        if eqn.primitive.name not in _SMOOTH_PRIMS:
            return False
    return True


#: primitives that only move elements (their structure is that of the numpy operation)
_MOVE_PRIMS = frozenset("slice squeeze reshape broadcast_in_dim concatenate stack transpose "
                        "expand_dims rev convert_element_type copy copy_p".split())
#: linear element-wise primitives
_LINEAR_PRIMS = frozenset("add add_any sub neg".split())
#: non-linear analytic primitives of one or two operands: every variable they depend on has
#: curvature in their result
_NONLINEAR_PRIMS = frozenset("""
exp exp2 log log1p expm1 sin cos tan asin acos atan sinh cosh tanh asinh acosh atanh sqrt
rsqrt cbrt square logistic erf pow atan2
""".split())
#: call wrappers whose sub-jaxpr is analysed in place
_CALL_PRIMS = frozenset("pjit jit closed_call core_call remat checkpoint custom_jvp_call "
                        "custom_vjp_call".split())


def _bits_move(name, params, ops, shape):
    """An element-moving primitive applied to object arrays of bit masks."""
    a = ops[0]
    if name == "slice":
        st = params.get("strides") or (1,) * a.ndim
        return a[tuple(slice(b, e, k) for b, e, k in zip(params["start_indices"],
                                                          params["limit_indices"], st))]
    if name == "squeeze":
        return np.squeeze(a, axis=tuple(params["dimensions"]))
    if name == "reshape":
        return np.reshape(a, shape)
    if name == "broadcast_in_dim":
        dims = tuple(params["broadcast_dimensions"])
        inter = [1] * len(shape)
        for d, k in zip(dims, a.shape):
            inter[d] = k
        return np.broadcast_to(np.reshape(a, inter), shape).copy()
    if name == "concatenate":
        return np.concatenate(ops, axis=params["dimension"])
    if name == "stack":
        return np.stack(ops, axis=params.get("axis", 0))
    if name == "transpose":
        return np.transpose(a, params["permutation"])
    if name == "expand_dims":
        return np.expand_dims(a, tuple(params["dimensions"]))
    if name == "rev":
        return np.flip(a, axis=tuple(params["dimensions"]))
    return a.copy()             # convert_element_type, copy


def _zeros_bits(shape):
    out = np.empty(shape, object)
    out.fill(0)
    return out


def _obj(x):
    """``x`` as an object array (an operation on 0-d object arrays returns a Python int)."""
    return np.asarray(x, dtype=object)


def _or_all(a) -> int:
    v = 0
    for x in np.asarray(a, object).ravel():
        v |= x
    return v


def _bits(x: int):
    """Indices of the set bits of ``x``."""
    while x:
        low = x & -x
        yield low.bit_length() - 1
        x ^= low


def _outer(a: int, b: int, na: int) -> int:
    """The symmetric pair mask {(i, j), (j, i): i ∈ a, j ∈ b}: bit i·na + j is pair (i, j)."""
    m = 0
    for i in _bits(a):
        m |= b << (i * na)
    for j in _bits(b):
        m |= a << (j * na)
    return m


def _jaxpr_curvature(jaxpr, ins, na: int):
    """Dependence and curvature masks of the outputs of ``jaxpr`` (see :func:`curvature_pairs`);
    ``ins``: one (dep, curv) pair of object arrays per input variable: dep a bit mask of the
    na variables, curv a mask of the pairs (bit i·na + j: ∂²/∂a_i∂a_j may be non-zero). None
    when a primitive has no rule."""
    from jax.extend.core import Literal

    env = {}

    def read(v):
        if isinstance(v, Literal):
            z = _zeros_bits(np.shape(v.val))
            return z, z
        if v not in env:            # constants of the jaxpr
            z = _zeros_bits(tuple(v.aval.shape))
            return z, z
        return env[v]

    def vec(fn):
        return np.vectorize(fn, otypes=[object])

    square = vec(lambda a: _outer(a, a, na))
    product = vec(lambda a, b: _outer(a, b, na) if (a and b) else 0)
    quotient = vec(lambda a, b: (_outer(a, b, na) | _outer(b, b, na)) if b else 0)

    for v, dc in zip(jaxpr.invars, ins):
        env[v] = dc
    for eqn in jaxpr.eqns:
        name = eqn.primitive.name
        ops = [read(v) for v in eqn.invars]
        shape = tuple(eqn.outvars[0].aval.shape) if eqn.outvars else ()
        if name in _CALL_PRIMS:
            sub = next((p for k, p in eqn.params.items()
                        if k in ("jaxpr", "call_jaxpr", "fun_jaxpr")), None)
            if sub is None:
                return None
            subj = getattr(sub, "jaxpr", sub)
            res = _jaxpr_curvature(subj, ops[len(ops) - len(subj.invars):], na)
            if res is None:
                return None
            for v, dc in zip(eqn.outvars, res):
                env[v] = dc
            continue
        if len(eqn.outvars) != 1:
            return None
        deps = [d for d, _ in ops]
        curvs = [c for _, c in ops]
        if name in _MOVE_PRIMS:
            d = _bits_move(name, eqn.params, deps, shape)
            c = _bits_move(name, eqn.params, curvs, shape)
        elif name in _LINEAR_PRIMS or name in ("mul", "div", "integer_pow") \
                or name in _NONLINEAR_PRIMS:
            bd = np.broadcast_arrays(*deps)
            bc = np.broadcast_arrays(*curvs)
            d = _zeros_bits(bd[0].shape)
            c = _zeros_bits(bd[0].shape)
            for x in bd:
                d = _obj(d | x)
            for x in bc:
                c = _obj(c | x)
            if name == "mul":       # (ab)'' = a''b + ab'' + a'b'ᵀ + b'a'ᵀ
                c = _obj(c | product(bd[0], bd[1]))
            elif name == "div":     # a/b adds a'b'ᵀ (both ways) and b'b'ᵀ
                c = _obj(c | quotient(bd[0], bd[1]))
            elif name == "integer_pow":
                y = int(eqn.params["y"])
                if y == 0:
                    d = c = _zeros_bits(d.shape)
                elif y != 1:
                    c = _obj(c | square(d))
            elif name in _NONLINEAR_PRIMS:  # g(a)'' = g'' a'a'ᵀ + g' a''
                c = _obj(c | square(d))
            d = np.broadcast_to(d, shape).copy()
            c = np.broadcast_to(c, shape).copy()
        elif name == "iota":
            d, c = _zeros_bits(shape), _zeros_bits(shape)
        elif name == "reduce_sum":
            axes = tuple(eqn.params["axes"])
            d = np.bitwise_or.reduce(deps[0], axis=axes) if axes else deps[0]
            c = np.bitwise_or.reduce(curvs[0], axis=axes) if axes else curvs[0]
            d, c = _obj(d).reshape(shape), _obj(c).reshape(shape)
        elif name == "dot_general":
            da, db = _or_all(deps[0]), _or_all(deps[1])
            cv = _or_all(curvs[0]) | _or_all(curvs[1]) | (_outer(da, db, na) if (da and db) else 0)
            d, c = _zeros_bits(shape), _zeros_bits(shape)
            d.fill(da | db)
            c.fill(cv)
        else:
            return None
        env[eqn.outvars[0]] = (d, c)
    return [read(v) for v in jaxpr.outvars]


def curvature_pairs(fn, na: int, nu: int):
    """Which second derivatives ∂²fn/∂a_i∂a_j of ``fn(a, u)`` may be non-zero: an (na, na)
    boolean matrix, symmetric (None: unknown, treat all as non-zero).

    Found structurally on the jaxpr of ``fn``, without compiling anything: every value
    carries the set of variables it depends on (dep) and the set of variable pairs of its
    Hessian that may be non-zero (curv). A linear primitive unites them; ``a·b`` adds
    dep(a) × dep(b) (both orders) when both depend on variables, ``a/b`` that and
    dep(b) × dep(b); an analytic non-linear primitive (exp, sin, integer powers, ...) adds
    dep × dep; a matrix product adds the product of its operands' whole dep sets;
    element-moving primitives move the sets like the elements. The result contains every
    non-zero pair (a superset where terms cancel exactly or a matrix product mixes
    elements). A primitive without a rule (comparisons, select, abs, custom rules, ...) gives
    None.
    """
    try:
        jx = jax.make_jaxpr(fn)(jnp.zeros(na), jnp.zeros(nu))
    except Exception:  # pragma: no cover - defensive: keep the general path
        return None
    if not _smooth_jaxpr(jx.jaxpr):
        return None
    dep_a = np.empty(na, object)
    for i in range(na):
        dep_a[i] = 1 << i
    res = _jaxpr_curvature(jx.jaxpr, [(dep_a, _zeros_bits(na)),
                                      (_zeros_bits(nu), _zeros_bits(nu))], na)
    if res is None:
        return None
    mask = 0
    for _, c in res:
        mask |= _or_all(c)
    S = np.zeros((na, na), bool)
    for b in _bits(mask):
        S[b // na, b % na] = True
    return S


def curvature_vars(fn, na: int, nu: int):
    """Indices of the arguments a of ``fn(a, u)`` that enter its second derivatives (None: all).

    Used to restrict the model curvature K = ∇²_a(λ·fn) to the variables that actually have
    curvature (e.g. the state–parameter products of a model linear in the states): the rows of
    :func:`curvature_pairs` with a non-zero pair (structural, nothing compiled; a superset only
    where terms cancel exactly).
    """
    S = curvature_pairs(fn, na, nu)
    return None if S is None else np.nonzero(S.any(axis=0))[0]


def hessian_cover(S) -> np.ndarray:
    """Indices C of a vertex cover of the Hessian pattern S (every non-zero pair (i, j) has i or
    j in C; every i with S[i, i] is in C): the Hessian is then exact from its columns C alone
    (the other entries by symmetry or structurally zero). Greedy: the diagonal first, then
    the variable covering most of the pairs left (the lowest index on ties)."""
    S = np.array(S, bool)
    S = S | S.T
    cover = set(np.nonzero(np.diag(S))[0].tolist())
    left = S.copy()
    for i in cover:
        left[i, :] = left[:, i] = False
    while left.any():
        i = int(np.argmax(left.sum(axis=0)))
        cover.add(i)
        left[i, :] = left[:, i] = False
    return np.array(sorted(cover), int)


# --------------------------------------------------------------------------- objective
#: how the Hessian assembly forms ∂F/∂(x, θ) and ∂h/∂(x, θ) at every sigma point: "autodiff"
#: (jax.jacfwd through the generated drift/output) or "generated" (Transition.jacobian, the
#: chain rule through the generated f_x, f_p; Model.output_jacobian). autodiff: as fast to run,
#: faster to compile on HFB-320, fits bit-identical to before (docs/performance.md)
POINT_JACOBIANS = "autodiff"

#: XLA options of the objective's jitted functions on the CPU backend. XLA-CPU's default MLIR
#: fusion emitters spend 1.4-1.8x the backend compile time of its elemental IR emitters on the
#: Hessian-block assembly (~500 small kernels for HFB-320, each compiled by LLVM), with the same
#: run time; the blocks are bit-identical at the start point and fitted ELBOs agree to ~1e-12
#: relative (docs/performance.md, ``benchmarks/bench_compile.py --options``).
CPU_COMPILER_OPTIONS = {"xla_cpu_use_fusion_emitters": False}

#: pairs / nodes per vmapped chunk of the Hessian assembly on the CPU: memory is one chunk of
#: per-point blocks, and a cache-sized chunk is faster than a large one (docs/performance.md)
ASSEMBLY_CHUNK = 512
#: the same on an accelerator, where each chunk is a sequence of kernel launches: few large
#: chunks (docs/gpu.md)
ASSEMBLY_CHUNK_ACCELERATOR = 16384


def assembly_chunk() -> int:
    """:data:`ASSEMBLY_CHUNK` on the CPU backend, :data:`ASSEMBLY_CHUNK_ACCELERATOR` elsewhere."""
    return ASSEMBLY_CHUNK if jax.default_backend() == "cpu" else ASSEMBLY_CHUNK_ACCELERATOR


def compiler_options() -> dict | None:
    """:data:`CPU_COMPILER_OPTIONS` when JAX's default backend is the CPU, else None (XLA defaults).

    Only the options this jaxlib's XLA knows are passed (:func:`supported_compiler_options`):
    XLA drops and renames its debug options between releases (jaxlib 0.11.2 refuses
    ``xla_cpu_use_fusion_emitters`` with "No such compile option"), and an unknown option
    makes every compilation fail."""
    if jax.default_backend() != "cpu" or not CPU_COMPILER_OPTIONS:
        return None
    return dict(supported_compiler_options(tuple(sorted(CPU_COMPILER_OPTIONS.items())))) or None


@functools.lru_cache(maxsize=None)
def supported_compiler_options(items: tuple) -> dict:
    """The options of ``items`` ((name, value) pairs) that XLA accepts on the default backend,
    each tried on a one-operation function (compiled once per option and process)."""
    out = {}
    for name, value in items:
        try:
            jax.jit(lambda x: x + 1.0).lower(np.float64(0.0)).compile(compiler_options={name: value})
        except Exception as e:  # XLA reports an unknown option as INVALID_ARGUMENT
            if "compile option" not in str(e):
                raise
            continue
        out[name] = value
    return out


class Objective:
    """Negative ELBO pieces for one problem (model + options); jitted per record shape."""

    def __init__(self, model, theta_map: ThetaMap, noise_map: NoiseMap, F, *,
                 store_key: str | None = None):
        self.model = model
        self.tm = theta_map
        self.nm = noise_map
        self.F = F
        self.point_jacobians = POINT_JACOBIANS
        n = model.nx
        self.n = n
        self.nl = n * (n - 1) // 2
        self.nq = n + self.nl + n * n
        self.ng = theta_map.n_free + noise_map.n
        self.nb = self.nq + self.ng
        self._tril = np.tril_indices(n, -1)
        self.chunk = assembly_chunk()
        self.parallel_solve = use_parallel_solve()
        na = n + model.np
        nu = F.step_width(model.nu) if hasattr(F, "step_width") else model.nu
        # which second derivatives of F and h over a = (x, θ) may be non-zero (None: all;
        # see curvature_pairs)
        self.curv_F, self.curv_h = self._curvature_structure(na, nu)
        self.traces = collections.Counter()  # jit traces per function (each trace is a compilation)
        opts = compiler_options()
        key = self._store_key(store_key)
        if key is None:
            self._blocks = jax.jit(self._blocks_impl, compiler_options=opts)
            self._value = jax.jit(self._value_impl, compiler_options=opts)
            self._factor = jax.jit(self._factor_impl, compiler_options=opts)
            self._back = jax.jit(self._back_impl, compiler_options=opts)
        else:       # traced programs kept on disk (vsidgen.compilecache.StoredJit)
            from ..compilecache import StoredJit

            self._blocks = StoredJit(self._blocks_impl, key=key + "|blocks", compiler_options=opts)
            self._value = StoredJit(self._value_impl, key=key + "|value", compiler_options=opts)
            self._factor = StoredJit(self._factor_impl, key=key + "|factor", compiler_options=opts)
            self._back = StoredJit(self._back_impl, key=key + "|back", compiler_options=opts)

    def _store_key(self, model_key: str | None) -> str | None:
        """The key of this objective's stored traced programs (:class:`StoredJit`): the
        model's generated code (``model_key``, :func:`generated_model_key`) and everything
        else the trace reads — the transition's setting, the maps' structure, the
        curvature patterns, the assembly settings and the estimator modules' constants —
        or None (nothing stored) without a model key, for a subclass, or when the
        persistent cache is off."""
        from ..compilecache import exported_dir

        if model_key is None or type(self) is not Objective or exported_dir() is None:
            return None
        F = self.F
        parts = (model_key, getattr(F, "key", None), getattr(F, "jac", None) is None,
                 self.point_jacobians, self.chunk, self.parallel_solve,
                 self.tm.static_key(), self.nm.static_key(),
                 None if self.curv_F is None else np.asarray(self.curv_F).tobytes(),
                 None if self.curv_h is None else np.asarray(self.curv_h).tobytes(),
                 _module_constants())
        return repr(parts)

    def _curvature_structure(self, na: int, nu: int):
        """(curv_F, curv_h): the Hessian patterns of F and h over a = (x, θ) (:func:`curvature_pairs`)."""
        n, F, h = self.n, self.F, self.model.output
        return (curvature_pairs(lambda a, u: F(a[:n], u, a[n:], 0.05), na, nu),
                curvature_pairs(lambda a, u: h(a[:n], u, a[n:]), na, nu))

    # -- the model functions (one model; :class:`SwitchedObjective` selects one of several by ``cfg``)
    def transition_of(self, cfg):
        """The transition F(x, v, θ, dt) evaluated under the configuration ``cfg``."""
        return self.F

    def output_of(self, cfg):
        """The output function h(x, u, θ) evaluated under the configuration ``cfg``."""
        return self.model.output

    # -- unpacking
    def unpack_s(self, s, cfg):
        nt = self.tm.n_free
        theta = self.tm.theta(s[:nt], cfg["theta"])
        w = s[nt:]
        return theta, self.nm.G(w, cfg["noise"]), self.nm.sigma(w, cfg["noise"])

    def cov_factors(self, r):
        """(Sc, C, Sm, d) of the assumed density's parameters r (:func:`cov_factors_of`)."""
        return (_cov_factors_jit if _concrete(r) else cov_factors_of)(r, self.n)

    # -- local terms (negative expected log densities)
    def pair_offsets(self, r):
        """Sigma-point offsets (4n, n) of x_k and x_{k+1} for the pair density.

        The last 2n points move x_{k+1} only (z₁ = 0): their x_k is the mean μ_k exactly, for
        every r, which the Hessian assembly uses (:meth:`_pair_term`)."""
        n = self.n
        Sc, C, Sm, _ = self.cov_factors(r)
        a = math.sqrt(2 * n)
        Z = jnp.zeros((n, n))
        dx0 = jnp.concatenate([a * Sm.T, -a * Sm.T, Z, Z])
        dx1 = jnp.concatenate([a * C.T, -a * C.T, a * Sc.T, -a * Sc.T])
        return dx0, dx1

    def node_offsets(self, r):
        """Sigma-point offsets (2n, n) of the marginal density."""
        n = self.n
        _, _, Sm, _ = self.cov_factors(r)
        a = math.sqrt(n)
        return jnp.concatenate([a * Sm.T, -a * Sm.T])

    @staticmethod
    def pair_from_F(X1, Fx, G, dt):
        """−E log N(x_{k+1}; F(x_k), Q) given the sigma points X1 and their transitions Fx (4n, n)."""
        n = X1.shape[1]
        Lq = jnp.sqrt(dt) * G
        res = tri_solve_small(Lq, (X1 - Fx).T)  # (n, 4n)
        quad = jnp.mean(jnp.sum(res ** 2, axis=0))
        logdet = 2.0 * jnp.sum(jnp.log(jnp.abs(jnp.diagonal(Lq))))
        return 0.5 * quad + 0.5 * logdet + 0.5 * n * LOG2PI

    @staticmethod
    def node_from_H(H, y, m, sig):
        """−E log N_mask(y; h(x), R) given the outputs H (2n, ny) at the sigma points."""
        e = (y - H) / sig
        per = 0.5 * jnp.mean(e ** 2, axis=0) + jnp.log(sig) + 0.5 * LOG2PI
        return jnp.sum(m * per)

    @staticmethod
    def _lin_eval(X, theta, lin):
        """First-order model f* + J* (a − a*) at the sigma points, a = (x, θ)."""
        Xs, fs, Js, ths = lin
        da = jnp.concatenate([X - Xs, jnp.broadcast_to(theta - ths, (X.shape[0], ths.shape[0]))], axis=1)
        return fs + jnp.einsum("ija,ia->ij", Js, da)

    def pair_nll(self, mu0, mu1, r, s, u0, dt, cfg, lin=None):
        """Pair term; ``u0``: the step input of the transition (u_k, or (u_k, u_{k+1}) with a
        first-order hold; :func:`step_inputs`); with ``lin`` = (X0*, F*, J*, θ*) F is replaced
        by its linearisation (see blocks)."""
        theta, G, _ = self.unpack_s(s, cfg)
        dx0, dx1 = self.pair_offsets(r)
        X0 = mu0 + dx0
        X1 = mu1 + dx1
        if lin is None:
            F = self.transition_of(cfg)
            Fx = jax.vmap(lambda x: F(x, u0, theta, dt))(X0)
        else:
            Fx = self._lin_eval(X0, theta, lin)
        return self.pair_from_F(X1, Fx, G, dt)

    def node_nll(self, mu, r, s, u, y, m, cfg, lin=None):
        theta, _, sig = self.unpack_s(s, cfg)
        X = mu + self.node_offsets(r)
        if lin is None:
            h = self.output_of(cfg)
            H = jax.vmap(lambda x: h(x, u, theta))(X)  # (2n, ny)
        else:
            H = self._lin_eval(X, theta, lin)
        return self.node_from_H(H, y, m, sig)

    def neg_entropy(self, r, N):
        """−H[q] for N samples (N may be a traced scalar: the true length of a padded record)."""
        _, _, Sm, d = self.cov_factors(r)
        n = self.n
        H = (jnp.sum(jnp.log(jnp.diagonal(Sm))) + 0.5 * (N - 1) * jnp.sum(d)
             + 0.5 * N * n * (1.0 + LOG2PI))
        return -H

    # -- record objective
    def _value_impl(self, mu, r, s, data, cfg):
        """Negative ELBO of one record; padded samples (see :func:`record_data`) contribute nothing."""
        self.traces["value"] += 1  # Python side effect: runs once per trace (tests count recompilations)
        u, y, m, dt, wp, wn, nt = data
        vp = jax.vmap(self.pair_nll, in_axes=(0, 0, None, None, 0, None, None))(
            mu[:-1], mu[1:], r, s, step_inputs(self.F, u), dt, cfg)
        vn = jax.vmap(self.node_nll, in_axes=(0, None, None, 0, 0, 0, None))(mu, r, s, u, y, m, cfg)
        return (jnp.sum(jnp.where(wp > 0, vp, 0.0)) + jnp.sum(jnp.where(wn > 0, vn, 0.0))
                + self.neg_entropy(r, nt))

    def value(self, mu, r, s, data, cfg):
        return self._value(mu, r, s, data, cfg)

    def _blocks_impl(self, mu, r, s, data, cfg):
        """Value, gradient and structured Hessian blocks of one record's negative ELBO (exact).

        Sigma-point assembly instead of nested autodiff of the whole pair term.
        Write the border b = (r, s) and, per sigma point i of pair k,
        z_i = (x_k,i, x_{k+1},i, θ) = (μ_k + δ0_i(r), μ_{k+1} + δ1_i(r), θ(s)). The pair
        term is c Σ_i ½ e_iᵀ P(b) e_i + const(b), e_i = x_{k+1},i − F(x_k,i, θ), c = 1/(4n),
        P = Q⁻¹. Its exact Hessian is

        * z–z per point: c ĴᵢᵀPĴᵢ + K_i, Ĵ_i = [J_x, −I, J_θ] (model Jacobian at the point),
          K_i = ∇²_(x,θ)(λ_i·F), λ_i = −c P e_i (the only second derivative of the model,
          in the (n + n_θ)-dimensional space of one sigma point);
        * z–b through P: −c Ĵᵢᵀ (∂P/∂b) e_i;
        * b–b: Σ_i A_iᵀ (Σ_k H_k,i) A_i (A_i = ∂z_i/∂b, shared by all pairs) + the
          Hessian of the shared function ½ tr(P(b) S) + (N−1) ½ log det Q(b),
          S = c Σ_k,i e eᵀ, + ∇²_b (Σ_k,i ∇_z ψ · z_i(b)) (curvature of the lifting).

        Cost-saving structure (all exact): K_i is formed only over the variables with model
        curvature (:func:`curvature_pairs`, e.g. the θ–x products of a model linear in x;
        skipped when there are none, as for linear outputs), from the columns of a vertex
        cover of its Hessian pattern (the states of a model linear in θ), the other entries
        by symmetry; ∂P/∂b and ∂σ/∂b are non-zero only
        in the process / measurement noise columns of b, so the coupling terms are formed in
        those columns only; the θ rows of A_i are the same for all points, so the per-pair
        θ-coupling is summed over the points first and multiplied by ∂θ/∂b once per record.

        The node (measurement) term is assembled the same way with h, σ(b) and
        Σ_j ½ Se_j/σ_j² + M_j log σ_j as the shared function. Pairs and nodes are
        processed in chunks (lax.scan) that accumulate the border sums, so memory is
        O(N n n_b) for W plus one chunk of per-point blocks. Tests compare the
        result with jax.hessian of the flat objective.
        """
        self.traces["blocks"] += 1
        u, y, m, dt, wp, wn, n_true = data
        N = mu.shape[0]  # N: padded length; n_true: number of real samples (traced)
        c = self._point_context(r, s, cfg, dt)
        pa, pr = self._chunked(functools.partial(self._pair_term, c), [mu[:-1], mu[1:], step_inputs(self.F, u)],
                               N - 1, wp)
        na, nr = self._chunked(functools.partial(self._node_term, c), [mu, u, y, m], N, wn)
        return self._border_assembly(c, pa, pr, na, nr, wn, n_true, cfg, dt)

    def _lift(self, bb, cfg, dt):
        """Border b → the sigma-point offsets of the pair and node densities, θ, σ and P = Q⁻¹."""
        n, nq = self.n, self.nq
        th, G, sig = self.unpack_s(bb[nq:], cfg)
        d0, d1 = self.pair_offsets(bb[:nq])
        dn = self.node_offsets(bb[:nq])
        Li = tri_solve_small(jnp.sqrt(dt) * G, jnp.eye(n))
        return d0, d1, dn, th, sig, Li.T @ Li

    def _point_context(self, r, s, cfg, dt) -> dict:
        """What every pair and node term shares: the lifted border and its Jacobian ∂z_i/∂b, the model
        functions and their Jacobians at a point, the curvature functions and the noise columns of b."""
        n = self.n
        npar = self.model.np
        nq = self.nq
        nz = 2 * n + npar
        b = jnp.concatenate([r, s])

        def lift(bb):
            return self._lift(bb, cfg, dt)

        d0, d1, dn, theta, sig, P = lift(b)
        Jd0, Jd1, Jdn, Jth, Jsig, JP = jax.jacfwd(lift)(b)
        Az = jnp.concatenate([Jd0, Jd1, jnp.broadcast_to(Jth, (4 * n,) + Jth.shape)], axis=1)  # (4n, nz, nb)
        An = jnp.concatenate([Jdn, jnp.broadcast_to(Jth, (2 * n,) + Jth.shape)], axis=1)  # (2n, n+np, nb)

        F_fn, h_fn = self.transition_of(cfg), self.output_of(cfg)

        def Fa(a, uk):
            return F_fn(a[:n], uk, a[n:], dt)

        def ha(a, uk):
            return h_fn(a[:n], uk, a[n:])

        if self.point_jacobians == "generated":
            def F_jac(a, uk):  # chain rule through the generated f_x, f_p
                Jx, Jp = self.F.jacobian(a[:n], uk, a[n:], dt)
                return jnp.concatenate([Jx, Jp], axis=1)

            def h_jac(a, uk):  # the generated h_x, h_p
                Hx, _, Hp = self.model.output_jacobian(a[:n], uk, a[n:])
                return jnp.concatenate([Hx, Hp], axis=1)
        else:
            F_jac = jax.jacfwd(Fa)
            h_jac = jax.jacfwd(ha)
        nza = n + npar
        nt = self.tm.n_free
        nb = self.nb
        # border columns through which P (process noise) and σ (measurement noise) depend on b
        pcols = nq + nt + np.arange(self.nm.n_proc if self.nm.fixed_G is None else 0)
        scols = nq + nt + self.nm.n_proc + np.arange(self.nm.n_meas)
        Ep = jnp.asarray(np.eye(nb)[pcols])  # (npc, nb) selection
        Es = jnp.asarray(np.eye(nb)[scols])
        return dict(
            n=n, npar=npar, nz=nz, nza=nza, b=b, lift=lift,
            d0=d0, d1=d1, dn=dn, theta=theta, sig=sig, P=P, Jth=Jth, Az=Az, An=An,
            Fa=Fa, ha=ha, F_jac=F_jac, h_jac=h_jac, Ep=Ep, Es=Es,
            JPc=JP[:, :, pcols],  # (n, n, npc)
            Jsigc=Jsig[:, scols],  # (ny, nsc)
            Ar=jnp.concatenate([Jd0, Jd1], axis=1)[:, :, :nq],  # (4n, 2n, nq): ∂(x_k, x_k+1)/∂r
            Arn=Jdn[:, :, :nq],  # (2n, n, nq)
            K_F=self._curvature(Fa, self.curv_F, nza),
            T_F=self._curvature_tensor(Fa, self.curv_F, nza),
            K_h=self._curvature(ha, self.curv_h, nza),
            cp=1.0 / (4 * n), cn=1.0 / (2 * n))

    @staticmethod
    def _restricted(S, na):
        """(kv, select, place, columns) for second derivatives over the variables with
        curvature only, or None when there are none. ``S``: the Hessian pattern over
        a = (x, θ) (:func:`curvature_pairs`; None: all pairs). kv: the variables of a with a
        non-zero pair; ``select(fun)`` is ``g(av, a, …) = fun(a with its kv entries replaced
        by av, …)`` (differentiate g in av); ``columns``: the positions in kv of a vertex cover
        of the pattern (:func:`hessian_cover`), None when it is all of kv; ``place(M)`` puts
        the trailing axes of M into a-space (zero outside kv; one gather): M is (…, nv, nv) a
        Hessian over kv, or with ``columns`` (…, nc, nv) its columns there — the other
        entries are taken by symmetry or are structurally zero."""
        S = np.ones((na, na), bool) if S is None else np.asarray(S, bool)
        S = S | S.T
        kv = np.nonzero(S.any(axis=0))[0]
        if len(kv) == 0:
            return None
        nv = len(kv)
        cols = hessian_cover(S[np.ix_(kv, kv)])
        cols = None if len(cols) == nv else cols
        Esel = jnp.asarray(np.eye(na)[kv])  # (nv, na)
        keep = jnp.asarray(np.isin(np.arange(na), kv, invert=True).astype(float))
        pos = np.full(na, -1, int)  # a-index -> position in kv
        pos[kv] = np.arange(nv)
        if cols is None:
            full = bool(np.array_equal(kv, np.arange(na)))
            zero, idx = nv * nv, None
            if not full:
                idx = np.full((na, na), zero, int)
                idx[np.ix_(kv, kv)] = (np.arange(nv)[:, None] * nv + np.arange(nv)[None, :])
        else:
            cpos = np.full(nv, -1, int)  # kv position -> column number
            cpos[cols] = np.arange(len(cols))
            zero = len(cols) * nv
            idx = np.full((na, na), zero, int)
            for i in kv:
                for j in kv:
                    pi, pj = pos[i], pos[j]
                    if cpos[pj] >= 0:
                        idx[i, j] = cpos[pj] * nv + pi
                    elif cpos[pi] >= 0:
                        idx[i, j] = cpos[pi] * nv + pj
                    elif S[i, j]:  # pragma: no cover - the cover guarantees it
                        raise AssertionError("Hessian cover misses a pair")

        def select(fun):
            return lambda av, a, *rest: fun(a * keep + av @ Esel, *rest)

        def place(M):
            if idx is None:  # every variable, in order: already a-space
                return M
            flat = M.reshape(M.shape[:-2] + (-1,))
            flat = jnp.concatenate([flat, jnp.zeros(flat.shape[:-1] + (1,), flat.dtype)], axis=-1)
            return flat[..., idx]
        return kv, select, place, cols

    @staticmethod
    def _columns(jac, cols, nv):
        """Forward-over-reverse columns ``cols`` of the derivative of ``jac`` (a function of av
        and further arguments, with outputs (…, nv)): (len(cols), …, nv); with cols None the
        whole Jacobian in jax.hessian's layout (…, nv, nv)."""
        if cols is None:
            return jax.jacfwd(jac)
        E = jnp.asarray(np.eye(nv)[cols])

        def columns(av, *rest):
            return jax.vmap(lambda v: jax.jvp(lambda x: jac(x, *rest), (av,), (v,))[1])(E)
        return columns

    @staticmethod
    def _curvature(fun, S, na):
        """Per-point curvature K = ∇²_a(λ·fun) over a = (x, θ), zero outside the variables with
        curvature (Hessian pattern ``S``, :func:`curvature_pairs`).

        Returns ``K(A, lam, u)`` for a chunk: A (K, P, na) points, lam (K, P, nout) multipliers,
        u (K, …) the items' inputs; result (K, P, na, na). Only the columns of a vertex cover
        of the pattern are differentiated (forward-over-reverse), the rest placed by symmetry:
        exact, with as many forward passes as the cover has variables (e.g. the states of a
        model linear in its parameters, instead of states and parameters)."""
        r = Objective._restricted(S, na)
        if r is None:
            return None
        kv, select, place, cols = r
        g = select(fun)
        hes = Objective._columns(jax.grad(lambda av, a, lam, uk: jnp.dot(lam, g(av, a, uk))), cols, len(kv))

        def K(A, lam, u):
            per_item = jax.vmap(hes, (0, 0, 0, None))
            return place(jax.vmap(per_item, (0, 0, 0, 0))(A[..., kv], A, lam, u))
        return K

    @staticmethod
    def _curvature_tensor(fun, S, na):
        """Second derivatives ∇²_a fun_j of every output j (zero outside the variables with
        curvature; only the columns of a cover differentiated, as in :meth:`_curvature`).

        Returns ``T(A, u)`` for a chunk: A (K, na) one point per item, u (K, …); result
        (K, nout, na, na). K(λ) of :meth:`_curvature` is Σ_j λ_j T_j at that point."""
        r = Objective._restricted(S, na)
        if r is None:
            return None
        kv, select, place, cols = r
        hes = Objective._columns(jax.jacrev(select(fun)), cols, len(kv))

        def T(A, u):
            H = jax.vmap(hes, (0, 0, 0))(A[..., kv], A, u)  # (K, nout, nv, nv) or (K, nc, nout, nv)
            return place(H if cols is None else jnp.swapaxes(H, 1, 2))
        return T

    @staticmethod
    def _points(fn, A, u):
        """``fn(a, u_k)`` at every point of every item of a chunk: A (K, P, na), u (K, …)."""
        return jax.vmap(jax.vmap(fn, (0, None)), (0, 0))(A, u)

    @staticmethod
    def _pair_term(c, mu0, mu1, uk, wk):
        """One chunk of pairs (leading axis k): per pair the blocks D (rows μ_k, μ_{k+1}), B,
        the border couplings (r, θ and noise parts) and the gradient; keys 's…' are the
        per-point pieces summed over the chunk's pairs for the border.

        Per sigma point i of pair k, with Ĵ = [J_x, −I, J_θ] and c_k = w_k/(4n):
        H_ki = c_k ĴᵀPĴ + K_ki (K only in the x_k, θ rows and columns), g_ki = −c_k ĴᵀPe,
        C_ki = −c_k Ĵᵀ(∂P/∂b)e. The sums the border needs (over k, per point) and the
        per-pair blocks (over the points) are contracted directly from the factors, never
        forming a per-point, per-pair H."""
        n, npar, P, cp = c["n"], c["npar"], c["P"], c["cp"]
        n2 = 2 * n
        X0 = mu0[:, None, :] + c["d0"][None]  # (K, 4n, n)
        X1 = mu1[:, None, :] + c["d1"][None]
        K_, npt = X0.shape[0], X0.shape[1]
        A0 = jnp.concatenate([X0, jnp.broadcast_to(c["theta"], (K_, npt, npar))], axis=2)
        # points 2n.. sit at x_k = μ_k (pair_offsets): the model and its derivatives are
        # evaluated once there, at the centre Ac
        Ao = A0[:, :n2]
        Ac = jnp.concatenate([mu0, jnp.broadcast_to(c["theta"], (K_, npar))], axis=1)
        Aoc = jnp.concatenate([Ao, Ac[:, None]], axis=1)  # one evaluation (one compiled copy)
        Foc = Objective._points(c["Fa"], Aoc, uk)  # (K, 2n+1, n)
        Joc = Objective._points(c["F_jac"], Aoc, uk)  # (K, 2n+1, n, n+np)
        Fo, Fc, Jo, Jc = Foc[:, :n2], Foc[:, n2], Joc[:, :n2], Joc[:, n2]
        Fs = jnp.concatenate([Fo, jnp.broadcast_to(Fc[:, None], (K_, npt - n2, n))], axis=1)
        J = jnp.concatenate([Jo, jnp.broadcast_to(Jc[:, None], (K_, npt - n2) + Jc.shape[1:])], axis=1)
        e = X1 - Fs
        Pe = e @ P
        cw = cp * wk  # (K,)
        Jh = jnp.concatenate([J[..., :n], jnp.broadcast_to(-jnp.eye(n), (K_, npt, n, n)), J[..., n:]],
                             axis=3)  # (K, 4n, n, nz)
        PJ = jnp.einsum("ab,kibw->kiaw", P, Jh)
        cJ = Jh * cw[:, None, None, None]
        cJm = cJ[..., :n2]  # rows μ_k, μ_{k+1}
        Hm = jnp.einsum("kiaz,kiaw->kzw", cJm, PJ)  # (K, 2n, nz): Σ_i H_ki rows μ
        HAr = jnp.einsum("kiaz,kiab->kzb", cJm, jnp.einsum("kiaw,iwb->kiab", PJ[..., :n2], c["Ar"]))
        sHz = jnp.einsum("kiaz,kiaw->izw", cJ, PJ)  # (4n, nz, nz)
        gz = -jnp.einsum("kiaz,kia->kiz", cJ, Pe)
        JPe = jnp.einsum("abl,kib->kial", c["JPc"], e)  # (K, 4n, n, npc)
        sCz = -jnp.einsum("kiaz,kial->izl", cJ, JPe)
        Cs = -jnp.einsum("kiaz,kial->kzl", cJm, JPe)
        if c["K_F"] is not None:
            lam = -cw[:, None, None] * Pe  # (K, 4n, n)
            Ko = c["K_F"](Ao, lam[:, :n2], uk)  # (K, 2n, na, na), a = (x_k, θ)
            Tc = c["T_F"](Ac, uk)  # (K, n, na, na) at the centre
            sKa = jnp.concatenate([jnp.sum(Ko, 0), jnp.einsum("kia,kavw->ivw", lam[:, n2:], Tc)])
            Z1 = jnp.zeros((npt, n, n + npar))
            Kz = jnp.concatenate([sKa[:, :n], Z1, sKa[:, n:]], axis=1)  # rows into z
            Z2 = jnp.zeros((npt, n2 + npar, n))
            sHz = sHz + jnp.concatenate([Kz[:, :, :n], Z2, Kz[:, :, n:]], axis=2)
            Kx = (jnp.sum(Ko[:, :, :n, :], 1)
                  + jnp.einsum("ka,kavw->kvw", jnp.sum(lam[:, n2:], 1), Tc[:, :, :n, :]))  # (K, n, na)
            Kx_z = jnp.concatenate([Kx[:, :, :n], jnp.zeros((K_, n, n)), Kx[:, :, n:]], axis=2)
            Hm = Hm.at[:, :n, :].add(Kx_z)
            # ∂x_k/∂r is 0 at the centre points: only the others couple the curvature to r
            HAr = HAr.at[:, :n, :].add(jnp.einsum("kivw,iwb->kvb", Ko[:, :, :n, :n], c["Ar"][:n2, :n, :]))
        return dict(D0=Hm[:, :n, :n], D1=Hm[:, n:, n:n2], B=Hm[:, :n, n:n2], Wr0=HAr[:, :n],
                    Wr1=HAr[:, n:], Wt0=Hm[:, :n, n2:], Wt1=Hm[:, n:, n2:], Wc0=Cs[:, :n],
                    Wc1=Cs[:, n:], g0=jnp.sum(gz[:, :, :n], 1), g1=jnp.sum(gz[:, :, n:n2], 1),
                    sHz=sHz, sCz=sCz, sgz=jnp.sum(gz, 0),
                    sS=jnp.einsum("k,kia,kib->ab", cw, e, e))

    @staticmethod
    def _node_term(c, muk, uk, yk, mk, wk):
        """One chunk of nodes (leading axis k): D (row μ_k), its border couplings and gradient;
        keys 's…' summed over the chunk for the border (contracted as in :meth:`_pair_term`)."""
        n, npar, sig, cn = c["n"], c["npar"], c["sig"], c["cn"]
        X = muk[:, None, :] + c["dn"][None]  # (K, 2n, n)
        K_, npt = X.shape[0], X.shape[1]
        A = jnp.concatenate([X, jnp.broadcast_to(c["theta"], (K_, npt, npar))], axis=2)
        Hx = Objective._points(c["ha"], A, uk)  # (K, 2n, ny)
        J = Objective._points(c["h_jac"], A, uk)  # (K, 2n, ny, n+np)
        mw = mk * wk[:, None]  # (K, ny)
        e = yk[:, None, :] - Hx
        iv = mw / sig ** 2
        cJ = cn * J
        Jw = J * iv[:, None, :, None]
        cJx = cJ[..., :n]
        Hm = jnp.einsum("kiaz,kiaw->kzw", cJx, Jw)  # (K, n, na)
        HAr = jnp.einsum("kiaz,kiab->kzb", cJx, jnp.einsum("kiaw,iwb->kiab", Jw[..., :n], c["Arn"]))
        sHz = jnp.einsum("kiaz,kiaw->izw", cJ, Jw)
        ei = e * iv[:, None, :]
        gz = -jnp.einsum("kiaz,kia->kiz", cJ, ei)
        JE = (e * (mw / sig ** 3)[:, None, :])[..., None] * c["Jsigc"]  # (K, 2n, ny, nsc)
        sCz = 2.0 * jnp.einsum("kiaz,kial->izl", cJ, JE)
        Cs = 2.0 * jnp.einsum("kiaz,kial->kzl", cJx, JE)
        if c["K_h"] is not None:
            Ka = c["K_h"](A, -cn * ei, uk)  # (K, 2n, na, na)
            sHz = sHz + jnp.sum(Ka, 0)
            Hm = Hm + jnp.sum(Ka[:, :, :n, :], 1)
            HAr = HAr + jnp.einsum("kivw,iwb->kvb", Ka[:, :, :n, :n], c["Arn"])
        return dict(D0=Hm[:, :, :n], Wr0=HAr, Wt0=Hm[:, :, n:], Wc0=Cs, g0=jnp.sum(gz[:, :, :n], 1),
                    sHz=sHz, sCz=sCz, sgz=jnp.sum(gz, 0),
                    sSe=cn * jnp.sum(mw[:, None, :] * e ** 2, (0, 1)), sM=jnp.sum(mw, 0))

    def _chunked(self, fn, args, count, w):
        """``fn`` over ``count`` items in chunks (lax.scan); ``fn`` takes a chunk (leading
        axis: items) and returns per-item arrays and keys 's…' already summed over the
        chunk, which are summed over the chunks here (the chunk sums are small: per-point
        border pieces); the others are stacked.

        ``w`` (count,): per-item weight passed last to ``fn`` (0 for padded samples)."""
        nc = -(-count // self.chunk)  # chunks of at most self.chunk items,
        ch = -(-count // nc)  # as equal as possible (601 pairs: 2 x 301, not 2 x 512)
        pad = nc * ch - count
        wts = jnp.concatenate([w, jnp.zeros(pad)])
        args = [jnp.concatenate([a, jnp.broadcast_to(a[-1:], (pad,) + a.shape[1:])]) if pad else a
                for a in args] + [wts]
        args = [a.reshape((nc, ch) + a.shape[1:]) for a in args]

        def body(carry, xs):  # fn is traced once (no eval_shape pass for the accumulators)
            return carry, fn(*xs)

        _, out = jax.lax.scan(body, None, args)
        acc = {k: jnp.sum(v, 0) for k, v in out.items() if k.startswith("s")}
        rest = {k: v for k, v in out.items() if not k.startswith("s")}
        rest = {k: v.reshape((nc * ch,) + v.shape[2:])[:count] for k, v in rest.items()}
        return acc, rest

    def _border_assembly(self, c, pa, pr, na, nr, wn, n_true, cfg, dt):
        """Value, border gradient and H_bb (the shared functions of b plus the summed point pieces
        through ∂z/∂b), and the per-sample blocks D, B, W, g_μ from the pair and node pieces."""
        n, npar, nq, nb = c["n"], c["npar"], self.nq, self.nb
        Az, An, Jth, Ep, Es = c["Az"], c["An"], c["Jth"], c["Ep"], c["Es"]

        # shared functions of the border: noise terms, lifting curvature, entropy. They are a
        # sum of three functions of disjoint parts of b = (r, z, w): the assumed density's
        # (entropy, sigma-point offsets), θ's (θ(z) of the points' lifting) and the noise's
        # (P = Q⁻¹ and σ), so their Hessian is block diagonal, each block its own derivative
        nt = self.tm.n_free
        sgp = jax.lax.stop_gradient(pa["sgz"])  # (4n, 2n + np): Σ_k ∇_z ψ per point
        sgn = jax.lax.stop_gradient(na["sgz"])  # (2n, n + np)
        sg_th = jnp.sum(sgp[:, 2 * n:], 0) + jnp.sum(sgn[:, n:], 0)  # (np,)

        def lifted(lin):
            return lin - jax.lax.stop_gradient(lin)  # value 0: only its derivatives count

        def part_r(rb):
            d0b, d1b = self.pair_offsets(rb)
            dnb = self.node_offsets(rb)
            lin = jnp.sum(sgp[:, :n] * d0b) + jnp.sum(sgp[:, n:2 * n] * d1b) + jnp.sum(sgn[:, :n] * dnb)
            return self.neg_entropy(rb, n_true) + lifted(lin)

        def part_z(zb):
            return lifted(jnp.dot(sg_th, self.tm.theta(zb, cfg["theta"])))

        def part_w(wb):
            Gb, sigb = self.nm.G(wb, cfg["noise"]), self.nm.sigma(wb, cfg["noise"])
            Lq = jnp.sqrt(dt) * Gb
            Li = tri_solve_small(Lq, jnp.eye(n))
            logdetQ = 2.0 * jnp.sum(jnp.log(jnp.abs(jnp.diagonal(Lq))))
            return (0.5 * jnp.sum((Li.T @ Li) * pa["sS"]) + (n_true - 1) * 0.5 * (logdetQ + n * LOG2PI)
                    + jnp.sum(0.5 * na["sSe"] / sigb ** 2 + na["sM"] * (jnp.log(sigb) + 0.5 * LOG2PI)))

        def fwd_fwd(fn, x):
            """(f, ∇f, ∇²f) forward over forward (the gradient a by-product): a smaller XLA graph
            than forward over reverse for these small functions of few variables."""
            def grad_aux(xx):
                g = jax.jacfwd(fn)(xx)
                return g, g
            H, g = jax.jacfwd(grad_aux, has_aux=True)(x)
            return fn(x), g, H

        b = c["b"]
        parts = [fwd_fwd(part_r, b[:nq]), fwd_fwd(part_w, b[nq + nt:])]
        # θ(z) is element-wise: forward over reverse, linear in the number of parameters
        fz, gz = jax.value_and_grad(part_z)(b[nq:nq + nt])
        parts.insert(1, (fz, gz, jax.hessian(part_z)(b[nq:nq + nt])))
        f = sum(p[0] for p in parts)
        gsh = jnp.concatenate([p[1] for p in parts])
        Hsh = block_diag(*[p[2] for p in parts])
        Hbb = (Hsh + jnp.einsum("iwa,iwv,ivb->ab", Az, pa["sHz"], Az)
               + jnp.einsum("iwa,iwv,ivb->ab", An, na["sHz"], An))
        Cb = (jnp.einsum("iwa,iwc,cb->ab", Az, pa["sCz"], Ep)
              + jnp.einsum("iwa,iwc,cb->ab", An, na["sCz"], Es))
        Hbb = Hbb + Cb + Cb.T
        D = nr["D0"].at[:-1].add(pr["D0"]).at[1:].add(pr["D1"])
        D = D + (1.0 - wn)[:, None, None] * jnp.eye(n)  # padded μ: identity block (H stays regular, Δμ = 0)

        def wfull(Wr, Wt, Wc, E):
            """Border coupling rows from their r, θ and noise-column parts."""
            Wz = jnp.concatenate([Wr, jnp.zeros(Wr.shape[:2] + (nb - nq,))], axis=2)
            return Wz + jnp.einsum("kip,pb->kib", Wt, Jth) + jnp.einsum("kic,cb->kib", Wc, E)

        W = (wfull(nr["Wr0"], nr["Wt0"], nr["Wc0"], Es).at[:-1].add(wfull(pr["Wr0"], pr["Wt0"], pr["Wc0"], Ep))
             .at[1:].add(wfull(pr["Wr1"], pr["Wt1"], pr["Wc1"], Ep)))
        gmu = nr["g0"].at[:-1].add(pr["g0"]).at[1:].add(pr["g1"])
        return dict(f=f, D=D, B=pr["B"], W=W, Hbb=Hbb, gmu=gmu, gb=gsh)

    def blocks(self, mu, r, s, data, cfg):
        return self._blocks(mu, r, s, data, cfg)

    def _factor_impl(self, blk, dmu, lam):
        self.traces["factor"] += 1
        """Eliminate μ: Schur complement S = Hbb − Wᵀ A⁻¹ W and reduced rhs −g_b + Wᵀ A⁻¹ g_μ.

        ``A`` is damped by λ·diag(dmu); the border damping is added globally by the caller.
        """
        D = blk["D"] + lam * jax.vmap(jnp.diag)(dmu)
        N, n, _ = D.shape
        R = jnp.concatenate([blk["gmu"][:, :, None], blk["W"]], axis=2)
        X, ok, _ = (btd_solve_parallel if self.parallel_solve else btd_solve)(D, blk["B"], R)
        Xg, Y = X[:, :, 0], X[:, :, 1:]
        S = blk["Hbb"] - jnp.einsum("kia,kib->ab", blk["W"], Y)
        rhs = -blk["gb"] + jnp.einsum("kia,ki->a", blk["W"], Xg)
        return dict(S=S, rhs=rhs, Xg=Xg, Y=Y, ok=ok)

    def factor(self, blk, dmu, lam):
        return self._factor(blk, dmu, lam)

    def _back_impl(self, fac, db):
        self.traces["back"] += 1
        return -fac["Xg"] - jnp.einsum("kib,b->ki", fac["Y"], db)

    def back(self, fac, db):
        return self._back(fac, db)


_OBJECTIVES: dict = {}


def generated_model_key(model, F) -> str | None:
    """Hash of the generated module whose functions ``model`` and its transition ``F`` run,
    or None when they are not exactly that module's (a model built in Python, a wrapped
    function): only then does the module's text determine what a trace of them computes."""
    import hashlib

    mod, path = getattr(model, "module", None), getattr(model, "module_path", None)
    if mod is None or path is None:
        return None
    jac = getattr(model, "jacobians", None)
    if (getattr(mod, "drift", None) is not model.drift or getattr(mod, "output", None) is not model.output
            or (jac is not None and getattr(mod, "drift_jac_x", None) is not jac.drift_x)
            or getattr(F, "fn", None) is None):
        return None
    executed = getattr(mod, "__vsidgen_source_sha256__", None)
    if executed is not None:        # the text the loader ran (model.runtime._import_module)
        return executed
    try:
        return hashlib.sha256(pathlib.Path(path).read_bytes()).hexdigest()
    except OSError:
        return None


@functools.lru_cache(maxsize=1)
def _constants_modules():
    from . import linalg
    from ..model import dynamics
    return (sys.modules[__name__], linalg, dynamics)


def _module_constants() -> str:
    """The upper-case module constants of the estimator's trace-time modules (settings a
    user or a test may change at run time), as text: part of a stored program's key."""
    out = []
    for mod in _constants_modules():
        for name in sorted(vars(mod)):
            if name.isupper() and not name.startswith("_"):
                v = getattr(mod, name)
                if isinstance(v, (bool, int, float, str, tuple, type(None), dict)):
                    out.append(f"{mod.__name__}.{name}={v!r}")
    return ";".join(out)


def get_objective(model, theta_map: ThetaMap, noise_map: NoiseMap, F, key_extra):
    """Objective with compiled functions shared between problems of the same structure.

    The numeric configuration (initial θ, bounds, floors, fixed noise) is a
    jit argument (``cfg``), so refitting the same model (other records, other
    fixed values) reuses the compiled code. Keyed on the model's functions,
    dimensions, integrator, the static index structure of the maps and the compiler
    options (and the folder of stored traced programs, :class:`vsidgen.compilecache.StoredJit`).
    """
    from ..compilecache import exported_dir

    key = (model.drift, model.output, POINT_JACOBIANS, use_parallel_solve(), assembly_chunk(),
           tuple(sorted((compiler_options() or {}).items())),
           model.nx, model.nu, model.ny, model.np, key_extra,
           getattr(F, "key", None),
           theta_map.static_key(), noise_map.static_key(), str(exported_dir()))
    obj = _OBJECTIVES.pop(key, None)     # least recently used first: a hit moves to the end
    if obj is None:
        if len(_OBJECTIVES) >= 16:
            _OBJECTIVES.pop(next(iter(_OBJECTIVES)))
        obj = Objective(model, theta_map, noise_map, F, store_key=generated_model_key(model, F))
    _OBJECTIVES[key] = obj
    return obj


class SwitchedObjective(Objective):
    """One compiled objective for several models of one layout, selected at run time.

    ``models`` (with their transitions ``Fs``) have the same states, inputs, outputs, number
    of parameters, free parameters and noise structure (the same :meth:`ThetaMap.static_key`
    and :meth:`NoiseMap.static_key`); they differ in their drift and output functions and
    in the run-time configuration (initial values, bounds, which parameters are free, noise
    floors). Every function evaluates the model ``k = cfg["branch"]`` (an int32 scalar of
    the configuration, :meth:`Problem` ``branch=k``) through ``jax.lax.switch``: ``k`` is a
    jit argument, never batched by the vmaps over samples and sigma points, so the switch
    stays a conditional that runs the selected branch only, and the problems of all the
    models share one trace and one XLA compilation of each function. Every value equals
    the one of the model's own :class:`Objective` up to rounding (a different compiled
    function). The variables with model curvature are the union over the models
    (:func:`curvature_pairs`; the curvature of the others is exactly zero there).
    """

    def __init__(self, models, theta_map: ThetaMap, noise_map: NoiseMap, Fs):
        models, Fs = list(models), list(Fs)
        shapes = {(m.nx, m.nu, m.ny, m.np) for m in models}
        keys = {getattr(F, "key", None) for F in Fs}
        if not models or len(shapes) != 1 or len(keys) != 1 or len(Fs) != len(models):
            raise FitError("a switched objective needs models of one shape and one transition setting")
        self.models = tuple(models)
        self.transitions = tuple(Fs)
        super().__init__(models[0], theta_map, noise_map, Fs[0])
        self.point_jacobians = "autodiff"

    def _curvature_structure(self, na: int, nu: int):
        """The union over the models of their Hessian patterns (:func:`curvature_pairs`,
        structural: nothing is compiled); None (all pairs) when one model has no structure."""
        n = self.n

        def union(fns):
            pats = [curvature_pairs(f, na, nu) for f in fns]
            if any(v is None for v in pats):
                return None
            return np.logical_or.reduce(pats)

        return (union([functools.partial(lambda a, u, F: F(a[:n], u, a[n:], 0.05), F=F)
                       for F in self.transitions]),
                union([functools.partial(lambda a, u, h: h(a[:n], u, a[n:]), h=m.output)
                       for m in self.models]))

    def transition_of(self, cfg):
        k, Fs = cfg["branch"], self.transitions

        def F(x, v, p, dt):
            return jax.lax.switch(k, Fs, x, v, p, dt)
        return F

    def output_of(self, cfg):
        k, hs = cfg["branch"], [m.output for m in self.models]

        def h(x, u, p):
            return jax.lax.switch(k, hs, x, u, p)
        return h


def make_cfg(theta_map: ThetaMap, noise_map: NoiseMap):
    return {"theta": {k: jnp.asarray(v) for k, v in theta_map.arrays().items()},
            "noise": {k: jnp.asarray(v) for k, v in noise_map.arrays().items()}}


def bucket_length(n: int) -> int:
    """Padded length of a record of n samples: n rounded up to a multiple of 2^e, e = max(0, ⌊log₂ n⌋ − 3).

    The ladder 8·2^e, 9·2^e, ..., 15·2^e, 16·2^e, ... has consecutive ratios ≤ 9/8, so the padding
    is < 2^e ≤ n/8 (≤ 12.5 %) and records whose lengths fall in one bucket share the compiled
    functions (their shapes are the same). n < 16 is not padded.
    """
    n = int(n)
    e = max(0, n.bit_length() - 4)
    return -(-n >> e) << e


def record_data(rec, output_index=None, *, length: int | None = None):
    """(u, y with NaN→0, mask, dt, pair weights, node weights, N) arrays of a record for the jitted functions.

    ``length`` ≥ N pads the record to that many samples (:func:`bucket_length`): inputs are
    repeated from the last sample, the observation mask, the node weights w_n and the pair
    weights w_p are 0 on the padding (w_p is also 0 for the transition from the last real
    sample into the padding), and N (the true length, a traced scalar) enters the entropy and
    the log det Q count. Every term of the objective is therefore exactly that of the
    unpadded record; the padded μ get an identity Hessian block (:meth:`Objective.blocks`).
    """
    y = np.asarray(rec.y, float)
    u = np.asarray(rec.u, float)
    N = y.shape[0]
    L = N if length is None else int(length)
    if L < N:
        raise FitError(f"padded length {L} is shorter than the record ({N} samples)")
    m = np.isfinite(y).astype(float)
    y = np.where(m > 0, y, 0.0)
    if L > N:
        y = np.concatenate([y, np.zeros((L - N, y.shape[1]))])
        m = np.concatenate([m, np.zeros((L - N, m.shape[1]))])
        u = np.concatenate([u, np.repeat(u[-1:], L - N, axis=0)])
    wn = (np.arange(L) < N).astype(float)
    wp = (np.arange(L - 1) < N - 1).astype(float)
    return (jnp.asarray(u), jnp.asarray(y), jnp.asarray(m), jnp.asarray(float(rec.dt)), jnp.asarray(wp),
            jnp.asarray(wn), jnp.asarray(float(N)))
