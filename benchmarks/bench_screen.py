"""Where the time of a diagnose round's score screen goes: per batch, per phase.

Fits the base model (``vsidgen.discrepancy.search.fit_spec``, diagnose's base fit), proposes
the catalogue's candidates (every effect, as round 1 of ``vsidgen diagnose``) and screens
the screenable ones batch by batch (:func:`vsidgen.discrepancy.score.batches`), timing per
batch: spec writing + code generation + import (``load_model``), the stage-0 embedding of
added states, the Hessian blocks (first call: trace + lower + XLA compile + run), the
reach analysis and the rest; JAX's compilation events (``jax.monitoring``: tracing,
lowering, backend compile) are summed per batch. No persistent compilation cache.

    python benchmarks/bench_screen.py                                   # Twin Otter short period
    python benchmarks/bench_screen.py --spec specs/hfb320.yaml --data WORK/hfb320_like_1000.csv
    python benchmarks/bench_screen.py --states-only                     # only the batches with states
"""

from __future__ import annotations

import argparse
import collections
import math
import os
import pathlib
import sys
import tempfile
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
FLIGHT = pathlib.Path(os.environ.get("VSIDGEN_FLIGHT_DATA", ROOT.parent / "shared" / "data" / "flight"))

#: XLA-CPU settings compared by --settings (added to vsidgen's CPU_COMPILER_OPTIONS); the
#: first is vsidgen's own
SETTINGS = (
    ("fit options (elemental emitters)", None),
    ("+ LLVM -O0", {"xla_backend_optimization_level": 0}),
    ("+ LLVM -O1", {"xla_backend_optimization_level": 1}),
    ("+ no expensive LLVM passes", {"xla_llvm_disable_expensive_passes": True}),
    ("+ -O0 + no expensive passes", {"xla_backend_optimization_level": 0,
                                     "xla_llvm_disable_expensive_passes": True}),
)

PHASES = {"/jax/core/compile/jaxpr_trace_duration": "trace",
          "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower",
          "/jax/core/compile/backend_compile_duration": "compile"}


def load_average() -> float:
    try:
        return os.getloadavg()[0]
    except OSError:  # pragma: no cover
        return float("nan")


class Timers:
    """Wall seconds per named phase, and JAX's compile events, of the current batch."""

    def __init__(self):
        self.t = collections.defaultdict(float)
        self.jax = collections.defaultdict(float)
        self.on = False

    def listen(self, event, duration, **_):
        if self.on and event in PHASES:
            self.jax[PHASES[event]] += float(duration)

    def wrap(self, owner, attr, name):
        fn = getattr(owner, attr)

        def timed(*a, **k):
            t0 = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                self.t[name] += time.perf_counter() - t0
        setattr(owner, attr, timed)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--spec", default=str(ROOT / "specs" / "totter_sp.yaml"))
    ap.add_argument("--data", default=str(FLIGHT / "totter_lon_9752ed20.csv"))
    ap.add_argument("--states-only", action="store_true", help="screen only the batches that add states")
    ap.add_argument("--max-batches", type=int, default=0, help="stop after this many batches (0: all)")
    ap.add_argument("--paths", nargs="+", default=["per-batch"], choices=["per-batch", "shared"],
                    help="screen path(s), one after the other in this process")
    ap.add_argument("--settings", action="store_true",
                    help="per-batch path once per XLA setting of SETTINGS (added to the CPU "
                         "options), one after the other in this process")
    a = ap.parse_args(argv)

    import jax
    jax.config.update("jax_enable_compilation_cache", False)

    from vsidgen.discrepancy import refit, score, search
    from vsidgen.discrepancy.base import registered_effects
    from vsidgen.estimator import problem as problem_mod
    from vsidgen.model import runtime

    tm = Timers()
    jax.monitoring.register_event_duration_secs_listener(tm.listen)
    work = pathlib.Path(tempfile.mkdtemp(prefix="bench_screen_"))
    gen = work / "generated"
    t0 = time.perf_counter()
    st = search.fit_spec(pathlib.Path(a.spec), [pathlib.Path(a.data)], generated_dir=gen)
    print(f"base fit {time.perf_counter() - t0:.1f} s, ELBO {st.elbo!r}, converged "
          f"{st.fit.converged}; load {load_average():.1f}")
    ev = search.locate_state(st)
    info = search.model_info_of(st)
    every = search.rank_candidates(info, ev, list(registered_effects()), max_candidates=10 ** 9,
                                   min_score=-math.inf)
    todo = [c for _, c in every if c.screenable]
    groups = score.batches(todo)
    if a.states_only:
        groups = [g for g in groups if any(c.states for c in g)]
    if a.max_batches:
        groups = groups[:a.max_batches]
    print(f"{len(every)} candidates, {len(todo)} screenable "
          f"({sum(1 for c in todo if c.states)} add states), {len(groups)} batches")
    tm.wrap(runtime, "load_model", "codegen+load")
    import vsidgen.model as model_pkg
    model_pkg.load_model = runtime.load_model
    tm.wrap(refit, "stage0_start", "stage0")
    tm.wrap(problem_mod.Problem, "blocks", "blocks")
    tm.wrap(score, "nesting_reach", "reach")
    tm.wrap(problem_mod.Problem, "reduced_system", "reduce")
    results = {}
    if a.settings:
        from vsidgen.estimator import core

        base = None
        own = dict(core.CPU_COMPILER_OPTIONS)
        print("| setting | blocks (first call) s | trace / lower / XLA compile s | batches wall s "
              "| max rel. diff of S |")
        print("|---|---|---|---|---|")
        for label, opts in SETTINGS:
            core.CPU_COMPILER_OPTIONS = {**own, **(opts or {})}
            tm.t.clear()
            tm.jax.clear()
            tm.on = True
            w0 = time.perf_counter()
            out = {}
            for i, g in enumerate(groups):
                out.update(score.screen_group(g, st, info, work / "settings", f"b{i + 1}",
                                              "bench_set", generated_dir=gen,
                                              det_std=refit.REFIT_DETERMINISTIC_STD))
            wall = time.perf_counter() - w0
            tm.on = False
            base = out if base is None else base
            diff = max((abs(r.statistic - base[k].statistic) / abs(base[k].statistic)
                        for k, r in out.items() if r.statistic is not None
                        and base[k].statistic), default=0.0)
            print(f"| {label} | {tm.t['blocks']:.1f} | {tm.jax['trace']:.1f} / {tm.jax['lower']:.1f} / "
                  f"{tm.jax['compile']:.1f} | {wall:.1f} | {diff:.2g} |", flush=True)
        print(f"load {load_average():.1f}")
        return 0
    for path in a.paths:
        print(f"\npath {path}; load {load_average():.1f}")
        print("| batch | candidates | added states | codegen+load s | stage0 s | blocks s | reach s "
              "| reduce s | other s | wall s | trace / lower / XLA compile s |")
        print("|---|---|---|---|---|---|---|---|---|---|---|")
        out = {}
        tot = time.perf_counter()
        if path == "per-batch":
            for i, g in enumerate(groups):
                tm.t.clear()
                tm.jax.clear()
                tm.on = True
                w0 = time.perf_counter()
                out.update(score.screen_group(g, st, info, work / "screen", f"b{i + 1}",
                                              "bench_sc", generated_dir=gen,
                                              det_std=refit.REFIT_DETERMINISTIC_STD))
                wall = time.perf_counter() - w0
                tm.on = False
                other = wall - sum(tm.t.values())
                print(f"| b{i + 1} | {len(g)} | {sum(len(c.states) for c in g)} | "
                      f"{tm.t['codegen+load']:.1f} | {tm.t['stage0']:.1f} | {tm.t['blocks']:.1f} | "
                      f"{tm.t['reach']:.1f} | {tm.t['reduce']:.1f} | {other:.1f} | {wall:.1f} | "
                      f"{tm.jax['trace']:.1f} / {tm.jax['lower']:.1f} / {tm.jax['compile']:.1f} |",
                      flush=True)
        else:
            tm.t.clear()
            tm.jax.clear()
            tm.on = True
            w0 = time.perf_counter()
            out.update(score.screen(sum(groups, []), st, info, work / "screen_shared", "bench_sh",
                                    generated_dir=gen, det_std=refit.REFIT_DETERMINISTIC_STD,
                                    shared=True))
            wall = time.perf_counter() - w0
            tm.on = False
            print(f"| all | {sum(len(g) for g in groups)} | - | {tm.t['codegen+load']:.1f} | "
                  f"{tm.t['stage0']:.1f} | {tm.t['blocks']:.1f} | {tm.t['reach']:.1f} | "
                  f"{tm.t['reduce']:.1f} | {wall - sum(tm.t.values()):.1f} | {wall:.1f} | "
                  f"{tm.jax['trace']:.1f} / {tm.jax['lower']:.1f} / {tm.jax['compile']:.1f} |")
        print(f"path {path}: screen wall {time.perf_counter() - tot:.1f} s; load {load_average():.1f}")
        results[path] = out
    if len(results) == 2:
        ra, rb = results["per-batch"], results["shared"]
        worst = 0.0
        for k, r in ra.items():
            s2 = rb.get(k)
            if r.statistic is None or s2 is None or s2.statistic is None:
                if (r.statistic is None) != (s2 is None or s2.statistic is None):
                    print(f"  {k}: per-batch {r.statistic} shared {None if s2 is None else s2.statistic}")
                continue
            worst = max(worst, abs(r.statistic - s2.statistic) / max(abs(r.statistic), 1e-300))
        print(f"largest relative difference of the statistics: {worst:.3g}")
    for k, r in sorted(results[a.paths[0]].items(), key=lambda kv: str(kv[0])):
        print(f"  {k}: S = {r.statistic!r} dof {r.dof} {r.note}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
