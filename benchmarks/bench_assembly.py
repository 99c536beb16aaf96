"""Time the estimator's per-iteration pieces on real-record problems (no fit).

Per case: the first call of the Hessian-block assembly (trace + compile, the persistent
cache disabled), then the median of ``--repeats`` calls of the assembly (value, gradient and
structured Hessian blocks), the block-tridiagonal elimination with a damped Newton step, and
the objective value, at the fit's start point. Prints one row per case.

Usage::

    python benchmarks/bench_assembly.py [--repeats 9] [--cases hfb320 attas_sp ...]
    python benchmarks/bench_assembly.py --integrator rk4 --hold foh   # the setting diagnose's
                                                                      # numerics stage adopts

To compare two versions, run it in a checkout of each (``git worktree add``) one after the
other on an otherwise idle machine: the figures are per call, so they compare across
processes as well as the machine's load allows (its load average is printed).
"""

from __future__ import annotations

import argparse
import os
import pathlib
import statistics
import sys
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]
FLIGHT = pathlib.Path(os.environ.get("VSIDGEN_FLIGHT_DATA", ROOT.parent / "shared" / "data" / "flight"))

CASES = {
    "hfb320": ("specs/hfb320.yaml", ["hfb320_1_10.csv"]),
    "attas_sp": ("specs/attas_sp.yaml", ["attas_elv1.csv"]),
    "attas_lat": ("specs/attas_lat.yaml", ["attas_ail1.csv", "attas_rud1.csv"]),
    "synthetic": ("specs/attas_sp.yaml", [str(ROOT / "data" / "attas_sp_synthetic.csv")]),
}


def _median_time(fn, repeats: int) -> float:
    import jax

    out = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(fn())
        out.append(time.perf_counter() - t)
    return statistics.median(out)


def run_case(name: str, repeats: int, integrator: str | None = None, hold: str | None = None,
             substeps: int | None = None) -> dict:
    import jax
    import numpy as np

    from vsidgen.data import load_record
    from vsidgen.estimator import FitOptions, Problem
    from vsidgen.model import load_model
    from vsidgen.spec import compile_spec

    spec, files = CASES[name]
    spec = str(ROOT / spec)
    paths = [f if os.path.isabs(f) else str(FLIGHT / f) for f in files]
    missing = [p for p in paths if not os.path.exists(p)]
    if missing:
        return {"case": name, "skipped": f"missing {missing[0]}"}
    model = load_model(spec)
    sym = compile_spec(spec)
    recs = [load_record(sym, p) for p in paths]
    opts = FitOptions(integrator=integrator or model.integrator,
                      substeps=int(substeps or model.substeps), input_hold=hold)
    P = Problem(model, recs, opts)
    s, rr = P.initial(opts)
    t = time.perf_counter()
    blks = jax.block_until_ready(P.blocks(s, rr))
    first = time.perf_counter() - t
    blocks = _median_time(lambda: P.blocks(s, rr), repeats)
    # Marquardt-damped as in the fit's first iterations (positive definite at the start)
    dmus = [np.maximum(np.abs(np.diagonal(np.asarray(b["D"]), axis1=1, axis2=2)), 1e-8)
            for b in blks]
    dglob = np.ones(P.nglob)

    def step_fn():
        sol = P.newton_step(blks, 1.0, dmus, dglob)
        return 0.0 if sol is None else sol[0]
    step_fn()
    step = _median_time(step_fn, repeats)
    P.value(s, rr)
    value = _median_time(lambda: P.value(s, rr), repeats)
    return {"case": name, "N": sum(len(r.u) for r in recs), "n": model.nx, "np": model.np,
            "first": first, "blocks": blocks, "step": step, "value": value}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=9)
    ap.add_argument("--cases", nargs="+", default=["hfb320", "attas_sp", "attas_lat"],
                    choices=sorted(CASES))
    ap.add_argument("--integrator", choices=("euler", "rk4"), default=None,
                    help="integrator (default: each spec's own)")
    ap.add_argument("--hold", choices=("zoh", "foh"), default=None,
                    help="input hold between samples (default: each spec's own)")
    ap.add_argument("--substeps", type=int, default=None, help="sub-steps (default: the spec's)")
    args = ap.parse_args(argv)
    os.environ["JAX_COMPILATION_CACHE_DIR"] = ""  # first call: trace + compile, uncached
    sys.path.insert(0, str(ROOT))
    print(f"load average at start: {os.getloadavg()[0]:.2f}")
    print(f"{'case':10s} {'N':>6s} {'n':>3s} {'np':>3s} {'1st blocks':>11s} {'blocks':>9s} "
          f"{'Newton step':>12s} {'value':>8s}")
    for name in args.cases:
        r = run_case(name, args.repeats, args.integrator, args.hold, args.substeps)
        if "skipped" in r:
            print(f"{name:10s} skipped: {r['skipped']}")
            continue
        print(f"{name:10s} {r['N']:6d} {r['n']:3d} {r['np']:3d} {r['first']:10.2f}s "
              f"{r['blocks'] * 1e3:7.1f}ms {r['step'] * 1e3:10.1f}ms {r['value'] * 1e3:6.1f}ms")
    print(f"load average at end: {os.getloadavg()[0]:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
