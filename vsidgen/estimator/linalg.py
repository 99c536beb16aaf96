"""Structured linear algebra for the Newton step of the variational estimator.

The Hessian of the negative ELBO over the decision vector
``[μ_0, ..., μ_{N-1} | b]`` of one record (``b`` = border: the record's
assumed-density parameters plus the shared θ/noise parameters) is

    H = [ A   W  ]      A block tridiagonal: diagonal blocks D_k (n×n),
        [ Wᵀ  Hbb]      upper blocks B_k = A[k, k+1], W (N n × nb) dense border.

``A`` is factored in O(N n³) by the block Cholesky recursion

    L_kk = chol(D_k − L_{k,k−1} L_{k,k−1}ᵀ),   L_{k+1,k} = B_kᵀ L_kk⁻ᵀ,

run with :func:`jax.lax.scan`. A non positive-definite ``A`` shows up as NaN in
the factor (JAX's Cholesky returns NaN instead of raising); callers test
``ok`` and increase the damping.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax.scipy.linalg import solve_triangular

from .. import precision  # noqa: F401  (float64, set once)


def btd_solve(D, B, R):
    """Solve ``A X = R`` for block-tridiagonal symmetric positive-definite ``A``.

    Args:
        D: (N, n, n) diagonal blocks.
        B: (N-1, n, n) upper off-diagonal blocks, ``B[k] = A[k, k+1]``.
        R: (N, n, m) right-hand sides.

    Returns:
        (X, ok, logdet): X (N, n, m); ok is a bool scalar (False when a pivot
        block was not positive definite); logdet = log det A.
    """
    N, n, _ = D.shape
    m = R.shape[-1]
    Bp = jnp.concatenate([B, jnp.zeros((1, n, n), D.dtype)], axis=0)

    def fwd(carry, inp):
        loff, zprev = carry  # L[k, k-1], z_{k-1}
        Dk, Bk, Rk = inp
        Lkk = jnp.linalg.cholesky(Dk - loff @ loff.T)
        zk = solve_triangular(Lkk, Rk - loff @ zprev, lower=True)
        lnext = solve_triangular(Lkk, Bk, lower=True).T  # L[k+1, k] = B_kᵀ L_kk⁻ᵀ
        return (lnext, zk), (Lkk, lnext, zk)

    init = (jnp.zeros((n, n), D.dtype), jnp.zeros((n, m), D.dtype))
    _, (Lkk, Lnext, Z) = jax.lax.scan(fwd, init, (D, Bp, R))

    def bwd(xnext, inp):
        Lk, Ln, zk = inp
        xk = solve_triangular(Lk.T, zk - Ln.T @ xnext, lower=False)
        return xk, xk

    _, X = jax.lax.scan(bwd, jnp.zeros((n, m), D.dtype), (Lkk, Lnext, Z), reverse=True)
    diag = jnp.diagonal(Lkk, axis1=1, axis2=2)
    ok = jnp.all(jnp.isfinite(Lkk)) & jnp.all(diag > 0)
    logdet = 2.0 * jnp.sum(jnp.log(diag))
    return X, ok, logdet


def btd_to_dense(D, B):
    """Dense matrix of a symmetric block-tridiagonal matrix (tests only)."""
    import numpy as np

    D = np.asarray(D)
    B = np.asarray(B)
    N, n, _ = D.shape
    A = np.zeros((N * n, N * n))
    for k in range(N):
        A[k * n:(k + 1) * n, k * n:(k + 1) * n] = D[k]
        if k < N - 1:
            A[k * n:(k + 1) * n, (k + 1) * n:(k + 2) * n] = B[k]
            A[(k + 1) * n:(k + 2) * n, k * n:(k + 1) * n] = B[k].T
    return A
