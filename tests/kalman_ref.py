"""Exact reference for linear-Gaussian test models: Kalman filter and Rauch–Tung–Striebel smoother
in numpy (shares nothing with vsidgen).

x_{k+1} = Ad x_k + Bd u_k + w_k, w_k ~ N(0, Q) (Q may be singular: no noise on a state, or one
noise source driving several); y_k = C x_k + v_k, v_k ~ N(0, R). The filter starts from
N(0, P0 I), so with a flat prior on x_0 log p(y) ≈ the returned value (n/2 log(2π P0) added).
"""

from __future__ import annotations

import math

import numpy as np


def kalman_rts(Ad, Bd, C, Q, R, u, y, *, P0=1e6, smooth=False):
    """log p(y) with a flat prior on x_0; with ``smooth`` also the RTS means and covariances."""
    n = Ad.shape[0]
    m, P = np.zeros(n), P0 * np.eye(n)
    ll = 0.5 * n * math.log(2 * math.pi * P0)
    mf, Pf, mp, Pp = [], [], [], []
    for k in range(len(y)):
        mp.append(m)
        Pp.append(P)
        S = C @ P @ C.T + R
        e = y[k] - C @ m
        ll += -0.5 * (e @ np.linalg.solve(S, e) + np.linalg.slogdet(2 * np.pi * S)[1])
        K = P @ C.T @ np.linalg.inv(S)
        m = m + K @ e
        P = (np.eye(n) - K @ C) @ P
        mf.append(m)
        Pf.append(P)
        m = Ad @ m + Bd @ u[k]
        P = Ad @ P @ Ad.T + Q
    if not smooth:
        return ll
    ms, Ps = [None] * len(mf), [None] * len(mf)
    ms[-1], Ps[-1] = mf[-1], Pf[-1]
    for k in range(len(mf) - 2, -1, -1):
        J = Pf[k] @ Ad.T @ np.linalg.inv(Pp[k + 1])
        ms[k] = mf[k] + J @ (ms[k + 1] - mp[k + 1])
        Ps[k] = Pf[k] + J @ (Ps[k + 1] - Pp[k + 1]) @ J.T
    return ll, np.array(ms), np.array(Ps)


def kalman_loglik_jax(Ad, Bd, C, Q, R, u, y, *, P0=1e6, D=None):
    """The log-likelihood of :func:`kalman_rts` (same model, prior and constant) in jax.numpy,
    so that maximum-likelihood references get exact gradients (``jax.grad``) instead of
    finite differences. ``D``: an optional feedthrough, y_k = C x_k + D u_k + v_k."""
    import jax
    import jax.numpy as jnp

    n = Ad.shape[0]
    ny = C.shape[0]
    Dm = jnp.zeros((ny, u.shape[1])) if D is None else D

    def step(carry, inp):
        m, P, ll = carry
        uk, yk = inp
        S = C @ P @ C.T + R
        L = jnp.linalg.cholesky(S)
        e = yk - C @ m - Dm @ uk
        a = jax.scipy.linalg.solve_triangular(L, e, lower=True)
        ll = ll - 0.5 * (a @ a + 2.0 * jnp.sum(jnp.log(jnp.diag(L))) + ny * math.log(2 * math.pi))
        K = jax.scipy.linalg.cho_solve((L, True), C @ P).T
        m = m + K @ e
        P = P - K @ C @ P
        P = 0.5 * (P + P.T)
        return (Ad @ m + Bd @ uk, Ad @ P @ Ad.T + Q, ll), None

    init = (jnp.zeros(n), P0 * jnp.eye(n), 0.5 * n * math.log(2 * math.pi * P0))
    (_, _, ll), _ = jax.lax.scan(step, init, (jnp.asarray(u, float), jnp.asarray(y, float)))
    return ll


def maximum_likelihood(loglik, v0, *, gtol=1e-8):
    """BFGS maximum of ``loglik(v)`` (a jax-traceable scalar function) with its exact
    gradient; returns scipy's OptimizeResult (``fun`` = the negated maximum)."""
    import jax
    import scipy.optimize

    from vsidgen import precision  # noqa: F401  (float64)

    vg = jax.jit(jax.value_and_grad(lambda v: -loglik(v)))

    def fun(v):
        f, g = vg(np.asarray(v, float))
        return float(f), np.asarray(g, float)

    return scipy.optimize.minimize(fun, np.asarray(v0, float), jac=True, method="BFGS",
                                   options={"gtol": gtol, "maxiter": 2000})
