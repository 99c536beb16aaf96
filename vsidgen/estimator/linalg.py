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


#: the Newton system's state blocks solved by :func:`btd_solve_parallel` (True), by the
#: sequential :func:`btd_solve` (False), or by the parallel one on an accelerator and the
#: sequential one on the CPU (None, the default; see :func:`use_parallel_solve`)
PARALLEL_SOLVE: bool | None = None


def use_parallel_solve() -> bool:
    """Whether the objective eliminates the state means with :func:`btd_solve_parallel`.

    :data:`PARALLEL_SOLVE`, or when that is None: on an accelerator (JAX's default backend is
    not the CPU). There each of the sequential recursion's N dependent steps costs kernel
    launches (17–24 µs per sample on an H100, docs/gpu.md) whatever its arithmetic;
    on the CPU the sequential recursion is as fast and compiles in a fraction of the time.
    """
    return jax.default_backend() != "cpu" if PARALLEL_SOLVE is None else bool(PARALLEL_SOLVE)


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


def btd_solve_parallel(D, B, R, *, unrolled: bool = False):
    """:func:`btd_solve` by odd-even (block cyclic) reduction: O(log N) sequential depth.

    Same arguments and results. Each level eliminates the odd-numbered blocks,
    k = 1, 3, …, with their Cholesky factors L_k (one batched factorisation), leaving
    the Schur complement on the even-numbered ones, again block tridiagonal:

        D'_j   = D_j − Gl_{j+1}ᵀGl_{j+1} − Gr_{j−1}ᵀGr_{j−1},
        B'_j   = A'[j, j+2] = −Gl_{j+1}ᵀ Gr_{j+1},
        R'_j   = R_j − Gl_{j+1}ᵀ z_{j+1} − Gr_{j−1}ᵀ z_{j−1},

    with, for odd k, Gl_k = L_k⁻¹A[k, k−1] = L_k⁻¹B_{k−1}ᵀ, Gr_k = L_k⁻¹A[k, k+1] = L_k⁻¹B_k
    (0 past the end) and z_k = L_k⁻¹R_k. The evens are solved recursively (⌈log₂N⌉ levels,
    shapes static), then x_k = L_k⁻ᵀ(z_k − Gl_k x_{k−1} − Gr_k x_{k+1}).

    This is the block Cholesky factorisation of A with its blocks reordered (odd first,
    level by level): a symmetric permutation of an SPD matrix is SPD, so it succeeds exactly
    when A is positive definite, and log det A is the sum of the pivots' log-determinants.
    It does about twice the arithmetic of the sequential recursion, in ~log₂N batched steps
    instead of N dependent ones: the right choice where each dependent step costs a kernel
    launch (a GPU), see :func:`use_parallel_solve`.

    The pivots are used through their inverse factors L_k⁻¹ (one batched triangular inversion
    per level, then matrix products): backward stable enough for the damped, well-conditioned
    n × n pivots of the Newton system, and the tests compare with the sequential solve.

    ``unrolled``: factor and invert the pivots with the unrolled arithmetic of the sequential
    recursion (n ≤ :data:`SMALL_BLOCK`) instead of batched library calls. Off by default: every
    level is then its own unrolled graph (XLA-CPU compiled N = 10⁵, n = 4 in 20–33 s instead of
    ~1 s, for the same run time).
    """
    N, n, _ = D.shape
    eye = jnp.eye(n, dtype=D.dtype)
    if unrolled and n <= SMALL_BLOCK:
        chol = jax.vmap(chol_small)
        inv_lower = jax.vmap(lambda L: tri_solve_small(L, eye))
    else:
        chol = jnp.linalg.cholesky
        inv_lower = lambda L: solve_triangular(L, jnp.broadcast_to(eye, L.shape), lower=True)  # noqa: E731

    def tr(M):
        return jnp.swapaxes(M, -1, -2)

    def level(D, B, R):
        # One factorisation and one triangular inversion per level, the rest matrix products:
        # the library calls form a single dependent chain (jaxlib 0.10's batched CPU LAPACK
        # kernels deadlock when two run concurrently on a 2-thread pool: seen as a hang).
        N = D.shape[0]
        L = chol(D if N == 1 else D[1::2])
        Li = inv_lower(L)
        diag = jnp.diagonal(L, axis1=1, axis2=2)
        ok = jnp.all(jnp.isfinite(L)) & jnp.all(diag > 0)
        logdet = 2.0 * jnp.sum(jnp.log(diag))
        if N == 1:
            return tr(Li) @ (Li @ R), ok, logdet
        ne, no = (N + 1) // 2, N // 2
        De, Re, Ro = D[0::2], R[0::2], R[1::2]
        El = tr(B[0::2][:no])  # A[k, k-1], k = 2i+1
        Er = B[1::2]  # A[k, k+1] where k+1 < N
        if Er.shape[0] < no:  # N even: the last odd block has no right neighbour
            Er = jnp.concatenate([Er, jnp.zeros((no - Er.shape[0], n, n), D.dtype)])
        Gl, Gr, Z = Li @ El, Li @ Er, Li @ Ro
        GlT, GrT = tr(Gl), tr(Gr)

        def to_left(V):  # odd i -> even i (pad to ne)
            return jnp.concatenate([V, jnp.zeros((ne - no,) + V.shape[1:], V.dtype)]) if ne > no else V

        def to_right(V):  # odd i -> even i+1
            return jnp.concatenate([jnp.zeros((1,) + V.shape[1:], V.dtype), V])[:ne]

        D2 = De - to_left(GlT @ Gl) - to_right(GrT @ Gr)
        R2 = Re - to_left(GlT @ Z) - to_right(GrT @ Z)
        B2 = -(GlT @ Gr)[:ne - 1]
        Xe, ok2, logdet2 = level(D2, B2, R2)
        Xr = jnp.concatenate([Xe[1:], jnp.zeros((1,) + Xe.shape[1:], Xe.dtype)])[:no]
        Xo = tr(Li) @ (Z - Gl @ Xe[:no] - Gr @ Xr)
        X = jnp.stack([Xe[:no], Xo], axis=1).reshape((2 * no,) + Xe.shape[1:])
        if ne > no:
            X = jnp.concatenate([X, Xe[no:]])
        return X, ok & ok2, logdet + logdet2

    return level(D, B, R)


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
