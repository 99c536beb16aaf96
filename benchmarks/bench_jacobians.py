"""Generated Jacobians against forward-mode autodiff: compile and run time.

Two measurements, each path after ``jax.clear_caches()`` (and vsidgen's objective cache
cleared) with the persistent compilation cache off, so each pays its own compile time:

1. **kernels**: per shipped spec, ``jit(vmap(...))`` over ``--points`` samples of
   ``(∂f/∂x, ∂f/∂p)``, ``(∂h/∂x, ∂h/∂p)`` and of the transition Jacobian
   ``(∂F/∂x, ∂F/∂p)`` (RK4, 2 sub-steps): the generated functions (chain rule for F)
   against ``jax.jacfwd`` of the generated ``drift``/``output``/``F``. Compile = first
   call minus a warm call; run = median of ``--repeat`` warm calls.
2. **blocks**: the estimator's gradient and Hessian blocks of one Newton iteration
   (``Problem.blocks``, the sigma-point assembly that forms ∂F/∂(x, θ) and ∂h/∂(x, θ) at
   every point; ``core.POINT_JACOBIANS`` "generated" vs "autodiff") for Euler and RK4 × 2,
   the two paths compiled once and then called alternately (so a change of machine load
   hits both).
3. **fits**: whole estimator fits (``vsidgen.estimator.fit``, CLI defaults) with the sigma-point
   Jacobians of the Hessian assembly from the generated functions and by autodiff
   (``vsidgen.estimator.core.POINT_JACOBIANS``). Compile = JAX's compilation-duration events.

    python benchmarks/bench_jacobians.py                     # kernels + both default fits
    python benchmarks/bench_jacobians.py --no-fits           # kernels and blocks only
"""

from __future__ import annotations

import argparse
import os
import pathlib
import statistics
import sys
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
FLIGHT = pathlib.Path(os.environ.get("VSIDGEN_FLIGHT_DATA", ROOT.parent / "shared" / "data" / "flight"))

EVENTS = ("/jax/core/compile/jaxpr_trace_duration", "/jax/core/compile/jaxpr_to_mlir_module_duration",
          "/jax/core/compile/backend_compile_duration")
FITS = (("attas_sp (README demo)", ROOT / "specs" / "attas_sp.yaml", (ROOT / "data" / "attas_sp_synthetic.csv",)),
        ("hfb320", ROOT / "specs" / "hfb320.yaml", (FLIGHT / "hfb320_1_10.csv",)))


def _clear():
    import jax

    from vsidgen.estimator import core
    core._OBJECTIVES.clear()
    jax.clear_caches()


def _timed(fn, args, repeat):
    import jax
    t0 = time.perf_counter()
    jax.block_until_ready(fn(*args))
    first = time.perf_counter() - t0
    runs = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        runs.append(time.perf_counter() - t0)
    run = statistics.median(runs)
    return max(first - run, 0.0), run


def kernels(points: int, repeat: int) -> None:
    import jax
    import jax.numpy as jnp
    import numpy as np

    from vsidgen.model.dynamics import transition
    from vsidgen.model import load_model

    print(f"## kernels: jit(vmap) over {points} samples; compile s / run ms (median of {repeat})")
    print("| spec | f: generated | f: jacfwd | h: generated | h: jacfwd | F rk4×2: chain rule | F rk4×2: jacfwd |")
    print("|---|---|---|---|---|---|---|")
    for spec in sorted((ROOT / "specs").glob("*.yaml")):
        m = load_model(spec, generated_dir=ROOT / "generated", build=False)
        rng = np.random.default_rng(0)
        X = jnp.asarray(rng.uniform(0.5, 1.5, (points, m.nx)))
        U = jnp.asarray(rng.uniform(-0.5, 0.5, (points, m.nu)))
        p = jnp.asarray([float(q.initial) for q in m.parameters]) + 0.1
        F = transition(m, integrator="rk4", substeps=2)
        cases = (
            lambda x, u: (lambda j: (j[0], j[2]))(m.drift_jacobian(x, u, p)),
            lambda x, u: jax.jacfwd(m.drift, argnums=(0, 2))(x, u, p),
            lambda x, u: (lambda j: (j[0], j[2]))(m.output_jacobian(x, u, p)),
            lambda x, u: jax.jacfwd(m.output, argnums=(0, 2))(x, u, p),
            lambda x, u: F.jacobian(x, u, p, 0.05),
            lambda x, u: jax.jacfwd(F.fn, argnums=(0, 2))(x, u, p, 0.05),
        )
        cells = []
        for fn in cases:
            _clear()
            c, r = _timed(jax.jit(jax.vmap(fn)), (X, U), repeat)
            cells.append(f"{c:.2f} / {1e3 * r:.2f}")
        print(f"| {spec.stem} | " + " | ".join(cells) + " |")


def blocks(cases, repeat: int) -> None:
    """The estimator's derivative blocks (one call = one Newton iteration's assembly) with the
    generated Jacobians and with autodiff, compiled once each, then called alternately."""
    import jax
    import numpy as np

    from vsidgen.data import load_record
    from vsidgen.estimator import core
    from vsidgen.estimator import Problem
    from vsidgen.estimator.results import FitOptions
    from vsidgen.model import load_model

    print(f"## estimator blocks: compile s (first call minus a warm call); run s: median of {repeat} "
          "alternating warm calls")
    print("| case | integrator | generated: compile | generated: run | autodiff: compile | autodiff: run |")
    print("|---|---|---|---|---|---|")
    for label, spec, data in cases:
        model = load_model(spec, generated_dir=ROOT / "generated", build=False)
        records = [load_record(model, d) for d in data]
        for integ, sub in (("euler", 1), ("rk4", 2)):
            calls, comp = {}, {}
            for name in ("generated", "autodiff"):
                _clear()
                core.POINT_JACOBIANS = name
                P = Problem(model, records, FitOptions(integrator=integ, substeps=sub))
                s, recs = P.initial(FitOptions())
                fn = (lambda P=P, s=s, recs=recs: P.blocks(s, recs))
                t0 = time.perf_counter()
                jax.block_until_ready(fn())
                first = time.perf_counter() - t0
                t0 = time.perf_counter()
                jax.block_until_ready(fn())
                comp[name] = first - (time.perf_counter() - t0)
                calls[name] = (fn, [])
            for _ in range(repeat):
                for name, (fn, times) in calls.items():
                    t0 = time.perf_counter()
                    jax.block_until_ready(fn())
                    times.append(time.perf_counter() - t0)
            med = {k: float(np.median(v[1])) for k, v in calls.items()}
            print(f"| {label} | {integ} ×{sub} | {comp['generated']:.1f} | {med['generated']:.3f} | "
                  f"{comp['autodiff']:.1f} | {med['autodiff']:.3f} |", flush=True)


def fits(cases) -> None:
    import jax

    from vsidgen.data import load_record
    from vsidgen.estimator import FitOptions, core, fit
    from vsidgen.model import load_model

    total = [0.0]
    jax.monitoring.register_event_duration_secs_listener(
        lambda event, duration, **_: total.__setitem__(0, total[0] + float(duration)) if event in EVENTS else None)
    print("## fits (CLI defaults): compile = JAX compilation events during the fit")
    print("| case | Jacobians | compile s | wall s | iterations | ELBO |")
    print("|---|---|---|---|---|---|")
    for label, spec, data in cases:
        model = load_model(spec, generated_dir=ROOT / "generated", build=False)
        records = [load_record(model, d) for d in data]
        for name in ("generated", "autodiff"):
            _clear()
            core.POINT_JACOBIANS = name
            total[0] = 0.0
            t0 = time.perf_counter()
            res = fit(model, records, options=FitOptions())
            wall = time.perf_counter() - t0
            print(f"| {label} | {name} | {total[0]:.1f} | {wall:.1f} | {res.iterations} | {res.elbo!r} |",
                  flush=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=4096)
    ap.add_argument("--repeat", type=int, default=20)
    ap.add_argument("--no-kernels", action="store_true")
    ap.add_argument("--no-fits", action="store_true")
    ap.add_argument("--no-blocks", action="store_true")
    ap.add_argument("--fit", nargs="*", default=None, help="fit cases by label prefix (default: all)")
    a = ap.parse_args(argv)
    import jax
    jax.config.update("jax_enable_compilation_cache", False)
    from vsidgen import precision  # noqa: F401  (float64 before any array is made)
    if not a.no_kernels:
        kernels(a.points, a.repeat)
    cases = [c for c in FITS if a.fit is None or any(c[0].startswith(f) for f in a.fit)]
    if not a.no_blocks:
        blocks(cases, a.repeat)
    if not a.no_fits:
        fits(cases)
    return 0


if __name__ == "__main__":
    sys.exit(main())
