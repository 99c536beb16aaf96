"""A fitted model as diagnose handles it (:class:`FitState`) and the fits that make one:
the estimator options of diagnose's fits, evaluation (and validation smoothing), a refit
warm-started from another fit, convergence by the estimator's typed stop reason."""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import pathlib
from typing import Any

import numpy as np

from ..estimator import WarmStart
from .refit import (REFIT_DETERMINISTIC_REL, REFIT_DETERMINISTIC_STD, noise_parameters, noise_stds,
                    parameter_start)


@dataclasses.dataclass(frozen=True)
class FitState:
    """A fitted model: spec, model, fit, evaluation signals (estimation and validation)."""

    spec_path: pathlib.Path
    model: Any
    records: tuple
    fit: Any
    signals: tuple
    vrecords: tuple = ()
    vfit: Any = None
    vsignals: tuple = ()
    #: the validation records fitted with θ fixed and their own noise (:func:`validate_own_noise`)
    vfit_noise: Any = None

    @property
    def elbo(self) -> float:
        return float(self.fit.elbo)

    @property
    def val_elbo(self) -> float | None:
        return None if self.vfit is None else float(self.vfit.elbo)

    @property
    def val_elbo_own_noise(self) -> float | None:
        """The validation ELBO with θ fixed and the validation records' own noise
        (:func:`validate_own_noise`); None where not computed."""
        return None if self.vfit_noise is None else float(self.vfit_noise.elbo)


#: the deadline of the refit under way in this context (:func:`refit_deadline`)
_REFIT_DEADLINE: contextvars.ContextVar = contextvars.ContextVar("refit_deadline", default=None)


@contextlib.contextmanager
def refit_deadline(deadline):
    """Within the block, every fit configured by :func:`diag_options` stops at ``deadline``
    (an object with ``left()``, the seconds to it, e.g. :class:`.family.TaskDeadline`; None:
    no deadline) with the estimator's ``StopReason.TIME_LIMIT``: a refit still running when a
    round's time is up ends as an unconverged refit (its 2ΔELBO a lower bound when its Hessian
    is positive definite) instead of running past the time the round kept for its decision."""
    token = _REFIT_DEADLINE.set(deadline)
    try:
        yield
    finally:
        _REFIT_DEADLINE.reset(token)


def diag_options(max_iter, **kw):
    """Refit options: the states a candidate adds are quasi-deterministic (fixed small std, see
    refit.py); inside :func:`refit_deadline`, the time limit is the time left to it (at least
    one iteration runs: the estimator checks its limit after each)."""
    from ..estimator import FitOptions
    kw.setdefault("deterministic", "quasi")
    d = _REFIT_DEADLINE.get()
    if d is not None:
        left = max(float(d.left()), 0.0)
        given = kw.get("time_limit")
        kw["time_limit"] = left if given is None else min(float(given), left)
    kw.setdefault("deterministic_input_scale", REFIT_DETERMINISTIC_REL)
    return FitOptions(max_iter=max_iter, deterministic_std=REFIT_DETERMINISTIC_STD, **kw)


def fit_stage2(model, records, res1, *, max_iter: int, notes: list, warm_start=None):
    """Stage 2 of a staged refit: every parameter free, from stage 1's optimum ``res1``.

    A rejected ``warm_start`` falls back to a cold start; a Levenberg–Marquardt stall (no
    progress or an indefinite Hessian) gets one restart from where it stopped; a stage 2 that
    ends below stage 1 is noted (it nests stage 1). Each event is appended to ``notes``."""
    from ..errors import FitError
    from ..estimator import StopReason, fit

    opts = {} if warm_start is None else {"warm_start": warm_start}
    try:
        res2 = fit(model, records, options=diag_options(2 * max_iter, **opts))
    except FitError as err:
        if not opts:
            raise
        notes.append(f"stage-2 warm start rejected ({str(err).splitlines()[0]}); cold start")
        res2 = fit(model, records, options=diag_options(2 * max_iter))
    if not res2.converged and getattr(res2, "stop_reason", None) in (StopReason.NO_PROGRESS,
                                                                     StopReason.INDEFINITE_HESSIAN):
        try:
            res2b = fit(model, records, options=diag_options(max_iter, warm_start=res2))
            if res2b.elbo >= res2.elbo:
                notes.append(f"stage 2 restarted after a stall: {res2b.status}")
                res2 = res2b
        except FitError as err:
            notes.append(f"stage-2 restart failed ({str(err).splitlines()[0]})")
    if res2.elbo < res1.elbo - 1e-6 * max(1.0, abs(res1.elbo)):
        notes.append(f"stage 2 ended below stage 1 (ELBO {res2.elbo:.6g} < {res1.elbo:.6g})")
    return res2


@dataclasses.dataclass(frozen=True)
class OwnNoiseValidation:
    """Validation at each record's own noise and trim, one fit per validation record:
    ``elbo`` their sum, ``converged`` whether every one converged, ``fits`` the FitResults."""

    elbo: float
    converged: bool
    fits: tuple


def validate_own_noise(model, vrecords, theta, *, max_iter, free=()):
    """Each validation record fitted on its own with θ fixed — except the trim constants
    ``free`` — and its own noise (:func:`vsidgen.estimator.validate_own_noise`, diagnose's
    options): a flight's turbulence, sensor noise and trim are its own, so two validation
    flights do not share them. :class:`OwnNoiseValidation` (the ELBOs summed); None when a
    fit fails (the gate then compares the estimation-noise smoothing)."""
    from ..errors import FitError
    from ..estimator import validate_own_noise as own_noise

    fits = []
    for rec in vrecords:
        try:
            fits.append(own_noise(model, [rec], theta, free=free,
                                  options=diag_options(max_iter)))
        except FitError:
            return None
    if not fits:
        return None
    return OwnNoiseValidation(float(sum(f.elbo for f in fits)),
                              all(bool(f.converged) for f in fits), tuple(fits))


def trim_free(spec_path, model) -> tuple[str, ...]:
    """The model's free trim constants (:meth:`.SymbolicModel.trim_parameters` of its spec:
    the model's own symbolic form when it was loaded from ``spec_path``), re-estimated with the
    noise on each validation flight; () when the spec cannot be read."""
    from ..errors import VsidgenError
    from ..spec import compile_spec

    sym = getattr(model, "symbolic", None)
    try:
        if sym is None or pathlib.Path(sym.source_path).resolve() != \
                pathlib.Path(spec_path).resolve():
            sym = compile_spec(spec_path)
        names = sym.trim_parameters()
    except (VsidgenError, OSError):
        return ()
    own = {p.name for p in model.parameters if not p.fixed}
    return tuple(n for n in names if n in own)


def evaluated(spec_path, model, records, res, vrecords, *, max_iter) -> FitState:
    """Evaluate a fit; smooth the validation records with θ and noise fixed (the validation
    signals and ELBO) and fit them with θ fixed and their own noise (the validation gate's
    ELBO, :func:`validate_own_noise`)."""
    from ..estimator import smooth
    from ..evaluation import evaluate

    signals = tuple(evaluate(model, r, res.theta, mu=np.asarray(sm.mu), G=res.G, R=res.R)
                    for r, sm in zip(records, res.smoothers))
    vfit, vsignals, vfit_noise = None, (), None
    if vrecords:
        vfit = smooth(model, list(vrecords), res.theta, res, options=diag_options(max_iter))
        vsignals = tuple(evaluate(model, r, res.theta, mu=np.asarray(sm.mu), G=res.G, R=res.R)
                         for r, sm in zip(vrecords, vfit.smoothers))
        vfit_noise = validate_own_noise(model, vrecords, res.theta, max_iter=max_iter,
                                        free=trim_free(spec_path, model))
    return FitState(pathlib.Path(spec_path), model, tuple(records), res, signals, tuple(vrecords),
                    vfit, vsignals, vfit_noise)


#: a fit stopped because no step raises the ELBO any more (no progress, damping overflow) with
#: a positive-definite Hessian and at most this Newton decrement λ²/2 (nats) left is at its
#: optimum for a likelihood-ratio decision (:func:`refit_converged`)
NEAR_OPTIMUM_NATS = 0.05


def near_optimum(res) -> bool:
    """The fit stopped without a step that raises the ELBO (typed stop reason NO_PROGRESS or
    DAMPING_OVERFLOW), its Hessian positive definite and its Newton decrement λ²/2 =
    ½ gᵀH⁻¹g at most ``NEAR_OPTIMUM_NATS``.

    λ²/2 is the ELBO gain the local quadratic model still predicts. Where the objective has a
    kink — a hinge ``max(α − α_b, 0)`` whose break point is estimated: its sigma-point
    expectation is piecewise smooth in α_b — every step is rejected and the damping grows
    until the step vanishes, a few hundredths of a nat short of the decrement test (a stall
    break refit stopped at 0.0165 nats with 2ΔELBO 480.5, and was not accepted). Its
    2ΔELBO is then within 2·λ²/2 ≤ 0.1 of the optimum's, and, as every ELBO of the candidate
    is a lower bound of its maximum, its significance is not in doubt."""
    from ..estimator import StopReason

    reason = getattr(res, "stop_reason", None)
    dec = float(getattr(res, "newton_decrement", float("nan")))
    return (reason in (StopReason.NO_PROGRESS, StopReason.DAMPING_OVERFLOW)
            and np.isfinite(dec) and 0.0 <= dec <= NEAR_OPTIMUM_NATS)


def refit_converged(res) -> bool:
    """Converged by the estimator's typed stop reason (Newton decrement or gradient test), or
    stopped at a point where no step is possible within ``NEAR_OPTIMUM_NATS`` of the optimum
    (:func:`near_optimum`)."""
    reason = getattr(res, "stop_reason", None)
    if reason is None:
        return bool(res.converged)
    return reason.converged or near_optimum(res)


def conv_label(res) -> str:
    """"converged", "at its optimum to λ²/2 = … nats (no step possible)" or "NOT converged"
    (:func:`refit_converged`) for messages."""
    if not refit_converged(res):
        return "NOT converged"
    reason = getattr(res, "stop_reason", None)
    if reason is not None and not reason.converged:
        return (f"converged to within λ²/2 = {float(res.newton_decrement):.3g} nats "
                "(no step raises the ELBO: a kink)")
    return "converged"


def stage1_iterations(max_iter: int) -> int:
    """Stage 1 only has to bring the new parameters near their optimum (stage 2 finishes)."""
    return max(10, min(max_iter, 40))


def warm_start_from(m, records, source: FitState, *, keep_theta: bool = False) -> WarmStart:
    """The start of a fit of model ``m`` on ``records``: ``m``'s parameter initial values,
    ``source``'s noise and assumed density (the same states, or a superset of ``m``'s: a
    candidate that added states, its density restricted to ``m``'s states,
    :func:`.refit.restrict_decision`). ``keep_theta``: ``source``'s fitted parameters instead
    (the same model refitted at another noise setting: started at the initial values, the
    held reference of a user's model stopped at a saddle after 1600 iterations, 264 nats
    below the limit's ELBO; session 44)."""
    from .refit import restrict_decision

    z, _ = parameter_start(m)
    if keep_theta and list(source.model.parameter_names) == list(m.parameter_names):
        z = np.asarray(source.fit.decision["s"][:len(z)], dtype=float)
    ps, od, ms = noise_stds(source.fit, source.model)
    ps = {k: v for k, v in ps.items() if k in m.state_names}
    od = {k: v for k, v in od.items() if k[0] in m.state_names and k[1] in m.state_names}
    s0 = np.concatenate([z, noise_parameters(m, records, REFIT_DETERMINISTIC_STD, proc_std=ps,
                                             proc_G=od, meas_std=ms)])
    recs = source.fit.decision["records"]
    if list(source.model.state_names) != list(m.state_names):
        recs = restrict_decision(recs, source.model.state_names, m.state_names)
    return WarmStart.from_decision({"s": s0, "records": recs})


def refit_warm(path: pathlib.Path, source: FitState, current: FitState, *, generated_dir,
               iterations: int, max_iter: int, keep_theta: bool = False) -> FitState:
    """Fit the spec at ``path`` on the current records, warm-started from ``source``'s noise
    and assumed density (the same state layout) and the spec's parameter initial values
    (``keep_theta``: ``source``'s estimates, :func:`warm_start_from`)."""
    from ..estimator import fit
    from ..model import load_model

    m = load_model(path, generated_dir=generated_dir)
    records = list(current.records)
    res = fit(m, records, options=diag_options(
        iterations, warm_start=warm_start_from(m, records, source, keep_theta=keep_theta)))
    return evaluated(path, m, records, res, current.vrecords, max_iter=max_iter)


__all__ = ["FitState", "NEAR_OPTIMUM_NATS", "conv_label", "diag_options", "evaluated", "near_optimum", "refit_converged", "refit_warm",
           "stage1_iterations", "warm_start_from"]
