"""Where the compile time of a cold fit goes: per jitted function, per phase, per XLA setting.

Three measurements (default case: HFB-320 on the real record ``hfb320_1_10``, null guesses,
CLI defaults):

* one fit in this process, JAX's compilation events summed by function name
  (``jax.monitoring`` duration events: tracing to a jaxpr, lowering to MLIR, XLA backend
  compile); records are padded to a bucket length, the bucket of each record is printed;
* ``--cold-warm``: that fit twice, each in a fresh process, with one persistent compilation
  cache that starts empty (cold, then warm), plus the fit with XLA's default compiler options
  (``vsidgen.estimator.core.CPU_COMPILER_OPTIONS`` emptied) in the same way;
* ``--options``: the objective's jitted functions (Hessian blocks, value, factorisation) at
  the start point, each traced and lowered once and compiled under every XLA setting of
  ``SETTINGS`` in this process: trace / lower / backend-compile seconds (wall and process
  CPU), run time (median of interleaved warm calls) and the largest relative difference of
  the outputs from those of XLA's defaults.

    python benchmarks/bench_compile.py                    # no persistent cache: cold
    python benchmarks/bench_compile.py --cache DIR        # persistent cache in DIR
    (run twice with the same DIR: the second run shows the warm-cache figures)
    python benchmarks/bench_compile.py --cold-warm        # cold and warm, fresh processes
    python benchmarks/bench_compile.py --options [--spec specs/attas_sp.yaml --data .../attas_elv1.csv]
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import pathlib
import re
import subprocess
import sys
import tempfile
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
FLIGHT = pathlib.Path(os.environ.get("VSIDGEN_FLIGHT_DATA", ROOT.parent / "shared" / "data" / "flight"))

PHASES = {"/jax/core/compile/jaxpr_trace_duration": "trace",
          "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower",
          "/jax/core/compile/backend_compile_duration": "compile"}

#: XLA-CPU compiler settings compared by --options (name, compiler_options); the first is XLA's default
SETTINGS = (
    ("XLA defaults", {}),
    ("elemental emitters (vsidgen's)", {"xla_cpu_use_fusion_emitters": False}),
    ("LLVM -O0", {"xla_backend_optimization_level": 0}),
    ("LLVM -O1", {"xla_backend_optimization_level": 1}),
    ("no expensive LLVM passes", {"xla_llvm_disable_expensive_passes": True}),
    ("elemental emitters + LLVM -O1", {"xla_cpu_use_fusion_emitters": False, "xla_backend_optimization_level": 1}),
)


def load_average() -> float:
    try:
        return os.getloadavg()[0]
    except OSError:  # pragma: no cover - not Unix
        return float("nan")


def fit_once(a) -> dict:
    """One fit in this process with the compile events summed per function (prints the table)."""
    import jax

    if a.cache:
        # what the CLI does (every program kept, the traced programs too): vsidgen's own
        # switch, with the cache folder of this benchmark
        os.environ["VSIDGEN_CACHE_DIR"] = a.cache
        from vsidgen.compilecache import enable_compilation_cache

        enable_compilation_cache()
    else:
        jax.config.update("jax_enable_compilation_cache", False)
    sums: dict = collections.defaultdict(lambda: collections.defaultdict(float))
    counts: collections.Counter = collections.Counter()
    active = [False]

    def listen(event, duration, fun_name=None, **_):
        if active[0] and event in PHASES:
            name = re.sub(r"^jit\((.*)\)$", r"\1", str(fun_name or "?"))  # trace: f, lower/compile: jit(f)
            sums[name][PHASES[event]] += float(duration)
            if PHASES[event] == "trace":
                counts[name] += 1

    jax.monitoring.register_event_duration_secs_listener(listen)
    from vsidgen.data import load_record
    from vsidgen.estimator import FitOptions, fit
    from vsidgen.estimator import core
    from vsidgen.estimator.core import bucket_length
    from vsidgen.model import load_model

    if a.xla_defaults:
        core.CPU_COMPILER_OPTIONS = {}
    t_load = time.perf_counter()
    model = load_model(a.spec)
    records = [load_record(model, p) for p in a.data]
    t_load = time.perf_counter() - t_load
    active[0] = True
    load0 = load_average()
    t0 = time.perf_counter()
    res = fit(model, records, options=FitOptions())
    wall = time.perf_counter() - t0
    active[0] = False
    tot = {ph: sum(d[ph] for d in sums.values()) for ph in ("trace", "lower", "compile")}
    print(f"spec {pathlib.Path(a.spec).name}, records "
          + ", ".join(f"{r.name} ({len(r.t)} samples, bucket {bucket_length(len(r.t))})"
                      for r in records)
          + f"; cache {'on: ' + a.cache if a.cache else 'off'}; compiler options "
          + json.dumps(core.compiler_options()))
    print(f"fit wall {wall:.1f} s (spec load/codegen {t_load:.1f} s before it), "
          f"{res.iterations} iterations, converged {res.converged}, ELBO {res.elbo!r}; "
          f"load {load0:.1f} -> {load_average():.1f}")
    print(f"compile events: trace {tot['trace']:.1f} s, lower {tot['lower']:.1f} s, "
          f"XLA compile {tot['compile']:.1f} s, total {sum(tot.values()):.1f} s")
    print("| function | traces | trace s | lower s | XLA compile s | total s |")
    print("|---|---|---|---|---|---|")
    rows = sorted(sums.items(), key=lambda kv: -sum(kv[1].values()))
    for name, d in rows[:a.top]:
        print(f"| `{name}` | {counts[name]} | {d['trace']:.2f} | {d['lower']:.2f} | "
              f"{d['compile']:.2f} | {sum(d.values()):.2f} |")
    rest = rows[a.top:]
    if rest:
        print(f"| {len(rest)} others | {sum(counts[n] for n, _ in rest)} | "
              + " | ".join(f"{sum(d[ph] for _, d in rest):.2f}" for ph in ("trace", "lower", "compile"))
              + f" | {sum(sum(d.values()) for _, d in rest):.2f} |")
    summary = dict(wall=wall, iterations=res.iterations, elbo=res.elbo, converged=res.converged, **tot)
    print("SUMMARY " + json.dumps(summary), flush=True)
    return summary


def cold_warm(a) -> int:
    """Cold and warm persistent-cache fits, vsidgen's options and XLA's defaults, fresh processes."""
    rows = []
    for label, extra in (("vsidgen options", []), ("XLA defaults", ["--xla-defaults"])):
        cache = tempfile.mkdtemp(prefix="bench_compile_cache_")
        for phase in ("cold", "warm"):
            cmd = [sys.executable, __file__, "--spec", a.spec, "--data", *a.data, "--cache", cache, *extra]
            t0 = time.perf_counter()
            out = subprocess.run(cmd, capture_output=True, text=True, check=True).stdout
            proc = time.perf_counter() - t0
            print(f"## {label}, {phase} cache\n" + out.replace("SUMMARY ", "summary: "), flush=True)
            s = json.loads(out.split("SUMMARY ", 1)[1].splitlines()[0])
            rows.append((label, phase, proc, s))
    print("| compiler options | cache | process wall s | fit wall s | trace / lower / XLA compile s | "
          "iterations | ELBO |")
    print("|---|---|---|---|---|---|---|")
    for label, phase, proc, s in rows:
        print(f"| {label} | {phase} | {proc:.1f} | {s['wall']:.1f} | {s['trace']:.1f} / {s['lower']:.1f} / "
              f"{s['compile']:.1f} | {s['iterations']} | {s['elbo']!r} |")
    return 0


def options(a) -> int:
    """Per-function trace / lower / compile / run under each XLA setting of SETTINGS (one process)."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    jax.config.update("jax_enable_compilation_cache", False)
    from vsidgen.data import load_record
    from vsidgen.estimator import FitOptions
    from vsidgen.estimator import Problem
    from vsidgen.model import load_model

    model = load_model(a.spec)
    records = [load_record(model, p) for p in a.data]
    opts = FitOptions()
    P = Problem(model, records, opts)
    s, recs = P.initial(opts, "unit")
    m, r = recs[0]
    L = P.padded[0]
    args = (P.pad(m, L), jnp.asarray(r), jnp.asarray(s), P.bdata[0], P.cfg)
    obj = P.obj
    blk = obj.blocks(*args)
    fargs = (blk, jnp.ones((L, model.nx)), 1e-3)
    fns = (("_blocks_impl", obj._blocks_impl, args), ("_value_impl", obj._value_impl, args),
           ("_factor_impl", obj._factor_impl, fargs))
    print(f"spec {pathlib.Path(a.spec).name}, {records[0].name}: {len(records[0].t)} samples "
          f"(bucket {L}); {os.cpu_count()} CPUs, load {load_average():.1f}")
    print("| function | setting | HLO chars | trace s | lower s | XLA compile s (CPU s) | run ms | max rel. diff |")
    print("|---|---|---|---|---|---|---|---|")
    for name, fn, fa in fns:
        jax.clear_caches()  # no trace or executable of an earlier call (the blocks for fargs) is reused
        t0 = time.perf_counter()
        traced = jax.jit(fn).trace(*fa)
        t1 = time.perf_counter()
        lowered = traced.lower()
        t2 = time.perf_counter()
        hlo = len(lowered.as_text())
        done = []
        for label, o in SETTINGS:
            w0, c0 = time.perf_counter(), time.process_time()
            c = lowered.compile(compiler_options=o) if o else lowered.compile()
            done.append((label, c, time.perf_counter() - w0, time.process_time() - c0,
                         jax.block_until_ready(c(*fa))))
        runs = [[] for _ in done]
        for _ in range(a.reps):  # interleaved, so a change of load hits every setting alike
            for i, d in enumerate(done):
                t = time.perf_counter()
                jax.block_until_ready(d[1](*fa))
                runs[i].append(time.perf_counter() - t)
        ref = [np.asarray(x, float) for x in jax.tree_util.tree_leaves(done[0][4])]
        for (label, _, cw, cc, out), rt in zip(done, runs):
            got = [np.asarray(x, float) for x in jax.tree_util.tree_leaves(out)]
            diff = max(float(np.max(np.abs(g - f)) / max(float(np.max(np.abs(f))), 1e-300))
                       for g, f in zip(got, ref) if f.size)
            print(f"| `{name}` | {label} | {hlo} | {t1 - t0:.2f} | {t2 - t1:.2f} | {cw:.2f} ({cc:.2f}) | "
                  f"{1e3 * float(np.median(rt)):.1f} | {diff:.1e} |", flush=True)
    print(f"load at the end {load_average():.1f}")
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--spec", default=str(ROOT / "specs" / "hfb320.yaml"))
    ap.add_argument("--data", nargs="+", default=[str(FLIGHT / "hfb320_1_10.csv")])
    ap.add_argument("--cache", default=None, help="persistent compilation cache directory")
    ap.add_argument("--top", type=int, default=12, help="functions listed (default 12)")
    ap.add_argument("--xla-defaults", action="store_true",
                    help="XLA's default compiler options instead of vsidgen's CPU_COMPILER_OPTIONS")
    ap.add_argument("--cold-warm", action="store_true", help="cold then warm cache, fresh processes")
    ap.add_argument("--options", action="store_true", help="compare XLA settings per function")
    ap.add_argument("--reps", type=int, default=11, help="warm calls per setting (--options; default 11)")
    a = ap.parse_args(argv)
    if a.cold_warm:
        return cold_warm(a)
    if a.options:
        return options(a)
    fit_once(a)
    return 0


if __name__ == "__main__":
    sys.exit(main())
