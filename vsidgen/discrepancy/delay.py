"""A pure transport delay of an input, in seconds, found by profiling the delay.

Physics: the aircraft responds to ``u(t − τ)`` while the recorder stores ``u(t)`` (transport
delay in a control system, filters, data acquisition). The model realises it by shifting the
recorded input itself, ``u_τ(t_k) = u(t_k − τ)``, linearly interpolated between samples, so
fractional-sample delays are represented (:func:`vsidgen.data.delay_input`; in a spec:
``inputs: {de: {delay: 0.12}}``). Unlike the Padé state of ``control_delay`` this adds no
state and is exact for any delay the sampling resolves.

τ is a nonlinear parameter whose likelihood is multimodal (a delay of one control period
fits nearly as well as one of three), so a local refit from τ = 0 stops in the nearest
optimum. Instead the ELBO is *profiled*: for each τ of :func:`delay_grid` (half, whole
and multiples of samples up to about a second) the current model is refitted (warm from
the current fit, all parameters and noise free) on records with the input shifted. The
best grid value is then refined by the vertex of the parabola through it and its two
neighbours and refitted there from the spec that carries the delay. Its standard error
comes from the curvature of that parabola (the profile likelihood's: ``var τ ≈ 1/c`` for
``ELBO(τ) ≈ a − c (τ − τ̂)²/2``).

Test: Λ = 2(ELBO(τ̂) − ELBO_current) with one degree of freedom. Because τ̂ was chosen as
the best of ``n`` grid values, its p-value is multiplied by ``n`` (Bonferroni over the
grid), which covers the maximisation over τ conservatively; the round's Holm correction
then counts the profiled input as one more candidate.

Screening (:func:`.score.screen_input_filters`): before any refit the delay gets a score
statistic like every other candidate, so it is ranked on the same p-value scale. For each
grid delay τ_k the family ``u + g_k (u_{τ_k} − u)`` (the recorded input moved towards its
delayed copy by a gate ``g_k``) contains the current model at ``g_k = 0`` and the input
delayed by τ_k at ``g_k = 1``, for any model, linear in u or not. All gates are parameters
of one model (the current one with the differences as extra input channels,
:func:`.score.gate_bank`), so one compilation and one Hessian assembly at the current
optimum give every grid delay's one-degree-of-freedom score statistic ``S_k``. The input's
statistic is ``max_k S_k``, its p-value ``min(1, K·P(χ²₁ > max_k S_k))`` (Bonferroni over
the ``K`` grid delays, as the profile's), and the best τ_k is where the profile starts.
(Lags and Padé delays are screened the same way over their time constants.)

Units: the spec carries the delay τ̂ applied to the recorded samples. A model that holds
its inputs over each sample (zero-order hold) already delays a continuously moving input by
half a sample on average (:func:`hold_lag`), so the physical transport delay reported is
τ̂ + lag; both are given.
"""

from __future__ import annotations

import dataclasses
import math
import pathlib
import time

import numpy as np
from scipy import stats

from ..data import delay_input
from .base import hold_lag

#: grid of delays in samples (refined around the best one); capped at ``MAX_DELAY_S``
GRID_SAMPLES = (0.5, 1.0, 1.5, 2.0, 3.0, 4.0, 6.0, 8.0, 12.0, 16.0, 24.0, 32.0)
MAX_DELAY_S = 1.0


def delay_grid(dt: float, max_s: float = MAX_DELAY_S) -> list[float]:
    """Delays (s) to profile: ``GRID_SAMPLES`` × dt up to ``max_s`` (at least the first two)."""
    g = [k * dt for k in GRID_SAMPLES if k * dt <= max_s + 1e-12]
    return g if len(g) >= 2 else [k * dt for k in GRID_SAMPLES[:2]]


def shifted_records(records, input_index: int, tau: float):
    """Records with input ``input_index`` delayed by ``tau`` seconds (other inputs unchanged)."""
    out = []
    for r in records:
        u = np.array(r.u, dtype=np.float64)
        u[:, input_index] = delay_input(u[:, input_index], np.asarray(r.t, float), tau)
        u.setflags(write=False)
        out.append(dataclasses.replace(r, u=u))
    return tuple(out)


def parabola_vertex(x, y) -> tuple[float, float]:
    """Vertex ``x̂`` and curvature ``c`` (> 0 for a maximum: y ≈ a − c (x − x̂)²/2) of the
    parabola through three points (x increasing)."""
    x0, x1, x2 = map(float, x)
    y0, y1, y2 = map(float, y)
    d01 = (y1 - y0) / (x1 - x0)
    d12 = (y2 - y1) / (x2 - x1)
    a2 = (d12 - d01) / (x2 - x0)          # y = a2 x² + ...
    if not a2 < 0:
        return math.nan, math.nan
    b = d01 - a2 * (x0 + x1)
    return -b / (2 * a2), -2 * a2


def _grid_task(current, j: int, tau: float, iterations: int):
    """ELBO of the current model refitted (warm) with input j delayed by tau; (elbo, converged)."""
    from ..estimator import fit
    from .fitstate import diag_options, refit_converged

    recs = shifted_records(current.records, j, tau)
    res = fit(current.model, list(recs), options=diag_options(iterations, warm_start=current.fit))
    return float(res.elbo), bool(refit_converged(res))


def write_delay_spec(current, u: str, tau: float, path: pathlib.Path, name: str):
    from .specwrite import extends_text, warm_parameters, write_spec

    return write_spec(path, f"vsidgen diagnose candidate transport_delay:{u}",
                      {"name": name,
                       "description": f"transport_delay:{u}: the model sees {u} delayed by "
                                      f"{tau:.6g} s",
                       "extends": extends_text(current.spec_path, path),
                       "inputs": {u: {"delay": float(tau)}},
                       "parameters": warm_parameters(current.model, current.fit.theta)})


def _final_task(current, u: str, j: int, tau: float, path, name, generated_dir, max_iter):
    """Refit at the refined delay from the spec that carries it; a FitState."""
    from ..estimator import fit
    from ..model import load_model
    from .fitstate import diag_options, evaluated

    write_delay_spec(current, u, tau, path, name)
    m = load_model(path, generated_dir=generated_dir)
    recs = shifted_records(current.records, j, tau)
    vrecs = shifted_records(current.vrecords, j, tau)
    res = fit(m, list(recs), options=diag_options(2 * max_iter, warm_start=current.fit))
    return evaluated(path, m, recs, res, vrecs, max_iter=max_iter)


@dataclasses.dataclass(frozen=True)
class DelayProfile:
    """The profiled ELBO of one input's delay and the refined estimate."""

    input: str
    grid: tuple[float, ...]
    elbos: tuple[float, ...]              # per grid value (NaN: failed)
    best_grid: float
    estimate: float
    std_error: float
    state: object = None                  # FitState at the estimate
    wall_s: float = 0.0
    at_zero: bool = False                 # the profile is highest at τ = 0 (the current model)

    def to_json(self) -> dict:
        def f(v):
            return None if v is None or not math.isfinite(v) else float(v)
        return {"input": self.input, "grid_s": [float(g) for g in self.grid],
                "elbo": [f(e) for e in self.elbos], "best_grid_s": f(self.best_grid),
                "estimate_s": f(self.estimate), "std_error_s": f(self.std_error),
                "at_zero": self.at_zero, "wall_s": round(self.wall_s, 2)}


def profile_delay(current, u: str, path: pathlib.Path, name: str, *, engine, generated_dir,
                  max_iter: int, deadline=None, start: float | None = None) -> DelayProfile | None:
    """Profile the delay of input ``u`` (see the module docstring); None when the run ran out
    of time. When the profile is highest at τ = 0 (the current model itself) no refit is
    made: ``at_zero`` is set and ``state`` is None.

    ``start`` (s, the best grid delay of the screen, :func:`.score.screen_input_filters`): refit the grid
    delays nearest ``start`` and its two neighbours, then climb the grid towards the higher
    neighbour until the best refit has refitted neighbours on both sides (a local maximum
    of the profile bracketed on the grid); without it every grid delay is refitted. Grid
    delays not refitted have ELBO NaN; the Bonferroni factor stays the whole grid's."""
    from ..engine import TaskStatus
    from .fitstate import stage1_iterations

    t0 = time.perf_counter()
    j = list(current.model.input_names).index(u)
    dt = float(np.median([r.dt for r in current.records]))
    grid = delay_grid(dt)
    iters = stage1_iterations(max_iter)
    xs = [0.0] + list(grid)
    ys = [current.elbo] + [math.nan] * len(grid)
    done = {0}

    def refit(idx) -> bool:
        idx = [i for i in dict.fromkeys(idx) if 0 < i < len(xs) and i not in done]
        if not idx:
            return True
        outs = engine.run(_grid_task, [(f"{u}@{xs[i]:.6g}", (current, j, xs[i], iters))
                                       for i in idx], deadline=deadline)
        if any(o.status is TaskStatus.CANCELLED for o in outs):
            return False
        for i, o in zip(idx, outs):
            ys[i] = o.value[0] if o.status is TaskStatus.DONE else math.nan
            done.add(i)
        return True

    if start is None or not math.isfinite(start):
        if not refit(range(1, len(xs))):
            return None
    else:
        s0 = 1 + int(np.argmin([abs(g - start) for g in grid]))
        if not refit((s0 - 1, s0, s0 + 1)):
            return None
        while True:
            b = max((i for i in done if math.isfinite(ys[i])), key=lambda k: ys[k])
            if not refit((b - 1, b + 1)):
                return None
            if b == max((i for i in done if math.isfinite(ys[i])), key=lambda k: ys[k]):
                break
    elbos = ys[1:]
    ok = [i for i in range(1, len(xs)) if math.isfinite(ys[i])]
    if not ok:
        return DelayProfile(u, tuple(grid), tuple(elbos), math.nan, math.nan, math.nan, None,
                            time.perf_counter() - t0)
    i = max(ok, key=lambda k: ys[k])
    if ys[i] <= ys[0]:
        return DelayProfile(u, tuple(grid), tuple(elbos), 0.0, 0.0, math.nan, None,
                            time.perf_counter() - t0, at_zero=True)
    est, curv = xs[i], math.nan
    if 0 < i < len(xs) - 1 and all(math.isfinite(ys[k]) for k in (i - 1, i, i + 1)):
        v, c = parabola_vertex(xs[i - 1:i + 2], ys[i - 1:i + 2])
        if math.isfinite(v) and xs[i - 1] < v < xs[i + 1]:
            est, curv = v, c
    oc = engine.run(_final_task, [(f"{u}@final", (current, u, j, est, path, name, generated_dir,
                                                  max_iter))], deadline=deadline)[0]
    state = oc.value if oc.status is TaskStatus.DONE else None
    if state is not None and state.elbo < ys[i] and est != xs[i]:
        # the vertex was worse than the best grid value: keep the grid value
        est, state2 = xs[i], None
        oc2 = engine.run(_final_task, [(f"{u}@grid", (current, u, j, est, path, name,
                                                      generated_dir, max_iter))],
                         deadline=deadline)[0]
        state2 = oc2.value if oc2.status is TaskStatus.DONE else None
        state = state2 if state2 is not None else state
    se = 1.0 / math.sqrt(curv) if curv > 0 else math.nan
    return DelayProfile(u, tuple(grid), tuple(elbos), xs[i], est, se, state,
                        time.perf_counter() - t0)


def delay_p_value(statistic: float, n_grid: int) -> float:
    """χ²₁ upper tail of Λ, times the number of grid values profiled (Bonferroni), at most 1."""
    if not (math.isfinite(statistic) and statistic > 0):
        return 1.0
    return float(min(1.0, n_grid * stats.chi2.sf(statistic, 1)))


__all__ = ["DelayProfile", "delay_grid", "delay_p_value", "parabola_vertex", "profile_delay",
           "hold_lag", "shifted_records"]
