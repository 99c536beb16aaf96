"""States without process noise (exact kinematics such as φ̇ = p) against an exact Kalman reference.

Linear model with three states: x1, x2 a damped oscillator driven by u with process noise,
x3 its integral (ẋ3 = x1, no process noise: deterministic given its neighbours); outputs
y = C x + v. The discrete model (Euler, Q = T diag(g1², g2², 0), singular) has an exact
likelihood from a Kalman filter, which handles a singular Q without approximation, and
exact smoothed means from the Rauch–Tung–Striebel smoother. Both are written here in
numpy; nothing is shared with vsidgen. With a flat prior on x_0 the filter is started
from N(0, P0 I) and log p(y) ≈ log p_KF(y) + (n/2) log(2π P0).
"""

from __future__ import annotations

import math
import types

import jax.numpy as jnp
import numpy as np
import pytest
import scipy.optimize
from kalman_ref import kalman_loglik_jax, kalman_rts, maximum_likelihood   # tests/ is on sys.path

from vsidgen.estimator import FitOptions, fit, smooth
from vsidgen.metadata import MeasurementNoiseSpec, Parameter, ProcessNoiseSpec, Variable
from vsidgen.model import Model

# one worker runs the whole module: its module-scoped fixtures are computed once
pytestmark = pytest.mark.xdist_group("test_deterministic_states")

T = 0.05
THETA_TRUE = np.array([-0.5, -2.0, -0.8, 1.5])  # a11, a21, a22, b2
G_TRUE = np.array([0.1, 0.2, 0.0])
R_STD = np.array([0.05, 0.08, 0.02])
C_OUT = np.array([[1.0, 0.0, 0.0], [0.5, 1.0, 0.0], [0.0, 0.0, 1.0]])
P0 = 1e6


def _A(p):
    return np.array([[p[0], 1.0, 0.0], [p[1], p[2], 0.0], [1.0, 0.0, 0.0]])


def drift(x, u, p):
    return jnp.stack([p[0] * x[0] + x[1], p[1] * x[0] + p[2] * x[1] + p[3] * u[0], x[0]])


def output(x, u, p):
    return jnp.asarray(C_OUT) @ x


def model(*, estimate=True):
    return Model(
        name="integ", drift=drift, output=output,
        states=(Variable("x1"), Variable("x2"), Variable("x3")), inputs=(Variable("u"),),
        outputs=(Variable("y1"), Variable("y2"), Variable("y3")),
        parameters=tuple(Parameter(n) for n in ("a11", "a21", "a22", "b2")),
        process_noise=ProcessNoiseSpec(states=("x1", "x2"), estimate=estimate,
                                       std={"x1": G_TRUE[0], "x2": G_TRUE[1]}),
        measurement_noise=tuple(MeasurementNoiseSpec(o, estimate=estimate, std=float(s), floor=0.0)
                                for o, s in zip(("y1", "y2", "y3"), R_STD)))


def record(N, seed):
    rng = np.random.default_rng(seed)
    k = np.arange(N)
    u = (np.sign(np.sin(k * T * 1.3)) + 0.3 * np.sin(k * T * 4.1))[:, None]
    x = np.array([0.3, -0.2, 0.1])
    X = np.empty((N, 3))
    for i in range(N):
        X[i] = x
        x = x + T * (_A(THETA_TRUE) @ x + np.array([0.0, THETA_TRUE[3], 0.0]) * u[i, 0]) \
            + math.sqrt(T) * G_TRUE * rng.normal(size=3)
    y = X @ C_OUT.T + R_STD * rng.normal(size=(N, 3))
    return types.SimpleNamespace(name="r", path=None, t=k * T, dt=T, u=u, y=y,
                                 input_names=("u",), output_names=("y1", "y2", "y3"))


def kalman(theta, g, r, rec, *, smooth=False):
    """Exact log-likelihood (flat prior on x_0) of the discrete model, singular Q allowed; RTS means."""
    return kalman_rts(np.eye(3) + T * _A(theta), T * np.array([[0.0], [theta[3]], [0.0]]), C_OUT,
                      T * np.diag(np.asarray(g, float) ** 2), np.diag(np.asarray(r, float) ** 2),
                      rec.u, rec.y, P0=P0, smooth=smooth)


@pytest.fixture(scope="module")
def rec():
    return record(400, seed=3)


@pytest.fixture(scope="module")
def fitted(rec):
    return fit(model(), [rec], options=FitOptions(noise_start="data"))


def test_smoothing_with_a_deterministic_state_matches_the_exact_smoother(rec):
    res = smooth(model(estimate=False), [rec], THETA_TRUE, {"G": np.diag(G_TRUE), "R": np.diag(R_STD ** 2)})
    assert res.converged, res.status
    assert res.deterministic_states == ("x3",)
    lim = res.deterministic_limit
    assert lim is not None and lim["reached"], lim
    ll, ms, Ps = kalman(THETA_TRUE, G_TRUE, R_STD, rec, smooth=True)
    gap = ll - res.elbo
    assert gap > -1e-3, gap                 # a lower bound on the exact likelihood (within the limit's tolerance)
    assert gap < 1.0, gap                   # and tight: only the stationary covariance at the ends is slack
    mid = slice(40, -40)
    err = np.abs(res.smoothers[0].mu[mid] - ms[mid]) / np.sqrt(np.diagonal(Ps[mid], axis1=1, axis2=2))
    assert err.max() < 0.05, err.max()      # smoothed means within 5 % of the exact posterior std


def test_fit_with_a_deterministic_state_from_null_guesses_matches_the_exact_mle(fitted, rec):
    res = fitted
    assert res.converged, res.status
    assert res.deterministic_states == ("x3",)
    assert res.deterministic_limit["reached"], res.deterministic_limit
    assert "x3" not in res.process_std and not np.any(res.G[2])   # reported without process noise
    se = res.std_errors
    assert np.all(np.isfinite(se)) and np.all(se > 0)
    assert np.all(np.abs(res.theta - THETA_TRUE) < 3 * se), (res.theta, se)
    # exact maximum likelihood of the model with Q33 = 0 (Kalman filter, BFGS)

    def loglik(v):    # the model with Q33 = 0, in jax.numpy for exact gradients
        A = jnp.array([[v[0], 1.0, 0.0], [v[1], v[2], 0.0], [1.0, 0.0, 0.0]])
        g = jnp.concatenate([jnp.exp(v[4:6]), jnp.zeros(1)])
        return kalman_loglik_jax(jnp.eye(3) + T * A, T * jnp.array([[0.0], [v[3]], [0.0]]), C_OUT,
                                 T * jnp.diag(g ** 2), jnp.diag(jnp.exp(v[6:9]) ** 2), rec.u, rec.y,
                                 P0=P0)

    v0 = np.concatenate([THETA_TRUE, np.log(G_TRUE[:2]), np.log(R_STD)])
    # the diffuse prior P0 = 1e6 costs ~6 of float64's digits at the first update: the two
    # implementations' rounding differs by ~1e-6 with another summation order (JAX on an H200:
    # 2.4e-6, docs/gpu.md), against log-likelihoods of ~1e3
    assert abs(float(loglik(v0)) - kalman(v0[:4], np.r_[G_TRUE[:2], 0.0], R_STD, rec)) < 1e-5
    opt = maximum_likelihood(loglik, v0)
    assert np.all(np.abs(res.theta - opt.x[:4]) < 0.5 * se), (res.theta, opt.x[:4], se)
    assert res.elbo <= -opt.fun + 1e-3          # the ELBO cannot exceed the maximised likelihood
    assert -opt.fun - res.elbo < 2.0, -opt.fun - res.elbo
    assert not any(w["code"] == "deterministic_limit_not_reached" for w in res.warnings)


def _drift2(x, u, p):
    return jnp.stack([p[0] * x[0] + x[1], p[1] * x[0] + p[2] * x[1] + p[3] * u[0]])


def _output2(x, u, p):
    return jnp.asarray(C_OUT[:2, :2]) @ x


def test_output_error_fit_matches_the_exact_output_error_estimate():
    """Every state deterministic (output error, stable model): the limit against a hand-written OE fit.

    Reference: the output-error maximum-likelihood estimate of the same discrete model, θ and
    x_0 by scipy least squares on the simulated outputs with the measurement variances
    concentrated out (R̂_j = mean squared residual of output j); standard errors from the
    Gauss–Newton information. The record has no process noise.
    """
    rng = np.random.default_rng(11)
    N = 300
    k = np.arange(N)
    u = (np.sign(np.sin(k * T * 1.3)) + 0.3 * np.sin(k * T * 4.1))[:, None]

    def simulate(theta, x0):
        A = np.array([[theta[0], 1.0], [theta[1], theta[2]]])
        Ad, Bd = np.eye(2) + T * A, T * np.array([0.0, theta[3]])
        X = np.empty((N, 2))
        x = np.asarray(x0, float)
        for i in range(N):
            X[i] = x
            x = Ad @ x + Bd * u[i, 0]
        return X @ C_OUT[:2, :2].T

    y = simulate(THETA_TRUE, [0.3, -0.2]) + R_STD[:2] * rng.normal(size=(N, 2))
    rec = types.SimpleNamespace(name="oe", path=None, t=k * T, dt=T, u=u, y=y,
                                input_names=("u",), output_names=("y1", "y2"))
    m = Model(name="oe2", drift=_drift2, output=_output2, states=(Variable("x1"), Variable("x2")),
              inputs=(Variable("u"),), outputs=(Variable("y1"), Variable("y2")),
              parameters=tuple(Parameter(n) for n in ("a11", "a21", "a22", "b2")),
              process_noise=ProcessNoiseSpec(states=("x1", "x2"), estimate=False),
              measurement_noise=tuple(MeasurementNoiseSpec(o, floor=0.0) for o in ("y1", "y2")))
    res = fit(m, [rec], options=FitOptions(noise_start="data"))
    assert res.converged, res.status
    lim = res.deterministic_limit
    assert res.deterministic_states == ("x1", "x2") and lim["reached"], lim
    assert lim["collapsed_directions"] == 2   # both directions contract: their spread collapses

    sig = R_STD[:2].copy()
    v = np.concatenate([THETA_TRUE, [0.3, -0.2]])
    for _ in range(4):  # alternate: weighted least squares in (θ, x0), then R̂ from the residuals
        sol = scipy.optimize.least_squares(lambda w: ((simulate(w[:4], w[4:]) - y) / sig).ravel(), v,
                                           xtol=1e-12, ftol=1e-12, gtol=1e-12)
        v = sol.x
        sig = np.sqrt(np.mean((simulate(v[:4], v[4:]) - y) ** 2, axis=0))
    J = sol.jac
    se_ref = np.sqrt(np.diag(np.linalg.inv(J.T @ J)))[:4]
    assert np.all(np.abs(res.theta - v[:4]) < 0.1 * se_ref), (res.theta, v[:4], se_ref)
    np.testing.assert_allclose(res.std_errors, se_ref, rtol=0.15)
    np.testing.assert_allclose([res.measurement_std[o] for o in ("y1", "y2")], sig, rtol=0.02)


def test_a_warm_started_limit_fit_restarts_at_its_optimum(fitted, rec):
    res = fit(model(), [rec], options=FitOptions(warm_start=fitted))
    assert res.converged and res.deterministic_limit["reached"], res.status
    first = res.deterministic_limit["stages"][0]
    assert first["std"] == fitted.deterministic_limit["std"]     # starts where the previous limit ended
    assert first["iterations"] <= 3, res.deterministic_limit["stages"]
    np.testing.assert_allclose(res.theta, fitted.theta, atol=0.1 * float(np.min(fitted.std_errors)))


class _Phases:
    """A progress callback that records the phases the estimator announces."""

    def __init__(self):
        self.phases, self.calls = [], 0

    def phase(self, ph):
        self.phases.append(ph)

    def __call__(self, it, elbo, grad, elapsed):
        self.calls += 1


def test_validation_smoothing_ends_at_the_estimations_noise_and_names_its_stages(rec):
    """Validation smoothing of a fit that took the deterministic limit follows the estimation's
    stds, from its first stage to exactly the std it ended with, never further; each stage is
    announced as a continuation stage, not as another noise start."""
    from vsidgen.estimator import FitPhase, PhaseKind

    val = record(300, seed=11)
    first, end = 0.05, 5e-5   # an estimation that stopped three stages down
    noise = {"G": np.diag(G_TRUE), "R": np.diag(R_STD ** 2),
             "deterministic_limit": {"states": ["x3"], "std": {"x3": end},
                                     "stages": [{"stage": 0, "std": {"x3": first}}]}}
    prog = _Phases()
    res = smooth(model(estimate=False), [val], THETA_TRUE, noise,
                 options=FitOptions(progress=prog))
    assert res.converged, res.status
    lim = res.deterministic_limit
    stds = [s["std"]["x3"] for s in lim["stages"]]
    assert stds[0] == pytest.approx(first) and stds[-1] == pytest.approx(end, rel=1e-12), stds
    assert min(stds) >= end * (1 - 1e-12), stds            # never beyond the estimation's noise
    assert lim["std"]["x3"] == pytest.approx(end, rel=1e-12) and lim["reached"], lim
    assert len(stds) == 4, stds                              # 0.05 -> 5e-3 -> 5e-4 -> 5e-5
    assert all(isinstance(p, FitPhase) and p.kind is PhaseKind.LIMIT_STAGE and p.smoothing
               for p in prog.phases), prog.phases
    assert [p.stage for p in prog.phases] == [0, 1, 2, 3]
    assert str(prog.phases[2]).startswith("validation smoothing: deterministic limit, stage 2")
    assert "noise start" not in " ".join(map(str, prog.phases))
    assert all("phase" in h for h in res.history if h)


def test_milder_stage_ends_the_limit_when_its_full_stage_equivalent_is_small():
    """The stopping rule of the deterministic-limit continuation, scaled to a full stage.

    Numbers from a new user's HFB-320 coefficient model (θ̇ = q deterministic), whose full
    stage at std 8.7e-7 did not converge: converged stages at std 8.7e-6, 2.76e-6 (ρ 0.316),
    1.55e-6 (ρ 0.562) with ELBOs 12995.1802, 12995.0228, 12995.0109 — L₀ + cε² with
    L₀ ≈ 12995.005. The first milder step (−0.157 nats) is a full-stage change of 0.173 > 0.1;
    the second (−0.0119) one of 0.017 < 0.1: the limit is reached there.
    """
    from vsidgen.estimator.fit import limit_stage_small

    assert limit_stage_small(-0.05, 0.01, 0.1, 0.1)            # a full stage: unchanged rule
    assert not limit_stage_small(-0.15, 0.01, 0.1, 0.1)
    assert not limit_stage_small(-0.05, 0.2, 0.1, 0.1)         # parameters still moving
    assert not limit_stage_small(12995.0228 - 12995.1802, 1e-4, 0.1 ** 0.5, 0.1)
    assert limit_stage_small(12995.0109 - 12995.0228, 1e-4, 0.1 ** 0.25, 0.1)
    # a mild stage's small change is not enough by itself: 0.03 nats at ρ = 0.866 is 0.11
    assert not limit_stage_small(-0.03, 1e-4, 0.1 ** 0.0625, 0.1)
