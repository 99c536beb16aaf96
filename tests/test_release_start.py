"""The "release" noise start of an unmeasured state with process noise, against an exact Kalman reference.

Linear model with two states, a yaw-rate/sideslip pair: x1 measured (y1 = x1), x2 unmeasured,
both with process noise, ẋ1 = a11 x1 + a12 x2 + b1 u, ẋ2 = a22 x2 − x1 + b2 u (the kinematic
−x1 as −r in a sideslip equation); the second output is an accelerometer, y2 = a22 x2 + b2 u,
which the unmeasured state's noise could absorb (as a sideslip with free process noise
absorbs a lateral accelerometer). The discrete model (Euler,
Q = T diag(g1², g2²)) has an exact likelihood from a numpy Kalman filter written here;
maximised by scipy it is the reference the fit from null guesses must reach. The same
model with x2 in other units (x2' = c·x2, parameters unchanged) must give the same iterates.
"""

from __future__ import annotations

import math
import types

import jax.numpy as jnp
import numpy as np
import pytest

from kalman_ref import kalman_loglik_jax, maximum_likelihood   # tests/ is on sys.path
from vsidgen.estimator import FitOptions, fit
from vsidgen.metadata import MeasurementNoiseSpec, Parameter, ProcessNoiseSpec, Variable
from vsidgen.model import Model

# one worker runs the whole module: its module-scoped fixtures are computed once
pytestmark = pytest.mark.xdist_group("test_release_start")

T = 0.05
THETA_TRUE = np.array([-1.0, 4.0, -3.0, -0.3, 0.1])  # a11, a12, b1, a22, b2
G_TRUE = np.array([0.05, 0.02])
R_STD = np.array([0.01, 0.005])
P0 = 1e6
C = 57.29577951308232  # x2 in "degrees"


def drift(x, u, p):
    c = p[5]
    return jnp.stack([p[0] * x[0] + p[1] * x[1] / c + p[2] * u[0], c * (p[3] * x[1] / c - x[0] + p[4] * u[0])])


def output(x, u, p):
    return jnp.stack([x[0], p[3] * x[1] / p[5] + p[4] * u[0]])


def make_model(c=1.0):
    """The model with x2 expressed in units of 1/c of the reference's (x2' = c·x2; c a fixed parameter,
    so that both models share compiled code)."""
    return Model(
        name="release", drift=drift, output=output,
        states=(Variable("x1"), Variable("x2")), inputs=(Variable("u"),),
        outputs=(Variable("y1"), Variable("y2")),
        parameters=tuple(Parameter(n) for n in ("a11", "a12", "b1", "a22", "b2")) + (
            Parameter("c", initial=c, fixed=True),),
        process_noise=ProcessNoiseSpec(states=("x1", "x2")),
        measurement_noise=tuple(MeasurementNoiseSpec(o, floor=0.0) for o in ("y1", "y2")))


def _mats(p):
    A = np.array([[p[0], p[1]], [-1.0, p[3]]])
    B = np.array([p[2], p[4]])
    Cm = np.array([[1.0, 0.0], [0.0, p[3]]])
    D = np.array([0.0, p[4]])
    return A, B, Cm, D


def record(N, seed):
    rng = np.random.default_rng(seed)
    k = np.arange(N)
    u = (np.sign(np.sin(k * T * 1.1)) + 0.4 * np.sin(k * T * 3.7))[:, None]
    A, B, Cm, D = _mats(THETA_TRUE)
    x = np.array([0.05, -0.02])
    Y = np.empty((N, 2))
    for i in range(N):
        Y[i] = Cm @ x + D * u[i, 0] + R_STD * rng.normal(size=2)
        x = x + T * (A @ x + B * u[i, 0]) + math.sqrt(T) * G_TRUE * rng.normal(size=2)
    return types.SimpleNamespace(name="r", path=None, t=k * T, dt=T, u=u, y=Y,
                                 input_names=("u",), output_names=("y1", "y2"))


def kalman_loglik(theta, g, r, rec):
    """Exact log-likelihood (flat prior on x_0) of the Euler-discretised model."""
    A, B, Cm, D = _mats(theta)
    Ad, Bd = np.eye(2) + T * A, T * B
    Q = T * np.diag(np.asarray(g, float) ** 2)
    R = np.diag(np.asarray(r, float) ** 2)
    m, P = np.zeros(2), P0 * np.eye(2)
    ll = math.log(2 * math.pi * P0)
    for k in range(len(rec.y)):
        S = Cm @ P @ Cm.T + R
        e = rec.y[k] - Cm @ m - D * rec.u[k, 0]
        ll += -0.5 * (e @ np.linalg.solve(S, e) + np.linalg.slogdet(2 * np.pi * S)[1])
        K = P @ Cm.T @ np.linalg.inv(S)
        m = m + K @ e
        P = (np.eye(2) - K @ Cm) @ P
        m = Ad @ m + Bd * rec.u[k, 0]
        P = Ad @ P @ Ad.T + Q
    return ll


@pytest.fixture(scope="module")
def rec():
    return record(300, seed=5)


@pytest.fixture(scope="module")
def fitted(rec):
    return fit(make_model(), [rec], options=FitOptions(noise_start="release"))


def test_release_start_from_null_guesses_reaches_the_exact_mle(fitted, rec):
    res = fitted
    assert res.converged, res.status
    assert "release start: x2 held deterministic first" in res.status
    se = res.std_errors
    se = se[:5]
    assert np.all(np.isfinite(se)) and np.all(se > 0)

    def loglik(v):    # kalman_loglik in jax.numpy, for exact gradients
        p = v[:5]
        A = jnp.array([[p[0], p[1]], [-1.0, p[3]]])
        Cm = jnp.array([[1.0, 0.0], [0.0, p[3]]])
        return kalman_loglik_jax(jnp.eye(2) + T * A, T * jnp.stack([p[2], p[4]])[:, None], Cm,
                                 T * jnp.diag(jnp.exp(v[5:7]) ** 2), jnp.diag(jnp.exp(v[7:9]) ** 2),
                                 rec.u, rec.y, P0=P0, D=jnp.stack([0.0, p[4]])[:, None])

    v0 = np.concatenate([THETA_TRUE, np.log(G_TRUE), np.log(R_STD)])
    # the diffuse prior P0 = 1e6 costs ~6 of float64's digits at the first update: the two
    # implementations' rounding differs by ~1e-6 with another summation order (JAX on an H200:
    # 2.4e-6, docs/gpu.md), against log-likelihoods of ~1e3
    assert abs(float(loglik(v0)) - kalman_loglik(v0[:5], G_TRUE, R_STD, rec)) < 1e-5
    opt = maximum_likelihood(loglik, v0)
    assert np.all(np.abs(res.theta[:5] - opt.x[:5]) < 0.5 * se), (res.theta[:5], opt.x[:5], se[:5])
    g2 = math.exp(opt.x[6])
    assert abs(res.process_std["x2"] / g2 - 1.0) < 0.25, (res.process_std, g2)
    assert res.elbo <= -opt.fun + 1e-3          # the ELBO cannot exceed the maximised likelihood
    assert -opt.fun - res.elbo < 2.0, -opt.fun - res.elbo


def test_release_start_iterates_do_not_depend_on_the_unmeasured_states_unit(fitted, rec):
    scaled = fit(make_model(C), [rec], options=FitOptions(noise_start="release"))
    e1 = np.array([h["elbo"] for h in fitted.history])
    e2 = np.array([h["elbo"] for h in scaled.history])
    assert e1.shape == e2.shape, (len(e1), len(e2))
    # the flat prior on x_0 is a density in state units: the ELBO shifts by ln c, nothing else changes
    np.testing.assert_allclose(e2 - math.log(C), e1, rtol=1e-8, atol=1e-6)
    np.testing.assert_allclose(scaled.theta[:5], fitted.theta[:5], rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(scaled.std_errors[:5], fitted.std_errors[:5], rtol=1e-5)
    assert scaled.process_std["x2"] == pytest.approx(C * fitted.process_std["x2"], rel=1e-6)
    mu1, mu2 = fitted.smoothers[0].mu, scaled.smoothers[0].mu
    np.testing.assert_allclose(mu2[:, 1], C * mu1[:, 1], rtol=1e-6, atol=1e-8 * C)
