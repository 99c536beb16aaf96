"""Options and result records of the variational estimator."""

from __future__ import annotations

import dataclasses
import math
import enum
from collections.abc import Callable

import numpy as np


class StopReason(enum.Enum):
    """Why the optimizer stopped (typed; ``message`` is for people, ``value`` is the stable code).

    Two members are optima: ``NEWTON_DECREMENT`` (the Hessian of −ELBO is positive definite
    on the free subspace and a full Newton step would raise the ELBO by less than
    ``FitOptions.decrement_tol`` nats) and ``GRADIENT`` (the relative gradient is below
    ``FitOptions.gtol``: stationary to floating-point precision). Every other member is a
    stop without an optimum, with its reason.
    """

    NEWTON_DECREMENT = "newton_decrement"
    GRADIENT = "gradient"
    ITERATION_LIMIT = "iteration_limit"
    TIME_LIMIT = "time_limit"
    STALLED = "stalled"
    NO_PROGRESS = "no_progress"
    INDEFINITE_HESSIAN = "indefinite_hessian"
    DAMPING_OVERFLOW = "damping_overflow"
    NONFINITE = "nonfinite"

    @property
    def converged(self) -> bool:
        return self in (StopReason.NEWTON_DECREMENT, StopReason.GRADIENT)

    @property
    def message(self) -> str:
        return _STOP_MESSAGES[self]


_STOP_MESSAGES = {
    StopReason.NEWTON_DECREMENT: "converged: a Newton step would raise the ELBO by less than the tolerance "
                                 "(positive-definite Hessian)",
    StopReason.GRADIENT: "converged: relative gradient below gtol",
    StopReason.ITERATION_LIMIT: "stopped at the iteration limit before reaching an optimum",
    StopReason.TIME_LIMIT: "stopped at the time limit before reaching an optimum",
    StopReason.STALLED: "abandoned: the ELBO stopped rising far from an optimum (another noise start is tried)",
    StopReason.NO_PROGRESS: "stopped: no step raises the ELBO although a Newton step predicts a gain "
                            "(line search failure)",
    StopReason.INDEFINITE_HESSIAN: "stopped: no further progress at a point where the Hessian of −ELBO is "
                                   "not positive definite (a saddle or a flat direction, not an optimum)",
    StopReason.DAMPING_OVERFLOW: "stopped: the damping overflowed without an acceptable step",
    StopReason.NONFINITE: "stopped: the gradient is not finite",
}


class StdErrorIssue(enum.Enum):
    """Why the standard errors of a fit need attention (typed; ``value`` is the stable code).

    Each member is raised only when its cause is present (see :func:`std_error_issues` in
    ``vsidgen.estimator.fit`` and docs/estimator.md): a converged fit of an identifiable
    model with no parameter near a bound carries none, and its standard errors are the
    square roots of diag [H⁻¹]_θθ (H the Hessian of −ELBO, noise and assumed densities
    re-optimised: the Schur complement), whose 95 % intervals were measured to cover the
    truth on the model zoo. ``message`` says what is wrong, ``action`` what to do.
    """

    NOT_CONVERGED = "not_converged"
    HESSIAN_NOT_PD = "hessian_not_positive_definite"
    NEAR_SINGULAR = "near_singular_information"
    AT_BOUND = "parameter_at_bound"
    DETERMINISTIC_LIMIT = "deterministic_limit_not_reached"

    @property
    def message(self) -> str:
        return _SE_MESSAGES[self][0]

    @property
    def action(self) -> str:
        return _SE_MESSAGES[self][1]


_SE_MESSAGES = {
    StdErrorIssue.NOT_CONVERGED: (
        "the fit did not reach an optimum: the curvature there is not the information of an estimate",
        "raise --max-iter, try another --noise-start or better initial values"),
    StdErrorIssue.HESSIAN_NOT_PD: (
        "the Hessian of −ELBO is not positive definite on the free parameters: no standard errors",
        "some combination of parameters is not determined by the data: fix one of the parameters "
        "named or fly a manoeuvre that separates them"),
    StdErrorIssue.NEAR_SINGULAR: (
        "the information is nearly singular: the data determine a combination of parameters, "
        "not each of them",
        "fix one of the parameters named (e.g. to a wind-tunnel value) or add a manoeuvre that "
        "excites them separately"),
    StdErrorIssue.AT_BOUND: (
        "a parameter is within 1.96 standard errors of a bound: its symmetric 95 % interval crosses "
        "the bound and the Gaussian interval is not valid",
        "check the bound; if it is physical, fix the parameter at it or report a one-sided interval"),
    StdErrorIssue.DETERMINISTIC_LIMIT: (
        "the limit of vanishing process noise on the states without it was not reached: estimates and "
        "standard errors are those of a small process noise on them",
        "give those states process noise in the spec if the data need it"),
}


@dataclasses.dataclass(frozen=True)
class StdErrorFlag:
    """One reason the standard errors need attention: the issue, the parameters involved, details."""

    issue: StdErrorIssue
    parameters: tuple[str, ...] = ()
    detail: str = ""

    @property
    def message(self) -> str:
        named = f" ({', '.join(self.parameters)})" if self.parameters else ""
        detail = f"; {self.detail}" if self.detail else ""
        return f"{self.issue.message}{named}{detail}: {self.issue.action}"

    def to_json(self) -> dict:
        return {"code": self.issue.value, "parameters": list(self.parameters), "detail": self.detail,
                "message": self.message}


class PhaseKind(enum.Enum):
    """What a run of optimizer iterations is part of (typed; ``value`` is the stable code).

    The optimizer restarts its iteration count for each of them; they are not all noise
    starts: the stages of the deterministic-limit continuation (process noise of states
    without it taken to zero, docs/estimator.md) are one fit continued at a smaller noise.
    """

    NOISE_START = "noise_start"      # one start of --noise-start (auto: each tried in turn)
    RELEASE_LEG = "release_leg"      # legs 2 and 3 of the release start (noise freed, released)
    LIMIT_STAGE = "limit_stage"      # a stage of the deterministic-limit continuation
    SMOOTHING = "smoothing"          # validation smoothing (θ and noise fixed)


@dataclasses.dataclass(frozen=True)
class FitPhase:
    """The phase a progress callback is told about before its iterations (``str()``: the label).

    ``start``: the noise start it belongs to; ``stage``: the continuation stage (numbered as
    ``FitResult.deterministic_limit["stages"]``, 0 = the first) and ``scale`` its process-noise
    std relative to the first stage's; ``max_stages``: the most full stages the continuation
    takes; ``leg``: the release start's leg; ``continued``: more iterations of a phase run
    before (a stalled start continued when no start converged).
    """

    kind: PhaseKind
    start: str | None = None
    stage: int | None = None
    scale: float | None = None
    max_stages: int | None = None
    leg: str | None = None
    continued: bool = False
    smoothing: bool = False

    def __str__(self) -> str:
        parts = []
        if self.smoothing:
            parts.append("validation smoothing")
        if self.start is not None:
            parts.append(f"noise start {self.start}")
        if self.kind is PhaseKind.RELEASE_LEG and self.leg:
            parts.append(self.leg)
        if self.kind is PhaseKind.LIMIT_STAGE:
            of = f" of at most {self.max_stages}" if self.max_stages else ""
            std = f", std × {self.scale:.2g}" if self.scale is not None else ""
            parts.append(f"deterministic limit, stage {self.stage}{of}{std}")
        text = ": ".join(parts) or self.kind.value
        return text + (" (continued)" if self.continued else "")


def announce(progress, phase: FitPhase) -> None:
    """Tell a progress callback that has a ``phase`` method which phase the next iterations
    belong to (a plain ``progress(iteration, elbo, grad_norm, elapsed)`` callback has none)."""
    hook = getattr(progress, "phase", None)
    if callable(hook):
        hook(phase)


@dataclasses.dataclass(frozen=True)
class FitOptions:
    """Options of :func:`vsidgen.estimator.fit` and :func:`~vsidgen.estimator.smooth`.

    Attributes:
        integrator: "euler" | "rk4"; None → ``model.integrator``.
        substeps: integration substeps per sample; None → ``model.substeps``.
        input_hold: "zoh" | "foh", inputs held or interpolated linearly between samples
            (:mod:`vsidgen.model.dynamics`); None → ``model.input_hold``.
        max_iter: iteration limit of the optimizer.
        gtol: convergence tolerance on the *relative gradient*
            ``max_i |∂(−L)/∂v_i| · max(|v_i|, 1) / max(|L|, 1)`` over the whole
            decision vector v (θ in unconstrained coordinates, noise log-stds,
            assumed-density parameters, state means); it is invariant to the
            scale of the ELBO and of each variable that is ≳ 1.
        init_states: "measured" (μ from outputs that equal a state, NaN
            interpolated, zero for unmeasured states) or "zero".
        optimizer: "structured-newton" (default: Levenberg–Marquardt damped
            Newton exploiting the block-tridiagonal Hessian) or "trust-constr"
            (scipy.optimize.minimize reference path, dense Hessian–vector products).
        progress: callback(iteration, elbo, grad_norm, elapsed_s) called each iteration; the
            iteration count restarts with each phase (noise start, continuation stage of the
            deterministic limit). A callback with a ``phase(FitPhase)`` method is told the
            phase before its iterations (:func:`announce`; ``str(phase)`` is its label).
        verbose: print one line per iteration.
        deterministic: how states without process noise (deterministic states, e.g.
            φ̇ = p) are treated. "limit" (default): the fit is the limit of process-noise
            std ε → 0 on those states, computed by continuation (a first stage with their
            noise estimated, then ε shrunk tenfold per stage with a warm start until the
            ELBO changes by less than ``limit_tol`` nats and every free parameter by less
            than ``limit_tol`` standard errors; see docs/estimator.md). "quasi": a fixed
            std ``deterministic_std`` (the diagnose refits' added states use this).
        deterministic_std: std (state unit/√s) of the deterministic states in "quasi" mode.
        deterministic_input_scale: None (default) or a factor: a deterministic state that
            carries an input (its unit, a drift depending on it: a lag or delay state,
            :func:`vsidgen.estimator.core.input_filter_scales`) gets the std
            ``deterministic_input_scale · std(u)`` per √s instead of ``deterministic_std``,
            scale-free in the unit the input is recorded in (the diagnose refits set it).
        input_state_prior: states that carry an input (a lag, Padé or actuator state of
            input u, :func:`vsidgen.estimator.core.input_filter_scales`) whose initial value
            gets a proper prior, x_0 ~ N(u_0, std(u)²) (u_0 the input's first finite sample,
            std(u) its spread over the record), instead of the flat prior of the other states.
            Under a flat prior the initial value of a fast lag is a free impulse on the first
            step (a kick of 10⁴ deg through a coupling of 10⁻³), which the evidence of the
            model then counts as a gain; the actuator starts within the command's range. The
            ELBO gains E_q log N(x_0; u_0, std(u)²) per such state and record. "all" (default):
            every such state whose input varies; "none": the flat prior; or state names.
        limit_tol: stopping tolerance of the deterministic limit, in nats for the ELBO
            and in standard errors for the parameters (per stage change).
        decrement_tol: convergence tolerance in nats on half the Newton decrement,
            λ²/2 = ½ gᵀH⁻¹g, the ELBO gain predicted for a full Newton step over all
            decision variables (active noise floors held fixed), required together with
            H positive definite on that free subspace. It is invariant to affine
            reparametrisations (the units of every parameter) and, being a difference of
            log-likelihoods, means the same for every record length. See docs/estimator.md.
        xtol: stop (not converged) when the relative step falls below this.
        negative_curvature: where the relative-gradient test is met at an indefinite
            Hessian (a saddle of the ELBO, not a maximum), step along the Hessian's most
            negative curvature (state means included, through the Schur complement of the
            border; ``estimator.fit._curvature_step``) and go on iterating, instead of
            reporting the saddle as converged.
        warm_start: a :class:`WarmStart`, or a previous FitResult of the same problem
            shape (its ``decision``), to start from.
        lambda0: initial Levenberg–Marquardt damping (Marquardt diagonal scaling).
        noise_start: starting point of the noise parameters (θ always starts at the
            spec's initial values): "data" (measurement std from the robust spread of
            the sample-to-sample differences, process std of measured states from the
            same spread / √T), "data-meas" (measurement std from the data, process std
            1 coherent unit/√s), "unit" (all std 1 coherent unit above their floors: 1 rad for
            an angle declared in deg, 1 m/s for a speed in ft/s), "release" (for unmeasured states
            with estimated process noise: those states first held deterministic in the
            exact limit with every other std fixed at its "data" start, then the other
            noise freed, then their stds released from where the limit ended; see
            docs/estimator.md; the "data" start where there is no such state) or "auto"
            (default: try every one of them, "release" first where it applies, then the
            others in the order above; the converged start with the highest ELBO is
            returned, else the highest ELBO of all; the highest start that stopped
            without an optimum (iteration limit, stalled) above every converged start, or
            when none converged, is continued for another ``max_iter`` iterations first,
            and returned, as not converged, if it still ends above them; ``iterations``
            and ``history`` count all starts). A converged start is a local optimum, not necessarily the best:
            on HFB-320 the "data" and "data-meas" starts converge at ELBO 14890.77, 73.9
            nats below the "unit" start's optimum. The likelihood surfaces of real records have local optima in which
            one channel's measurement std collapses onto its floor; different noise
            starts reach different ones.
        stall_window, stall_rtol: while further noise starts remain ("auto"), a start is
            abandoned as *stalled* when its ELBO L rose by less than
            ``stall_rtol · max(|L|, 1)`` over the last ``stall_window`` iterations without
            meeting the gradient criterion, unless a noise std is sliding onto a positive
            floor fast enough to make it active within the remaining iterations (then the
            start is about to converge). A start creeping along a collapsed-noise valley (a
            measurement std shrinking towards a floor it would need hundreds of iterations
            to reach, with the state glued to the measurement) gains nothing per iteration
            while its gradient stays large (it may still be continued after the others:
            see ``noise_start``).
            ``stall_window=0`` disables the test.
        parallel_starts: run the noise starts of ``"auto"`` concurrently, one thread each
            (they share the problem's compiled functions; XLA runs them in parallel while
            each start's sequential scans and host-side steps leave cores idle). The result
            is the serial one: every start follows its own deterministic path, and the last
            start is abandoned as stalled exactly when the serial run would abandon it —
            only if an earlier start converged (it waits for them to decide). Progress is
            reported for the first unfinished start. False: one start after the other.
        bucket: pad each record to a bucket length (:func:`vsidgen.estimator.core.bucket_length`,
            ≤ 12.5 % longer) for the structured optimizer, with the padding masked out of every
            term, so records of different lengths in one bucket reuse the compiled functions;
            the ELBO, gradient and optimum are those of the unpadded records.
        time_limit: wall-clock budget in seconds (None: none); when it is exceeded the
            optimizer stops after the current iteration (not converged, status says so,
            ``iteration_limit`` warning). Used by the benchmark to bound the reference path.
        held_parameters: names of free parameters held at their start values (the warm
            start's, or the spec's initial values): the optimizer never moves them and
            convergence is judged on the other variables (projected gradient and Newton
            decrement, like an active bound). The problem's layout is that of the model, so a
            fit with some parameters held and one with none share every compiled function
            (diagnose's staged refits). Structured optimizer only.
    """

    integrator: str | None = None
    substeps: int | None = None
    input_hold: str | None = None
    max_iter: int = 200
    gtol: float = 1e-6
    decrement_tol: float = 1e-3
    init_states: str = "measured"
    optimizer: str = "structured-newton"
    progress: Callable | None = None
    verbose: bool = False
    deterministic: str = "limit"
    deterministic_std: float = 1e-6
    deterministic_input_scale: float | None = None
    limit_tol: float = 0.1
    xtol: float = 1e-13
    negative_curvature: bool = True
    warm_start: WarmStart | FitResult | None = None
    lambda0: float = 1e-3
    noise_start: str = "auto"
    stall_window: int = 10
    bucket: bool = True
    time_limit: float | None = None
    stall_rtol: float = 1e-8
    held_parameters: tuple[str, ...] = ()
    parallel_starts: bool = True
    input_state_prior: str | tuple[str, ...] = "all"

    def __post_init__(self):
        """Numbers checked where they are given (``FitOptions(max_iter=-1)`` ended in a
        TypeError inside the optimizer; session 44)."""
        from ..errors import FitError

        def count(name, low):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < low:
                raise FitError(f"FitOptions: {name} must be an integer >= {low}, got {v!r}")

        def positive(name, *, optional=False, zero=False):
            v = getattr(self, name)
            if v is None and optional:
                return
            if isinstance(v, bool) or not isinstance(v, (int, float, np.number)) or not (
                    math.isfinite(float(v)) and (float(v) >= 0 if zero else float(v) > 0)):
                raise FitError(f"FitOptions: {name} must be a finite number "
                               f"{'>= 0' if zero else '> 0'}, got {v!r}")

        count("max_iter", 1)
        count("stall_window", 0)
        for name in ("gtol", "decrement_tol", "deterministic_std", "limit_tol", "xtol",
                     "lambda0", "stall_rtol"):
            positive(name)
        positive("time_limit", optional=True, zero=True)   # 0: one iteration (a deadline passed)
        positive("deterministic_input_scale", optional=True)
        if self.substeps is not None or self.integrator is not None or self.input_hold is not None:
            from ..model.dynamics import INPUT_HOLDS, INTEGRATORS
            from ..limits import MAX_SUBSTEPS
            if self.integrator is not None and self.integrator not in INTEGRATORS:
                raise FitError(f"FitOptions: integrator must be one of {', '.join(INTEGRATORS)}, "
                               f"got {self.integrator!r}")
            if self.input_hold is not None and self.input_hold not in INPUT_HOLDS:
                raise FitError(f"FitOptions: input_hold must be one of {', '.join(INPUT_HOLDS)}, "
                               f"got {self.input_hold!r}")
            if self.substeps is not None:
                count("substeps", 1)
                if self.substeps > MAX_SUBSTEPS:
                    raise FitError(f"FitOptions: substeps must be at most {MAX_SUBSTEPS}, got "
                                   f"{self.substeps!r}")


@dataclasses.dataclass(frozen=True)
class WarmStart:
    """A start for :func:`vsidgen.estimator.fit` of a problem of known shape, in place of the
    fit's own initial guess.

    ``shared`` holds the unconstrained decision variables shared by all records: the free
    parameters (``ThetaMap`` coordinates) followed by the noise parameters (``NoiseMap``
    coordinates); ``records`` per record the assumed density's means ``mu`` (N, nx) and its
    covariance parameters ``r`` (log-diagonal d of Σ_cond, strict lower part of L, cross
    matrix C). ``FitResult.decision`` holds the same for a finished fit.
    """

    shared: np.ndarray
    records: tuple[tuple[np.ndarray, np.ndarray], ...]
    #: for a fit in the deterministic limit: ``{"std": {state: std}}``, the process-noise std
    #: of the deterministic states this decision belongs to (a quasi-deterministic fit's fixed
    #: std); the continuation starts there instead of at the data scale. None: the data scale.
    deterministic_limit: dict | None = None

    @classmethod
    def from_decision(cls, decision: dict) -> WarmStart:
        """From the ``{"s": shared, "records": [{"mu", "r"}, ...]}`` layout of ``FitResult.decision``."""
        return cls(shared=np.asarray(decision["s"], float),
                   records=tuple((np.asarray(d["mu"], float), np.asarray(d["r"], float))
                                 for d in decision["records"]))


@dataclasses.dataclass(frozen=True)
class SmootherPath:
    """Assumed density of one record: means and (time-invariant) covariances."""

    name: str
    mu: np.ndarray          # (N, nx)
    cov_marg: np.ndarray    # (nx, nx) Σ_marg
    cov_cond: np.ndarray    # (nx, nx) Σ_cond = cov(x_{k+1} | x_k)
    cross: np.ndarray       # (nx, nx) C, cov(x_{k+1}, x_k) = C S_mᵀ

    @property
    def std(self) -> np.ndarray:
        """Marginal standard deviation per state (nx,)."""
        return np.sqrt(np.diag(self.cov_marg))


@dataclasses.dataclass(frozen=True, repr=False)
class FitResult:
    """Outcome of a fit (or of a validation smoothing run).

    ``theta`` holds all parameters in model order; ``std_errors`` the square
    roots of diag cov(θ_free) with cov = [H⁻¹]_θθ (H the Hessian of −ELBO in
    natural θ coordinates, all other variables marginalised), NaN for fixed
    parameters; ``correlation`` is free × free. ``std_error_flags`` lists every reason
    (:class:`StdErrorIssue`) the standard errors need attention, and
    ``std_errors_reliable`` is True exactly when a fit has none (always False for a
    smoothing run, which has no standard errors). Noise at its floor and a smoothed state
    far from its measurement are warnings about the noise model, not about the standard
    errors (docs/estimator.md).
    """

    parameter_names: tuple[str, ...]
    theta: np.ndarray
    std_errors: np.ndarray
    correlation: np.ndarray
    free_mask: np.ndarray
    process_std: dict
    measurement_std: dict
    measurement_floor: dict
    G: np.ndarray
    R: np.ndarray
    elbo: float
    converged: bool
    status: str
    iterations: int
    wall_time_s: float
    smoothers: tuple[SmootherPath, ...]
    warnings: tuple[dict, ...] = ()
    std_errors_reliable: bool = True
    history: tuple[dict, ...] = ()
    decision: dict | None = None     # {"s": shared vector, "records": [{"mu", "r"}]} for warm start
    covariance: np.ndarray | None = None   # free × free cov(θ_free)
    optimizer: str = "structured-newton"
    stop_reason: StopReason | None = None
    newton_decrement: float = float("nan")   # λ²/2 in nats at the returned point (NaN: H not PD)
    deterministic_states: tuple[str, ...] = ()
    std_error_flags: tuple[StdErrorFlag, ...] = ()
    deterministic_limit: dict | None = None   # continuation record of the deterministic limit (see FitOptions)
    #: the process-noise factor the ELBO was computed with: ``G`` with the rows of the states
    #: without process noise at the std the objective gave them (a quasi-deterministic
    #: state's fixed std, the last stage of the deterministic limit); ``G`` reports them as 0.
    #: A statistic compared with the ELBO (a one-step predictive likelihood) uses this one.
    G_objective: np.ndarray | None = None

    def __repr__(self) -> str:
        """One line a notebook can show (the arrays are attributes: ``theta``, ``smoothers``)."""
        est = ", ".join(f"{n}={v:.5g}" for n, v in list(zip(self.parameter_names, self.theta))[:6])
        more = ", …" if len(self.parameter_names) > 6 else ""
        return (f"FitResult(elbo={self.elbo:.6g}, converged={self.converged}, "
                f"iterations={self.iterations}, theta={{{est}{more}}})")
    @property
    def estimates(self) -> dict:
        return dict(zip(self.parameter_names, map(float, self.theta)))

    def __str__(self) -> str:
        lines = [f"ELBO {self.elbo:.6g}; {self.status}; {self.iterations} iterations, {self.wall_time_s:.2f} s"]
        for name, v, se in zip(self.parameter_names, self.theta, self.std_errors):
            lines.append(f"  {name:>12s} = {v: .6g}  ± {se:.3g}")
        for w in self.warnings:
            lines.append(f"  warning [{w['code']}]: {w['message']}")
        return "\n".join(lines)
