"""Where the compile time of a cold fit goes: per jitted function, per phase.

Runs one fit (default: HFB-320 on the real record ``hfb320_1_10``, null guesses, CLI
defaults) in this process and sums JAX's compilation events by function name
(``jax.monitoring`` duration events: tracing to a jaxpr, lowering to MLIR, XLA backend
compile). Records are padded to a bucket length; the bucket of each record is printed.

    python benchmarks/bench_compile.py                    # no persistent cache: cold
    python benchmarks/bench_compile.py --cache DIR        # persistent cache in DIR
    (run twice with the same DIR: the second run shows the warm-cache figures)
"""

from __future__ import annotations

import argparse
import collections
import os
import pathlib
import sys
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
FLIGHT = pathlib.Path(os.environ.get("VSIDGEN_FLIGHT_DATA", ROOT.parent / "shared" / "data" / "flight"))

PHASES = {"/jax/core/compile/jaxpr_trace_duration": "trace",
          "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower",
          "/jax/core/compile/backend_compile_duration": "compile"}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--spec", default=str(ROOT / "specs" / "hfb320.yaml"))
    ap.add_argument("--data", nargs="+", default=[str(FLIGHT / "hfb320_1_10.csv")])
    ap.add_argument("--cache", default=None, help="persistent compilation cache directory")
    ap.add_argument("--top", type=int, default=12, help="functions listed (default 12)")
    a = ap.parse_args(argv)

    import jax

    if a.cache:
        pathlib.Path(a.cache).mkdir(parents=True, exist_ok=True)
        jax.config.update("jax_compilation_cache_dir", a.cache)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.2)
    else:
        jax.config.update("jax_enable_compilation_cache", False)
    sums: dict = collections.defaultdict(lambda: collections.defaultdict(float))
    counts: collections.Counter = collections.Counter()
    active = [False]

    def listen(event, duration, fun_name=None, **_):
        if active[0] and event in PHASES:
            name = str(fun_name or "?")
            sums[name][PHASES[event]] += float(duration)
            if PHASES[event] == "trace":
                counts[name] += 1

    jax.monitoring.register_event_duration_secs_listener(listen)
    from vsidgen.data import load_record
    from vsidgen.estimator import FitOptions, fit
    from vsidgen.estimator.core import bucket_length
    from vsidgen.model import load_model

    t_load = time.perf_counter()
    model = load_model(a.spec)
    records = [load_record(model, p) for p in a.data]
    t_load = time.perf_counter() - t_load
    active[0] = True
    t0 = time.perf_counter()
    res = fit(model, records, options=FitOptions())
    wall = time.perf_counter() - t0
    active[0] = False
    tot = {ph: sum(d[ph] for d in sums.values()) for ph in ("trace", "lower", "compile")}
    print(f"spec {pathlib.Path(a.spec).name}, records "
          + ", ".join(f"{r.name} ({len(r.t)} samples, bucket {bucket_length(len(r.t))})"
                      for r in records)
          + f"; cache {'on: ' + a.cache if a.cache else 'off'}")
    print(f"fit wall {wall:.1f} s (spec load/codegen {t_load:.1f} s before it), "
          f"{res.iterations} iterations, converged {res.converged}, ELBO {res.elbo:.6f}")
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
    return 0


if __name__ == "__main__":
    sys.exit(main())
