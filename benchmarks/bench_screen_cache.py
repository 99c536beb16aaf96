"""Does the persistent compilation cache serve the score screen of a second record of one spec?

Each record runs in its own process (as separate ``vsidgen diagnose`` runs do), one after the
other, with one persistent compilation cache that starts empty: the base fit, locate, and the
score screen of every screenable candidate that adds no state (the Hessian–vector-product batch,
the input-filter and missing-mode banks). It prints, per record, the screen's wall time, JAX's
backend-compile time and the cache hits and misses, then the ratio of the first record's screen
wall time to each later one's.

    python benchmarks/bench_screen_cache.py                       # two independent HFB-320 null records
    python benchmarks/bench_screen_cache.py --spec specs/hfb320.yaml --records A.csv B.csv
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import subprocess
import sys
import tempfile

ROOT = pathlib.Path(__file__).resolve().parents[1]

CHILD = r"""
import collections, json, math, pathlib, sys, tempfile, time
sys.path.insert(0, {root!r})
from vsidgen.compilecache import enable_compilation_cache
enable_compilation_cache()
import jax
ev = collections.defaultdict(float)
jax.monitoring.register_event_duration_secs_listener(lambda e, d, **_: ev.__setitem__(e, ev[e] + d))
jax.monitoring.register_event_listener(lambda e, **_: ev.__setitem__(e, ev[e] + 1))
from vsidgen.discrepancy import refit, score, search
from vsidgen.discrepancy.base import registered_effects
work = pathlib.Path(tempfile.mkdtemp())
st = search.fit_spec(pathlib.Path({spec!r}), [pathlib.Path({record!r})], generated_dir=work / "gen")
info = search.model_info_of(st)
every = search.rank_candidates(info, search.locate_state(st), list(registered_effects()),
                               max_candidates=10 ** 9, min_score=-math.inf)
cands = [c for _, c in every if c.screenable and not c.states]
ev.clear()
t0 = time.perf_counter()
out = score.screen(cands, st, info, work / "screen", "bench", generated_dir=work / "gen",
                   det_std=refit.REFIT_DETERMINISTIC_STD, include_states=False)
print(json.dumps({{"candidates": len(cands), "wall_s": time.perf_counter() - t0,
                  "compile_s": ev["/jax/core/compile/backend_compile_duration"],
                  "hits": ev.get("/jax/compilation_cache/cache_hits", 0),
                  "misses": ev.get("/jax/compilation_cache/cache_misses", 0),
                  "statistics": {{k: r.statistic for k, r in out.items()}}}}))
"""


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--spec", default=str(ROOT / "specs" / "hfb320.yaml"))
    ap.add_argument("--records", nargs="+", help="CSV records (default: two independent "
                    "HFB-320 null records made by benchmarks/independent/sim.py)")
    a = ap.parse_args(argv)
    work = pathlib.Path(tempfile.mkdtemp(prefix="bench_screen_cache_"))
    records = a.records
    if not records:
        sys.path.insert(0, str(ROOT / "benchmarks" / "independent"))
        import sim
        records = []
        for seed in (0, 1):
            cols, _ = sim.simulate_hfb(seed=seed)
            path = work / f"hfb_none_s{seed}.csv"
            sim.write_csv(path, cols)
            records.append(str(path))
    env = dict(os.environ, VSIDGEN_CACHE_DIR=str(work / "cache"))
    print("| record | candidates | screen wall s | backend compile s | cache hits | misses |")
    print("|---|---|---|---|---|---|")
    walls = []
    for rec in records:
        code = CHILD.format(root=str(ROOT), spec=a.spec, record=rec)
        proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                              text=True)
        if proc.returncode:
            print(proc.stderr[-2000:], file=sys.stderr)
            return 1
        r = json.loads(proc.stdout.strip().splitlines()[-1])
        walls.append(r["wall_s"])
        print(f"| {pathlib.Path(rec).name} | {r['candidates']} | {r['wall_s']:.1f} | "
              f"{r['compile_s']:.1f} | {r['hits']:.0f} | {r['misses']:.0f} |", flush=True)
    for rec, w in zip(records[1:], walls[1:]):
        print(f"screen wall time, first record / {pathlib.Path(rec).name}: {walls[0] / w:.2f}×")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
