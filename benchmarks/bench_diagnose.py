"""Diagnose wall time against the number of workers, with the same-findings check.

Each configuration runs ``vsidgen diagnose`` in a fresh process (a fresh, empty persistent
compilation cache per configuration unless ``--shared-cache``) and prints, per case and
worker count: candidates examined, refits, compile time, wall time, workers, speed-up
over 1 worker, and whether the findings (keys, and every refit's 2ΔELBO to 1e-6) equal
those of the 1-worker run.

The default case is a 1,000-sample HFB-320-like record simulated from ``specs/hfb320.yaml``
(θ at the Euler estimates of the real record, the real record's elevator and thrust
histories resampled to 0.06 s, turbulence and sensor noise), written to ``--work``.

    python benchmarks/bench_diagnose.py --workers 1 2 [N ...] [--max-candidates 8]
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import subprocess
import sys
import tempfile
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
FLIGHT = pathlib.Path(os.environ.get("VSIDGEN_FLIGHT_DATA", ROOT.parent / "shared" / "data" / "flight"))

#: Euler estimates of specs/hfb320.yaml on hfb320_1_10 (README)
HFB_THETA = dict(CD0=0.1244, CDV=-0.0657, CDAL=0.3153, CL0=-0.124, CLV=0.163, CLAL=4.492,
                 CM0=0.1329, CMV=-0.0146, CMAL=-0.980, CMQ=-28.0, CMDE=-1.417)


def make_hfb1000(path: pathlib.Path, *, n: int = 1000, seed: int = 7) -> pathlib.Path:
    """An HFB-320-like record of ``n`` samples (see the module docstring)."""
    import numpy as np

    from vsidgen.data import load_record
    from vsidgen.model import load_model
    from vsidgen.simulate import simulate_to_csv

    model = load_model(ROOT / "specs" / "hfb320.yaml")
    real = load_record(model, FLIGHT / "hfb320_1_10.csv")
    t_real = np.asarray(real.t, float)
    dt = (t_real[-1] - t_real[0]) / (n - 1)
    t = t_real[0] + dt * np.arange(n)
    u = {name: np.interp(t, t_real, np.asarray(real.u)[:, j])
         for j, name in enumerate(model.input_names)}
    y0 = np.asarray(real.y)[0]
    x0 = {s: float(y0[model.output_names.index(s)]) for s in model.state_names}
    simulate_to_csv(model, path, theta=HFB_THETA, t=t, u=u, x0=x0,
                    process_std={"V": 0.05, "alpha": 0.002, "theta": 0.0005, "q": 0.002},
                    measurement_std={"V": 0.05, "alpha": 0.0005, "theta": 0.0003, "q": 0.0005,
                                     "qdot": 0.005, "ax": 0.02, "az": 0.05},
                    seed=seed)
    return path


def run_one(spec, data, out, workers, extra, cache) -> dict:
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""),
               VSIDGEN_CACHE_DIR=cache)
    cmd = [sys.executable, "-m", "vsidgen.cli", "diagnose", str(spec), *map(str, data),
           "--out", str(out), "--workers", str(workers), "--quiet", *extra]
    t0 = time.perf_counter()
    p = subprocess.run(cmd, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if p.returncode not in (0, 1):
        raise SystemExit(f"diagnose failed ({p.returncode}): {' '.join(cmd)}\n{p.stderr[-3000:]}")
    doc = json.loads((pathlib.Path(out) / "findings.json").read_text())
    trials = [t for r in doc["rounds"] for t in r.get("trials", ())]
    comp = doc.get("compile_s") or {}
    compile_s = (comp.get("this_process") or 0.0) + (comp.get("refits") or 0.0 if workers > 1 else 0.0)
    return {"workers": workers, "wall_s": wall, "rounds": len(doc["rounds"]),
            "candidates": sum(r.get("n_candidates") or r.get("n_examined") or 0
                              for r in doc["rounds"]),
            "refits": len(trials), "compile_s": compile_s,
            "refit_compile_s": comp.get("refits"), "findings": [f["key"] for f in doc["findings"]],
            "stats": {t["key"]: t["statistic"] for t in trials}, "stop": doc["stop"]["reason"]}


def same(a: dict, b: dict) -> bool:
    if a["findings"] != b["findings"] or set(a["stats"]) != set(b["stats"]):
        return False
    for k, v in a["stats"].items():
        w = b["stats"][k]
        if (v is None) != (w is None) or (v is not None and abs(v - w) > 1e-6 * max(1.0, abs(v))):
            return False
    return True


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workers", nargs="+", type=int, default=[1, 2])
    ap.add_argument("--spec", default=None, help="spec (default: specs/hfb320.yaml, HFB-1000 record)")
    ap.add_argument("--data", nargs="+", default=None)
    ap.add_argument("--work", default=None, help="work folder (default: a temporary one)")
    ap.add_argument("--shared-cache", action="store_true",
                    help="one persistent compilation cache for all configurations")
    ap.add_argument("diagnose_args", nargs=argparse.REMAINDER,
                    help="after --: extra diagnose options, e.g. -- --max-rounds 1")
    a = ap.parse_args(argv)
    work = pathlib.Path(a.work or tempfile.mkdtemp(prefix="bench_diagnose_"))
    work.mkdir(parents=True, exist_ok=True)
    if a.spec is None:
        spec = ROOT / "specs" / "hfb320.yaml"
        data = [work / "hfb320_like_1000.csv"]
        if not data[0].is_file():
            make_hfb1000(data[0])
        case = "HFB-320-like, 1000 samples"
    else:
        spec, data, case = pathlib.Path(a.spec), [pathlib.Path(d) for d in a.data], pathlib.Path(a.spec).stem
    extra = [x for x in a.diagnose_args if x != "--"]
    rows = []
    for w in a.workers:
        cache = str(work / ("cache" if a.shared_cache else f"cache_w{w}"))
        r = run_one(spec, data, work / f"w{w}", w, extra, cache)
        rows.append(r)
        print(f"# {case}: workers {w}: {r['wall_s']:.1f} s", file=sys.stderr, flush=True)
    ref = rows[0]
    print(f"case: {case}; diagnose options: {' '.join(extra) or '(CLI defaults)'}; "
          f"{os.cpu_count()} CPUs")
    print("| workers | rounds | candidates | refits | compile (s) | wall (s) | speed-up | "
          "findings | same findings as 1st row |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['workers']} | {r['rounds']} | {r['candidates']} | {r['refits']} | "
              f"{r['compile_s']:.0f} | {r['wall_s']:.0f} | {ref['wall_s'] / r['wall_s']:.2f}× | "
              f"{', '.join(r['findings']) or 'none'}{'' if r['stop'] == 'completed' else ' (' + r['stop'] + ')'} | "
              f"{'yes' if same(ref, r) else 'NO'} |")
    return 0 if all(same(ref, r) for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
