"""The noise model before physics: correlated turbulence as a candidate of its own.

An aircraft flies through one air mass: a vertical gust ``w_g`` changes the aerodynamic angle
of attack ``α − w_g/V``, and every equation that depends on α receives it through its own
derivative — ``Z_α·w_g/V`` in the α equation, ``M_α·w_g/V`` in the q equation. The process
noise of those equations is therefore *correlated* (for a single gust component exactly of
rank one), while a spec with ``noise.process.structure: diagonal`` models each equation's
turbulence as independent. That mismatch is systematic and the physical catalogue can absorb
part of it: a term that mixes the states of two equations mixes their noise too, so on a
record with no concealed effect a flow-vane position ``α + D·q`` raised the ELBO exactly as
much as a correlated noise model does (independent benchmark, ``sp_none_0_s0``: Λ = 17.29 vs
17.30) and was reported as a sensor effect.

So before any physical candidate, :func:`run_noise_model` refits the current model with a
full (lower-triangular) process-noise factor ``G`` on the same states, warm-started from the
current fit. At ``G_ij = 0`` (i ≠ j) it *is* the current model, an interior point of the
larger family, so Wilks' theorem applies:

    Λ = 2(ELBO_full − ELBO_diagonal)  ~  χ²_k,   k = n(n − 1)/2

for ``n`` process-noise states with estimated intensities. The alternative is adopted when
the refit converged and Λ exceeds the χ²_k quantile at level α (one hypothesis in this stage).
A refit that stopped before an optimum gives a lower bound of Λ (the optimizer takes ascent
steps only): above the threshold the diagonal model is rejected all the same, but the
iterate is not adopted (:func:`decide`, ``SIGNIFICANT_NOT_CONVERGED``) and the findings say
that the search went on with the diagonal noise. Measured on the independent
benchmark's HFB-320 and lateral null records (``docs/diagnose.md``): the refit stops at the
iteration limit with an indefinite Hessian while ``Q`` approaches a singular matrix (one gust
acting on several equations), the ELBO still rising.
**Score test first.** The refit is slow where the noise must travel far (a funnel: on
the HFB-320 null record the V noise std grows 38× while its path roughness follows, about
0.2 nats per Levenberg–Marquardt iteration), and it is needed only when the diagonal
model is rejected. :func:`score_test` therefore computes Rao's score (Lagrange-multiplier)
statistic of the off-diagonal factor entries at the nesting point first — the gradient and
the exact Hessian of the full-factor problem at the current optimum, every other variable
(state means, assumed density, θ, the diagonal noise) profiled out:

    S = g_γᵀ (H_γγ − H_γρ H_ρρ⁻¹ H_ργ)⁻¹ g_γ  ~  χ²_k under the null,

invariant to the parameterisation of the tested entries (G_ij at G_ij = 0 maps linearly to
Q_ij = G_jj G_ij), hence to the order of the states. When S is at or below the χ²_k
quantile and the profiled curvature is positive definite, the diagonal model is kept
(``decided_by: score``) without refitting. When S is significant, or the profiled
curvature has a negative eigenvalue (the current optimum is a saddle of the larger family:
the ELBO rises along a correlation even where its gradient vanishes), or no statistic can
be formed, the alternative is refitted and decided by the likelihood ratio as above.

It is reported as a **noise-model finding** ("the turbulence is correlated between the
equations …", with the correlation coefficients ``ρ_ij = Q_ij/√(Q_ii Q_jj)`` of ``Q = G Gᵀ``),
never as a physical effect, and the physical search continues with it (the final spec carries
``structure: full``). The estimator already supports the full factor; no parameter of the
aircraft model is added.
"""

from __future__ import annotations

import dataclasses
import enum
import math
import os
import pathlib
import time
from typing import Any

import numpy as np
from scipy import stats


class NoiseModelVerdict(enum.Enum):
    """Outcome of a noise-model alternative (``findings.json`` → ``noise_model.trials[].verdict``)."""

    ADOPTED = "adopted"
    NOT_SIGNIFICANT = "not_significant"
    NOT_CONVERGED = "not_converged"                        # refit not at an optimum, Λ ≤ threshold
    SIGNIFICANT_NOT_CONVERGED = "significant_not_converged"  # Λ (a lower bound) > threshold
    NOT_TESTED = "not_tested_base_unconverged"   # nothing can be decided against a non-optimum
    FAILED = "failed"


class NoiseAlternative(enum.Enum):
    """A noise model tested against the current one."""

    CORRELATED = "correlated_process_noise"   # structure: full on the same states
    AIR_GUST = "air_relative_gust"            # a gust state in the flow-angle definitions (.gust)


@dataclasses.dataclass(frozen=True)
class NoiseScore:
    """Rao's score statistic of the alternative's added noise parameters at the nesting
    point (:func:`score_test`); ``statistic`` None when none could be formed (``note``)."""

    statistic: float | None
    dof: int
    threshold: float
    p_value: float = math.nan
    ascent: bool = False                 # profiled curvature with a negative eigenvalue
    per_pair: tuple[tuple[str, str, float], ...] = ()   # one-entry statistics (χ²₁ each)
    note: str = ""
    wall_s: float = 0.0

    @property
    def keeps_current(self) -> bool:
        """The score test alone keeps the current noise model (no refit needed)."""
        return (self.statistic is not None and not self.ascent
                and self.statistic <= self.threshold)

    def to_json(self) -> dict:
        def f(v):
            return None if v is None or not math.isfinite(v) else float(v)
        return {"statistic": f(self.statistic), "dof": self.dof, "threshold": f(self.threshold),
                "p_value": f(self.p_value), "ascent": self.ascent,
                "per_pair": [{"states": [a, b], "statistic": f(v)} for a, b, v in self.per_pair],
                "note": self.note, "wall_s": round(self.wall_s, 2)}


@dataclasses.dataclass(frozen=True)
class NoiseModelTrial:
    """The current model refitted with one noise-model alternative."""

    alternative: NoiseAlternative
    spec_path: pathlib.Path
    dof: int
    state: Any = None                    # search.FitState (None: failed)
    statistic: float = math.nan          # 2(ELBO_alternative − ELBO_current)
    threshold: float = math.nan
    p_value: float = math.nan
    converged: bool = False
    verdict: NoiseModelVerdict = NoiseModelVerdict.FAILED
    correlations: tuple[tuple[str, str, float], ...] = ()
    error: str | None = None
    wall_s: float = 0.0
    stop_reason: Any = None              # estimator.StopReason of the refit (None: not run)
    iterations: int = 0
    independent_shares: tuple[tuple[str, float], ...] = ()
    start: str | None = None             # the start decided with (STARTS)
    #: every start run: (start, (ELBO, converged, iterations, wall s) or None when it failed)
    starts: tuple = ()
    score: NoiseScore | None = None      # the score test at the nesting point
    decided_by: str = "likelihood_ratio"  # or "score" (kept without a refit)

    def to_json(self) -> dict:
        def f(v):
            return None if v is None or not math.isfinite(v) else float(v)
        return {"alternative": self.alternative.value, "spec": str(self.spec_path),
                "dof": self.dof, "elbo": None if self.state is None else f(self.state.elbo),
                "statistic": f(self.statistic), "threshold": f(self.threshold),
                "p_value": f(self.p_value), "converged": self.converged,
                "verdict": self.verdict.value,
                "correlations": [{"states": [a, b], "rho": f(r)} for a, b, r in self.correlations],
                "independent_shares": [{"state": a, "share": f(v)}
                                       for a, v in self.independent_shares],
                "stop_reason": None if self.stop_reason is None else self.stop_reason.value,
                "iterations": self.iterations, "start": self.start,
                "starts": [{"start": st, "failed": v is None,
                            **({} if v is None else {"elbo": f(v[0]), "converged": v[1],
                                                     "iterations": v[2], "wall_s": round(v[3], 2)})}
                           for st, v in self.starts],
                "error": self.error, "wall_s": round(self.wall_s, 2),
                "decided_by": self.decided_by,
                "score": None if self.score is None else self.score.to_json()}


@dataclasses.dataclass(frozen=True)
class NoiseModelResult:
    """The noise-model stage of a diagnose run."""

    structure: str                       # the current process-noise structure
    states: tuple[str, ...]              # its states with estimated intensities
    elbo_current: float
    trials: tuple[NoiseModelTrial, ...]
    alpha: float
    adopted: NoiseModelTrial | None = None

    def adopted_json(self, *, recommendation: str, explanation: str) -> dict | None:
        """The adopted alternative's record in findings.json (None when none was adopted)."""
        a = self.adopted
        if a is None:
            return None
        return {"alternative": a.alternative.value, "spec": str(a.spec_path),
                "statistic": float(a.statistic), "threshold": float(a.threshold),
                "dof": a.dof, "p_value": float(a.p_value),
                "elbo_before": float(self.elbo_current), "elbo_after": float(a.state.elbo),
                "correlations": a.to_json()["correlations"],
                "recommendation": recommendation, "explanation": explanation}

    def to_json(self) -> dict:
        adopted = None if self.adopted is None else self.adopted_json(
            recommendation="use noise: {process: {structure: full}}",
            explanation=explanation(self.adopted))
        sig = [t for t in self.trials
               if t.verdict is NoiseModelVerdict.SIGNIFICANT_NOT_CONVERGED]
        unresolved = None
        if adopted is None and sig:
            t = max(sig, key=lambda t: t.statistic)
            unresolved = {"alternative": t.alternative.value, "statistic_lower_bound":
                          float(t.statistic), "threshold": float(t.threshold), "dof": t.dof,
                          "stop_reason": None if t.stop_reason is None else t.stop_reason.value,
                          "correlations": t.to_json()["correlations"],
                          "independent_shares": t.to_json()["independent_shares"]}
        return {"kind": "noise_model",
                "test": "2*(ELBO_full - ELBO_diagonal) against chi2(n(n-1)/2) at alpha: the "
                        "diagonal process noise is the full one with zero off-diagonal factor "
                        "entries (nested, interior point); refitted only when Rao's score "
                        "statistic at the current fit is significant, its profiled curvature "
                        "is not positive definite, or it cannot be formed (trials[].score, "
                        "trials[].decided_by)",
                "current": {"structure": self.structure, "states": list(self.states)},
                "elbo_current": float(self.elbo_current), "alpha": self.alpha,
                "trials": [t.to_json() for t in self.trials], "adopted": adopted,
                "significant_not_adopted": unresolved}


def noise_alternatives(model) -> list[tuple[NoiseAlternative, int]]:
    """Alternatives to test for ``model`` with their added noise parameters: the full factor
    when at least two states have estimated, independent (diagonal) process noise."""
    pn = model.process_noise
    if pn is None or not pn.estimate or pn.structure != "diagonal":
        return []
    n = len(pn.states or model.state_names)
    return [(NoiseAlternative.CORRELATED, n * (n - 1) // 2)] if n >= 2 else []


def correlations(G, names) -> tuple[tuple[str, str, float], ...]:
    """Correlation coefficients ``Q_ij/√(Q_ii Q_jj)`` of ``Q = G Gᵀ`` for every pair of
    states with process noise."""
    G = np.asarray(G, float)
    Q = G @ G.T
    d = np.sqrt(np.clip(np.diag(Q), 0.0, None))
    out = []
    for i in range(len(names)):
        for j in range(i):
            if d[i] > 0 and d[j] > 0:
                out.append((names[j], names[i], float(Q[i, j] / (d[i] * d[j]))))
    return tuple(out)


def independent_shares(G, names) -> tuple[tuple[str, float], ...]:
    """Per state, the share of its process-noise std not explained by the states before it:
    ``G_ii/√Q_ii`` with ``Q = G Gᵀ`` (G lower triangular on ``names``' order).

    1 for independent noise; 0 when the state's noise is a linear combination of the earlier
    states' (Q singular). A share near 0 marks a factor close to a singular Q (one gust
    acting on several equations with almost nothing independent left)."""
    G = np.asarray(G, float)
    q = np.sqrt(np.sum(G ** 2, axis=1))
    return tuple((n, float(abs(G[i, i]) / q[i]) if q[i] > 0 else math.nan)
                 for i, n in enumerate(names))


def explanation(trial: NoiseModelTrial) -> str:
    """Plain words for an adopted noise model."""
    rho = ", ".join(f"ρ({a}, {b}) = {r:+.2f}" for a, b, r in trial.correlations)
    return ("Noise model, not physics: the turbulence (process noise) is correlated between the "
            "state equations — one gust acting on several equations through their aerodynamic "
            f"derivatives — rather than independent per equation ({rho}; 2ΔELBO = "
            f"{trial.statistic:.4g} > {trial.threshold:.4g}, χ²({trial.dof})). Use "
            "`noise: {process: {structure: full}}` in the spec; the physical search continues "
            "with it.")


def write_noise_spec(current, path: pathlib.Path, name: str):
    """Spec extending the current one with a full process-noise factor (current estimates as
    initial values)."""
    from .specwrite import extends_text, warm_parameters, write_spec

    return write_spec(path, "vsidgen diagnose: noise model with correlated process noise",
                      {"name": name,
                       "description": "the current model with correlated process noise "
                                      "(structure: full)",
                       "extends": extends_text(current.spec_path, path),
                       "noise": {"process": {"structure": "full"}},
                       "parameters": warm_parameters(current.model, current.fit.theta)})


def score_test(current, path: pathlib.Path, *, generated_dir, dof: int,
               alpha: float) -> NoiseScore:
    """Rao's score statistic of the off-diagonal process-noise factor entries of the spec at
    ``path`` (the current model with ``structure: full``) at the nesting point: the current
    fit's θ, noise and assumed density, off-diagonal entries 0 (module docstring).

    The full-factor problem's exact gradient and Hessian blocks there (one evaluation); the
    state means are eliminated (block-tridiagonal Schur complement), then every other border
    variable (assumed-density parameters, θ, diagonal and measurement noise; floors that are
    active stay held) is profiled out of the tested entries' block."""
    from ..estimator.problem import NEGATIVE_CURVATURE_TOL, Problem
    from ..model import load_model
    from .fitstate import diag_options, warm_start_from

    t0 = time.perf_counter()
    thr = float(stats.chi2.isf(alpha, max(dof, 1)))

    def none(note):
        return NoiseScore(None, dof, thr, note=note, wall_s=time.perf_counter() - t0)

    m = load_model(path, generated_dir=generated_dir)
    records = list(current.records)
    # exactly the warm refit's start (refit_warm): the nesting point
    opts = diag_options(1, warm_start=warm_start_from(m, records, current))
    P = Problem(m, records, opts)
    s, recs = P.initial(opts)
    blks = P.blocks(s, recs)
    S, rhs = P.score_system(blks)
    if S is None:
        return none("state-mean block not positive definite at the nesting point")
    off = P.layout.shared_offset
    ne = len(P.nm.proc_est_idx)
    gam = off + P.tm.n_free + ne + np.arange(len(P.nm.offdiag))
    held = off + np.nonzero(P.floor_active(s, P.gradient(blks).shared))[0]
    skip = set(gam.tolist()) | set(held.tolist())
    rest = np.array([j for j in range(S.shape[0]) if j not in skip], int)
    try:
        L0 = np.linalg.cholesky(S[np.ix_(rest, rest)])
    except np.linalg.LinAlgError:
        return none("the Hessian of the current model is not positive definite at its fit")

    def solve0(B):
        return np.linalg.solve(L0.T, np.linalg.solve(L0, B))

    SJ = S[np.ix_(gam, rest)]
    schur = S[np.ix_(gam, gam)] - SJ @ solve0(SJ.T)
    schur = 0.5 * (schur + schur.T)
    rJ = rhs[gam] - SJ @ solve0(rhs[rest])
    eig = np.linalg.eigvalsh(schur)
    names = m.state_names
    per = tuple((names[b], names[a], float(rJ[j] ** 2 / schur[j, j]) if schur[j, j] > 0
                 else math.nan) for j, (a, b) in enumerate(P.nm.offdiag))
    if eig[0] < -NEGATIVE_CURVATURE_TOL * max(float(np.max(np.abs(eig))), 1e-300):
        return NoiseScore(None, dof, thr, ascent=True, per_pair=per,
                          note="negative profiled curvature along the correlations: the "
                               "current optimum is a saddle of the correlated model",
                          wall_s=time.perf_counter() - t0)
    if eig[0] <= 0:
        return none("profiled curvature of the correlations not positive definite")
    stat = float(max(rJ @ np.linalg.solve(schur, rJ), 0.0))
    if not math.isfinite(stat):
        return none("score statistic not finite")
    return NoiseScore(stat, dof, thr, float(stats.chi2.sf(stat, max(dof, 1))), per_pair=per,
                      wall_s=time.perf_counter() - t0)


#: the two starts of the alternative's refit (:func:`run_noise_model`)
STARTS = ("warm", "cold")


def _score_errors():
    from ..errors import VsidgenError

    return (VsidgenError, ValueError, ArithmeticError, np.linalg.LinAlgError, KeyError)


_SCORE_ERRORS = _score_errors()


class Superseded(Exception):
    """A start ended early: another start already decided the stage."""


#: iterations between two polls of the stop flag by the cold start on a worker
POLL_EVERY = 5


def _stop_poll(stop_key):
    """Progress callback of the cold start: raises :class:`Superseded` once the run has
    raised the stop flag ``stop_key`` (the warm start converged; a worker of a cluster
    cannot otherwise be interrupted)."""
    from ..engine import stop_requested

    def poll(it, elbo, relgrad, elapsed):
        if it % POLL_EVERY == 0 and stop_requested(stop_key):
            raise Superseded(f"stopped at iteration {it}: the warm start converged")
    return poll


def noise_refit_task(current, path, generated_dir, max_iter, start, stop_key=None):
    """One start of the alternative's refit (runs on an engine worker); a FitState.

    ``warm``: from the current fit's noise and assumed density (off-diagonal factor 0);
    ``cold``: θ from the current estimates (the spec's initial values), the noise and the
    assumed density from the estimator's own noise starts (multi-start); it ends early
    (:class:`Superseded`) when the flag ``stop_key`` is raised."""
    from ..estimator import fit
    from ..model import load_model
    from .fitstate import diag_options, evaluated, refit_warm

    if start == "warm":
        return refit_warm(path, current, current, generated_dir=generated_dir,
                          iterations=2 * max_iter, max_iter=max_iter)
    m = load_model(path, generated_dir=generated_dir)
    records = list(current.records)
    kw = {} if stop_key is None else {"progress": _stop_poll(stop_key)}
    res = fit(m, records, options=diag_options(2 * max_iter, **kw))
    return evaluated(path, m, records, res, current.vrecords, max_iter=max_iter)


def _warm_converged(oc) -> bool:
    from ..engine import TaskStatus
    from .fitstate import refit_converged

    return (oc.key == "warm" and oc.status is TaskStatus.DONE
            and bool(refit_converged(oc.value.fit)))


def _best_start(outs):
    """The refit to decide with; (start, outcome) or None.

    A converged warm start decides: it is the optimum the current fit leads to, and the
    cold start is then not needed (serially it is not run, on a cluster it is stopped), so
    the decision does not depend on the number of workers. Otherwise the start with the
    highest ELBO, converged or not: a converged start below another start's iterate is a
    worse local optimum (a cold multi-start can land in one), not the alternative's
    maximum; the highest iterate, if it did not converge, still gives a lower bound of the
    statistic (:func:`decide`)."""
    from ..engine import TaskStatus

    done = [(st, o) for st, o in outs if o.status is TaskStatus.DONE]
    if not done:
        return None
    warm = [(st, o) for st, o in done if _warm_converged(o)]
    if warm:
        return warm[0]
    return max(done, key=lambda so: so[1].value.elbo)


def decide(trial: NoiseModelTrial, elbo_current: float, alpha: float) -> NoiseModelTrial:
    """Statistic, threshold (χ²_dof at α), p-value and verdict of one refitted alternative.

    A refit that stopped before an optimum still decides one way: the optimizer accepts only
    ascent steps, so ``Λ = 2(ELBO_iterate − ELBO_current)`` is a lower bound of the
    likelihood-ratio statistic ``2(sup ELBO_alternative − ELBO_current)``. Above the threshold
    the current noise model is rejected as surely as by the converged value
    (``SIGNIFICANT_NOT_CONVERGED``), but the iterate is no estimate to carry on (a refit from
    it would keep climbing the noise and count that as its gain), so it is not adopted; at
    or below the threshold the test is inconclusive (``NOT_CONVERGED``)."""
    thr = float(stats.chi2.isf(alpha, max(trial.dof, 1)))
    if trial.state is None:
        return dataclasses.replace(trial, threshold=thr, verdict=NoiseModelVerdict.FAILED)
    lam = 2.0 * (trial.state.elbo - elbo_current)
    p = float(stats.chi2.sf(max(lam, 0.0), max(trial.dof, 1)))
    if not trial.converged:
        v = (NoiseModelVerdict.SIGNIFICANT_NOT_CONVERGED if lam > thr
             else NoiseModelVerdict.NOT_CONVERGED)
    else:
        v = NoiseModelVerdict.ADOPTED if lam > thr else NoiseModelVerdict.NOT_SIGNIFICANT
    return dataclasses.replace(trial, statistic=lam, threshold=thr, p_value=p, verdict=v)


def run_noise_model(current, out: pathlib.Path, *, alpha: float, generated_dir, max_iter: int,
                    engine, deadline=None, progress=None,
                    after_round: int | None = None) -> NoiseModelResult:
    """Refit ``current`` (a search.FitState) with correlated process noise and decide (see
    the module docstring). The adopted trial's state is the model the run continues from.
    ``after_round``: None before physics (spec files ``r0_nII_…``); K when diagnose re-tests
    the noise model because round K accepted an effect (spec files ``rK_nII_…``)."""
    from ..engine import NOT_NEEDED, TaskStatus
    from .fitstate import refit_converged
    from .specwrite import safe_name

    tag = "r0" if after_round is None else f"r{int(after_round)}"
    model = current.model
    pn = model.process_noise
    states = tuple(pn.states or model.state_names) if pn is not None else ()
    structure = pn.structure if pn is not None else "diagonal"
    alts = noise_alternatives(model)
    if not alts:
        return NoiseModelResult(structure, states, current.elbo, (), alpha)
    if not refit_converged(current.fit):
        # neither the score (the gradient is not zero at a non-optimum) nor a refit's gain
        # (it also finishes the fit) tests the noise model against an unconverged fit
        if progress is not None:
            progress("noise model: not tested (the current fit did not converge)")
        return NoiseModelResult(structure, states, current.elbo, tuple(
            NoiseModelTrial(alt, pathlib.Path(out) / "candidates"
                            / f"{tag}_n{i + 1:02d}_noise_{alt.value}.yaml", dof,
                            verdict=NoiseModelVerdict.NOT_TESTED)
            for i, (alt, dof) in enumerate(alts)), alpha)
    t0 = time.perf_counter()
    trials = []
    for i, (alt, dof) in enumerate(alts):
        path = pathlib.Path(out) / "candidates" / f"{tag}_n{i + 1:02d}_noise_{alt.value}.yaml"
        if progress is not None:
            progress(("noise model first" if after_round is None else
                      f"noise model re-tested (round {after_round} accepted an effect)")
                     + ": refitting with correlated process noise on "
                     f"{', '.join(states)} ({dof} parameter{'s' if dof > 1 else ''} added)")
        write_noise_spec(current, path, f"{safe_name(model.name)[:30]}_"
                         f"{'' if after_round is None else tag}noise{i + 1}")
        try:
            score = score_test(current, path, generated_dir=generated_dir, dof=dof, alpha=alpha)
        except _SCORE_ERRORS as err:   # no statistic: the refit decides
            score = NoiseScore(None, dof, float(stats.chi2.isf(alpha, max(dof, 1))),
                               note=f"failed: {str(err).splitlines()[0][:200]}")
        if progress is not None:
            progress("    score test at the current fit: " + (
                f"S = {score.statistic:.4g} (threshold {score.threshold:.4g}, χ²({dof}))"
                if score.statistic is not None else score.note)
                + ("; no refit needed" if score.keeps_current else "; refitting"))
        if score.keeps_current:
            trials.append(NoiseModelTrial(alt, path, dof, statistic=score.statistic,
                                          threshold=score.threshold, p_value=score.p_value,
                                          converged=True,
                                          verdict=NoiseModelVerdict.NOT_SIGNIFICANT,
                                          wall_s=score.wall_s, score=score,
                                          decided_by="score"))
            continue
        # two starts: warm (from the current fit) and cold (the estimator's noise starts). From
        # the diagonal optimum the warm refit can crawl along a curved valley: on the
        # independent HFB-320 null record it rose 0.15 nats per iteration for 400 iterations
        # (ρ(V, α) → 0.9996) and stopped 0.25 nats below the optimum the cold multi-start
        # reached and converged at (a funnel: the V noise std grows 38× while the smoothed
        # path's roughness follows). Both starts are submitted in this order; once the warm
        # start has converged the cold one is not needed: serially it is not started, on a
        # cluster it is cancelled and, if already running, stops at its next poll of the
        # flag, so the decision is the same for any number of workers.
        stop_key = f"vsidgen-noise-stop-{os.urandom(6).hex()}"

        def decided(oc):
            if _warm_converged(oc):
                engine.request_stop(stop_key)
                return True
            return False

        outs = [(st, o) for st, o in zip(STARTS, engine.run(
            noise_refit_task, [(st, (current, path, generated_dir, max_iter, st, stop_key))
                          for st in STARTS], deadline=deadline, stop_when=decided))
                if not (o.status is TaskStatus.CANCELLED and o.error == NOT_NEEDED)]
        starts = tuple((st, None if o.status is not TaskStatus.DONE else
                        (float(o.value.elbo), bool(refit_converged(o.value.fit)),
                         int(getattr(o.value.fit, "iterations", 0)), float(o.wall_s)))
                       for st, o in outs)
        best = _best_start(outs)
        if best is None:
            errs = [f"{st}: {o.status.value}: {o.error}" for st, o in outs]
            trials.append(decide(NoiseModelTrial(alt, path, dof, error="; ".join(errs),
                                                 wall_s=sum(o.wall_s for _, o in outs),
                                                 starts=starts, score=score),
                                 current.elbo, alpha))
            continue
        start, o = best
        st = o.value
        names = [n for n in st.model.state_names if n in states]
        idx = [st.model.state_names.index(n) for n in names]
        Gs = np.asarray(st.fit.G, float)[np.ix_(idx, idx)]
        trials.append(decide(NoiseModelTrial(alt, path, dof, st, converged=refit_converged(st.fit),
                                             correlations=correlations(Gs, names),
                                             wall_s=sum(x.wall_s for _, x in outs),
                                             start=start, starts=starts,
                                             stop_reason=getattr(st.fit, "stop_reason", None),
                                             iterations=int(getattr(st.fit, "iterations", 0)),
                                             independent_shares=independent_shares(Gs, names),
                                             score=score),
                             current.elbo, alpha))
    good = [t for t in trials if t.verdict is NoiseModelVerdict.ADOPTED]
    adopted = max(good, key=lambda t: t.state.elbo) if good else None
    if progress is not None:
        for t in trials:
            if len(t.starts) > 1:
                progress("    starts: " + ", ".join(
                    f"{st} " + ("failed" if v is None else
                                f"ELBO {v[0]:.6g} ({'converged' if v[1] else 'NOT converged'}, "
                                f"{v[2]} it., {v[3]:.0f} s)") for st, v in t.starts)
                         + f"; deciding with the {t.start} start")
            progress(f"    {t.alternative.value}: 2ΔELBO {t.statistic:.4g} (threshold "
                     f"{t.threshold:.4g}, χ²({t.dof})) {t.verdict.value}"
                     + (f" [{t.error}]" if t.error else "")
                     + ("" if t.stop_reason is None or t.converged else
                        f" (refit stopped: {t.stop_reason.value} after {t.iterations} "
                        "iterations; independent share G_ii/√Q_ii: "
                        + ", ".join(f"{a} {v:.2g}" for a, v in t.independent_shares) + ")"))
        progress(("noise model: correlated process noise adopted" if adopted is not None
                  else "noise model: the current process noise is kept")
                 + f" ({time.perf_counter() - t0:.0f} s)")
    return NoiseModelResult(structure, states, current.elbo, tuple(trials), alpha, adopted)


__all__ = ["NoiseAlternative", "NoiseModelResult", "NoiseModelTrial", "NoiseModelVerdict",
           "NoiseScore", "correlations", "decide", "independent_shares", "noise_alternatives",
           "noise_refit_task", "run_noise_model", "score_test"]
