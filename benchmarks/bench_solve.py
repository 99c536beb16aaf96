"""The Newton system's state-mean elimination: sequential block Cholesky vs cyclic reduction.

Not a test: it prints figures. For block-tridiagonal SPD systems of N blocks of n × n with m
right-hand sides (the fit's: m = 1 + n_b, the gradient and the border columns), both
:func:`vsidgen.estimator.linalg.btd_solve` (N dependent steps, ``lax.scan``) and
:func:`~vsidgen.estimator.linalg.btd_solve_parallel` (odd-even cyclic reduction, ⌈log₂N⌉
levels) are compiled and run **in this process**, on JAX's default backend, and the script
prints compile time, median run time, their ratio and the largest difference of the
solutions.

    python benchmarks/bench_solve.py                          # N = 1e3 .. 1e5, n = 2 and 4
    python benchmarks/bench_solve.py --sizes 1e4 1e6 --sequential-max-n 1e5
"""

from __future__ import annotations

import argparse
import os
import sys
import time


def system(N: int, n: int, m: int, seed: int = 0):
    """A random diagonally dominant symmetric block-tridiagonal system (D, B, R)."""
    import jax.numpy as jnp
    import numpy as np

    rng = np.random.default_rng(seed)
    C = rng.normal(size=(N, n, n))
    D = C @ np.swapaxes(C, 1, 2) + 4.0 * n * np.eye(n)
    B = rng.normal(size=(N - 1, n, n))
    return jnp.asarray(D), jnp.asarray(B), jnp.asarray(rng.normal(size=(N, n, m)))


def timed(fn, args, repeats: int):
    import jax

    t = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    first = time.perf_counter() - t
    runs = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(fn(*args))
        runs.append(time.perf_counter() - t)
    runs.sort()
    return out, first, runs[len(runs) // 2]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", type=float, nargs="*", default=[1e3, 1e4, 1e5])
    ap.add_argument("--blocks", type=int, nargs="*", default=[2, 4], help="block sizes n")
    ap.add_argument("--rhs", type=int, nargs="*", default=None, help="right-hand sides per block size (default 1 + n_b of attas_sp / hfb320: 20, 49)")
    ap.add_argument("--sequential-max-n", type=float, default=1e6, help="skip the sequential solve above this N")
    ap.add_argument("--repeats", type=int, default=5)
    a = ap.parse_args(argv)

    import jax
    import numpy as np

    from vsidgen.estimator.linalg import btd_solve, btd_solve_parallel
    from vsidgen.estimator.core import compiler_options

    rhs = a.rhs or [{2: 20, 4: 49}.get(n, 1 + 3 * n * n) for n in a.blocks]
    print(f"# backend {jax.default_backend()} ({jax.devices()[0].device_kind}), jax {jax.__version__}, "
          f"{os.cpu_count()} CPUs, load {os.getloadavg()[0]:.2f}; {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}")
    print(f"{'N':>9s} {'n':>2s} {'m':>3s} {'seq compile':>11s} {'seq run':>10s} {'par compile':>11s} "
          f"{'par run':>10s} {'seq/par':>8s} {'max |dx|':>9s}", flush=True)
    opts = compiler_options()
    for n, m in zip(a.blocks, rhs):
        for size in a.sizes:
            N = int(size)
            args = system(N, n, m)
            par, pc, pr = timed(jax.jit(btd_solve_parallel, compiler_options=opts), args, a.repeats)
            if N <= a.sequential_max_n:
                seq, sc, sr = timed(jax.jit(btd_solve, compiler_options=opts), args, a.repeats)
                diff = float(np.max(np.abs(np.asarray(seq[0]) - np.asarray(par[0]))))
                cols = f"{sc - sr:11.2f} {sr * 1e3:8.2f}ms"
                ratio, dtxt = f"{sr / pr:8.1f}", f"{diff:9.1e}"
            else:
                cols, ratio, dtxt = f"{'-':>11s} {'-':>10s}", f"{'-':>8s}", f"{'-':>9s}"
            print(f"{N:9d} {n:2d} {m:3d} {cols} {pc - pr:11.2f} {pr * 1e3:8.2f}ms {ratio} {dtxt}"
                  + ("" if bool(par[1]) else "  (not positive definite?)"), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
