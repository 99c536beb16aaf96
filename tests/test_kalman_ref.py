"""The test references agree with each other: the jax Kalman log-likelihood (exact gradients
for the maximum-likelihood references) equals the numpy one, and the BFGS maximiser finds a
known maximum."""

import numpy as np

from kalman_ref import kalman_loglik_jax, kalman_rts, maximum_likelihood  # tests/ on sys.path
from vsidgen import precision  # noqa: F401  (float64)


def _case(seed=0, n=3, ny=2, N=120):
    rng = np.random.default_rng(seed)
    Ad = np.eye(n) + 0.05 * rng.normal(size=(n, n))
    Bd = 0.05 * rng.normal(size=(n, 1))
    C = rng.normal(size=(ny, n))
    lq = 0.1 * rng.normal(size=(n, 1))
    Q = np.diag([0.01, 0.0, 0.02])[:n, :n] + lq @ lq.T          # singular-ish, as in the tests
    R = np.diag(rng.uniform(0.01, 0.1, ny) ** 2)
    u = rng.normal(size=(N, 1))
    y = rng.normal(size=(N, ny))
    return Ad, Bd, C, Q, R, u, y


def test_jax_and_numpy_kalman_likelihoods_agree():
    for seed in range(3):
        Ad, Bd, C, Q, R, u, y = _case(seed)
        ref = kalman_rts(Ad, Bd, C, Q, R, u, y)
        got = float(kalman_loglik_jax(Ad, Bd, C, Q, R, u, y))
        assert abs(got - ref) < 1e-7 * max(1.0, abs(ref)), (got, ref)


def test_maximum_likelihood_of_a_scalar_gaussian_is_the_sample_moments():
    import jax.numpy as jnp

    x = np.random.default_rng(4).normal(1.5, 0.3, size=500)

    def loglik(v):
        return jnp.sum(-0.5 * ((x - v[0]) / jnp.exp(v[1])) ** 2 - v[1]) - 0.5 * x.size * np.log(2 * np.pi)

    opt = maximum_likelihood(loglik, [0.0, 0.0])
    assert opt.success, opt.message
    np.testing.assert_allclose(opt.x, [x.mean(), np.log(x.std())], atol=1e-7)
