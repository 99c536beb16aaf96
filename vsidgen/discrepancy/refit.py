"""Staged refit of a nested candidate (robust against poor optima of the ELBO).

A candidate spec *nests* the current model: at its nesting values (zero gains,
the smallest admissible lag) it reproduces the current model, plus — for
candidates that add states — quasi-deterministic (or, for wind, vanishing-noise)
extra states. Refitting it from scratch often stopped in a poor optimum below the
base ELBO. The refit is therefore done in stages that each start exactly where the
previous one ended, so that the (monotone) Levenberg–Marquardt iteration can only
go up:

stage 0 (only for candidates that add states)
    the candidate model at its nesting point, θ and noise fixed (base estimates,
    new parameters at their nesting values), only the assumed density q is fitted
    (``estimator.smooth``). It starts from the base smoother: base state means
    copied, the new states simulated along them with the candidate's own
    transition from their equilibrium at the first sample (a lag state starts at
    the recorded input), their covariance from the scalar stationary solution.
    Its ELBO is the *nested reference* ``ELBO_ref``.
stage 1
    base parameters held at their estimates (``FitOptions.held_parameters``), the
    new parameters and the noise free; warm start from stage 0 (or from the base fit
    when no state is added, where the start *is* the base optimum).
stage 2
    everything free, starting from stage 1's optimum (warm start). Stages 1 and 2
    are the same problem (one spec, one layout), so they share every compiled
    function.

Because the model has a flat prior on the initial state, an added state
contributes the entropy of its own initial marginal, ``½ log(2πe P₀)`` per record,
to the ELBO (P₀ its stationary variance; ≈ −12 nats for a quasi-deterministic
state). A state that carries an input (a lag, Padé or actuator state) has a proper
prior on its initial value instead, N(u₀, std(u)²) (``FitOptions.input_state_prior``):
under the flat prior the initial value of a fast lag is a free impulse on the first
step — on a new user's ATTAS pitch model an "elevator lag" of 9e-5 s started at
−4478 deg (the elevator's first sample 2.3 deg) and gained 19 nats on each record,
accepted at 2ΔELBO 38.9 and lifting the validation ELBO by 660. Its term is then
``½ log(2πe P₀) − ½ log(2π std²) − ½ P₀/std²`` (:func:`initial_prior_term`). The
nested reference therefore is ``ELBO_ref = max(ELBO_stage0, ELBO_base + H₀)``, H₀ the
sum of these terms — the base model with decoupled copies of the new states — and the
test statistic is ``Λ = 2 (ELBO_candidate − ELBO_ref)`` (``= 2ΔELBO`` against the base
when no state is added). The same terms, from the fitted marginals, are removed from
the candidate's validation ELBO before it is compared with the base's.
"""

from __future__ import annotations

import dataclasses
import enum
import math
from typing import Any

import numpy as np

from ..report import finite_or_none as _f

#: process-noise std (state unit/√s) of the states the candidates add without process
#: noise (lags, delays, modes). Small against any physical signal (over a 0.15 s lag it
#: accumulates 4e-4 rad against elevator inputs of ~0.02 rad), large enough to keep the
#: assumed density well conditioned: with 1e-5 the benchmark's lag refit needed > 400
#: Levenberg–Marquardt iterations, with 1e-3 it converges in ~55. Used in every stage and
#: in the reference.
REFIT_DETERMINISTIC_STD = 1e-3

#: the same for a state that carries an input (a lag or delay state: its unit is the input's),
#: relative to the input's std, per √s (:attr:`FitOptions.deterministic_input_scale`), in any
#: unit — an engine thrust in N gets its own scale instead of 1e-3. It was 0.07 (1e-3 rad/√s
#: against the benchmark's 0.0136-rad elevator std) until session 39: on a new user's Twin
#: Otter lateral model without L_r (real record totter_lat_f1_014) the Padé state's noise at
#: 7 % of the aileron's spread per √s was an input-noise channel into p and r, and a 0.29-s
#: "aileron delay" (2ΔELBO 2399) outranked the missing L_r (2122); at 0.7 % it scores 346 and
#: in the deterministic limit it falls to 0.004 s. The benchmark's lags and delays are
#: recovered the same at 0.7 % (hfb_de_lag_0.05_s1 0.04766 ± 0.00094 s, lat_dr_lag_0.15_s0
#: 0.1535 ± 0.0017 s, sp_de_delay_0.04_s0 0.04264 ± 0.0011 s).
REFIT_DETERMINISTIC_REL = 0.007


def quasi_stds(model, records, det_std) -> np.ndarray:
    """Per state of ``model``: the std (state unit/√s) a quasi-deterministic state has in the
    refits — ``REFIT_DETERMINISTIC_REL × std(u)`` for a state carrying input ``u``,
    ``det_std`` for any other (what :class:`~vsidgen.estimator.Problem` sets with
    ``deterministic_input_scale``)."""
    from ..estimator.core import quasi_deterministic_stds

    return quasi_deterministic_stds(model, records, det_std, REFIT_DETERMINISTIC_REL)


class RefitVerdict(str, enum.Enum):
    """What a converged refit's result may be used for (typed; findings.json stores the value).

    ``ordinary``: a test result (significant or not). ``below_nesting_point``: the refit ended
    below its nested reference ELBO. Every stage starts where the previous one ended and the
    optimiser only ascends, so this is an optimiser failure (or a candidate family that does
    not contain the current model exactly, such as a lag whose smallest time constant is a
    one-sample shift): neither a rejection nor evidence; it is flagged, never reported as
    "not significant". ``non_causal``: the estimate is physically impossible as labelled
    (a channel that reads *before* the motion, a negative delay or time constant); it is not
    accepted under that label. ``beyond_range``: a time constant ended at the upper end of the
    range its label allows (an actuator lag of 5 s, a control delay of 1 s): the data want a
    slower process than the label names — on a new user's Tu-144 model without trim terms an
    "elevator lag" ended at 5.0 s, a low-passed elevator standing in for the missing constants
    and slow dynamics — so it is not accepted under that label either. So is an estimate whose
    95 % interval reaches that end (``upper − θ̂ < 1.96 s.e.``, the estimator's ``AT_BOUND``
    rule): on a new user's ATTAS roll model without lateral coupling a left-aileron "delay"
    of 0.970 ± 0.030 s (bound 1 s) stood in for the missing coupling.
    """

    ORDINARY = "ordinary"
    BELOW_NESTING_POINT = "below_nesting_point"
    NON_CAUSAL = "non_causal"
    BEYOND_RANGE = "beyond_range"


#: Λ below −BELOW_TOL (2ΔELBO, i.e. 0.05 nats) counts as ending below the nested reference
BELOW_TOL = 0.1


#: a time constant within this fraction of its label's upper limit is at the limit
RANGE_TOL = 1e-3

#: two-sided 95 % normal quantile: an estimate closer than this many standard errors to its
#: label's upper limit cannot be told from it (as ``estimator.fit``'s ``AT_BOUND`` flag)
RANGE_Z = 1.959963984540054


def refit_verdict(statistic: float, estimates: dict[str, float], causal_sign: dict[str, int],
                  label_upper: dict[str, float] | None = None,
                  std_errors: dict[str, float] | None = None) -> RefitVerdict:
    """Verdict of a refit from its statistic ``Λ = 2(ELBO − ELBO_ref)`` and its estimates.

    ``causal_sign`` maps parameters whose sign is physical (a time skew: +1, late) to the
    admissible sign; an estimate of the other sign is non-causal. ``label_upper`` maps time
    constants to the largest value their label allows (the candidate's upper bound); an
    estimate within :data:`RANGE_TOL` of it (relative), or within :data:`RANGE_Z` of its
    standard error (``std_errors``, when finite), is beyond the label's range.
    """
    if math.isfinite(statistic) and statistic < -BELOW_TOL:
        return RefitVerdict.BELOW_NESTING_POINT
    for name, sign in causal_sign.items():
        v = estimates.get(name)
        if v is not None and math.isfinite(v) and v * sign < 0:
            return RefitVerdict.NON_CAUSAL
    for name, hi in (label_upper or {}).items():
        v = estimates.get(name)
        if v is None or not math.isfinite(v):
            continue
        se = (std_errors or {}).get(name)
        if v >= hi * (1.0 - RANGE_TOL) or (se is not None and math.isfinite(se)
                                          and hi - v < RANGE_Z * se):
            return RefitVerdict.BEYOND_RANGE
    return RefitVerdict.ORDINARY


@dataclasses.dataclass
class RefitOutcome:
    """What the staged refit produced (the FitState of the final stage and its history)."""

    state: Any = None                 # FitState of stage 2 (None when it failed)
    elbo_ref: float = math.nan        # nested reference ELBO (see module docstring)
    elbo_stage0: float | None = None
    elbo_stage1: float | None = None
    converged_stage0: bool | None = None
    converged_stage1: bool | None = None
    x0_entropy: float = 0.0           # Σ ½ log(2πe P₀) of the added states (estimation records)
    val_x0_entropy: float = 0.0       # the same on the validation records (candidate fit)
    warm: str = ""                    # how the stages were started
    notes: list = dataclasses.field(default_factory=list)
    wall_s: float = 0.0
    compile_s: float | None = None    # JAX trace + lower + XLA compile time spent in the refit
    #: 2ΔELBO of the candidate over its nested reference in the deterministic limit of the
    #: added states minus the same at their quasi-deterministic std (``limit_statistic``; None:
    #: not taken). ``elbo_ref`` and ``x0_entropy`` include −½ of it: the reference is raised by
    #: the gain the fixed noise of the added states gave the candidate (module docstring).
    limit_correction: float | None = None
    limit_detail: dict | None = None

    @property
    def elbo_nesting(self) -> float:
        """The nested reference at the noise the candidate's own fit was made at (the added
        states quasi-deterministic): ``elbo_ref`` without the limit correction. A refit whose
        ELBO ends below it ended below its nesting point (``RefitVerdict.BELOW_NESTING_POINT``)
        whatever the corrected statistic says."""
        return self.elbo_ref + 0.5 * (self.limit_correction or 0.0)

    def to_json(self) -> dict:
        f = _f
        return {"elbo_ref": f(self.elbo_ref), "elbo_stage0": f(self.elbo_stage0),
                "limit_correction": f(self.limit_correction), "limit": self.limit_detail,
                "elbo_stage1": f(self.elbo_stage1), "converged_stage0": self.converged_stage0,
                "converged_stage1": self.converged_stage1, "x0_entropy": f(self.x0_entropy),
                "val_x0_entropy": f(self.val_x0_entropy), "warm_start": self.warm,
                "notes": list(self.notes), "wall_s": round(self.wall_s, 2),
                "compile_s": None if self.compile_s is None else round(self.compile_s, 2)}


def noise_parameters(model, records, det_std, *, proc_std: dict, proc_G: dict, meas_std: dict):
    """Unconstrained noise parameters of ``model`` holding the given stds (layout of the estimator).

    proc_std: {state: std} (states absent get ``det_std``); proc_G: {(row, col): value}
    off-diagonal entries by state names; meas_std: {output: std}.
    """
    from ..estimator import FitOptions, Problem

    P = Problem(model, records, FitOptions(deterministic_std=det_std,
                                           deterministic_input_scale=REFIT_DETERMINISTIC_REL))
    return P.noise_vector(proc_std=proc_std, proc_G=proc_G, meas_std=meas_std, default_std=det_std)


def parameter_start(model):
    """Unconstrained start of the free parameters and the θ it maps to (the estimator's map)."""
    from ..estimator import parameter_start as start

    return start(model)


def noise_stds(fit, model) -> tuple[dict, dict, dict]:
    """The noise of ``fit`` (a fit of ``model``) by name: process std per state (the diagonal
    of G), off-diagonal G entries {(row state, column state): value}, measurement std per
    output; the arguments :func:`noise_parameters` takes."""
    G = np.asarray(fit.G, float)
    names = model.state_names
    proc_std = dict(fit.process_std)
    # the reported G is lower triangular; its diagonal is the estimator's diagonal
    for i, n in enumerate(names):
        if n in proc_std:
            proc_std[n] = float(abs(G[i, i]))
    offd = {(names[a], names[b]): float(G[a, b]) for a in range(len(names)) for b in range(a)
            if G[a, b] != 0.0}
    return proc_std, offd, dict(fit.measurement_std)


def _embed_r(r0, n0, n1, base_idx, new_idx, d_new, c_new):
    """Assumed-density parameters (d, strict-lower L, C) of n0 states embedded in n1 states."""
    from ..estimator import join_density, split_density

    d0, L0, c0 = split_density(r0, n0)
    d1 = np.zeros(n1)
    L1 = np.eye(n1)
    C1 = np.zeros((n1, n1))
    bi = np.asarray(base_idx)
    d1[bi] = d0
    L1[np.ix_(bi, bi)] = L0
    C1[np.ix_(bi, bi)] = c0
    for k, j in enumerate(new_idx):
        d1[j] = d_new[k]
        C1[j, j] = c_new[k]
    return join_density(d1, L1, C1)


def restrict_density(r, names_from, names_to) -> np.ndarray:
    """Assumed-density parameters r of the states ``names_from`` restricted to ``names_to``
    (a subset): the marginal Σ_m and the lag-one cross covariance cov(x_{k+1}, x_k) = C S_mᵀ
    of the kept states exactly (their sub-blocks), C' = cov' S_m'^{-T} and
    Σ_cond' = Σ_m' − C'C'ᵀ (the Schur complement of a sub-block of a positive-definite joint
    covariance, hence positive definite). The kept states' path is not Markov in general;
    this is the stationary Markov density with the same marginal and lag-one moments."""
    from ..estimator import join_density
    from ..estimator.core import cov_factors_of

    names_from = list(names_from)
    idx = np.asarray([names_from.index(k) for k in names_to], int)
    _, C, Sm, _ = (np.asarray(a, float) for a in cov_factors_of(np.asarray(r, float),
                                                                len(names_from)))
    marg = (Sm @ Sm.T)[np.ix_(idx, idx)]
    cross = (C @ Sm.T)[np.ix_(idx, idx)]
    C1 = np.linalg.solve(np.linalg.cholesky(marg), cross.T).T      # cross · chol(marg)^{-T}
    Lc = np.linalg.cholesky(marg - C1 @ C1.T)
    dg = np.diag(Lc)
    return join_density(2.0 * np.log(dg), Lc / dg[None, :], C1)


def restrict_decision(decision_records, names_from, names_to) -> list[dict]:
    """Per-record ``{"mu", "r"}`` of an assumed density over ``names_from`` restricted to
    the states ``names_to`` (means: their columns; covariances: :func:`restrict_density`)."""
    names_from = list(names_from)
    idx = [names_from.index(k) for k in names_to]
    return [{"mu": np.asarray(d["mu"], float)[:, idx],
             "r": restrict_density(d["r"], names_from, names_to)} for d in decision_records]


def stage0_start(model1, records, base_fit, base_model, theta1, det_std):
    """Warm-start decision of the candidate at its nesting point (see module docstring).

    Returns (decision, G1, R1, x0_entropy, notes).
    """
    import jax
    import jax.numpy as jnp

    from ..estimator.problem import initial_prior_term, input_state_prior_scales
    from ..model.dynamics import transition

    names0 = list(base_model.state_names)
    names1 = list(model1.state_names)
    base_idx = [names1.index(n) for n in names0]
    new_idx = [j for j, n in enumerate(names1) if n not in names0]
    n0, n1 = len(names0), len(names1)
    prior = input_state_prior_scales(model1, records)   # the fits' default ("all")
    F = transition(model1, integrator=None, substeps=None)
    th = jnp.asarray(theta1)
    ni = np.asarray(new_idx)

    @jax.jit
    def sim(mu, u, z0, dt):
        def step(z, inp):
            x, uk = inp
            xn = F(x.at[ni].set(z), uk, th, dt)
            return xn[ni], z
        zl, zs = jax.lax.scan(step, z0, (mu[:-1], F.step_inputs(u)))
        return jnp.concatenate([zs, zl[None]], axis=0)

    jacF = jax.jit(jax.vmap(lambda x, u, dt: F.jacobian(x, u, th, dt)[0], in_axes=(0, 0, None)))

    def jacf(x, u):
        return model1.drift_jacobian(x, u, th)[0]
    recs = []
    H0 = 0.0
    notes = []
    G0 = np.asarray(base_fit.G, float)
    G1 = np.zeros((n1, n1))
    G1[np.ix_(base_idx, base_idx)] = G0
    for ri, (rec, dec) in enumerate(zip(records, base_fit.decision["records"])):
        mu0 = np.asarray(dec["mu"], float)
        u = np.asarray(rec.u, float)
        dt = float(rec.dt)
        mu1 = np.zeros((mu0.shape[0], n1))
        mu1[:, base_idx] = mu0
        # equilibrium of the new states at the first sample (a lag starts at the input)
        x = jnp.asarray(mu1[0])
        f = np.asarray(model1.drift(x, jnp.asarray(u[0]), th), float)[ni]
        J = np.asarray(jacf(x, jnp.asarray(u[0])), float)[np.ix_(ni, ni)]
        # (singular, e.g. a speed state beside an attitude integrator: the least-squares
        # equilibrium, the speed equation in trim and the integrator at 0)
        try:
            z0 = (-np.linalg.solve(J, f) if np.linalg.cond(J) < 1e12
                  else -np.linalg.lstsq(J, f, rcond=1e-10)[0])
        except np.linalg.LinAlgError:
            z0 = np.zeros(len(ni))
        if not np.all(np.isfinite(z0)):
            z0 = np.zeros(len(ni))
        zs = np.array(sim(jnp.asarray(mu1), jnp.asarray(u), jnp.asarray(z0), dt), float)
        if not np.all(np.isfinite(zs)):
            notes.append("new states diverged in the start simulation; started at 0")
            zs = np.zeros_like(zs)
        mu1[:, ni] = zs
        Js = np.asarray(jacF(jnp.asarray(mu1[:-1]), jnp.asarray(F.step_inputs(u)), dt), float)
        a = np.clip(Js[:, ni, ni].mean(axis=0), -0.999, 0.999)
        Q = dt * quasi_stds(model1, [rec], det_std)[ni] ** 2
        P = Q / (1.0 - a ** 2)
        for jj, j in enumerate(new_idx):   # the initial-value prior's mean (input_state_prior)
            if j in prior:
                zs[0, jj] = prior[j][1][ri]
        d_new = np.log(Q)
        c_new = a * np.sqrt(P)
        r1 = _embed_r(dec["r"], n0, n1, base_idx, new_idx, d_new, c_new)
        recs.append({"mu": mu1, "r": r1})
        H0 += sum(initial_prior_term(P[jj], prior.get(j, (None,))[0]) for jj, j in enumerate(new_idx))
    R1 = np.asarray(base_fit.R, float)
    return {"s": np.zeros(0), "records": recs}, G1, R1, H0, notes


def x0_entropy(fit, names_new, model, records) -> float:
    """Σ over records and added states of their initial-value term from a fit's smoother
    marginals P₀: ½ log(2πe P₀), or :func:`initial_prior_term` for a state with the
    initial-value prior (``records``: the fit's, which set the prior's scale)."""
    from ..estimator.problem import initial_prior_term, input_state_prior_scales

    idx = [model.state_names.index(n) for n in names_new]
    prior = input_state_prior_scales(model, records)
    tot = 0.0
    for sm in fit.smoothers:
        P = np.asarray(sm.cov_marg, float)
        for j in idx:
            tot += initial_prior_term(P[j, j], prior.get(j, (None,))[0])
    return tot


_COMPILE_EVENTS = ("/jax/core/compile/jaxpr_trace_duration",
                   "/jax/core/compile/jaxpr_to_mlir_module_duration",
                   "/jax/core/compile/backend_compile_duration")
_compile_total = [0.0]
_listening = [False]


def compile_seconds() -> float:
    """Seconds this process has spent tracing, lowering and compiling JAX functions since the
    first call (a ``jax.monitoring`` listener, registered once per process)."""
    if not _listening[0]:
        import jax

        def listen(event, duration, **_):
            if event in _COMPILE_EVENTS:
                _compile_total[0] += float(duration)
        jax.monitoring.register_event_duration_secs_listener(listen)
        _listening[0] = True
    return _compile_total[0]
