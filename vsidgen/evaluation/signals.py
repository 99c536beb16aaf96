"""The paper's four evaluation signals of an identified model, and fit metrics.

For one record (time stamps ``t_k``, sample period ``T``, inputs ``u_k``,
measurements ``y_k``), the estimate ``θ*``, the smoother mean ``μ_k`` and the
noise matrices ``G`` (process, ``dx = f dt + G dW``) and ``R`` (measurement
covariance), with the mean transition ``F`` of :mod:`vsidgen.model.dynamics`:

1. **smoother outputs** ``ŷ_k = h(μ_k, u_k, θ*)``;
2. **free simulation** from ``x_0 = μ_0`` with ``θ*`` and no noise:
   ``x_{k+1} = F(x_k, u_k, θ*)``, ``ŷ_k = h(x_k, u_k, θ*)``;
3. **one-step predictions of the steady-state Kalman filter** for ``θ*``. As
   in the filter-error method, the system is linearised once, at the first
   sample: ``A = ∂F/∂x (μ_0, u_0, θ*)``, ``H = ∂h/∂x (μ_0, u_0, θ*)``
   (the generated Jacobians: ``h_x`` directly, ``F_x`` composed from ``f_x`` by the
   chain rule, :meth:`vsidgen.model.dynamics.Transition.jacobian`), ``Q = T G Gᵀ``. The predicted covariance ``P`` solves the
   discrete algebraic Riccati equation

   .. math:: P = A P Aᵀ − A P Hᵀ (H P Hᵀ + R)^{-1} H P Aᵀ + Q

   (``scipy.linalg.solve_discrete_are`` on the dual problem ``(Aᵀ, Hᵀ)``),
   ``K = P Hᵀ (H P Hᵀ + R)^{-1}``. The predictor itself is nonlinear:

   .. math::

       ŷ_k = h(x̂_{k|k-1}, u_k),\\quad
       x̂_{k|k} = x̂_{k|k-1} + K (y_k − ŷ_k),\\quad
       x̂_{k+1|k} = F(x̂_{k|k}, u_k, θ*),\\quad x̂_{0|-1} = μ_0.

   A missing measurement (NaN) contributes a zero innovation (its column of
   ``K`` is simply not used; the gain is not re-optimised for the subset). If
   the Riccati equation has no stabilising solution (undetectable or singular
   problem), the prediction falls back to the free simulation and a message
   is added to :attr:`Signals.warnings`. With ``Q = 0`` and a stable ``A`` the
   gain is ``K = 0`` (prediction = simulation, no warning).
4. **state derivatives**: finite differences ``(μ_{k+1} − μ_k)/T`` versus the
   drift ``f(μ_k, u_k, θ*)``, ``k = 0..N-2`` (for the Euler transition and a
   smoother path that obeys the model exactly these coincide).

Fit metrics (:func:`fit_metrics`, NaN-aware: samples where either value is
not finite are dropped), with ``e = y − ŷ``::

    rms   = sqrt(mean(e²))
    theil = rms(e) / (rms(y) + rms(ŷ))        Theil's inequality coefficient U
    r2    = 1 − Σe² / Σ(y − mean(y))²          coefficient of determination
    n     = number of samples used
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg

from ..model.dynamics import transition
from ..errors import VsidgenError
from ..model.runtime import finite_theta

from .. import precision  # noqa: F401  (float64, set once)


@dataclasses.dataclass(frozen=True, eq=False)
class Signals:
    """Evaluation signals of one record (see the module docstring).

    Attributes:
        record: record name; ``t`` (N,) seconds.
        y_meas, y_smooth, y_sim, y_pred: (N, ny) measured, smoother, simulated,
            one-step predicted outputs.
        x_smooth: (N, nx) smoother mean μ.
        xdot_fd, f_smooth: (N-1, nx) finite-difference and drift state derivatives.
        metrics: ``{"smoother"|"simulation"|"prediction": {output: m},
            "derivative": {state: m}}`` with ``m = {"rms", "theil", "r2", "n"}``.
        output_names, state_names: channel names in column order.
        warnings: human-readable messages (e.g. Riccati fallback).
        gain: (nx, ny) steady-state Kalman gain K (None after a fallback).
        innovation_cov: (ny, ny) covariance ``S = H P Hᵀ + R`` of the predictor's
            innovations ``y_k − ŷ_k`` (``R`` when ``K = 0``; None after a fallback), for
            :func:`predictive_loglik`.
        growth_rates: the unstable modes of the fitted model linearised at the first sample,
            ``ln|λ_i|/T`` (1/s, largest first) for the eigenvalues ``λ_i`` of ``∂F/∂x`` with
            ``|λ_i| > 1``: a free simulation diverges along them (e-folding time 1/rate).
    """

    record: str
    t: np.ndarray
    y_meas: np.ndarray
    y_smooth: np.ndarray
    y_sim: np.ndarray
    y_pred: np.ndarray
    x_smooth: np.ndarray
    xdot_fd: np.ndarray
    f_smooth: np.ndarray
    metrics: dict
    output_names: tuple[str, ...] = ()
    state_names: tuple[str, ...] = ()
    warnings: tuple[str, ...] = ()
    gain: np.ndarray | None = None
    innovation_cov: np.ndarray | None = None
    growth_rates: tuple[float, ...] = ()


def fit_metrics(measured, predicted) -> dict:
    """NaN-aware fit metrics ``{"rms", "theil", "r2", "fit_percent", "n"}`` (formulas in the module docstring).

    ``fit_percent`` is the normalised-RMSE fit of MATLAB's ``compare``,
    ``100 (1 − ‖y − ŷ‖ / ‖y − ȳ‖)`` (100 = perfect, 0 = no better than the mean,
    negative = worse), i.e. ``100 (1 − √(1 − R²))``.

    Undefined values (no samples, ``Σ(y − ȳ)² = 0``, ``rms(y) + rms(ŷ) = 0``)
    are NaN.
    """
    y = np.asarray(measured, dtype=np.float64).ravel()
    p = np.asarray(predicted, dtype=np.float64).ravel()
    if y.shape != p.shape:
        raise VsidgenError(f"fit_metrics: shapes differ ({y.shape} vs {p.shape})")
    ok = np.isfinite(y) & np.isfinite(p)
    y, p = y[ok], p[ok]
    n = int(y.size)
    if n == 0:
        return {"rms": math.nan, "theil": math.nan, "r2": math.nan, "fit_percent": math.nan, "n": 0}
    e = y - p
    rms = float(np.sqrt(np.mean(e ** 2)))
    den = float(np.sqrt(np.mean(y ** 2)) + np.sqrt(np.mean(p ** 2)))
    theil = rms / den if den > 0 else math.nan
    sst = float(np.sum((y - y.mean()) ** 2))
    r2 = 1.0 - float(np.sum(e ** 2)) / sst if sst > 0 else math.nan
    fit_percent = 100.0 * (1.0 - math.sqrt(float(np.sum(e ** 2)) / sst)) if sst > 0 else math.nan
    return {"rms": rms, "theil": theil, "r2": r2, "fit_percent": fit_percent, "n": n}


def steady_state_filter(A, H, Q, R) -> tuple[np.ndarray, np.ndarray]:
    """Steady-state (predictor-form covariance) Kalman gain ``K = P Hᵀ (H P Hᵀ + R)⁻¹`` and
    innovation covariance ``S = H P Hᵀ + R``.

    ``P`` is the stabilising solution of the filter DARE (module docstring);
    the predictor ``A (I − K H)`` must have spectral radius <= 1 (else the
    solution is not stabilising: an unstable mode is undetectable).

    Raises:
        numpy.linalg.LinAlgError / ValueError: no stabilising solution.
    """
    A, H, Q, R = (np.asarray(a, dtype=np.float64) for a in (A, H, Q, R))
    P = scipy.linalg.solve_discrete_are(A.T, H.T, Q, R)
    S = H @ P @ H.T + R
    K = np.linalg.solve(S.T, (P @ H.T).T).T
    if not (np.isfinite(P).all() and np.isfinite(K).all()):
        raise np.linalg.LinAlgError("non-finite Riccati solution")
    rho = np.max(np.abs(np.linalg.eigvals(A @ (np.eye(A.shape[0]) - K @ H))))
    if rho > 1.0 + 1e-9:
        raise np.linalg.LinAlgError(
            f"the filter is unstable (spectral radius {rho:.6g} of A(I - KH)): "
            "an unstable mode is not seen by the outputs (undetectable)")
    return K, S


def predictive_loglik(signals: Signals) -> np.ndarray | None:
    r"""Per-sample log-likelihood of the one-step predictions (signal 3), (N,):

    .. math:: ℓ_k = −½ (\log\det(2π S_{oo}) + e_oᵀ S_{oo}^{-1} e_o),\quad e = y_k − ŷ_k,

    over the outputs ``o`` measured at sample k (S's rows and columns of the missing ones
    removed: the marginal of the Gaussian; ℓ_k = 0 when none is). For a linear model this is
    the exact log-likelihood decomposition of the record, ``Σ_k ℓ_k = log p(y_{0:N})``, once the
    filter has reached its steady state. None when the filter is unavailable (no
    stabilising Riccati solution) or ``S`` is not positive definite."""
    S = signals.innovation_cov
    if S is None:
        return None
    e = np.asarray(signals.y_meas, dtype=np.float64) - np.asarray(signals.y_pred, dtype=np.float64)
    masks, group = np.unique(np.isfinite(e), axis=0, return_inverse=True)
    out = np.zeros(e.shape[0])
    for g, m in enumerate(masks):
        if not m.any():
            continue
        rows = np.flatnonzero(group.ravel() == g)
        try:
            c, low = scipy.linalg.cho_factor(S[np.ix_(m, m)], lower=True)
        except (np.linalg.LinAlgError, ValueError):
            return None              # S not positive definite (or not finite)
        eo = e[np.ix_(rows, np.flatnonzero(m))]
        quad = np.einsum("ij,ij->i", eo, scipy.linalg.cho_solve((c, low), eo.T).T)
        logdet = 2.0 * float(np.sum(np.log(np.diag(c))))
        out[rows] = -0.5 * (quad + logdet + m.sum() * math.log(2.0 * math.pi))
    return out


def _matrix(a, shape0, name, square=False) -> np.ndarray:
    m = np.asarray(a, dtype=np.float64)
    if m.ndim != 2 or m.shape[0] != shape0 or (square and m.shape[1] != shape0):
        want = f"({shape0}, {shape0})" if square else f"({shape0}, k)"
        raise VsidgenError(f"evaluate: {name} must be a {want} matrix, got shape {m.shape}")
    if not np.isfinite(m).all():
        raise VsidgenError(f"evaluate: {name} holds NaN or inf")
    return m


_SCANS: dict = {}


def _scans(model, F):
    """Jitted free simulation ``y_sim(x0, U, V, p, T)`` and steady-state Kalman predictor
    ``y_pred(x0, U, V, Y, K, p, T)`` of ``model`` with transition ``F``. θ, K and T are
    arguments, so one compilation per model functions, setting and record length serves every
    evaluation (diagnose evaluates each refit of a round's gated model)."""
    key = (model.drift, model.output, F.key)
    hit = _SCANS.get(key)
    if hit is not None:
        return hit
    h = model.output

    @jax.jit
    def free_sim(x0, U, V, p, T):
        def body(x, inp):
            uk, vk = inp
            return F(x, vk, p, T), h(x, uk, p)
        _, ys = jax.lax.scan(body, x0, (U, V))
        return ys

    @jax.jit
    def predictor(x0, U, V, Y, K, p, T):
        def body(xp, inp):
            uk, vk, yk = inp
            yp = h(xp, uk, p)
            innov = jnp.where(jnp.isnan(yk), 0.0, yk - yp)
            xf = xp + K @ innov
            return F(xf, vk, p, T), yp
        _, yps = jax.lax.scan(body, x0, (U, V, Y))
        return yps

    f = model.drift

    euler_held = (F.integrator == "euler" and F.substeps == 1 and F.inputs == "zoh")

    @jax.jit
    def on_path(mu, U, V, p, T):
        """Outputs along the smoother mean and the model's rate at its samples (one
        compilation; evaluated op by op, each operation compiled on its own).

        The rate is the drift ``f(x_k, u_k)`` for Euler with held inputs, else the
        transition's mean rate over the step, ``(F(x_k, v_k) − x_k)/T``: what the model
        predicts the state moves from one sample to the next under its own integrator and
        input hold, which the finite differences of the smoothed path are compared with. The
        drift at the sample differs from it by O(T) terms in the input's rate, which locate
        flagged as missing input-rate physics in a correct RK4/first-order-hold model
        (session 47, an independent lateral record: ``udot:da`` at p = 6e-62)."""
        ys = jax.vmap(lambda x, uk: h(x, uk, p))(mu, U)
        if euler_held:
            return ys, jax.vmap(lambda x, uk: f(x, uk, p))(mu[:-1], U[:-1])
        return ys, jax.vmap(lambda x, vk: (F(x, vk, p, T) - x) / T)(mu[:-1], V[:-1])

    @jax.jit
    def linearised(x0, u0, v0, p, T):
        """(∂F/∂x, ∂h/∂x) at one sample, for the steady-state Kalman predictor."""
        return F.jacobian(x0, v0, p, T)[0], model.output_jacobian(x0, u0, p)[0]

    if len(_SCANS) >= 32:
        _SCANS.pop(next(iter(_SCANS)))
    _SCANS[key] = (free_sim, predictor, on_path, linearised)
    return _SCANS[key]


def evaluate(model, record, theta, *, mu, G, R, integrator: str | None = None,
             substeps: int | None = None, input_hold: str | None = None) -> Signals:
    """Compute the four evaluation signals and their fit metrics for one record.

    Args:
        model: :class:`vsidgen.model.Model`.
        record: :class:`vsidgen.data.Record` (``t``, ``dt``, ``u``, ``y``).
        theta: estimate θ*, (np,) array or dict name -> value.
        mu: (N, nx) smoother mean.
        G: (nx, k) process-noise matrix (state-unit/√s); ``Q = T G Gᵀ``.
        R: (ny, ny) measurement-noise covariance.
        integrator, substeps, input_hold: transition F (``None``: the model's choice, as
            used by the estimator); with ``input_hold="foh"`` the free simulation and the
            predictor step from sample k with the input interpolated to u_{k+1}.
    """
    p = jnp.asarray(finite_theta(model, theta, who="evaluate"))
    mu = np.asarray(mu, dtype=np.float64)
    u = np.asarray(record.u, dtype=np.float64)
    y = np.asarray(record.y, dtype=np.float64)
    n = u.shape[0]
    if mu.shape != (n, model.nx):
        raise VsidgenError(f"evaluate: mu has shape {mu.shape}, expected ({n}, {model.nx})")
    if u.shape != (n, model.nu) or y.shape != (n, model.ny):
        raise VsidgenError(f"evaluate: record '{record.name}' has u {u.shape} / y {y.shape}, "
                           f"model {model.name} expects ({n}, {model.nu}) / ({n}, {model.ny})")
    for kind, have, want in (("input", getattr(record, "input_names", None), model.input_names),
                             ("output", getattr(record, "output_names", None), model.output_names)):
        if have is not None and tuple(have) != tuple(want):
            raise VsidgenError(f"evaluate: record '{record.name}' {kind}s {tuple(have)} differ from "
                               f"the model's {tuple(want)}")
    G = _matrix(G, model.nx, "G")
    R = _matrix(R, model.ny, "R", square=True)
    T = float(record.dt)
    F = transition(model, integrator=integrator, substeps=substeps, inputs=input_hold)
    warnings: list[str] = []

    mu_j, u_j = jnp.asarray(mu), jnp.asarray(u)
    free_sim, predictor, on_path, linearised = _scans(model, F)
    v_j = F.scan_inputs(u_j)  # step input per sample (the last one is never used)
    Tj = jnp.asarray(T)
    y_smooth, f_smooth = (np.asarray(a) for a in on_path(mu_j, u_j, v_j, p, Tj))
    xdot_fd = np.diff(mu, axis=0) / T

    y_sim = np.asarray(free_sim(mu_j[0], u_j, v_j, p, Tj))
    if not np.isfinite(y_sim).all():
        k = int(np.flatnonzero(~np.isfinite(y_sim).all(axis=1))[0])
        warnings.append(f"free simulation diverged at sample {k} (t = {record.t[k]:.6g} s)")

    # steady-state Kalman filter, linearised at the first sample
    x0, u0, v0 = mu_j[0], u_j[0], v_j[0]
    A, H = (np.asarray(a) for a in linearised(x0, u0, v0, p, Tj))
    Q = T * G @ G.T
    lam = np.abs(np.linalg.eigvals(A)) if np.isfinite(A).all() else np.zeros(0)
    growth = tuple(sorted((float(np.log(v) / T) for v in lam if v > 1.0 + 1e-9), reverse=True))
    K = S = None
    try:
        K, S = steady_state_filter(A, H, Q, R)
    except (np.linalg.LinAlgError, ValueError) as exc:
        if not Q.any() and np.max(np.abs(np.linalg.eigvals(A))) < 1.0:
            K, S = np.zeros((model.nx, model.ny)), R.copy()
        else:
            warnings.append("steady-state Kalman filter unavailable (Riccati equation has no "
                            f"stabilising solution: {exc}); prediction signal = free simulation")
    if K is not None:
        y_pred = np.asarray(predictor(mu_j[0], u_j, v_j, jnp.asarray(y), jnp.asarray(K), p, Tj))
    else:
        y_pred = y_sim.copy()

    metrics = {
        "smoother": {o: fit_metrics(y[:, j], y_smooth[:, j]) for j, o in enumerate(model.output_names)},
        "simulation": {o: fit_metrics(y[:, j], y_sim[:, j]) for j, o in enumerate(model.output_names)},
        "prediction": {o: fit_metrics(y[:, j], y_pred[:, j]) for j, o in enumerate(model.output_names)},
        "derivative": {s: fit_metrics(xdot_fd[:, i], f_smooth[:, i]) for i, s in enumerate(model.state_names)},
    }
    return Signals(record=record.name, t=np.asarray(record.t), y_meas=y, y_smooth=y_smooth,
                   y_sim=y_sim, y_pred=y_pred, x_smooth=mu, xdot_fd=xdot_fd, f_smooth=f_smooth,
                   metrics=metrics, output_names=model.output_names, state_names=model.state_names,
                   warnings=tuple(warnings), gain=K, innovation_cov=S, growth_rates=growth)


def iid_gaussian_loglik(y) -> float:
    """Log-likelihood (nats) of the outputs ``y`` (N, ny; NaN = missing) under the model that
    knows nothing of the dynamics: each channel independent Gaussian samples at its own mean
    and variance (maximum likelihood), −½ Σ_j n_j (ln(2π s_j²) + 1). In the units of ``y``,
    like the ELBO: the difference of the two per sample does not depend on the units. A
    channel without spread (s_j = 0) is left out."""
    y = np.asarray(y, float)
    y = y.reshape(len(y), -1)
    total = 0.0
    for j in range(y.shape[1]):
        col = y[:, j][np.isfinite(y[:, j])]
        var = float(np.var(col)) if col.size > 1 else 0.0
        if var > 0:
            total += -0.5 * col.size * (math.log(2.0 * math.pi * var) + 1.0)
    return total


def validation_elbo_warning(elbo, n_samples: int, validation_elbo, validation_y) -> dict | None:
    """A warning when the validation ELBO per sample is far below the estimation's, else None.

    ``elbo``/``n_samples``: the estimation's ELBO and its number of samples (all records);
    ``validation_elbo``: the validation smoothing's; ``validation_y``: the outputs (N, ny) of
    each validation record. "Far below" on a scale-free yardstick: the ELBO per sample drops
    from estimation to validation by more than the model gains, per sample, over a model
    without dynamics on the validation records (:func:`iid_gaussian_loglik`) — the validation
    ELBO per sample is below that model's log-likelihood per sample, i.e. the model scores the
    validation records worse than knowing nothing of their dynamics. Differences per sample of
    log-likelihoods of the same channels depend neither on their units nor on the records'
    lengths. A non-finite validation ELBO is always named.
    """
    ys = [np.asarray(y, float) for y in validation_y]
    n_val = sum(len(y) for y in ys)
    if not n_samples or not n_val or not math.isfinite(float(elbo)):
        return None
    per_est = float(elbo) / n_samples
    per_val = float(validation_elbo) / n_val
    per_base = sum(iid_gaussian_loglik(y) for y in ys) / n_val
    if per_val >= per_base:
        return None
    return {"code": "validation_elbo_far_below", "reliable": True,
            "elbo_per_sample": per_val, "estimation_elbo_per_sample": per_est,
            "no_dynamics_per_sample": per_base,
            "message": f"validation ELBO {float(validation_elbo):.6g} = {per_val:.4g} nats per sample, far "
                       f"below the estimation's {per_est:.4g} nats per sample: below the {per_base:.4g} "
                       f"nats per sample of a model without dynamics on the validation records (each "
                       f"output independent Gaussian at its mean and variance); the model does not "
                       f"describe the validation records (check them, their data map and the states "
                       f"without process noise)"}


#: the evaluation signals judged by :func:`unexplained_outputs`, in the order they are named
OUTPUT_SIGNALS = ("smoother", "simulation", "prediction")
_SIGNAL_WORDS = {"smoother": "smoother-mean output", "simulation": "free simulation",
                 "prediction": "one-step Kalman prediction"}


def unexplained_outputs(signals: Signals, *, kind: str = "estimation") -> list[dict]:
    """Warnings for output channels that an evaluation signal does not explain at all.

    A channel is named when the fraction of its variance that the smoother-mean output, the
    free simulation or the one-step Kalman prediction explains, R² = 1 − Σe²/Σ(y − ȳ)² (the
    ``r2`` of :func:`fit_metrics`; NRMSE fit ≤ 0 %), is at most 0: that signal predicts the
    channel no better than the channel's own mean does — the model explains none of it. The
    criterion is scale free and needs no threshold; R² ≤ 0 of the prediction or the smoother
    (which see the data) says the model or its noise settings miss the channel altogether, of
    the free simulation that the model does not reproduce the channel without the data.
    (Persistence, ŷ_k = y_{k−1}, is no reference for the one-step prediction: at the sample
    rates of flight records it beats good models on slowly varying channels — ATTAS lateral,
    textbook model, simulation R² 0.97, prediction of ay 2.1× the persistence RMS.)

    Each such signal's squared error splits exactly into its mean and the rest,
    ``Σe² = N ē² + Σ(e − ē)²``: ``r2_without_offset`` is the R² the signal would have with its
    mean residual ē removed, ``1 − Σ(e − ē)²/Σ(y − ȳ)²``. When it is above 0 for every named
    signal, the model does explain the channel's variations and what it misses is a constant:
    the message names the offset (ē of the first named signal) and suggests the missing bias
    or trim term (Twin Otter lateral record f1_017, a user's ``ay = Y_β β + Y_δr δr`` without a
    bias: R² −1.9, ē −1.15 m/s², R² 0.85 without it).

    One warning per record and output: ``{"code": "output_not_explained", "reliable": True,
    "record", "output", "kind" (estimation|validation), "r2": {signal: R²}, "offset": {signal:
    ē}, "r2_without_offset": {signal: R²}, "growth_rate", "message"}``: ``growth_rate`` is the
    largest of :attr:`Signals.growth_rates` (None for a stable linearisation); when the free
    simulation is named and the model is unstable there, the message says so and names the
    usual causes (ATTAS ``attas_elv1`` fitted without ``M0``: M_q +0.81/s, simulation R² −905).
    """
    arrays = {"smoother": signals.y_smooth, "simulation": signals.y_sim,
              "prediction": signals.y_pred}
    out = []
    for j, o in enumerate(signals.output_names):
        bad = {}
        for sig in OUTPUT_SIGNALS:
            r2 = (signals.metrics.get(sig) or {}).get(o, {}).get("r2", math.nan)
            if r2 is not None and not math.isnan(r2) and r2 <= 0.0:
                bad[sig] = float(r2)
        if not bad:
            continue
        offset, r2_off = {}, {}
        y = np.asarray(signals.y_meas, float)[:, j]
        for sig in bad:
            e = y - np.asarray(arrays[sig], float)[:, j]
            ok = np.isfinite(e)
            sst = float(np.sum((y[ok] - y[ok].mean()) ** 2)) if ok.any() else 0.0
            if sst > 0:
                offset[sig] = float(e[ok].mean())
                r2_off[sig] = 1.0 - float(np.sum((e[ok] - e[ok].mean()) ** 2)) / sst
        what = "; ".join(f"{_SIGNAL_WORDS[k]} R² = {v:.3g}" for k, v in bad.items())
        where = f"{'validation ' if kind == 'validation' else ''}record '{signals.record}'"
        hint = (f"check the equation of '{o}', its data column and its measurement-noise "
                f"settings")
        unstable = ""
        if "simulation" in bad and signals.growth_rates:
            g = signals.growth_rates[0]
            unstable = (f"; the fitted model is unstable at the record's first sample (a mode "
                     f"growing at {g:.3g}/s, e-folding in {1.0 / g:.3g} s), so its free "
                     f"simulation drifts away: a derivative whose sign the data did not fix, or "
                     f"a term the equations lack that the others bend to absorb — a constant "
                     f"(trim) term in an equation written in the recorded variables is a common "
                     f"one (`vsidgen diagnose` tests them)")
        # above 0 beyond rounding (a constant signal has exactly 0 without its offset)
        if r2_off and len(r2_off) == len(bad) and all(v > 1e-9 for v in r2_off.values()):
            first = next(iter(r2_off))
            hint = (f"without its mean residual, {offset[first]:.4g}, the "
                    f"{_SIGNAL_WORDS[first]} would have R² = {r2_off[first]:.3g}: the equation "
                    f"of '{o}' may lack a constant (a sensor bias or trim term, a parameter "
                    f"added to it), or its data column is offset"
                    + (", or this record was flown at another trim than the estimation "
                       "records (a constant that differs between records)"
                       if kind == "validation" else ""))
        out.append({"code": "output_not_explained", "reliable": True, "record": signals.record,
                    "output": o, "kind": kind, "r2": bad, "offset": offset,
                    "r2_without_offset": r2_off,
                    "growth_rate": signals.growth_rates[0] if signals.growth_rates else None,
                    "message": f"{where}, output '{o}': the model explains none of its variance "
                               f"({what}; R² ≤ 0: no better than the channel's mean); {hint}"
                               f"{unstable}"})
    return out


__all__ = ["OUTPUT_SIGNALS", "Signals", "evaluate", "fit_metrics", "iid_gaussian_loglik", "predictive_loglik",
           "steady_state_filter",
           "unexplained_outputs", "validation_elbo_warning"]
