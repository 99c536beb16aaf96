"""One compiled model per round: the round's candidates as gated terms of one model.

Every candidate that adds no state and nests the current model exactly at its initial
parameter values (``Candidate.screenable``; transport delays are profiled, not refitted)
is a set of terms ``g_c(x, u; φ_c)`` with ``g_c(·; φ_c⁰) ≡ 0`` at its nesting values
``φ_c⁰``. The *gated model* of a group of such candidates is the current model plus all
their terms,

    ``ẋ = f(x, u; θ) + Σ_c g_c^f(x, u; φ_c)``,  ``y = h(x, u; θ) + Σ_c g_c^h(x, u; φ_c)``,

so with every ``φ_c = φ_c⁰`` it *is* the current model (same drift, outputs, noise layout
and assumed density), and with all ``φ_d = φ_d⁰, d ≠ c`` it is candidate ``c``'s model.
Candidate ``c``'s refit is therefore a fit of the gated model in which the other
candidates' parameters are ``fixed`` at their nesting values. Which parameters are free is
a run-time array of the estimator's parameter map (:class:`~vsidgen.estimator.core.ThetaMap`,
its static key is only the *number* of free parameters), and fixed values are run-time
arrays as well, so one compilation of the gated model serves every candidate's stages 1
and 2 (the candidate's and the current parameters free, the current ones held at their
estimates in stage 1: ``FitOptions.held_parameters``; ``n_θ + k`` free parameters), the
validation smoothing (nothing free) and the projected refits (the current parameters free,
every candidate at nesting: ``n_θ``) of the round.
Candidates with the same number ``k`` of new parameters share every compiled function.

The stages are those of :func:`.search.staged_refit` for a candidate that adds no state
(stage 1 warm-started from the current optimum, stage 2 from stage 1, one restart after a
stall); the statistics are the same numbers up to the optimizer's tolerance (test:
``tests/test_gated.py`` against the per-candidate path).

Candidates that add states are not gated: an inert added state (a lag at its smallest
time constant, a mode at zero gain) still changes the dimension of the assumed density and
adds the entropy of its own marginal, so a model with every candidate's states would not
be the current model at the nesting point, and its extra states would cost every other
candidate's refit (the factorisation is cubic in the state dimension). They keep their own
spec (:func:`.search.staged_refit`); those of one shape share one compilation as a model
family instead (:mod:`.family`). Candidates whose new names collide go to separate groups
(one compilation each).

The accepted candidate of a round becomes its own spec (:func:`adopt`): the gated fit
configured for it is its fit (same likelihood, same free parameters), carried over without
a new compilation; the next round extends that spec.
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
import pathlib
import time

import numpy as np

from ..errors import FitError
from ..estimator import WarmStart
from .base import Candidate, ModelInfo
from .fitstate import FitState, diag_options, evaluated, fit_stage2, refit_warm, stage1_iterations
from .refit import (REFIT_DETERMINISTIC_STD as DET, RefitOutcome, noise_parameters, noise_stds,
                    parameter_start)
from .specwrite import clip_to_bounds, warm_parameters, write_spec


def gateable(c: Candidate) -> bool:
    """Whether ``c`` can be a gated term: no added state, exact nesting, not profiled."""
    return bool(c.screenable and not c.states and (c.info or {}).get("profile") != "delay")


def _names(c: Candidate) -> set:
    return ({p.name for p in c.parameters} | {s.name for s in c.states}
            | set((c.definitions or {}).keys()))


def gated_groups(cands) -> list[list[Candidate]]:
    """Gateable candidates in groups whose new names do not collide (first fit, in order)."""
    groups: list[list[Candidate]] = []
    used: list[set] = []
    for c in cands:
        own = _names(c)
        for g, u in zip(groups, used):
            if not (own & u):
                g.append(c)
                u |= own
                break
        else:
            groups.append([c])
            used.append(set(own))
    return groups


@dataclasses.dataclass(frozen=True)
class GatedGroup:
    """A written gated spec: its path, the candidates it holds and the current model's
    parameter names (the rest are candidates' parameters)."""

    path: pathlib.Path
    keys: tuple[str, ...]
    base_names: tuple[str, ...]


def write_gated_spec(cands, current: FitState, info: ModelInfo, path: pathlib.Path,
                     name: str) -> GatedGroup:
    """Write the gated spec of ``cands`` (extends the current spec; current parameters start
    at their estimates, the candidates' at their nesting values)."""
    from .score import batch_spec_dict

    d, bnames = batch_spec_dict(cands, current.spec_path, name=name, path=path, info=info)
    if any(k != v for m in bnames.values() for k, v in m.items()):
        raise ValueError("gated group with colliding names (use gated_groups)")
    d["description"] = "gated candidates: " + ", ".join(c.key for c in cands)[:380]
    params = warm_parameters(current.model, current.fit.theta)
    params.update(d.get("parameters") or {})
    d["parameters"] = params
    write_spec(path, "vsidgen diagnose: the round's candidates as gated terms of one model", d)
    return GatedGroup(pathlib.Path(path), tuple(c.key for c in cands),
                      tuple(current.model.parameter_names))


_LOADED: dict = {}


def gated_model(group: GatedGroup, generated_dir):
    """The gated model of ``group``, loaded once per process (one Model object, so every
    refit of the round finds the estimator's compiled objective in its cache)."""
    from ..model import load_model

    key = (str(group.path.resolve()), hashlib.sha256(group.path.read_bytes()).hexdigest())
    m = _LOADED.get(key)
    if m is None:
        if len(_LOADED) >= 8:
            _LOADED.pop(next(iter(_LOADED)))
        m = load_model(group.path, generated_dir=generated_dir)
        _LOADED[key] = m
    return m


def configured(model, base_names, own, values: dict, *, free_base: bool):
    """``model`` with parameter metadata for one fit (same functions, so the same compiled
    code): current parameters free when ``free_base`` (else fixed at their initial values),
    the parameters named in ``own`` free (as the candidate declares them), every other
    candidate parameter fixed at its nesting (initial) value; ``values`` overrides initial
    values (clipped to the bounds)."""
    base = set(base_names)
    out = []
    for p in model.parameters:
        init = float(values.get(p.name, p.initial))
        if p.name in base:
            fixed = bool(p.fixed) or not free_base
        elif p.name in own:
            fixed = bool(p.fixed)
        else:
            fixed, init = True, float(p.initial)
        if not fixed and math.isfinite(init):
            init = clip_to_bounds(init, (p.lower, p.upper))
        out.append(dataclasses.replace(p, fixed=fixed, initial=init))
    return dataclasses.replace(model, parameters=tuple(out))


def _warm(model, records, fit_result, source_model, z):
    ps, od, ms = noise_stds(fit_result, source_model)
    s = np.concatenate([z, noise_parameters(model, records, DET, proc_std=ps, proc_G=od,
                                            meas_std=ms)])
    return WarmStart.from_decision({"s": s, "records": fit_result.decision["records"]})


def gated_refit(c: Candidate, current: FitState, group: GatedGroup, path: pathlib.Path, *,
                generated_dir, max_iter: int, progress=None) -> RefitOutcome:
    """Staged refit of candidate ``c`` as a fit of its group's gated model (see the module
    docstring). The result's FitState carries the gated model configured for ``c`` and
    ``spec_path = path`` (``c``'s own spec, written by the caller)."""
    from ..estimator import fit

    t0 = time.perf_counter()
    gm = gated_model(group, generated_dir)
    out = RefitOutcome()
    records = list(current.records)
    base_fit = current.fit
    own = {p.name for p in c.parameters}
    out.elbo_ref = current.elbo
    # ---- stage 1: current parameters held, the candidate's free, the others at nesting;
    # stage 2 is the same problem with nothing held (one layout: shared compiled functions)
    m2 = configured(gm, group.base_names, own, {}, free_base=True)
    held = tuple(p.name for p in m2.parameters if not p.fixed and p.name not in own)
    z1, _ = parameter_start(m2)
    opts1 = {"held_parameters": held}
    if base_fit.decision is not None:
        opts1["warm_start"] = _warm(m2, records, base_fit, current.model, z1)
        out.warm = "base (gated model)"
    else:
        out.warm = "cold"
    try:
        res1 = fit(m2, records, options=diag_options(stage1_iterations(max_iter), **opts1))
    except FitError as err:
        if "warm_start" not in opts1:
            raise
        out.notes.append(f"warm start rejected ({str(err).splitlines()[0]}); cold start")
        res1 = fit(m2, records, options=diag_options(stage1_iterations(max_iter),
                                                     held_parameters=held))
    out.elbo_stage1, out.converged_stage1 = float(res1.elbo), bool(res1.converged)
    if progress is not None:
        progress(f"    stage 1: ELBO {res1.elbo:.6g} (reference {out.elbo_ref:.6g}, "
                 f"{'converged' if res1.converged else 'not converged'})")
    # ---- stage 2: everything of c free from stage 1's optimum
    ws2 = None if res1.decision is None else WarmStart.from_decision(res1.decision)
    res2 = fit_stage2(m2, records, res1, max_iter=max_iter, notes=out.notes, warm_start=ws2)
    out.state = evaluated(path, m2, records, res2, current.vrecords, max_iter=max_iter)
    out.wall_s = time.perf_counter() - t0
    return out


def candidate_spec(c: Candidate, st: FitState, current: FitState, info: ModelInfo,
                   path: pathlib.Path, name: str) -> pathlib.Path:
    """Write ``c``'s own spec (extends the current spec) with every parameter's initial value
    at the estimates of ``st`` (a fit of the gated model configured for ``c``)."""
    est = dict(zip(st.model.parameter_names, map(float, st.fit.theta)))
    d = c.spec_dict(current.spec_path, name=name, candidate_path=path, info=info)
    theta = [est.get(n, float(v)) for n, v in zip(current.model.parameter_names,
                                                  current.fit.theta)]
    params = warm_parameters(current.model, theta)
    new = d.get("parameters") or {}
    for k, v in new.items():
        if k in est and math.isfinite(est[k]) and not v.get("fixed"):
            v["initial"] = clip_to_bounds(est[k], v.get("bounds"))
    params.update(new)
    d["parameters"] = params
    return write_spec(path, f"vsidgen diagnose candidate {c.key}\n# effect: {c.effect}; "
                            f"target: {c.target}", d)


def _restricted(fit, names_from, names_to):
    """A FitResult of the gated model expressed in the parameters ``names_to`` (a subset that
    holds every free parameter, in the same order): θ, standard errors and the free mask are
    restricted; the free × free correlation and covariance, the noise, the assumed density
    and the decision vector are those of the same free parameters and stay as they are."""
    idx = [list(names_from).index(n) for n in names_to]
    return dataclasses.replace(fit, parameter_names=tuple(names_to),
                               theta=np.asarray(fit.theta)[idx],
                               std_errors=np.asarray(fit.std_errors)[idx],
                               free_mask=np.asarray(fit.free_mask)[idx])


def adopt(c: Candidate, st: FitState, current: FitState, info: ModelInfo, path: pathlib.Path,
          name: str, *, generated_dir, max_iter: int) -> FitState:
    """The accepted candidate as its own spec and model (the next round extends this spec).

    The gated model configured for ``c`` *is* ``c``'s model (the other candidates' terms are
    zero at their fixed nesting values), so its fit, evaluation signals and validation
    smoothing are those of ``c``'s own spec, written with the estimates as initial values:
    they are carried over with the other candidates' (fixed) parameters dropped, after
    checking that both models free the same parameters in the same order. Otherwise ``c``'s
    spec is fitted warm from the gated optimum (the same point, so the fit stops at once)."""
    from ..model import load_model

    candidate_spec(c, st, current, info, path, name)
    own = load_model(path, generated_dir=generated_dir)
    gn, on = list(st.model.parameter_names), list(own.parameter_names)
    free_g = [p.name for p in st.model.parameters if not p.fixed]
    free_o = [p.name for p in own.parameters if not p.fixed]
    fixed_g = {p.name: float(p.initial) for p in st.model.parameters if p.fixed}
    same_fixed = all(math.isclose(float(p.initial), fixed_g.get(p.name, math.nan), rel_tol=1e-12,
                                  abs_tol=1e-300) for p in own.parameters if p.fixed)
    if (set(on) <= set(gn) and free_g == free_o and same_fixed
            and own.state_names == st.model.state_names
            and own.output_names == st.model.output_names):
        vfit = None if st.vfit is None else _restricted(st.vfit, gn, on)
        return dataclasses.replace(st, spec_path=pathlib.Path(path), model=own,
                                   fit=_restricted(st.fit, gn, on), vfit=vfit)
    return refit_warm(path, st, current, generated_dir=generated_dir, iterations=max_iter,
                      max_iter=max_iter)


def gated_projected(c: Candidate, st: FitState, current: FitState, group: GatedGroup,
                    path: pathlib.Path, *, generated_dir, max_iter: int) -> FitState:
    """The projected refit (:func:`.search.projected_refit`) on the gated model: the current
    parameters free from the candidate's optimum, every candidate at its nesting values (the
    current model exactly), noise and assumed density warm from the candidate's fit.
    ``path`` gets a spec of the same model (extends ``c``'s spec, its terms fixed at nesting)
    for the record."""
    from ..estimator import fit
    from .specwrite import extends_text

    gm = gated_model(group, generated_dir)
    est = dict(zip(st.model.parameter_names, map(float, st.fit.theta)))
    base_est = {n: est[n] for n in group.base_names if n in est}
    m = configured(gm, group.base_names, set(), base_est, free_base=True)
    theta = [base_est.get(n, float(v)) for n, v in zip(current.model.parameter_names,
                                                       current.fit.theta)]
    params = warm_parameters(current.model, theta)
    for q in c.parameters:
        params[q.name] = {**q.spec(), "initial": float(q.initial), "fixed": True}
    write_spec(path, f"vsidgen diagnose: projected refit of {c.key}",
               {"name": f"{path.stem}"[:60].replace(".", "_"),
                "description": f"{c.key} with its new terms at their nesting values "
                               "(the current model), started at the candidate's optimum",
                "extends": extends_text(st.spec_path, path), "parameters": params})
    z, _ = parameter_start(m)
    res = fit(m, list(current.records), options=diag_options(
        2 * max_iter, warm_start=_warm(m, list(current.records), st.fit, st.model, z)))
    return evaluated(path, m, list(current.records), res, current.vrecords, max_iter=max_iter)


__all__ = ["GatedGroup", "adopt", "candidate_spec", "configured", "gateable", "gated_groups",
           "gated_model", "gated_projected", "gated_refit", "write_gated_spec"]
