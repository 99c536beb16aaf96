"""Evaluation signals against independent numpy references on a linear model."""

from __future__ import annotations

import dataclasses
import math

import jax.numpy as jnp
import numpy as np
import pytest

from vsidgen.data import Record
from vsidgen.evaluation import evaluate, fit_metrics
from vsidgen.metadata import Parameter, ProcessNoiseSpec, Variable
from vsidgen.model import Model
from vsidgen.data.simulate import simulate, three_two_one_one

A = np.array([[-0.8, 1.0], [-5.0, -2.0]])
B = np.array([[0.0], [-8.0]])
C = np.array([[1.0, 0.0], [0.0, 1.0], [5.0, 0.0]])
D = np.array([[0.0], [0.0], [0.2]])
THETA = np.array([-0.8, -5.0, -2.0, -8.0])


def _model(output=None):
    def drift(x, u, p):
        return jnp.array([[p[0], 1.0], [p[1], p[2]]]) @ x + jnp.array([0.0, p[3]]) * u[0]

    def out(x, u, p):
        return jnp.asarray(C) @ x + jnp.asarray(D) @ u

    return Model(name="lin", drift=drift, output=output or out,
                 states=(Variable("alpha"), Variable("q")), inputs=(Variable("de"),),
                 outputs=(Variable("alpha"), Variable("q"), Variable("nz")),
                 parameters=tuple(Parameter(n) for n in ("Za", "Ma", "Mq", "Mde")),
                 process_noise=ProcessNoiseSpec(states=("alpha", "q")), measurement_noise=())


def _record(res, y=None):
    return Record(name="syn", path=None, t=res.t, dt=float(res.t[1] - res.t[0]), u=res.u,
                  y=res.y if y is None else y, input_names=("de",),
                  output_names=("alpha", "q", "nz"), t_raw=res.t)


T = 0.02
TT = np.arange(0, 8, T)
G = np.diag([0.05, 0.3])
RM = np.diag([1e-3, 4e-3, 0.05]) ** 2


def _sim(**kw):
    u = {"de": three_two_one_one(TT, amplitude=0.03, start=1, unit=0.4)}
    return simulate(_model(), theta=THETA, t=TT, u=u, x0=[0.02, 0.0], **kw)


def _numpy_kf(y, u, x0, Q, R):
    """Independent steady-state KF: Riccati recursion iterated to convergence."""
    Ad, Bd = np.eye(2) + T * A, T * B
    P = np.eye(2)
    for _ in range(100_000):
        S = C @ P @ C.T + R
        Pn = Ad @ P @ Ad.T - Ad @ P @ C.T @ np.linalg.inv(S) @ C @ P @ Ad.T + Q
        if np.max(np.abs(Pn - P)) < 1e-18:
            P = Pn
            break
        P = Pn
    K = P @ C.T @ np.linalg.inv(C @ P @ C.T + R)
    x = x0.copy()
    out = np.empty_like(y)
    for k in range(y.shape[0]):
        yp = C @ x + D @ u[k]
        out[k] = yp
        e = np.where(np.isnan(y[k]), 0.0, y[k] - yp)
        x = Ad @ (x + K @ e) + Bd @ u[k]
    return out, K


def test_prediction_matches_numpy_kalman_filter():
    res = _sim(process_std={"alpha": 0.05, "q": 0.3}, measurement_std={"alpha": 1e-3, "q": 4e-3, "nz": 0.05},
               seed=11)
    y = res.y.copy()
    y[[5, 50, 51], 0] = np.nan          # missing samples: zero innovation
    y[200, :] = np.nan
    mu = res.x + 1e-3 * np.sin(np.arange(TT.size))[:, None]   # a smoother path, not exactly the truth
    sig = evaluate(_model(), _record(res, y), THETA, mu=mu, G=G, R=RM)
    ref, K = _numpy_kf(y, res.u, mu[0], T * G @ G.T, RM)
    np.testing.assert_allclose(sig.gain, K, rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(sig.y_pred, ref, rtol=1e-9, atol=1e-12)
    assert sig.warnings == ()
    # the filter tracks the noisy data far better than the free simulation
    assert sig.metrics["prediction"]["q"]["rms"] < 0.5 * sig.metrics["simulation"]["q"]["rms"]
    assert sig.metrics["prediction"]["alpha"]["n"] == TT.size - 4


def test_smoother_simulation_and_derivative_signals():
    res = _sim()            # deterministic Euler path: mu obeys the model exactly
    y = res.y + 0.01
    sig = evaluate(_model(), _record(res, y), dict(zip(("Za", "Ma", "Mq", "Mde"), THETA)),
                   mu=res.x, G=np.zeros((2, 2)), R=RM)
    np.testing.assert_allclose(sig.y_smooth, res.x @ C.T + res.u @ D.T, atol=1e-15)
    np.testing.assert_allclose(sig.y_sim, res.y, atol=1e-14)
    # finite differences of an Euler path equal the drift
    assert sig.xdot_fd.shape == (TT.size - 1, 2) and sig.f_smooth.shape == (TT.size - 1, 2)
    np.testing.assert_allclose(sig.xdot_fd, sig.f_smooth, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(sig.f_smooth, res.x[:-1] @ A.T + res.u[:-1] @ B.T, atol=1e-14)
    assert sig.metrics["derivative"]["q"]["r2"] == pytest.approx(1.0, abs=1e-12)
    # Q = 0, stable A: K = 0, prediction = simulation, no warning
    assert np.abs(sig.gain).max() < 1e-15
    np.testing.assert_allclose(sig.y_pred, sig.y_sim, atol=1e-14)
    assert sig.warnings == ()
    m = sig.metrics["smoother"]["alpha"]
    assert m["rms"] == pytest.approx(0.01, rel=1e-9) and m["n"] == TT.size
    assert set(sig.metrics) == {"smoother", "simulation", "prediction", "derivative"}
    assert set(sig.metrics["derivative"]) == {"alpha", "q"}


def test_riccati_failure_falls_back_to_simulation():
    # outputs blind to an unstable state: undetectable -> no stabilising solution
    def blind(x, u, p):
        return jnp.array([u[0], 2 * u[0], 0.0 * x[0]])

    model = _model(output=blind)
    th = np.array([0.5, -5.0, 0.3, -8.0])     # unstable
    t = np.arange(0, 1, T)
    res = simulate(model, theta=th, t=t, u={"de": 0.01}, x0=[0.0, 0.0])
    rec = Record(name="r", path=None, t=t, dt=T, u=res.u, y=res.y, input_names=("de",),
                 output_names=("alpha", "q", "nz"), t_raw=t)
    sig = evaluate(model, rec, th, mu=res.x, G=G, R=RM)
    assert len(sig.warnings) == 1 and "Riccati" in sig.warnings[0]
    assert sig.gain is None
    np.testing.assert_array_equal(sig.y_pred, sig.y_sim)


def test_fit_metrics_hand_computed():
    m = fit_metrics([1.0, 2.0, 3.0, np.nan, 7.0], [1.0, 2.0, 4.0, 5.0, np.inf])
    assert m["n"] == 3
    assert m["rms"] == pytest.approx(math.sqrt(1 / 3), rel=1e-15)
    assert m["theil"] == pytest.approx(math.sqrt(1 / 3) / (math.sqrt(14 / 3) + math.sqrt(7)), rel=1e-14)
    assert m["r2"] == pytest.approx(0.5, rel=1e-15)     # SSE 1, SST 2
    perfect = fit_metrics([1.0, -2.0], [1.0, -2.0])
    assert perfect["rms"] == 0.0 and perfect["theil"] == 0.0 and perfect["r2"] == 1.0
    empty = fit_metrics([np.nan], [1.0])
    assert empty["n"] == 0 and math.isnan(empty["rms"])
    const = fit_metrics([2.0, 2.0], [2.0, 3.0])
    assert math.isnan(const["r2"])


def _signals_with(y, **predicted):
    from vsidgen.evaluation import Signals

    metrics = {k: {"y": fit_metrics(y, v)} for k, v in predicted.items()}
    n = len(y)
    arr = {k: np.asarray(predicted.get(k, y), float)[:, None]
           for k in ("smoother", "simulation", "prediction")}
    return Signals(record="r1", t=np.arange(n) * 0.1, y_meas=y[:, None], y_smooth=arr["smoother"],
                   y_sim=arr["simulation"], y_pred=arr["prediction"], x_smooth=np.zeros((n, 1)),
                   xdot_fd=np.zeros((n - 1, 1)), f_smooth=np.zeros((n - 1, 1)), metrics=metrics,
                   output_names=("y",), state_names=("x",))


def test_an_output_the_model_does_not_explain_is_named_with_its_r2():
    """R² <= 0 (no better than the channel's mean) of the free simulation or the one-step
    prediction is a warning naming record, output, signal and number; a good fit has none."""
    from vsidgen.evaluation import unexplained_outputs

    rng = np.random.default_rng(1)
    y = np.sin(np.linspace(0, 20, 400)) + 0.05 * rng.normal(size=400)
    good = _signals_with(y, smoother=y, simulation=y + 0.1 * rng.normal(size=400), prediction=y)
    assert unexplained_outputs(good) == []
    flat = np.full_like(y, y.mean() + 0.3)        # explains nothing (and is offset)
    bad = _signals_with(y, smoother=y, simulation=flat, prediction=y)
    (w,) = unexplained_outputs(bad, kind="validation")
    r2 = fit_metrics(y, flat)["r2"]
    assert w["code"] == "output_not_explained" and w["output"] == "y" and w["record"] == "r1"
    assert w["r2"] == {"simulation": r2} and r2 < 0
    assert "validation record 'r1', output 'y'" in w["message"] and f"{r2:.3g}" in w["message"]
    # a flat signal explains nothing even without its offset: no bias hint
    assert abs(w["r2_without_offset"]["simulation"]) < 1e-12 and "lack a constant" not in w["message"]


def test_an_output_missing_only_a_constant_is_named_with_its_offset():
    """A signal that follows the channel's variations but sits 2 standard deviations off has
    R² <= 0; removing its mean residual (exactly: Σe² = N ē² + Σ(e − ē)²) leaves R² > 0, and the
    warning names the offset and the missing constant."""
    from vsidgen.evaluation import unexplained_outputs

    rng = np.random.default_rng(3)
    y = np.sin(np.linspace(0, 20, 400)) + 0.1 * rng.normal(size=400)
    off = y - 1.5 + 0.05 * rng.normal(size=400)     # a missing bias of -1.5
    (w,) = unexplained_outputs(_signals_with(y, smoother=off, simulation=off, prediction=off))
    e = y - off
    want = 1 - np.sum((e - e.mean()) ** 2) / np.sum((y - y.mean()) ** 2)
    assert set(w["r2"]) == {"smoother", "simulation", "prediction"}
    assert w["offset"]["smoother"] == pytest.approx(e.mean()) and e.mean() == pytest.approx(1.5, abs=0.02)
    assert w["r2_without_offset"]["simulation"] == pytest.approx(want) and want > 0.9
    assert "lack a constant" in w["message"] and f"{e.mean():.4g}" in w["message"]
    assert "another trim" not in w["message"]
    (v,) = unexplained_outputs(_signals_with(y, smoother=off, simulation=off, prediction=off),
                               kind="validation")
    assert "another trim than the estimation records" in v["message"]


def test_validation_elbo_per_sample_below_a_model_without_dynamics_is_flagged():
    """Scale-free: per-sample ELBOs against the log-likelihood of independent Gaussians at each
    validation channel's mean and variance; the same in any unit of the outputs."""
    from vsidgen.evaluation import iid_gaussian_loglik, validation_elbo_warning

    rng = np.random.default_rng(2)
    y = rng.normal(size=(500, 2)) * [0.02, 0.05]
    base = iid_gaussian_loglik(y)
    assert validation_elbo_warning(7375.0, 626, base + 50.0, [y]) is None
    w = validation_elbo_warning(7375.0, 626, -3.9e6, [y])
    assert w["code"] == "validation_elbo_far_below"
    assert w["elbo_per_sample"] == pytest.approx(-3.9e6 / 500)
    assert w["no_dynamics_per_sample"] == pytest.approx(base / 500)
    assert "-3.9e+06" in w["message"] and "per sample" in w["message"]
    # outputs in units 1000× smaller: every log-likelihood shifts by the same amount per sample
    shift = -2 * 500 * math.log(1000.0)
    assert iid_gaussian_loglik(y * 1000.0) == pytest.approx(base + shift)
    assert validation_elbo_warning(7375.0 + shift * 626 / 500, 626, base + 50.0 + shift, [y * 1000.0]) is None
    assert validation_elbo_warning(7375.0, 626, base - 1.0, [y]) is not None


def test_predictive_loglik_is_the_exact_likelihood_of_a_linear_model():
    """Σ_k ℓ_k of the steady-state filter equals log p(y_0..y_N) of the linear Gaussian model
    with x_0 ~ N(μ_0, P) at the filter's steady-state P: the reference is the joint Gaussian of
    all outputs, built by hand (state covariances propagated, outputs stacked) and evaluated by
    scipy.stats.multivariate_normal; no filter involved."""
    from scipy import stats

    from vsidgen.evaluation import predictive_loglik

    res = _sim(process_std={"alpha": 0.05, "q": 0.3},
               measurement_std={"alpha": 1e-3, "q": 4e-3, "nz": 0.05}, seed=5)
    n = 60
    rec = Record(name="syn", path=None, t=res.t[:n], dt=T, u=res.u[:n], y=res.y[:n],
                 input_names=("de",), output_names=("alpha", "q", "nz"), t_raw=res.t[:n])
    mu = res.x[:n]
    sig = evaluate(_model(), rec, THETA, mu=mu, G=G, R=RM)
    ll = predictive_loglik(sig)
    assert ll.shape == (n,) and np.isfinite(ll).all()
    # the hand-built joint Gaussian
    Ad, Bd, Q = np.eye(2) + T * A, T * B, T * G @ G.T
    P = np.eye(2)
    for _ in range(100_000):                      # Riccati recursion to its fixed point
        S = C @ P @ C.T + RM
        Pn = Ad @ P @ Ad.T - Ad @ P @ C.T @ np.linalg.solve(S, C @ P @ Ad.T) + Q
        if np.max(np.abs(Pn - P)) < 1e-18:
            P = Pn
            break
        P = Pn
    m, covs = [mu[0]], [P]
    for k in range(n - 1):
        m.append(Ad @ m[-1] + Bd @ res.u[k])
        covs.append(Ad @ covs[-1] @ Ad.T + Q)
    ny = C.shape[0]
    mean = np.concatenate([C @ m[k] + D @ res.u[k] for k in range(n)])
    cov = np.zeros((n * ny, n * ny))
    for i in range(n):
        for j in range(i + 1):
            cx = np.linalg.matrix_power(Ad, i - j) @ covs[j]        # Cov(x_i, x_j)
            block = C @ cx @ C.T + (RM if i == j else 0.0)
            cov[i * ny:(i + 1) * ny, j * ny:(j + 1) * ny] = block
            cov[j * ny:(j + 1) * ny, i * ny:(i + 1) * ny] = block.T
    ref = stats.multivariate_normal(mean, cov).logpdf(res.y[:n].reshape(-1))
    assert float(ll.sum()) == pytest.approx(ref, rel=1e-9, abs=1e-7)
    # a sample with nothing measured contributes nothing; one channel missing: its marginal
    y = res.y[:n].copy()
    y[10, :] = np.nan
    y[11, 2] = np.nan
    sig2 = evaluate(_model(), dataclasses.replace(rec, y=y), THETA, mu=mu, G=G, R=RM)
    ll2 = predictive_loglik(sig2)
    assert ll2[10] == 0.0 and np.isfinite(ll2).all()
    e = (y[11] - sig2.y_pred[11])[:2]
    S2 = sig2.innovation_cov[:2, :2]
    assert ll2[11] == pytest.approx(stats.multivariate_normal(np.zeros(2), S2).logpdf(e), rel=1e-12)


def test_predictive_loglik_without_a_usable_innovation_covariance_is_none():
    from vsidgen.evaluation import predictive_loglik

    sig = _signals_with(np.zeros(5), smoother=np.zeros(5), simulation=np.zeros(5),
                        prediction=np.zeros(5))
    assert predictive_loglik(sig) is None                       # no filter
    bad = dataclasses.replace(sig, innovation_cov=np.array([[-1.0]]))
    assert predictive_loglik(bad) is None                       # not positive definite
    ok = dataclasses.replace(sig, innovation_cov=np.array([[4.0]]))
    np.testing.assert_allclose(predictive_loglik(ok), -0.5 * math.log(2 * math.pi * 4.0))


def test_an_unstable_fit_says_its_free_simulation_diverges_along_a_growing_mode():
    """``growth_rates``: ln|λ|/T of the eigenvalues of the Euler transition I + T A with
    |λ| > 1 (a hand-computed reference); none for the stable model. A free simulation that
    explains nothing from an unstable fit gets the growth rate and the usual causes."""
    from vsidgen.evaluation import unexplained_outputs

    res = _sim()
    stable = evaluate(_model(), _record(res), dict(zip(("Za", "Ma", "Mq", "Mde"), THETA)),
                      mu=res.x, G=np.diag([0.05, 0.3]), R=RM)
    assert stable.growth_rates == ()
    bad_theta = np.array([-0.8, 5.0, -2.0, -8.0])           # M_α > 0: statically unstable
    sig = evaluate(_model(), _record(res), dict(zip(("Za", "Ma", "Mq", "Mde"), bad_theta)),
                   mu=res.x, G=np.diag([0.05, 0.3]), R=RM)
    lam = np.linalg.eigvals(np.eye(2) + T * np.array([[-0.8, 1.0], [5.0, -2.0]]))
    want = sorted((math.log(abs(v)) / T for v in lam if abs(v) > 1), reverse=True)
    assert len(want) == 1 and want[0] > 0
    assert sig.growth_rates == pytest.approx(tuple(want), rel=1e-9)
    warns = unexplained_outputs(sig)
    sim_named = [w for w in warns if "simulation" in w["r2"]]
    assert sim_named, warns
    for w in sim_named:
        assert w["growth_rate"] == pytest.approx(want[0], rel=1e-9)
        assert "unstable" in w["message"] and "trim" in w["message"]
        assert f"{want[0]:.3g}/s" in w["message"]


def test_derivative_signal_is_the_transitions_rate_under_rk4_and_a_first_order_hold():
    """Session 47: the drift at the sample differs from what an RK4/first-order-hold model
    moves over the step by O(T) terms in the input's rate, and locate flagged `udot:da` in a
    correct model. The derivative signal is now the transition's mean rate; on the model's own
    noise-free path it equals the finite differences. The rate is checked against an
    independent numpy RK4 with the input linear over the step."""
    res = simulate(_model(), theta=THETA, t=TT, u={"de": three_two_one_one(
        TT, amplitude=0.03, start=1, unit=0.4) + 0.01 * np.sin(3 * TT)}, x0=[0.02, 0.0],
        integrator="rk4", input_hold="foh")
    sig = evaluate(_model(), _record(res), dict(zip(("Za", "Ma", "Mq", "Mde"), THETA)),
                   mu=res.x, G=np.zeros((2, 2)), R=RM, integrator="rk4", input_hold="foh")
    np.testing.assert_allclose(sig.xdot_fd, sig.f_smooth, rtol=1e-8, atol=1e-10)

    def f(x, u):
        return A @ x + B[:, 0] * u

    k = 60
    x, u0, u1 = res.x[k], res.u[k, 0], res.u[k + 1, 0]
    um = 0.5 * (u0 + u1)
    k1 = f(x, u0)
    k2 = f(x + T / 2 * k1, um)
    k3 = f(x + T / 2 * k2, um)
    k4 = f(x + T * k3, u1)
    rate = (k1 + 2 * k2 + 2 * k3 + k4) / 6
    np.testing.assert_allclose(sig.f_smooth[k], rate, rtol=1e-10, atol=1e-12)
    # and it is not the drift at the sample where the input moves
    assert np.abs(sig.f_smooth[k] - f(x, u0)).max() > 1e-6
