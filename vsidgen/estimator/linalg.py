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

For the small blocks of aircraft models (n ≤ :data:`SMALL_BLOCK`) the per-step Cholesky and
triangular solves are unrolled arithmetic (:func:`chol_small`, :func:`tri_solve_small`)
instead of LAPACK calls: each LAPACK call inside the sequential scan costs more in dispatch
than the 4×4 arithmetic it does (docs/performance.md).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax.scipy.linalg import solve_triangular

from .. import precision  # noqa: F401  (float64, set once)


#: largest block size whose Cholesky factor and triangular solves are unrolled arithmetic
SMALL_BLOCK = 12

# Unrolled Cholesky / triangular solves for small (n ≲ 12) matrices: plain arithmetic runs
# faster than LAPACK calls inside a scan and differentiates twice into a much smaller XLA
# graph than the LAPACK-backed primitives (compile time of the Hessians).
def chol_small(A):
    """Lower Cholesky factor of a small SPD matrix (NaN if not positive definite)."""
    n = A.shape[0]
    L = [[None] * n for _ in range(n)]
    for j in range(n):
        acc = A[j, j] - sum(L[j][k] * L[j][k] for k in range(j))
        L[j][j] = jnp.sqrt(acc)
        for i in range(j + 1, n):
            L[i][j] = (A[i, j] - sum(L[i][k] * L[j][k] for k in range(j))) / L[j][j]
    zero = jnp.zeros((), A.dtype)
    return jnp.stack([jnp.stack([L[i][j] if j <= i else zero for j in range(n)]) for i in range(n)])


def tri_solve_small(L, B):
    """Solve L X = B for small lower-triangular L; B (n, m)."""
    n = L.shape[0]
    X = []
    for i in range(n):
        acc = B[i] - sum(L[i, k] * X[k] for k in range(i)) if i else B[i]
        X.append(acc / L[i, i])
    return jnp.stack(X)


def tri_solve_small_upper(U, B):
    """Solve U X = B for small upper-triangular U; B (n, m)."""
    n = U.shape[0]
    X = [None] * n
    for i in reversed(range(n)):
        acc = B[i] - sum(U[i, k] * X[k] for k in range(i + 1, n)) if i < n - 1 else B[i]
        X[i] = acc / U[i, i]
    return jnp.stack(X)


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
    small = n <= SMALL_BLOCK
    chol = chol_small if small else jnp.linalg.cholesky

    def lower(L, X):
        return tri_solve_small(L, X) if small else solve_triangular(L, X, lower=True)

    def upper(U, X):
        return tri_solve_small_upper(U, X) if small else solve_triangular(U, X, lower=False)

    def fwd(carry, inp):
        loff, zprev = carry  # L[k, k-1], z_{k-1}
        Dk, Bk, Rk = inp
        Lkk = chol(Dk - loff @ loff.T)
        zk = lower(Lkk, Rk - loff @ zprev)
        lnext = lower(Lkk, Bk).T  # L[k+1, k] = B_kᵀ L_kk⁻ᵀ
        return (lnext, zk), (Lkk, lnext, zk)

    init = (jnp.zeros((n, n), D.dtype), jnp.zeros((n, m), D.dtype))
    _, (Lkk, Lnext, Z) = jax.lax.scan(fwd, init, (D, Bp, R))

    def bwd(xnext, inp):
        Lk, Ln, zk = inp
        xk = upper(Lk.T, zk - Ln.T @ xnext)
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
