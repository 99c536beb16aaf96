"""Score (Lagrange-multiplier) pre-screen of every candidate without a refit.


At the current optimum the candidate model is evaluated at its nesting point (new
parameters at the values that reproduce the current model, current parameters,
noise and assumed density at their estimates; added states embedded as in stage 0
of the staged refit, see :func:`.refit.stage0_start`). With the estimator's exact
gradient ``g`` and Hessian ``H`` of the negative ELBO over the *whole* decision
vector (θ, noise, assumed-density parameters and state means of every record,
block-tridiagonal in time, eliminated as in the estimator's Newton step) the
Newton decrement

    ``gain = ½ gᵀ H⁻¹ g``

is the ELBO increase a quadratic model predicts for re-optimising everything. The
same decrement with the new parameters held at their nesting values (``gain₀``)
is what re-optimising the rest alone would give. At an exact optimum of the current
model ``gain₀ = 0`` and

    ``S = 2 (gain − gain₀) = g_nᵀ (H/H_rest)⁻¹ g_n``

is the score statistic of the new parameters, profiled over every other variable
through the Schur complement: it approximates the likelihood-ratio statistic
``2ΔELBO`` of the refit, asymptotically ``χ²_k`` under the current model. Taking
the difference keeps the approximation when the start is not exactly stationary
(added states embedded by simulation).

A direction along which the ELBO is flat at the nesting point (a time constant
whose gain is still zero, e.g. the lag of an α̇ term with zero gain) carries no
information at the null (Davies' problem): such parameters are held at their
nesting values and not counted in the degrees of freedom. New noise parameters
(a wind state's intensity at its vanishing start) are held likewise; a candidate
with nothing testable left gets ``None`` (its locate score decides).


Cost: candidates are screened in *batches*. A batch is one spec that adds several
candidates at once, every new parameter at its nesting value: frozen at those
values it is exactly the current model, so its gradient and Hessian at the current
optimum contain every candidate's blocks. One compilation, one Hessian assembly and
one elimination of the state means serve the whole batch; each candidate's
statistic is then a small Schur complement of the reduced (global) system
(holding a global variable fixed = deleting its row and column there). Candidates
whose new names collide, and those that add states beyond ``max_states`` per
batch, go to further batches.
"""

from __future__ import annotations

import dataclasses
import math
import pathlib

import numpy as np
from scipy import stats

from ..report import finite_or_none


@dataclasses.dataclass(frozen=True)
class ScoreResult:
    """Score statistic of one candidate (``statistic`` ≈ 2ΔELBO of its refit)."""

    statistic: float | None
    dof: int
    p_value: float | None
    tested: tuple[str, ...] = ()      # new parameters in the test
    held: tuple[str, ...] = ()        # new parameters held (flat at the null)
    gain_full: float = math.nan
    gain_rest: float = math.nan
    step: dict = dataclasses.field(default_factory=dict)   # one-step estimates of the tested
    note: str = ""

    @property
    def log10p(self) -> float:
        """−log10 p (inf-safe), the screening priority."""
        if self.statistic is None or self.dof < 1:
            return math.nan
        lp = float(stats.chi2.logsf(max(self.statistic, 0.0), self.dof))
        return -lp / math.log(10.0)

    def to_json(self) -> dict:
        f = finite_or_none
        return {"statistic": f(self.statistic), "dof": self.dof, "p_value": f(self.p_value),
                "minus_log10_p": f(self.log10p), "tested": list(self.tested),
                "held": list(self.held), "gain_full": f(self.gain_full),
                "gain_rest": f(self.gain_rest), "one_step": {k: f(v) for k, v in self.step.items()},
                "note": self.note}



def _names(c) -> set:
    return ({p.name for p in c.parameters} | {s.name for s in c.states}
            | set((c.definitions or {}).keys()))


def batches(candidates, *, max_states: int = 8) -> list[list]:
    """Group screenable candidates: all that add no state in one batch; those that add
    states in batches of at most ``max_states`` added states."""
    plain = [c for c in candidates if not c.states]
    out = [plain] if plain else []
    cur, ns = [], 0
    for c in (c for c in candidates if c.states):
        if cur and ns + len(c.states) > max_states:
            out.append(cur)
            cur, ns = [], 0
        cur.append(c)
        ns += len(c.states)
    if cur:
        out.append(cur)
    return out


def _rename(obj, ren: dict):
    """Apply the name map ``ren`` to every expression text and key of a spec fragment."""
    import re
    if not ren:
        return obj
    pat = re.compile(r"\b(" + "|".join(map(re.escape, sorted(ren, key=len, reverse=True)))
                     + r")\b")
    if isinstance(obj, str):
        return pat.sub(lambda mt: ren[mt.group(1)], obj)
    if isinstance(obj, dict):
        return {(ren.get(k, k) if isinstance(k, str) else k): _rename(v, ren)
                for k, v in obj.items()}
    if isinstance(obj, list):
        return [_rename(v, ren) for v in obj]
    return obj


def batch_spec_dict(cands, base_spec, *, name, path, info) -> tuple[dict, dict]:
    """One spec adding every candidate of ``cands`` (add_terms on one equation are summed).

    Names that two candidates both create (e.g. the slope of hinges at different break
    points) are made unique with a suffix. Returns (spec mapping, {key: {name: batch name}}).
    """
    d = {"name": name, "description": "score-test batch: " + ", ".join(c.key for c in cands)[:380],
         "extends": None}
    merged: dict = {}
    used: set = set()
    names: dict = {}
    for j, c in enumerate(cands):
        dc = c.spec_dict(base_spec, name=name, candidate_path=path, info=info)
        own = _names(c)
        ren = {n: f"{n}_b{j}" for n in own if n in used}
        used |= {ren.get(n, n) for n in own}
        names[c.key] = {n: ren.get(n, n) for n in own}
        d["extends"] = dc["extends"]
        dc = {k: (_rename(v, ren) if k in ("states", "parameters", "definitions", "drift",
                                           "add_terms", "noise") else v) for k, v in dc.items()}
        for sect in ("states", "parameters", "definitions", "drift"):
            if dc.get(sect):
                d.setdefault(sect, {}).update(dc[sect])
        for sect, terms in (dc.get("add_terms") or {}).items():
            for k, v in terms.items():
                merged.setdefault(sect, {}).setdefault(k, []).append(v)
        if dc.get("noise"):
            st = d.setdefault("noise", {"process": {"states": []}})["process"]["states"]
            for n in dc["noise"]["process"]["states"]:
                if n not in st:
                    st.append(n)
    if merged:
        d["add_terms"] = {sect: {k: " + ".join(f"({t})" for t in v) for k, v in terms.items()}
                          for sect, terms in merged.items()}
    return d, names


#: relative Marquardt damping of the score system: keeps the elimination of the state means and the
#: Cholesky factor of the global system defined where a curvature vanishes at the nesting point
SCORE_DAMPING = 1e-10


def _reduced_system(problem, blks, lam=SCORE_DAMPING):
    """Global Schur complement S (μ eliminated, :meth:`~vsidgen.estimator.Problem.reduced_system`) and
    reduced rhs, with the tiny Marquardt damping λ·max(|diag|, 1e-300) on every diagonal."""
    dmus = [np.maximum(np.abs(np.diagonal(np.asarray(b["D"]), axis1=1, axis2=2)), 1e-300)
            for b in blks]
    red = problem.reduced_system(blks, lam=lam, dmus=dmus)
    if red is None:
        return None, None
    S = red.S
    S += lam * np.diag(np.maximum(np.abs(np.diag(S)), 1e-300))
    return S, red.rhs


def screen_batch(cands, current, info, path: pathlib.Path, name: str, *, generated_dir,
                 det_std: float) -> dict:
    """Score statistics of the candidates of one batch: {key: ScoreResult}."""
    from ..estimator import FitOptions, Problem
    from ..model import load_model
    from .refit import noise_stds, stage0_start
    from .specwrite import warm_parameters, write_spec

    d, bnames = batch_spec_dict(cands, current.spec_path, name=name, path=path, info=info)
    params = warm_parameters(current.model, current.fit.theta)
    params.update(d.get("parameters") or {})
    d["parameters"] = params
    write_spec(path, "vsidgen diagnose score-test batch", d)
    m = load_model(path, generated_dir=generated_dir)
    records = list(current.records)
    base_fit = current.fit
    # the model's own integrator, sub-steps and input hold; records unpadded
    P = Problem(m, records, FitOptions(deterministic_std=det_std, bucket=False))
    z0 = P.parameter_start()
    theta = P.theta(z0)
    proc_std, offd, meas_std = noise_stds(base_fit, current.model)
    s = np.concatenate([z0, P.noise_vector(proc_std=proc_std, proc_G=offd, meas_std=meas_std,
                                           default_std=det_std)])
    new_states = [n for n in m.state_names if n not in current.model.state_names]
    if new_states:
        # the added states' assumed density is fitted first (θ, noise fixed: stage 0 of the
        # refit), so that the Hessian is taken at a stationary point of everything but the
        # new parameters
        from ..estimator import WarmStart, smooth
        dec, G1, R1, _, _ = stage0_start(m, records, base_fit, current.model, theta, det_std)
        r0 = smooth(m, records, theta, {"G": G1, "R": R1},
                    options=FitOptions(max_iter=100, deterministic="quasi", deterministic_std=det_std,
                                       warm_start=WarmStart.from_decision(dec)))
        recs = [(np.asarray(x["mu"], float), np.asarray(x["r"], float))
                for x in r0.decision["records"]]
    else:
        recs = [(np.asarray(x["mu"], float), np.asarray(x["r"], float))
                for x in base_fit.decision["records"]]
    blks = P.blocks(s, recs)
    nglob = P.layout.nglob
    free_names = P.free_names
    gpos = {n: int(j) for n, j in zip(free_names, P.layout.theta_index)}
    new_noise = [j for j in (P.process_noise_index(n) for n in new_states) if j is not None]
    new_par = {bnames[c.key][p.name] for c in cands for p in c.parameters if not p.fixed}
    Hdiag = np.diag(P.gather(blks)[1])
    S, rhs = _reduced_system(P, blks)
    out = {}
    if S is None:
        for c in cands:
            out[c.key] = ScoreResult(None, 0, None, note="state block not positive definite")
        return out
    # null: every new parameter and new-state noise held at its nesting value
    held_all = set(gpos[n] for n in new_par if n in gpos) | set(new_noise)
    rest = np.array([j for j in range(nglob) if j not in held_all], int)
    try:
        L0 = np.linalg.cholesky(S[np.ix_(rest, rest)])
    except np.linalg.LinAlgError:
        for c in cands:
            out[c.key] = ScoreResult(None, 0, None, note="Hessian not positive definite")
        return out

    def solve0(B):
        return np.linalg.solve(L0.T, np.linalg.solve(L0, B))

    a0 = solve0(rhs[rest])
    gain0 = 0.5 * float(rhs[rest] @ a0)
    dth = P.theta_jacobian(z0)
    free_idx = [m.parameter_names.index(n) for n in free_names]
    for c in cands:
        names = [p.name for p in c.parameters if not p.fixed and bnames[c.key][p.name] in gpos]
        bn = bnames[c.key]
        tested = [n for n in names if Hdiag[gpos[bn[n]]] > 1e-300]
        held = [n for n in names if n not in tested]
        if not tested:
            out[c.key] = ScoreResult(None, 0, None, held=tuple(held),
                                     note="no new parameter is informative at the nesting point")
            continue
        J = np.array([gpos[bn[n]] for n in tested], int)
        SJ0 = S[np.ix_(J, rest)]
        schur = S[np.ix_(J, J)] - SJ0 @ solve0(SJ0.T)
        rJ = rhs[J] - SJ0 @ a0
        try:
            dz = np.linalg.solve(schur, rJ)
        except np.linalg.LinAlgError:
            out[c.key] = ScoreResult(None, len(tested), None, tuple(tested), tuple(held),
                                     note="singular Schur complement")
            continue
        stat = float(max(rJ @ dz, 0.0))
        if not math.isfinite(stat) or np.any(np.linalg.eigvalsh(0.5 * (schur + schur.T)) <= 0):
            out[c.key] = ScoreResult(None, len(tested), None, tuple(tested), tuple(held),
                                     note="Schur complement not positive definite")
            continue
        step = {}
        for n, dzn in zip(tested, dz):
            j = free_names.index(bn[n])
            step[n] = float(theta[free_idx[j]] + dth[j] * dzn)
        out[c.key] = ScoreResult(stat, len(tested), float(stats.chi2.sf(stat, len(tested))),
                                 tuple(tested), tuple(held), gain0 + 0.5 * stat, gain0, step)
    return out


def screen(candidates, current, info, workdir: pathlib.Path, name: str, *, generated_dir,
           det_std: float, include_states: bool = False, progress=None) -> dict:
    """Score-screen every screenable candidate: {key: ScoreResult} (see the module docstring).

    ``include_states`` (default False): also screen candidates that add states (unsteady
    aerodynamics, missing modes). Their batch needs its own compilation and a smoothing
    run of the added states, which costs minutes on a 2-core machine, and the Schur
    complement of their gains was often not positive definite in the tests (the stiff,
    quasi-deterministic added states); by default they are ranked by their locate score.

    A small batch (≤ 8) that fails to build or evaluate is split into single candidates
    once; a candidate that still fails gets ``statistic None`` and a note (its locate
    score then decides).
    """
    from ..errors import FitError, SpecError, VsidgenError

    todo = [c for c in candidates if c.screenable and (include_states or not c.states)]
    out: dict = {}
    errs = (SpecError, FitError, VsidgenError, ValueError, ArithmeticError,
            np.linalg.LinAlgError, KeyError)

    def run(group, tag):
        try:
            out.update(screen_batch(group, current, info, workdir / f"{tag}.yaml",
                                    f"{name}_{tag}", generated_dir=generated_dir, det_std=det_std))
            return True
        except errs as err:
            if len(group) == 1 or len(group) > 8:
                for c in group:
                    out[c.key] = ScoreResult(None, 0, None,
                                             note=f"failed: {str(err).splitlines()[0][:200]}")
                return True
            return False

    for i, group in enumerate(batches(todo)):
        if progress is not None:
            progress(f"    score screen: batch {i + 1} ({len(group)} candidates)")
        if not run(group, f"b{i + 1}"):
            for j, c in enumerate(group):
                run([c], f"b{i + 1}_{j + 1}")
    return out
