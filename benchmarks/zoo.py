"""Model zoo benchmark: fits from null guesses on records from an independent simulator.

For each zoo model (``benchmarks/zoo/*.yaml``; truth, hand-written numpy dynamics and the
simulator in ``benchmarks/zoo/models.py`` — no vsidgen code is used to make the data) and
each seed: simulate an estimation record (seed) and a validation record (seed + 1000) in
the spec's CSV units, load them through the spec's data map, fit from the spec's null
initial guesses, smooth the validation record with θ and noise fixed, and print per fit
and per model:

* converged (the estimator's typed stop reason) and the validation smoothing's,
* the fraction of free parameters within 3 s.e. of the truth,
* coverage of the 95 % intervals (fraction with |θ̂ − θ| / s.e. < 1.96),
* estimation and validation ELBO per sample (same aircraft, same kind of record: they
  should be close; a validation ELBO far below flags a failed smoothing),
* iterations and wall time.

Usage::

    python benchmarks/zoo.py [--models sp_oe,lat4] [--seeds 1,2,3] [--jobs 2] [--json out.json]
"""

from __future__ import annotations

import argparse
import concurrent.futures as cf
import json
import os
import pathlib
import sys
import tempfile
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]
ZOO = ROOT / "benchmarks" / "zoo"


def run_one(name: str, seed: int, max_iter: int = 200) -> dict:
    """Simulate, fit and validate one (model, seed); returns a flat summary record."""
    sys.path.insert(0, str(ZOO))
    sys.path.insert(0, str(ROOT))
    import numpy as np

    import models as zoo_models
    from vsidgen.data import load_record
    from vsidgen.estimator import FitOptions, fit, smooth
    from vsidgen.model import load_model

    m = zoo_models.MODELS[name]
    with tempfile.TemporaryDirectory() as td:
        td = pathlib.Path(td)
        model = load_model(ZOO / m.spec, generated_dir=td)
        est = load_record(model, zoo_models.write_csv(m, td / f"{name}_{seed}.csv", seed))
        val = load_record(model, zoo_models.write_csv(m, td / f"{name}_{seed}_val.csv", seed + 1000))
        t0 = time.perf_counter()
        res = fit(model, [est], options=FitOptions(max_iter=max_iter))
        wall = time.perf_counter() - t0
        vres = smooth(model, [val], res.theta, res, options=FitOptions(max_iter=max_iter))
    truth = np.array([m.truth[p] for p in model.parameter_names])
    free = np.asarray(res.free_mask, bool)
    z = (res.theta - truth)[free] / res.std_errors[free]
    z = np.where(np.isfinite(z), z, np.inf)
    n_est, n_val = est.y.shape[0], val.y.shape[0]
    return {"model": name, "seed": seed, "converged": bool(res.converged),
            "stop_reason": None if res.stop_reason is None else res.stop_reason.value,
            "decrement": float(res.newton_decrement), "status": res.status,
            "within3": float(np.mean(np.abs(z) < 3.0)), "cover95": float(np.mean(np.abs(z) < 1.96)),
            "n_free": int(free.sum()), "z": [float(v) for v in z],
            "se_reliable": bool(res.std_errors_reliable),
            "se_issues": [f.issue.value for f in res.std_error_flags],
            "warnings": [w["code"] for w in res.warnings],
            "elbo_per_sample": float(res.elbo) / n_est, "val_elbo_per_sample": float(vres.elbo) / n_val,
            "val_converged": bool(vres.converged), "val_iterations": int(vres.iterations),
            "iterations": int(res.iterations), "wall_s": wall,
            "deterministic": list(res.deterministic_states)}


def _table(rows) -> str:
    out = ["| model | fits | converged | validation converged | within 3 s.e. | 95 % coverage | "
           "ELBO/sample est. | ELBO/sample val. | iterations (median) | wall s (median) |",
           "|---|---|---|---|---|---|---|---|---|---|"]
    import numpy as np

    groups = {}
    for r in rows:
        groups.setdefault(r["model"], []).append(r)
    groups["all"] = list(rows)
    for name, rs in groups.items():
        ok = [r for r in rs if "error" not in r]
        if not ok:
            out.append(f"| {name} | {len(rs)} | error | | | | | | | |")
            continue
        zs = np.concatenate([np.asarray(r["z"]) for r in ok]) if ok else np.zeros(0)
        out.append(
            f"| {name} | {len(rs)} | {sum(r['converged'] for r in ok)}/{len(rs)} | "
            f"{sum(r['val_converged'] for r in ok)}/{len(rs)} | {np.mean(np.abs(zs) < 3):.0%} | "
            f"{np.mean(np.abs(zs) < 1.96):.0%} ({len(zs)}) | "
            f"{np.median([r['elbo_per_sample'] for r in ok]):.3f} | "
            f"{np.median([r['val_elbo_per_sample'] for r in ok]):.3f} | "
            f"{np.median([r['iterations'] for r in ok]):.0f} | {np.median([r['wall_s'] for r in ok]):.1f} |")
    return "\n".join(out)


def _safe(name, seed, max_iter):
    try:
        return run_one(name, seed, max_iter)
    except Exception as err:  # a benchmark reports failures instead of stopping
        return {"model": name, "seed": seed, "error": f"{type(err).__name__}: {err}"}


def main(argv=None) -> int:
    sys.path.insert(0, str(ZOO))
    import models as zoo_models

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", default=",".join(zoo_models.MODELS))
    ap.add_argument("--seeds", default="1,2,3")
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--max-iter", type=int, default=200)
    ap.add_argument("--json", default=None, help="write every fit's summary here")
    a = ap.parse_args(argv)
    names = [n for n in a.models.split(",") if n]
    seeds = [int(s) for s in a.seeds.split(",") if s]
    jobs = [(n, s) for n in names for s in seeds]
    rows = []
    if a.jobs > 1:
        os.environ.setdefault("XLA_FLAGS", "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1")
        import multiprocessing as mp

        with cf.ProcessPoolExecutor(a.jobs, mp_context=mp.get_context("spawn")) as ex:
            futs = {ex.submit(_safe, n, s, a.max_iter): (n, s) for n, s in jobs}
            for f in cf.as_completed(futs):
                rows.append(f.result())
                _print_row(rows[-1])
    else:
        for n, s in jobs:
            rows.append(_safe(n, s, a.max_iter))
            _print_row(rows[-1])
    rows.sort(key=lambda r: (names.index(r["model"]), r["seed"]))
    print(_table(rows))
    if a.json:
        pathlib.Path(a.json).write_text(json.dumps(rows, indent=1))
    return 0


def _print_row(r):
    if "error" in r:
        print(f"{r['model']:12s} seed {r['seed']}: ERROR {r['error']}", flush=True)
        return
    print(f"{r['model']:12s} seed {r['seed']}: converged={r['converged']} ({r['stop_reason']}, "
          f"λ²/2={r['decrement']:.2g}) val_converged={r['val_converged']} within3={r['within3']:.2f} "
          f"cover95={r['cover95']:.2f} elbo/N={r['elbo_per_sample']:.3f} val={r['val_elbo_per_sample']:.3f} "
          f"it={r['iterations']} {r['wall_s']:.1f}s warnings={r['warnings']}", flush=True)


if __name__ == "__main__":
    raise SystemExit(main())
