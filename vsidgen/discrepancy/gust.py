"""The noise model before physics, second alternative: turbulence in the air-relative velocity.

A model written in body axes often *defines* its flow angles and airspeed from its velocity
states — ``a = atan2(w, u)``, ``V = sqrt(u² + w²)`` — so its aerodynamics take the state w as
the air-relative velocity. In turbulence they are not the same: the aircraft's inertial
velocity obeys the kinematic equation, and the aerodynamics see ``w − w_g``. Written with
the state as the air-relative velocity, the w equation receives ``−ẇ_g``: a *differentiated*
gust, whose increments telescope (a blue spectrum), which white process noise on ẇ cannot
represent. The misfit is systematic, and the physical catalogue absorbs part of it: on the
independent benchmark's body-axis null records (``hfbb_none_0_s0``, ``_s5``) a pitch mode
driven by q was named at 2ΔELBO 26.1 and 25.2 against 19.2, while a gust state in the
definitions raised the ELBO of ``_s5`` by 180.7 nats and left nothing significant.

So after the correlated-noise alternative (:mod:`.noisemodel`) and before any physical
candidate, :func:`run_gust_model` refits the current model with a gust state ``W`` of the
velocity component the flow angle is most sensitive to (``|∂α/∂x|`` largest among the
velocity states of α's expression: w for ``atan2(w, u)``), substituted as ``x − W`` in every
definition that uses that state (the flow angles and the airspeed; the kinematic drift keeps
the inertial velocity), with first-order dynamics ``Ẇ = −W/τ_W`` and process noise of its own
(correlated with the others when the noise structure is full). Its correlation time τ_W
starts at one sample (a Dryden gust of scale length L has τ = L/V: 0.06 s for the benchmark's
6 m at 105 m/s) and is estimated.

The test is ``Λ = 2(ELBO_gust − ELBO_current)``. The current model is the gust model with
the gust's variance at zero — on the boundary of the parameter space, where Wilks' χ² with
the number of added parameters k is conservative (the null distribution is a mixture with
smaller quantiles) — and τ_W is not identified under the null (Davies' problem), for which the
p-value is multiplied by the number of √2-spaced correlation times in τ_W's range
(Bonferroni, conservative). The gust's own initial-value entropy stays in the alternative's
ELBO (against it). Adopted, it is reported as a noise-model finding ("turbulence enters the
air-relative velocity"), never as a physical effect, and the physical search continues
with it.
"""

from __future__ import annotations

import dataclasses
import math
import pathlib
import time

import numpy as np
from scipy import stats

from .noisemodel import (NoiseAlternative, NoiseModelResult, NoiseModelTrial, NoiseModelVerdict,
                         correlations, decide)

#: the flow-angle roles a gust is looked for in (a vertical and a lateral gust)
GUST_ROLES = ("alpha", "beta")
#: τ_W's range: from half an integration step (RK4 and Euler are stable there) to this (s)
GUST_TAU_UPPER = 100.0
#: spacing of the correlation times counted for the Bonferroni multiplicity
GUST_GRID_RATIO = math.sqrt(2.0)


@dataclasses.dataclass(frozen=True)
class GustPlan:
    """What the gust alternative adds for one flow angle: the velocity state it perturbs, the
    names of the gust state and its correlation time, the rewritten definitions
    ``{name: spec text}`` and τ_W's start and bounds (s)."""

    role: str
    output: str
    velocity: str
    gust: str
    tau: str
    unit: str | None
    definitions: dict
    tau_start: float
    tau_bounds: tuple[float, float]

    @property
    def multiplicity(self) -> int:
        lo, hi = self.tau_bounds
        return 1 + int(math.floor(math.log(hi / lo) / math.log(GUST_GRID_RATIO)))


def gust_plans(current, info) -> list[GustPlan]:
    """The gusts that apply to ``current`` (a FitState; ``info`` its ModelInfo): one per
    flow-angle output (role α or β) that is not a state, computed through definitions from
    two or more velocity states (states of one unit), the perturbed one the state with the
    largest ``|∂(flow angle)/∂x|`` at the smoother's mean; [] when none applies (state flow
    angles, or a flow angle written inline in its observation)."""
    import sympy

    from ..spec import compile_spec
    from .base import spec_text

    sym = compile_spec(current.spec_path)
    defs = dict(sym.definitions)
    states = {v.name: v.unit for v in sym.states}
    mu = np.concatenate([np.asarray(s.mu, float) for s in current.fit.smoothers], axis=0)
    mean = dict(zip(current.model.state_names, mu.mean(axis=0)))
    values = {**info.constant_values,
              **dict(zip(current.model.parameter_names, map(float, current.fit.theta)))}
    h = float(info.dt or 0.01) / max(int(info.substeps or 1), 1)
    plans, taken = [], []
    for o, role in info.output_roles.items():
        if role not in GUST_ROLES or o in states:
            continue
        expr = info.observations_expanded.get(o)
        if expr is None:
            continue
        names = {s.name for s in expr.free_symbols}
        vel = [s for s in states if s in names and states[s] is not None]
        units = [states[s] for s in vel]
        vel = [s for s in vel if units.count(states[s]) >= 2]
        if len(vel) < 2:
            continue
        at = {s: values.get(s.name, mean.get(s.name, 0.0)) for s in expr.free_symbols}
        sens = {}
        for s in vel:
            d = sympy.diff(expr, next(x for x in expr.free_symbols if x.name == s))
            try:
                sens[s] = abs(float(d.subs(at)))
            except (TypeError, ValueError):
                sens[s] = 0.0
        x = max(vel, key=lambda s: sens[s])
        if not sens[x] > 0:
            continue
        users = {n: e for n, e in defs.items() if any(s.name == x for s in e.free_symbols)}
        raw_obs = dict(zip((v.name for v in sym.outputs), sym.observations)).get(o)
        if not users or raw_obs is None or any(s.name == x for s in raw_obs.free_symbols):
            continue    # the flow angle is not computed through definitions of x
        gust = info.fresh(f"D_GUST_{x}", taken=taken)
        tau = info.fresh(f"D_TAU_GUST_{x}", taken=[*taken, gust])
        taken += [gust, tau]
        xs = next(s for e in users.values() for s in e.free_symbols if s.name == x)
        W = sympy.Symbol(gust, real=True)
        rew = {}
        for n, e in users.items():
            text = spec_text(e.subs(xs, xs - W))
            if text is None:
                break
            rew[n] = text
        else:
            lo = 0.5 * h
            plans.append(GustPlan(role, o, x, gust, tau, states[x], rew,
                                  max(float(info.dt or h), lo), (lo, GUST_TAU_UPPER)))
    return plans


def write_gust_spec(current, plans, path: pathlib.Path, name: str, *, hold_tau: bool = False,
                    start=None) -> pathlib.Path:
    """Spec extending the current one with the gust states of ``plans`` (the process-noise
    states: the current ones and the gusts). Initial values: ``start``'s estimates (a fit of
    the gust model) or the current ones; ``hold_tau``: the correlation times fixed at their
    start (the first leg of :func:`gust_refit_task`)."""
    from .specwrite import extends_text, warm_parameters, write_spec

    pn = current.model.process_noise
    noisy = list(pn.states or current.model.state_names) if pn is not None else []
    params = warm_parameters(current.model, current.fit.theta)
    est = ({} if start is None else
           dict(zip(start.model.parameter_names, map(float, start.fit.theta))))
    for k, v in params.items():
        if k in est and not v.get("fixed"):
            v["initial"] = est[k]
    states, drift, defs = {}, {}, {}
    for p in plans:
        states[p.gust] = {"unit": p.unit or "1",
                          "description": f"gust in {p.velocity}: the aerodynamics see "
                                         f"{p.velocity} - {p.gust}"}
        params[p.tau] = {"unit": "s", "description": f"correlation time of the {p.velocity} gust",
                         "initial": float(est.get(p.tau, p.tau_start)),
                         **({"fixed": True} if hold_tau else {"bounds": list(p.tau_bounds)})}
        drift[p.gust] = f"-{p.gust}/{p.tau}"
        defs.update(p.definitions)
    return write_spec(path, "vsidgen diagnose: noise model with turbulence in the air-relative "
                            "velocity",
                      {"name": name,
                       "description": "the current model with a gust in the air-relative "
                                      "velocity its flow angles and airspeed are defined from",
                       "extends": extends_text(current.spec_path, path),
                       "states": states, "parameters": params, "definitions": defs,
                       "drift": drift,
                       "noise": {"process": {"states": noisy + [p.gust for p in plans]}}})


def gust_refit_task(current, plans, path: pathlib.Path, name: str, generated_dir,
                    max_iter: int):
    """The gust alternative's refit (runs on an engine worker); a FitState.

    Warm from the current fit, in two legs: (1) the correlation times held at one sample, the
    gust states embedded along their own transition (:func:`.refit.stage0_start`) with the
    process-noise std of the velocity they perturb (a scale-free start off the boundary,
    where the gradient of a vanishing std vanishes too), everything else free; (2) the
    correlation times free, from the first leg's optimum. (A cold multi-start with τ free
    stopped at its iteration limit on ``hfbb_none_0_s5``, 1413 iterations, 647 s, 64 nats
    below the optimum a fit with τ held reaches.)"""
    from ..estimator import WarmStart, fit
    from ..model import load_model
    from .fitstate import FitState, diag_options, refit_warm
    from .refit import (REFIT_DETERMINISTIC_STD, noise_parameters, noise_stds, parameter_start,
                        stage0_start)

    records = list(current.records)
    leg1 = path.with_name(f"{path.stem}_held.yaml")
    write_gust_spec(current, plans, leg1, f"{name}_h", hold_tau=True)
    m1 = load_model(leg1, generated_dir=generated_dir)
    z, theta = parameter_start(m1)
    dec0 = stage0_start(m1, records, current.fit, current.model, theta,
                        REFIT_DETERMINISTIC_STD)[0]
    ps, od, ms = noise_stds(current.fit, current.model)
    for p in plans:
        ps[p.gust] = ps.get(p.velocity, REFIT_DETERMINISTIC_STD)
    s1 = np.concatenate([z, noise_parameters(m1, records, REFIT_DETERMINISTIC_STD, proc_std=ps,
                                             proc_G=od, meas_std=ms)])
    r1 = fit(m1, records, options=diag_options(
        2 * max_iter, warm_start=WarmStart.from_decision({"s": s1, "records": dec0["records"]})))
    # the first leg is only the second's start: no evaluation signals, no validation fits
    st1 = FitState(leg1, m1, tuple(records), r1, ())
    write_gust_spec(current, plans, path, name, start=st1)
    return refit_warm(path, st1, current, generated_dir=generated_dir,
                      iterations=2 * max_iter, max_iter=max_iter)


def gust_dof(current, plans) -> int:
    """Parameters the gust alternative adds: per gust its noise std, its correlation time and,
    with a full noise structure, its correlations with the current noisy states and the
    gusts before it."""
    pn = current.model.process_noise
    full = pn is not None and pn.structure == "full"
    n0 = len(pn.states or current.model.state_names) if pn is not None else 0
    return sum(2 + ((n0 + i) if full else 0) for i in range(len(plans)))


def explanation(trial: NoiseModelTrial, plans) -> str:
    """Plain words for an adopted gust alternative."""
    est = dict(zip(trial.state.model.parameter_names, map(float, trial.state.fit.theta)))
    what = "; ".join(f"the aerodynamics see {p.velocity} − {p.gust} (the {p.role} definitions "
                     f"{', '.join(p.definitions)}), a gust of correlation time "
                     f"{p.tau} = {est.get(p.tau, math.nan):.3g} s" for p in plans)
    return ("Noise model, not physics: the turbulence enters the air-relative velocity the flow "
            "angles and airspeed are defined from, rather than forcing the rate of the model's "
            f"velocity state ({what}; 2ΔELBO = {trial.statistic:.4g} > {trial.threshold:.4g}, "
            f"χ²({trial.dof}) with its p-value multiplied by the number of correlation times "
            "searched). The model's velocity state is then the inertial one. Add the gust "
            f"state(s) as in {trial.spec_path.name}; the physical search continues with it.")


def applicable_plans(current, info) -> list[GustPlan]:
    """:func:`gust_plans` of ``current`` where the alternative can be tested: a converged fit
    whose process noise is estimated (else no plan)."""
    from .fitstate import refit_converged

    pn = current.model.process_noise
    if pn is None or not pn.estimate or not refit_converged(current.fit):
        return []
    return gust_plans(current, info)


def run_gust_model(current, info, out: pathlib.Path, *, alpha: float, generated_dir,
                   max_iter: int, engine, deadline=None, progress=None):
    """Refit ``current`` with the gusts of :func:`gust_plans` and decide (module docstring).
    Returns ``(NoiseModelResult, plans)``; the adopted trial's state is the model the run
    continues from. Nothing is tested (no trials) when no gust applies."""
    from ..engine import TaskStatus
    from .fitstate import refit_converged
    from .specwrite import safe_name

    model = current.model
    pn = model.process_noise
    states = tuple(pn.states or model.state_names) if pn is not None else ()
    structure = pn.structure if pn is not None else "diagonal"
    plans = applicable_plans(current, info)
    if not plans:
        return NoiseModelResult(structure, states, current.elbo, (), alpha), plans
    t0 = time.perf_counter()
    path = pathlib.Path(out) / "candidates" / "r0_g01_noise_air_relative_gust.yaml"
    dof = gust_dof(current, plans)
    m = max(p.multiplicity for p in plans)
    if progress is not None:
        progress("noise model: refitting with turbulence in the air-relative velocity ("
                 + ", ".join(f"{p.velocity} − {p.gust} in {', '.join(p.definitions)}"
                             for p in plans) + f"; {dof} parameters added)")
    (o,) = engine.run(gust_refit_task, [("gust", (current, plans, path,
                                                  f"{safe_name(model.name)[:30]}_gust",
                                                  generated_dir, max_iter))], deadline=deadline)
    if o.status is not TaskStatus.DONE:
        trial = decide(NoiseModelTrial(NoiseAlternative.AIR_GUST, path, dof,
                                       error=f"{o.status.value}: {o.error}", wall_s=o.wall_s),
                       current.elbo, alpha / m)
    else:
        st = o.value
        names = [n for n in st.model.state_names if n in states or n in {p.gust for p in plans}]
        idx = [st.model.state_names.index(n) for n in names]
        trial = decide(NoiseModelTrial(
            NoiseAlternative.AIR_GUST, path, dof, st, converged=refit_converged(st.fit),
            correlations=correlations(np.asarray(st.fit.G, float)[np.ix_(idx, idx)], names),
            wall_s=o.wall_s, start="warm", stop_reason=getattr(st.fit, "stop_reason", None),
            iterations=int(getattr(st.fit, "iterations", 0))), current.elbo, alpha / m)
    if math.isfinite(trial.statistic):
        p = float(stats.chi2.sf(max(trial.statistic, 0.0), max(dof, 1)))
        trial = dataclasses.replace(trial, p_value=min(1.0, m * p))
    adopted = trial if trial.verdict is NoiseModelVerdict.ADOPTED else None
    if progress is not None:
        progress(f"    air-relative gust: 2ΔELBO {trial.statistic:.4g} (threshold "
                 f"{trial.threshold:.4g}: χ²({dof}) at α/{m}) {trial.verdict.value}"
                 + (f" [{trial.error}]" if trial.error else "")
                 + f" ({time.perf_counter() - t0:.0f} s)")
    return NoiseModelResult(structure, states, current.elbo, (trial,), alpha, adopted), plans


def to_json(result: NoiseModelResult, plans) -> dict:
    """findings.json ``noise_gust``: the trial, the gusts tried and the adopted alternative."""
    a = result.adopted
    adopted = None if a is None else result.adopted_json(
        recommendation=f"add the gust state(s) of {a.spec_path.name}",
        explanation=explanation(a, plans))
    return {"kind": "noise_gust",
            "test": "2*(ELBO_gust - ELBO_current) against chi2(k), k the added parameters, at "
                    "alpha / m, m the number of sqrt(2)-spaced correlation times in the gust's "
                    "range (its variance at zero is on the boundary: conservative; its "
                    "correlation time unidentified under the null: Bonferroni)",
            "gusts": [{"role": p.role, "output": p.output, "velocity": p.velocity,
                       "gust_state": p.gust, "correlation_time": p.tau,
                       "definitions": dict(p.definitions), "multiplicity": p.multiplicity}
                      for p in plans],
            "elbo_current": float(result.elbo_current), "alpha": result.alpha,
            "trials": [t.to_json() for t in result.trials], "adopted": adopted}


__all__ = ["GustPlan", "applicable_plans", "explanation", "gust_dof", "gust_plans", "gust_refit_task", "run_gust_model", "to_json",
           "write_gust_spec"]
