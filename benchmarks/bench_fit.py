"""Fit benchmark: vsidgen's structured Newton optimizer vs the reference approach (trust-constr).

Not a test: it prints figures. For each case both optimizers run **in this process**, one
after the other, from null initial guesses (the specs' initial values, 0) with
measured-state initialisation, and the script prints per fit

* compile: seconds spent tracing, lowering and compiling JAX code during the fit (summed
  from JAX's own compilation-duration events), then ``1st iter``: time to the first
  iterate (compile + first evaluation);
* iterations, wall time (to convergence, or to the stop), final ELBO, convergence;
* peak memory of the fit: the kernel's resident-set high-water mark (VmHWM) is reset
  before each fit (``echo 5 > /proc/self/clear_refs``) and read afterwards; the reset sets
  it to the current RSS, which after earlier fits includes memory the allocator kept, so
  the RSS before the fit is printed beside it (``(before)``): the peak is an upper bound
  on the fit's own need;

and per case the time vsidgen needed to exceed the reference's final ELBO and the ratios
(reference wall / that time, and reference wall / vsidgen's wall to convergence). When the
reference stops on its wall budget (``--reference-budget``) without converging, the ratios
are lower bounds and printed as "≥".

Compile times are made comparable: ``jax.clear_caches()`` (and vsidgen's objective cache)
is cleared before each fit and the persistent compilation cache is not used.

Cases: HFB-320 and ATTAS short period (real flight data from ../shared/data/flight;
skipped with a message when absent) and synthetic ATTAS short-period records of N samples
(vsidgen.data.simulate.simulate, specs/attas_sp.yaml, dt = 0.04 s, repeated 3-2-1-1 + doublet
manoeuvres, process and measurement noise).

    python benchmarks/bench_fit.py                 # hfb320, attas_sp, synthetic 1e3..1e6
    python benchmarks/bench_fit.py --quick         # hfb320, attas_sp, synthetic 1e3, 1e4
    python benchmarks/bench_fit.py --sizes 1000 100000 --no-real
    python benchmarks/bench_fit.py --reference-max-n 10000 --reference-budget 600

Pin it to one core for reproducible figures on a shared machine: ``taskset -c 1 python ...``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import pathlib
import sys
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]
FLIGHT = pathlib.Path(os.environ.get("VSIDGEN_FLIGHT_DATA") or ROOT.parent / "shared" / "data" / "flight")
REAL = {
    "hfb320": ("specs/hfb320.yaml", ["hfb320_1_10.csv"]),
    "attas_sp": ("specs/attas_sp.yaml", ["attas_elv1.csv"]),
}
SYN_THETA = {"Z0": -0.009, "ZAL": -0.483, "ZQ": 0.104, "ZDE": 0.676,
             "M0": 0.475, "MAL": -4.93, "MQ": -2.01, "MDE": -7.21}
OPTIMIZERS = ("structured-newton", "trust-constr")


def synthetic_record(model, n: int, seed: int = 1):
    import numpy as np

    from vsidgen.data import Record
    from vsidgen.data.simulate import simulate

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


# --------------------------------------------------------------------------- measurement helpers
def _reset_peak() -> bool:
    """Reset the kernel's peak-RSS mark of this process (Linux ≥ 4.0); False where unsupported."""
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
        return True
    except OSError:
        return False


def _status_kib(key: str) -> float:
    try:
        for line in pathlib.Path("/proc/self/status").read_text().splitlines():
            if line.startswith(key + ":"):
                return float(line.split()[1])
    except OSError:
        pass
    return float("nan")


class _CompileClock:
    """Sums JAX's compilation-duration events (trace, lowering, backend compile) while active."""

    EVENTS = ("/jax/core/compile/jaxpr_trace_duration", "/jax/core/compile/jaxpr_to_mlir_module_duration",
              "/jax/core/compile/backend_compile_duration")

    def __init__(self):
        import jax

        self.total = 0.0
        self.active = False
        jax.monitoring.register_event_duration_secs_listener(self._listen)

    def _listen(self, event, duration, **_):
        if self.active and event in self.EVENTS:
            self.total += float(duration)


def _fresh_jax():
    """Forget every compiled function (fair compile times for the next fit)."""
    import jax

    from vsidgen.estimator import core

    core._OBJECTIVES.clear()
    jax.clear_caches()


def load_case(case: str):
    from vsidgen.data import load_record
    from vsidgen.model import load_model

    if case in REAL:
        spec, files = REAL[case]
        model = load_model(ROOT / spec)
        records = [load_record(model, FLIGHT / f) for f in files]
    else:
        import jax

        model = load_model(ROOT / "specs/attas_sp.yaml")
        with jax.default_device(jax.devices("cpu")[0]):  # a sequential simulation: CPU, whatever the backend
            records = [synthetic_record(model, int(float(case.removeprefix("syn"))))]
    return model, records


def run_fit(model, records, optimizer: str, *, max_iter: int, budget: float | None, clock: _CompileClock) -> dict:
    """One fit in this process with fresh JAX caches; returns the measured figures."""
    import gc

    from vsidgen.estimator import FitOptions, fit

    _fresh_jax()
    gc.collect()
    rss0 = _status_kib("VmRSS")
    peak_ok = _reset_peak()
    clock.total, clock.active = 0.0, True
    t0 = time.perf_counter()
    try:
        res = fit(model, records, options=FitOptions(optimizer=optimizer, max_iter=max_iter, time_limit=budget))
    finally:
        clock.active = False
    wall = time.perf_counter() - t0
    hist = [{"it": h["iteration"], "elbo": h["elbo"], "t": h["elapsed_s"]} for h in res.history]
    return {"optimizer": optimizer, "n": sum(len(r.t) for r in records), "wall_s": wall,
            "compile_s": clock.total, "first_iterate_s": hist[0]["t"] if hist else float("nan"),
            "iterations": res.iterations, "elbo": res.elbo, "converged": res.converged, "status": res.status,
            "budget_stop": "time limit" in res.status,
            "warnings": [w["code"] for w in res.warnings], "history": hist,
            "peak_gib": _status_kib("VmHWM") / 2 ** 20 if peak_ok else float("nan"),
            "rss_before_gib": rss0 / 2 ** 20}


def time_to_exceed(hist, elbo):
    """Elapsed time of the first iterate whose ELBO is ≥ ``elbo`` (None if never)."""
    for h in hist:
        if h["elbo"] >= elbo:
            return h["t"]
    return None


def per_iteration(d) -> float:
    """Seconds per iteration after the first iterate (compile excluded)."""
    h = d["history"]
    if len(h) < 2:
        return float("nan")
    return (h[-1]["t"] - h[0]["t"]) / (len(h) - 1)


def compare(vs: dict, ref: dict) -> str:
    lb = "≥ " if not ref["converged"] else ""
    how = ("stopped by its wall budget" if ref["budget_stop"] else "converged" if ref["converged"]
           else "stopped without converging")
    t = time_to_exceed(vs["history"], ref["elbo"])
    out = f"reference {how} at ELBO {ref['elbo']:.6f} after {ref['wall_s']:.1f} s; "
    if t is None:
        out += (f"vsidgen did not reach it (final {vs['elbo']:.6f}, difference {vs['elbo'] - ref['elbo']:.3g})")
    else:
        out += (f"vsidgen exceeded it after {t:.2f} s (compile included): ratio {lb}{ref['wall_s'] / t:.1f}x; "
                f"vsidgen converged={vs['converged']} after {vs['wall_s']:.2f} s at ELBO {vs['elbo']:.6f}: "
                f"ratio to convergence {lb}{ref['wall_s'] / vs['wall_s']:.1f}x")
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="real cases + synthetic 1e3, 1e4")
    ap.add_argument("--sizes", type=float, nargs="*", help="synthetic record lengths (default 1e3 1e4 1e5 1e6)")
    ap.add_argument("--no-real", action="store_true", help="skip the real-data cases")
    ap.add_argument("--real", nargs="*", choices=sorted(REAL), help="real cases to run (default: all)")
    ap.add_argument("--reference-max-n", type=float, default=1e4,
                    help="largest synthetic N for which the reference (trust-constr) is run (default 1e4)")
    ap.add_argument("--reference-budget", type=float, default=600.0,
                    help="wall budget of the reference per case in seconds (default 600; 0: none)")
    ap.add_argument("--max-iter", type=int, default=200)
    ap.add_argument("--json", help="also write the results to this file")
    ap.add_argument("--no-reference", action="store_true", help="skip the trust-constr reference fits")
    ap.add_argument("--time-limit", type=float, default=None,
                    help="wall budget of each structured-newton fit in seconds (stops cleanly; default none)")
    ap.add_argument("--solve", choices=("auto", "sequential", "parallel"), default="auto",
                    help="how the state means are eliminated (vsidgen.estimator.linalg.PARALLEL_SOLVE; "
                         "auto: cyclic reduction on an accelerator, the sequential recursion on the CPU)")
    a = ap.parse_args(argv)

    import jax

    from vsidgen.estimator import core, linalg

    linalg.PARALLEL_SOLVE = {"auto": None, "sequential": False, "parallel": True}[a.solve]
    print(f"# backend {jax.default_backend()} ({jax.devices()[0].device_kind}); state means eliminated by "
          f"{'cyclic reduction' if linalg.use_parallel_solve() else 'the sequential recursion'}; "
          f"assembly chunk {core.assembly_chunk()}")

    jax.config.update("jax_enable_compilation_cache", False)  # no persistent cache: compile every time
    clock = _CompileClock()
    sizes = a.sizes if a.sizes is not None else ([1e3, 1e4] if a.quick else [1e3, 1e4, 1e5, 1e6])
    real = [] if a.no_real else (a.real if a.real is not None else list(REAL))
    cases = [c for c in real if (FLIGHT / REAL[c][1][0]).exists()]
    if len(cases) < len(real):
        print(f"# real data not found under {FLIGHT}: skipped {sorted(set(real) - set(cases))}")
    cases += [f"syn{int(s)}" for s in sizes]
    load = os.getloadavg()
    aff = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else []
    print(f"# machine: {os.cpu_count()} CPUs (this process pinned to {aff}), jax {jax.__version__}, "
          f"load average at start {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}; {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}")
    hdr = (f"{'case':>10s} {'N':>8s} {'optimizer':>17s} {'compile s':>9s} {'1st iter s':>10s} {'iters':>6s} "
           f"{'wall s':>8s} {'s/iter':>7s} {'ELBO':>16s} {'conv':>5s} {'peak GiB':>8s} {'(before)':>8s}")
    print(hdr, flush=True)
    rows = []
    for case in cases:
        model, records = load_case(case)
        res = {}
        for opt in OPTIMIZERS:
            if opt == "trust-constr" and a.no_reference:
                continue
            if opt == "trust-constr" and case.startswith("syn") and float(case[3:]) > a.reference_max_n:
                print(f"{case:>10s} {'':>8s} {opt:>17s}  skipped: N > --reference-max-n {a.reference_max_n:g}")
                continue
            budget = a.reference_budget if (opt == "trust-constr" and a.reference_budget > 0) else a.time_limit
            d = run_fit(model, records, opt, max_iter=a.max_iter, budget=budget, clock=clock)
            d["case"] = case
            res[opt] = d
            rows.append(d)
            print(f"{case:>10s} {d['n']:8d} {opt:>17s} {d['compile_s']:9.2f} {d['first_iterate_s']:10.2f} "
                  f"{d['iterations']:6d} {d['wall_s']:8.2f} {per_iteration(d):7.3f} {d['elbo']:16.6f} "
                  f"{str(d['converged']):>5s} {d['peak_gib']:8.2f} {d['rss_before_gib']:8.2f}"
                  + (" (budget)" if d["budget_stop"] else "")
                  + (f"  warnings: {','.join(d['warnings'])}" if d["warnings"] else ""), flush=True)
        if len(res) == 2:
            print(f"{'':>10s} {compare(res['structured-newton'], res['trust-constr'])}", flush=True)
        del model, records
    syn = [d for d in rows if d["optimizer"] == "structured-newton" and d["case"].startswith("syn")
           and d["iterations"] > 0]
    if len(syn) >= 2:
        per = [(d["n"], per_iteration(d)) for d in syn]
        print("# time per iteration (after the first iterate): "
              + ", ".join(f"N={n}: {t * 1e3:.1f} ms" for n, t in per))
        lo = [p for p in per if p[0] >= 1e4] or per
        if len(lo) >= 2:
            slope = math.log(lo[-1][1] / lo[0][1]) / math.log(lo[-1][0] / lo[0][0])
            print(f"# log-log slope of time per iteration vs N between N={lo[0][0]} and N={lo[-1][0]}: {slope:.2f}")
    load = os.getloadavg()
    print(f"# load average at end {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}")
    if a.json:
        pathlib.Path(a.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
