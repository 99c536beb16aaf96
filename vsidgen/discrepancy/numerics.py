"""Numerical explanations before physics: the model's own discretisation as a candidate.

The estimator integrates the model over each sample with a chosen method (Euler or RK4),
a number of sub-steps and an input hold between samples (zero-order: inputs held; first
order: inputs interpolated linearly; :mod:`vsidgen.model.dynamics`). An aircraft integrates in
continuous time with inputs that move between samples, so a coarse setting leaves a
mismatch of its own: Euler with held inputs lags the continuous response by about half a
sample, which the physics catalogue would otherwise name a time skew, an α̇ term or an
actuator lag.

Before any physics candidate, :func:`run_numerics` refits the current model with each
setting of :func:`numerics_settings` (integrator rk4 if euler, 4 sub-steps, the
first-order hold; each a *model setting*, no term and no parameter added), warm-started
from the current fit.

Decision. The settings are not nested in the current model and add no parameter, so
Λ = 2(ELBO_setting − ELBO_current) has no χ² reference distribution. A setting is adopted
only when Λ exceeds the threshold a physics candidate with *one* new parameter would face
in a family of the m settings tried: the χ²₁ quantile at the Holm level α/(m − rank) of its
rank. That is stricter than any information criterion for models of equal dimension (AIC
and BIC accept any Λ > 0): a numerics setting is adopted only on evidence that would
accept a one-parameter physical effect, and among the significant ones the one with the
largest ELBO is adopted (within 0.5 nats of it: the one with the fewest drift evaluations
per sample, then the larger ELBO). The
adopted setting is a *modelling-numerics finding* ("use integrator: {...}"), reported
apart from the physical findings; the rest of the run (and the final spec) uses it.

Order. The most accurate setting of each input hold (the most drift evaluations per sample,
RK4 first among equals: :func:`most_accurate_per_hold`) is refitted first. Holm's procedure
adopts nothing unless the largest statistic clears its strictest level, χ²₁ at α/m; a coarser
integrator's discretisation lies between the current one and the most accurate of the same
hold, so it explains less of a discretisation mismatch. (The hold is not an accuracy: the
first-order hold models inputs that move between samples, the zero-order hold inputs a data
system held, and either can be the right one.) When every probe converges below that level
the other settings are therefore not refitted (verdict ``not_tried``; each would cost a
compilation of its own) and the decision is the one the whole family would give. Otherwise
every setting is refitted and decided as above.
"""

from __future__ import annotations

import dataclasses
import enum
import math
import pathlib
import time
from typing import Any

from scipy import stats

#: sub-steps proposed when the current setting has fewer
SUBSTEPS = 4


class NumericsVerdict(enum.Enum):
    """Outcome of one numerics setting (``findings.json`` → ``numerics.trials[].verdict``)."""

    ADOPTED = "adopted"
    SIGNIFICANT = "significant"          # above its threshold, but another setting was better
    NOT_SIGNIFICANT = "not_significant"
    NOT_CONVERGED = "not_converged"
    NOT_TRIED = "not_tried"              # no most accurate setting (per hold) was significant
    NOT_TESTED = "not_tested_base_unconverged"   # nothing can be decided against a non-optimum
    FAILED = "failed"


@dataclasses.dataclass(frozen=True)
class NumericsSetting:
    """One integrator setting: method, sub-steps and input hold."""

    method: str
    substeps: int
    inputs: str

    @classmethod
    def of(cls, model) -> "NumericsSetting":
        return cls(getattr(model, "integrator", "euler") or "euler",
                   int(getattr(model, "substeps", 1) or 1),
                   getattr(model, "input_hold", "zoh") or "zoh")

    def spec(self) -> dict:
        """The spec's ``integrator:`` mapping."""
        return {"method": self.method, "substeps": self.substeps, "inputs": self.inputs}

    @property
    def text(self) -> str:
        return (f"integrator: {{method: {self.method}, substeps: {self.substeps}, "
                f"inputs: {self.inputs}}}")

    @property
    def label(self) -> str:
        return f"{self.method}x{self.substeps}_{self.inputs}"

    def hold_lag(self, dt: float) -> float:
        """Delay (s) this setting's transition applies to a continuously moving input
        (:func:`.base.setting_hold_lag`)."""
        from .base import setting_hold_lag

        return setting_hold_lag(self.inputs, self.method, self.substeps, dt)

    @property
    def cost(self) -> int:
        """Drift evaluations per sample (tie-break: the cheaper setting)."""
        return self.substeps * (4 if self.method == "rk4" else 1)

    def to_json(self) -> dict:
        return {**self.spec(), "text": self.text}


def accurate_alternative(current: NumericsSetting) -> NumericsSetting:
    """The setting an input filter's timing (a transport delay, a lag) is compared with: RK4
    with a first-order hold for an Euler model — one Euler step has a phase error of the order
    of the hold's half sample, which depends on the model, so only an accurate integration
    times the input reliably (a first-order hold with one Euler step would equal the
    zero-order hold) — and the other input hold for any other integrator."""
    if current.method == "euler":
        return NumericsSetting("rk4", 1, "foh")
    return dataclasses.replace(current, inputs="foh" if current.inputs == "zoh" else "zoh")


def numerics_settings(current: NumericsSetting) -> list[NumericsSetting]:
    """Settings to test against ``current``: rk4 if euler, ``SUBSTEPS`` sub-steps if fewer,
    and the first-order hold with each integrator (a first-order hold with one Euler step
    evaluates the input only at the start of the interval, where it equals the zero-order
    hold, so that combination is never proposed). ``current`` itself is excluded."""
    methods = [current.method] + (["rk4"] if current.method == "euler" else [])
    subs = [current.substeps] + ([SUBSTEPS] if current.substeps < SUBSTEPS else [])
    holds = [current.inputs] + (["foh"] if current.inputs == "zoh" else [])
    out = []
    for m in methods:
        for s in subs:
            for h in holds:
                st = NumericsSetting(m, s, h)
                if st == current or (m == "euler" and s == 1 and h == "foh"):
                    continue
                if m != current.method and s != current.substeps:
                    continue   # rk4 with more sub-steps: one change at a time besides the hold
                out.append(st)
    return out


def most_accurate_per_hold(settings: list[NumericsSetting]) -> list[int]:
    """Indices of the most accurate setting (most drift evaluations per sample, RK4 first
    among equals) for each input hold among ``settings``, the first-order hold first.

    The hold is not an axis of accuracy: a first-order hold is the right model of inputs that
    move between samples, the zero-order hold of inputs a data system held. A coarser
    integrator lies between the current setting and the most accurate one *of its hold*, not
    of the other: on a new user's Twin Otter lateral record RK4 with a first-order hold lost
    (2ΔELBO −620.6) while RK4 with the held inputs gained, and one probe had taken both for
    one change (session 46)."""
    out = []
    for hold in ("foh", "zoh"):
        idx = [i for i, st in enumerate(settings) if st.inputs == hold]
        if idx:
            out.append(max(idx, key=lambda i: (settings[i].cost, settings[i].method == "rk4")))
    return out


@dataclasses.dataclass(frozen=True)
class NumericsTrial:
    """The current model refitted with one setting."""

    setting: NumericsSetting
    spec_path: pathlib.Path
    state: Any = None                    # search.FitState (None: failed)
    statistic: float = math.nan          # 2(ELBO_setting − ELBO_current)
    threshold: float = math.nan
    converged: bool = False
    verdict: NumericsVerdict = NumericsVerdict.FAILED
    error: str | None = None
    wall_s: float = 0.0

    def to_json(self) -> dict:
        def f(v):
            return None if v is None or not math.isfinite(v) else float(v)
        return {"setting": self.setting.to_json(), "spec": str(self.spec_path),
                "elbo": None if self.state is None else f(self.state.elbo),
                "statistic": f(self.statistic), "threshold": f(self.threshold),
                "converged": self.converged, "verdict": self.verdict.value,
                "error": self.error, "wall_s": round(self.wall_s, 2)}


@dataclasses.dataclass(frozen=True)
class NumericsResult:
    """The numerics stage of a diagnose run."""

    current: NumericsSetting
    elbo_current: float
    trials: tuple[NumericsTrial, ...]
    alpha: float
    adopted: NumericsTrial | None = None

    def to_json(self) -> dict:
        adopted = None
        if self.adopted is not None:
            a = self.adopted
            adopted = {"setting": a.setting.to_json(), "spec": str(a.spec_path),
                       "statistic": float(a.statistic), "threshold": float(a.threshold),
                       "elbo_before": float(self.elbo_current), "elbo_after": float(a.state.elbo),
                       "recommendation": f"use {a.setting.text}",
                       "explanation": explanation(self.current, a)}
        return {"kind": "modelling_numerics",
                "test": "2*(ELBO_setting - ELBO_current) against the chi2(1) quantile at the Holm "
                        "level of its rank over the settings tried (not nested, no parameter "
                        "added: the evidence a one-parameter physical effect would need)",
                "current": self.current.to_json(), "elbo_current": float(self.elbo_current),
                "alpha": self.alpha, "trials": [t.to_json() for t in self.trials],
                "adopted": adopted}


def explanation(current: NumericsSetting, trial: NumericsTrial) -> str:
    """Plain words for an adopted setting."""
    parts = []
    s = trial.setting
    if s.inputs != current.inputs:
        parts.append("the inputs move between samples (first-order hold: interpolated linearly) "
                     "instead of being held over each sample")
    if s.method != current.method:
        parts.append(f"the {s.method} integrator replaces {current.method}")
    if s.substeps != current.substeps:
        parts.append(f"{s.substeps} sub-steps per sample instead of {current.substeps}")
    return ("Modelling numerics, not physics: the mismatch shrinks when " + "; ".join(parts)
            + f" (2ΔELBO = {trial.statistic:.4g} > {trial.threshold:.4g}, no parameter added). "
            f"Use `{s.text}` in the spec; the physical search continues with it.")


def decide(trials, elbo_current: float, alpha: float, *,
           family: int | None = None) -> tuple[list[NumericsTrial], NumericsTrial | None]:
    """Thresholds (χ²₁ at Holm levels over ``family`` settings, default all trials), verdicts
    and the adopted trial (see module docstring)."""
    m = len(trials) if family is None else max(int(family), len(trials))
    order = sorted(range(len(trials)), key=lambda i: -(trials[i].statistic
                                             if trials[i].state is not None
                                             and math.isfinite(trials[i].statistic) else -math.inf))
    out = list(trials)
    going = True
    for rank, i in enumerate(order):
        t = trials[i]
        thr = float(stats.chi2.isf(alpha / (m - rank), 1))
        if t.state is None:
            out[i] = dataclasses.replace(t, threshold=thr, verdict=NumericsVerdict.FAILED)
            going = False
            continue
        sig = going and t.converged and t.statistic > thr
        if not t.converged:
            v = NumericsVerdict.NOT_CONVERGED
        else:
            v = NumericsVerdict.SIGNIFICANT if sig else NumericsVerdict.NOT_SIGNIFICANT
        going = sig
        out[i] = dataclasses.replace(t, threshold=thr, verdict=v)
    good = [t for t in out if t.verdict is NumericsVerdict.SIGNIFICANT]
    if not good:
        return out, None
    top = max(t.state.elbo for t in good)
    best = min((t for t in good if t.state.elbo >= top - 0.5),
               key=lambda t: (t.setting.cost, -t.state.elbo))
    out = [dataclasses.replace(t, verdict=NumericsVerdict.ADOPTED) if t is best else t for t in out]
    return out, next(t for t in out if t.verdict is NumericsVerdict.ADOPTED)


def write_setting_spec(current, setting: NumericsSetting, path: pathlib.Path, name: str, *,
                       bounds: dict | None = None):
    """Spec extending the current one with ``setting`` (current estimates as initial values;
    ``bounds``: {parameter: [lower, upper]} replacing the current model's, initial values
    clipped into them)."""
    from .specwrite import clip_to_bounds, extends_text, warm_parameters, write_spec

    params = warm_parameters(current.model, current.fit.theta)
    for k, b in (bounds or {}).items():
        if k in params:
            params[k]["bounds"] = list(b)
            params[k]["initial"] = clip_to_bounds(params[k]["initial"], list(b))
    return write_spec(path, f"vsidgen diagnose: modelling numerics {setting.text}",
                      {"name": name,
                       "description": f"the current model with {setting.text}",
                       "extends": extends_text(current.spec_path, path),
                       "integrator": setting.spec(),
                       "parameters": params})


def refit_setting(setting, current, path, name, generated_dir, max_iter):
    """One setting's warm refit (runs on an engine worker); a FitState."""
    from .fitstate import refit_warm

    write_setting_spec(current, setting, path, name)
    return refit_warm(path, current, current, generated_dir=generated_dir,
                       iterations=2 * max_iter, max_iter=max_iter)


def run_numerics(current, out: pathlib.Path, *, alpha: float, generated_dir, max_iter: int,
                  engine, deadline=None, progress=None) -> NumericsResult:
    """Refit ``current`` (a search.FitState) with every setting of :func:`numerics_settings`
    and decide (see the module docstring). Returns the :class:`NumericsResult`; its
    ``adopted`` trial's state is the model the rest of the run continues from."""
    from ..engine import TaskStatus
    from .fitstate import refit_converged
    from .specwrite import safe_name

    cur = NumericsSetting.of(current.model)
    settings = numerics_settings(cur)
    if not refit_converged(current.fit):
        # the current ELBO is below its optimum: any refit gains by merely finishing the fit,
        # so a setting's 2ΔELBO says nothing about the numerics (it would be a false finding)
        if progress is not None:
            progress("modelling numerics: not tested (the current fit did not converge, so a "
                     "refit's gain would not measure the integrator setting)")
        return NumericsResult(cur, current.elbo, tuple(
            NumericsTrial(s, pathlib.Path(out) / "candidates" / f"r0_{i + 1:02d}_numerics_{s.label}.yaml",
                          verdict=NumericsVerdict.NOT_TESTED) for i, s in enumerate(settings)),
            alpha)
    tasks = []
    paths = {}
    for i, s in enumerate(settings):
        p = pathlib.Path(out) / "candidates" / f"r0_{i + 1:02d}_numerics_{s.label}.yaml"
        paths[s.label] = (s, p)
        tasks.append((s.label, (s, current, p, f"{safe_name(current.model.name)[:30]}_num{i + 1}",
                                generated_dir, max_iter)))
    t0 = time.perf_counter()

    def refit(batch):
        got = []
        for o in (engine.run(refit_setting, batch, deadline=deadline) if batch else []):
            s, p = paths[o.key]
            if o.status is not TaskStatus.DONE:
                got.append(NumericsTrial(s, p, error=f"{o.status.value}: {o.error}",
                                         wall_s=o.wall_s))
                continue
            st = o.value
            got.append(NumericsTrial(s, p, st, 2.0 * (st.elbo - current.elbo),
                                     converged=refit_converged(st.fit), wall_s=o.wall_s))
        return got

    m = len(tasks)
    firsts = most_accurate_per_hold(settings)
    trials = []
    if firsts and m > len(firsts):
        if progress is not None:
            progress("modelling numerics first: refitting with the most accurate setting of "
                     "each input hold, " + ", ".join(settings[i].text for i in firsts))
        trials = refit([tasks[i] for i in firsts])
        strictest = float(stats.chi2.isf(alpha / m, 1))
        if all(t.state is not None and t.converged and not t.statistic > strictest
               for t in trials):
            trials += [NumericsTrial(settings[i], paths[settings[i].label][1],
                                     verdict=NumericsVerdict.NOT_TRIED)
                       for i in range(m) if i not in firsts]
        else:
            if progress is not None:
                progress("modelling numerics: refitting with " + ", ".join(
                    settings[i].text for i in range(m) if i not in firsts))
            trials += refit([tk for i, tk in enumerate(tasks) if i not in firsts])
    else:
        if progress is not None and tasks:
            progress("modelling numerics first: refitting with " + ", ".join(s.text for s in settings))
        trials = refit(tasks)
    tried = [t for t in trials if t.verdict is not NumericsVerdict.NOT_TRIED]
    skipped = [t for t in trials if t.verdict is NumericsVerdict.NOT_TRIED]
    decided, adopted = decide(tried, current.elbo, alpha, family=m)
    trials = list(decided) + skipped
    if progress is not None:
        for t in trials:
            if t.verdict is NumericsVerdict.NOT_TRIED:
                progress(f"    {t.setting.text}: not tried (the most accurate setting of each "
                         "input hold was not significant)")
                continue
            progress(f"    {t.setting.text}: 2ΔELBO {t.statistic:.4g} (threshold "
                     f"{t.threshold:.4g}) {t.verdict.value}" + (f" [{t.error}]" if t.error else ""))
        progress((f"modelling numerics: {adopted.setting.text} adopted" if adopted is not None
                  else "modelling numerics: the current setting is kept")
                 + f" ({time.perf_counter() - t0:.0f} s)")
    return NumericsResult(cur, current.elbo, tuple(trials), alpha, adopted)


__all__ = ["NumericsResult", "NumericsSetting", "NumericsTrial", "NumericsVerdict",
           "accurate_alternative", "decide", "most_accurate_per_hold", "numerics_settings",
           "refit_setting", "run_numerics"]
