"""Concurrent noise starts against one start after the other, in one process.

``FitOptions(parallel_starts=True)`` (the default) runs the noise starts of ``"auto"`` in one
thread each; ``False`` runs them serially. Both fits of a pair use the same compiled functions
(a first fit compiles them and is not counted), alternate, and must give the same result bit
for bit (checked: θ, ELBO, iterations). Prints the wall time of each fit, the median ratio
serial / concurrent and the process CPU time per wall second (how many cores were busy).

    python benchmarks/bench_starts.py                      # HFB-320 (hfb320_1_10)
    python benchmarks/bench_starts.py --spec specs/attas_sp.yaml --data .../attas_elv1.csv
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


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--spec", default=str(ROOT / "specs" / "hfb320.yaml"))
    ap.add_argument("--data", nargs="+", default=[str(FLIGHT / "hfb320_1_10.csv")])
    ap.add_argument("--repeats", type=int, default=3, help="pairs of fits (default 3)")
    args = ap.parse_args()

    import numpy as np

    from vsidgen.data import load_record
    from vsidgen.estimator import FitOptions, fit
    from vsidgen.model import load_model

    model = load_model(args.spec)
    records = [load_record(model, p) for p in args.data]
    t = time.perf_counter()
    ref = fit(model, records, options=FitOptions(parallel_starts=False))
    print(f"{model.name}: first fit (compiles) {time.perf_counter() - t:.1f} s, {ref.iterations} iterations, "
          f"ELBO {ref.elbo:.6f}; load average {os.getloadavg()[0]:.2f}", flush=True)
    walls: dict[bool, list[float]] = {False: [], True: []}
    for _ in range(args.repeats):
        for par in (False, True):
            c0, t0 = time.process_time(), time.perf_counter()
            res = fit(model, records, options=FitOptions(parallel_starts=par))
            wall, cpu = time.perf_counter() - t0, time.process_time() - c0
            walls[par].append(wall)
            same = (np.array_equal(res.theta, ref.theta) and res.elbo == ref.elbo
                    and res.iterations == ref.iterations)
            print(f"  {'concurrent' if par else 'serial    '} {wall:6.2f} s wall, {cpu / wall:4.2f} cores busy, "
                  f"{res.iterations} iterations, same result as the first fit: {same}", flush=True)
            if not same:
                print("  RESULT DIFFERS", res.elbo, ref.elbo)
                return 1
    ratios = [s / p for s, p in zip(walls[False], walls[True])]
    print(f"median serial {statistics.median(walls[False]):.2f} s, concurrent {statistics.median(walls[True]):.2f} s, "
          f"ratio serial/concurrent {statistics.median(ratios):.2f} (pairs: {', '.join(f'{r:.2f}' for r in ratios)}); "
          f"load average {os.getloadavg()[0]:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
