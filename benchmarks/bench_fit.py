"""Fit benchmark: vsidgen's structured Newton optimizer vs the reference approach (trust-constr).

Prints, per case, for each optimizer: time to the first iterate (jit compile + first
evaluation), iterations, wall time to converge (compile included), final ELBO, peak
memory (ru_maxrss of the process that ran it) and the time vsidgen needed to reach the
reference's final ELBO, with the ratio.

Cases: HFB-320 and ATTAS short period (real flight data from ../shared/data/flight;
skipped with a message when absent) and synthetic ATTAS short-period records of N samples
(vsidgen.simulate.simulate, specs/attas_sp.yaml, dt = 0.04 s, repeated 3-2-1-1 + doublet
manoeuvres, process and measurement noise). All fits start from null initial guesses
(the specs' initial values, 0) with measured-state initialisation.

Each (case, optimizer) runs in its own child process (``--one``), so the peak memory and
the compile time are those of that fit alone; the parent runs them one after the other
(never in parallel) and prints the table.

    python benchmarks/bench_fit.py                 # hfb320, attas_sp, synthetic 1e3..1e6
    python benchmarks/bench_fit.py --quick         # hfb320, attas_sp, synthetic 1e3, 1e4
    python benchmarks/bench_fit.py --sizes 1000 100000 --no-real
    python benchmarks/bench_fit.py --reference-max-n 10000   # largest N for trust-constr
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import resource
import subprocess
import sys
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]
FLIGHT = ROOT.parent / "shared" / "data" / "flight"
REAL = {
    "hfb320": ("specs/hfb320.yaml", ["hfb320_1_10.csv"]),
    "attas_sp": ("specs/attas_sp.yaml", ["attas_elv1.csv"]),
}
SYN_THETA = {"Z0": -0.009, "ZAL": -0.483, "ZQ": 0.104, "ZDE": 0.676,
             "M0": 0.475, "MAL": -4.93, "MQ": -2.01, "MDE": -7.21}


def synthetic_record(model, n: int, seed: int = 1):
    import numpy as np

    from vsidgen.data import Record
    from vsidgen.simulate import simulate

    dt = 0.04
    t = np.arange(n) * dt
    period = 25.0  # a 3-2-1-1 and a doublet every 25 s
    tau = np.mod(t, period)
    de = np.full(n, 0.04)
    for start, width, amp in ((2.0, 1.5, 0.02), (2.0 + 3 * 1.0, 1.0, -0.02), (7.0, 0.5, 0.02),
                              (7.5, 0.5, -0.02), (14.0, 1.5, 0.025), (15.5, 1.5, -0.025)):
        de += np.where((tau >= start) & (tau < start + width), amp, 0.0)
    sim = simulate(model, theta=SYN_THETA, t=t, u={"de": de}, x0={"alpha": 0.037, "q": 0.0},
                   process_std={"alpha": 0.005, "q": 0.01}, measurement_std={"alpha": 0.0017, "q": 0.0028},
                   seed=seed)
    return Record(name=f"syn{n}", path=None, t=t, dt=dt, u=sim.u, y=sim.y,
                  input_names=model.input_names, output_names=model.output_names, t_raw=t)


def run_one(case: str, optimizer: str, max_iter: int) -> dict:
    """Run one fit in this process and return the measured figures."""
    from vsidgen.data import load_record
    from vsidgen.estimator import FitOptions, fit
    from vsidgen.model import load_model

    if case in REAL:
        spec, files = REAL[case]
        model = load_model(ROOT / spec)
        records = [load_record(model, FLIGHT / f) for f in files]
    else:
        model = load_model(ROOT / "specs/attas_sp.yaml")
        records = [synthetic_record(model, int(float(case.removeprefix("syn"))))]
    n = sum(len(r.t) for r in records)
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t0 = time.perf_counter()
    log = os.environ.get("BENCH_PROGRESS")
    fh = open(log, "w") if log else None

    def progress(it, elbo, rg, elapsed):
        if fh is not None:
            fh.write(json.dumps({"it": it, "elbo": elbo, "t": elapsed}) + "\n")
            fh.flush()

    res = fit(model, records, options=FitOptions(optimizer=optimizer, max_iter=max_iter, progress=progress))
    wall = time.perf_counter() - t0
    hist = [{"it": h["iteration"], "elbo": h["elbo"], "t": h["elapsed_s"]} for h in res.history]
    return {"case": case, "optimizer": optimizer, "n": n, "wall_s": wall,
            "first_iterate_s": hist[0]["t"] if hist else float("nan"),
            "iterations": res.iterations, "elbo": res.elbo, "converged": res.converged, "status": res.status,
            "warnings": [w["code"] for w in res.warnings], "history": hist,
            "maxrss_gib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20,
            "maxrss_before_fit_gib": rss0 / 2 ** 20}


def child(case: str, optimizer: str, max_iter: int, timeout: float) -> dict:
    cmd = [sys.executable, __file__, "--one", case, "--optimizer", optimizer, "--max-iter", str(max_iter)]
    t0 = time.perf_counter()
    import tempfile

    prog = tempfile.NamedTemporaryFile(suffix=".jsonl", delete=False).name
    try:
        out = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, cwd=ROOT,
                             env={**os.environ, "BENCH_PROGRESS": prog})
    except subprocess.TimeoutExpired:
        lines = [json.loads(x) for x in pathlib.Path(prog).read_text().splitlines() if x.strip()]
        best = max(lines, key=lambda h: h["elbo"]) if lines else None
        msg = f"timed out after {timeout:.0f} s"
        if best:
            msg += f" (best ELBO so far {best['elbo']:.6f} at {best['t']:.1f} s, iteration {best['it']})"
        return {"case": case, "optimizer": optimizer, "error": msg, "partial": lines}
    finally:
        pass
    if out.returncode != 0:
        return {"case": case, "optimizer": optimizer, "error": out.stderr.strip().splitlines()[-1:]}
    d = json.loads(out.stdout.strip().splitlines()[-1])
    d["process_s"] = time.perf_counter() - t0
    return d


def time_to_reach(hist, elbo):
    for h in hist:
        if h["elbo"] >= elbo:
            return h["t"]
    return None


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="real cases + synthetic 1e3, 1e4")
    ap.add_argument("--sizes", type=float, nargs="*", help="synthetic record lengths (default 1e3 1e4 1e5 1e6)")
    ap.add_argument("--no-real", action="store_true", help="skip the real-data cases")
    ap.add_argument("--reference-max-n", type=float, default=1e4,
                    help="largest N for which the reference (trust-constr) is run (default 1e4)")
    ap.add_argument("--max-iter", type=int, default=200)
    ap.add_argument("--timeout", type=float, default=1800, help="seconds per (case, optimizer)")
    ap.add_argument("--json", help="also write the results to this file")
    ap.add_argument("--one", help=argparse.SUPPRESS)
    ap.add_argument("--optimizer", default="structured-newton", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.one:
        print(json.dumps(run_one(a.one, a.optimizer, a.max_iter)))
        return 0
    sizes = a.sizes if a.sizes is not None else ([1e3, 1e4] if a.quick else [1e3, 1e4, 1e5, 1e6])
    cases = [] if a.no_real else [c for c in REAL if (FLIGHT / REAL[c][1][0]).exists()]
    if not a.no_real and len(cases) < len(REAL):
        print(f"# real data not found under {FLIGHT}: skipped {sorted(set(REAL) - set(cases))}")
    cases += [f"syn{int(s)}" for s in sizes]
    try:
        load = os.getloadavg()
    except OSError:
        load = (float("nan"),) * 3
    print(f"# machine: {os.cpu_count()} CPUs, load average at start {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}")
    rows = []
    hdr = (f"{'case':>10s} {'N':>8s} {'optimizer':>17s} {'1st iter s':>10s} {'iters':>6s} {'wall s':>8s} "
           f"{'ELBO':>16s} {'conv':>5s} {'peak GiB':>8s}")
    print(hdr)
    for case in cases:
        n = None
        res = {}
        for opt in ("trust-constr", "structured-newton"):
            if opt == "trust-constr" and case.startswith("syn") and float(case[3:]) > a.reference_max_n:
                print(f"{case:>10s} {'':>8s} {opt:>17s}  skipped: N > --reference-max-n {a.reference_max_n:g} "
                      "(see docs/performance.md for the measured scaling of trust-constr)")
                continue
            d = child(case, opt, a.max_iter, a.timeout)
            res[opt] = d
            rows.append(d)
            if "error" in d:
                print(f"{case:>10s} {'':>8s} {opt:>17s}  error: {d['error']}")
                continue
            n = d["n"]
            print(f"{case:>10s} {n:8d} {opt:>17s} {d['first_iterate_s']:10.2f} {d['iterations']:6d} "
                  f"{d['wall_s']:8.2f} {d['elbo']:16.6f} {str(d['converged']):>5s} {d['maxrss_gib']:8.2f}"
                  + (f"  warnings: {','.join(d['warnings'])}" if d["warnings"] else ""), flush=True)
        ref, vs = res.get("trust-constr"), res.get("structured-newton")
        if ref and vs and "error" not in ref and "error" not in vs:
            t = time_to_reach(vs["history"], ref["elbo"])
            if t is None:
                print(f"{'':>10s} vsidgen did not reach the reference ELBO {ref['elbo']:.6f} "
                      f"(final {vs['elbo']:.6f}, difference {vs['elbo'] - ref['elbo']:.3g})")
            else:
                print(f"{'':>10s} vsidgen reached the reference ELBO {ref['elbo']:.6f} after {t:.2f} s "
                      f"(compile included): speed-up {ref['wall_s'] / t:.1f}x "
                      f"(to convergence: {ref['wall_s'] / vs['wall_s']:.1f}x)", flush=True)
    syn = [d for d in rows if d.get("optimizer") == "structured-newton" and d["case"].startswith("syn")
           and "error" not in d and d["iterations"] > 0]
    if len(syn) >= 2:
        import math
        per = [(d["n"], (d["wall_s"] - d["first_iterate_s"]) / max(d["iterations"], 1)) for d in syn]
        print("# time per iteration (after the first iterate): "
              + ", ".join(f"N={n}: {t * 1e3:.1f} ms" for n, t in per))
        lo = [p for p in per if p[0] >= 1e4] or per
        if len(lo) >= 2:
            slope = math.log(lo[-1][1] / lo[0][1]) / math.log(lo[-1][0] / lo[0][0])
            print(f"# log-log slope of time per iteration vs N between N={lo[0][0]} and N={lo[-1][0]}: {slope:.2f}")
    try:
        load = os.getloadavg()
        print(f"# load average at end {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}")
    except OSError:
        pass
    if a.json:
        pathlib.Path(a.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
