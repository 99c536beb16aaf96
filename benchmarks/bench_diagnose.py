"""Diagnose wall time: gated model per round vs one model per candidate, and workers.

Each configuration runs ``vsidgen diagnose`` in a fresh process (a fresh, empty persistent
compilation cache per configuration unless ``--shared-cache``), one after the other, and
prints per path (``gated``: the candidates that add no state share one compiled model per
round, the default; ``per-candidate``: ``--per-candidate-models``, every candidate compiles
its own model) and worker count: candidates examined, refits, compile time, wall time, the
phases (base fit and locate, modelling numerics, the rounds; from the time-stamped progress
lines, written to ``WORK/<config>.log``), the load average (``uptime``) before and after,
and whether the findings equal those of the first row (keys, and every refit's 2ΔELBO to
1e-6 for the same path, to 0.1 across paths). The last lines give the per-candidate /
gated wall-time ratio per worker count: on a shared machine that ratio, measured one run
after the other, is the useful figure, not the absolute times.

The default case is a 1,000-sample HFB-320-like record simulated from ``specs/hfb320.yaml``
(θ at the Euler estimates of the real record, the real record's elevator and thrust
histories resampled to 0.06 s, turbulence and sensor noise), written to ``--work``.

    python benchmarks/bench_diagnose.py --workers 1 2 [N ...] [--paths gated per-candidate]
        [--xla-defaults] [-- --max-rounds 1]

``--xla-defaults`` compiles with XLA's default options instead of vsidgen's
``CPU_COMPILER_OPTIONS`` (through a ``sitecustomize`` on the child processes' ``PYTHONPATH``).
"""

from __future__ import annotations

import argparse
import json
import math
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
    from vsidgen.data.simulate import simulate_to_csv

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


def load_average() -> float:
    """1-minute load average (what ``uptime`` prints first)."""
    try:
        return os.getloadavg()[0]
    except OSError:  # pragma: no cover - not Unix
        return float("nan")


#: progress-line prefixes that start a phase (the rest of the run until the next one)
PHASES = (("base fit + locate", "fitting the base model"),
          ("numerics", "modelling numerics first"),
          ("rounds", "round 1:"))


def xla_defaults_dir(work: pathlib.Path) -> pathlib.Path:
    """A folder whose ``sitecustomize`` empties ``CPU_COMPILER_OPTIONS`` in every Python process
    started with it on ``PYTHONPATH`` (the diagnose process and its dask workers): XLA's defaults."""
    d = work / "xla_defaults"
    d.mkdir(parents=True, exist_ok=True)
    (d / "sitecustomize.py").write_text("import vsidgen.estimator.core as _core\n"
                                        "_core.CPU_COMPILER_OPTIONS = {}\n")
    return d


def run_one(spec, data, out, workers, extra, cache, *, gated: bool, log: pathlib.Path,
            pre_path: pathlib.Path | None = None, cores: str | None = None,
            platform: str | None = None) -> dict:
    path = [str(pre_path)] if pre_path else []
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(path + [str(ROOT), os.environ.get("PYTHONPATH", "")]),
               VSIDGEN_CACHE_DIR=cache)
    if platform:
        env["JAX_PLATFORMS"] = platform
    cmd = ["taskset", "-c", cores] if cores else []
    cmd += [sys.executable, "-m", "vsidgen.cli", "diagnose", str(spec), *map(str, data),
           "--out", str(out), "--workers", str(workers), "--overwrite", *extra]
    if not gated:
        cmd.append("--per-candidate-models")
    load0 = load_average()
    t0 = time.perf_counter()
    starts: dict[str, float] = {}
    with open(log, "w") as fh:
        p = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                             text=True)
        tail = []
        for line in p.stdout:
            t = time.perf_counter() - t0
            fh.write(f"{t:8.1f} {line}")
            tail = (tail + [line])[-60:]
            for name, prefix in PHASES:
                if name not in starts and line.lstrip().startswith(prefix):
                    starts[name] = t
        p.wait()
    wall = time.perf_counter() - t0
    load1 = load_average()
    if p.returncode not in (0, 1):
        raise SystemExit(f"diagnose failed ({p.returncode}): {' '.join(cmd)}\n{''.join(tail)}")
    marks = sorted(starts.items(), key=lambda kv: kv[1]) + [("end", wall)]
    phases = {a: b_t - a_t for (a, a_t), (_, b_t) in zip(marks, marks[1:])}
    doc = json.loads((pathlib.Path(out) / "findings.json").read_text())
    trials = [t for r in doc["rounds"] for t in r.get("trials", ())]
    comp = doc.get("compile_s") or {}
    compile_s = (comp.get("this_process") or 0.0) + (comp.get("refits") or 0.0 if workers > 1 else 0.0)
    return {"path": "gated" if gated else "per-candidate", "phases": phases,
            "cores": cores or "all", "platform": platform or "default",
            "load": (load0, load1), "workers": workers, "wall_s": wall, "rounds": len(doc["rounds"]),
            "candidates": sum(r.get("n_candidates") or r.get("n_examined") or 0
                              for r in doc["rounds"]),
            "refits": len(trials), "compile_s": compile_s,
            "refit_compile_s": comp.get("refits"), "findings": [f["key"] for f in doc["findings"]],
            "stats": {t["key"]: t["statistic"] for t in trials}, "stop": doc["stop"]["reason"]}


def same(a: dict, b: dict) -> bool:
    """Same findings and statistics: to 1e-6 (relative) on the same path, to 0.1 (2ΔELBO)
    between the gated and the per-candidate path (the optimizer's tolerance)."""
    if a["findings"] != b["findings"] or set(a["stats"]) != set(b["stats"]):
        return False
    for k, v in a["stats"].items():
        w = b["stats"][k]
        tol = 1e-6 * max(1.0, abs(v or 0.0)) if a["path"] == b["path"] else 0.1
        if (v is None) != (w is None) or (v is not None and abs(v - w) > tol):
            return False
    return True


def side_by_side(configs, spec, data, work, extra, *, shared_cache: bool) -> list[dict]:
    """Run the gated diagnose once per ``WORKERS:CORES:PLATFORM`` configuration, all at the
    same time (threads waiting on pinned child processes); rows in the order given."""
    from concurrent.futures import ThreadPoolExecutor

    def one(cfg: str) -> dict:
        w, cores, platform = cfg.split(":")
        tag = f"w{w}_c{cores.replace(',', '_')}_{platform}"
        cache = str(work / ("cache" if shared_cache else f"cache_{tag}"))
        r = run_one(spec, data, work / tag, int(w), extra, cache, gated=True,
                    log=work / f"{tag}.log", cores=cores, platform=platform)
        print(f"# {tag}: {r['wall_s']:.1f} s", file=sys.stderr, flush=True)
        return r

    with ThreadPoolExecutor(len(configs)) as ex:
        return list(ex.map(one, configs))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workers", nargs="+", type=int, default=[1, 2])
    ap.add_argument("--paths", nargs="+", choices=("gated", "per-candidate"),
                    default=["gated", "per-candidate"])
    ap.add_argument("--spec", default=None, help="spec (default: specs/hfb320.yaml, HFB-1000 record)")
    ap.add_argument("--data", nargs="+", default=None)
    ap.add_argument("--work", default=None, help="work folder (default: a temporary one)")
    ap.add_argument("--shared-cache", action="store_true",
                    help="one persistent compilation cache for all configurations")
    ap.add_argument("--xla-defaults", action="store_true",
                    help="compile with XLA's default options instead of vsidgen's CPU_COMPILER_OPTIONS")
    ap.add_argument("--side-by-side", nargs="+", default=None, metavar="WORKERS:CORES:PLATFORM",
                    help="run these configurations at the same time instead of one after the "
                         "other, each pinned to its cores (taskset) with JAX_PLATFORMS=PLATFORM "
                         "(e.g. 1:0-3:cuda 1:4-7:cpu 2:8-9:cpu); gated path only")
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
    if a.side_by_side:
        rows = side_by_side(a.side_by_side, spec, data, work, extra, shared_cache=a.shared_cache)
    for w in ([] if a.side_by_side else a.workers):
        for path in a.paths:
            tag = f"{path}_w{w}" + ("_xla_defaults" if a.xla_defaults else "")
            cache = str(work / ("cache" if a.shared_cache else f"cache_{tag}"))
            r = run_one(spec, data, work / tag, w, extra, cache, gated=path == "gated",
                        log=work / f"{tag}.log", pre_path=xla_defaults_dir(work) if a.xla_defaults else None)
            rows.append(r)
            print(f"# {case}: {path}, workers {w}: {r['wall_s']:.1f} s (load "
                  f"{r['load'][0]:.1f} -> {r['load'][1]:.1f})", file=sys.stderr, flush=True)
    ref = rows[0]
    print(f"case: {case}; diagnose options: {' '.join(extra) or '(CLI defaults)'}; "
          f"{os.cpu_count()} CPUs; compiler options: {'XLA defaults' if a.xla_defaults else 'vsidgen'}")
    print("| path | workers | cores | platform | rounds | candidates | refits | compile (s) | wall (s) | "
          "base fit + locate / numerics / rounds (s) | load before → after | findings | "
          "same findings as 1st row |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        ph = " / ".join(f"{r['phases'][n]:.0f}" if n in r["phases"] else "–" for n, _ in PHASES)
        print(f"| {r['path']} | {r['workers']} | {r['cores']} | {r['platform']} | "
              f"{r['rounds']} | {r['candidates']} | "
              f"{r['refits']} | {r['compile_s']:.0f} | {r['wall_s']:.0f} | {ph} | "
              f"{r['load'][0]:.1f} → {r['load'][1]:.1f} | "
              f"{', '.join(r['findings']) or 'none'}{'' if r['stop'] == 'completed' else ' (' + r['stop'] + ')'} | "
              f"{'yes' if same(ref, r) else 'NO'} |")
    by = {(r["path"], r["workers"]): r for r in rows}
    for w in a.workers:
        g, s = by.get(("gated", w)), by.get(("per-candidate", w))
        if g and s:
            rs = (s["phases"].get("rounds", math.nan) / g["phases"]["rounds"]
                  if g["phases"].get("rounds") else math.nan)
            print(f"workers {w}: per-candidate / gated wall time {s['wall_s'] / g['wall_s']:.2f}x"
                  f" (rounds only: {rs:.2f}x)")
    return 0 if all(same(ref, r) for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
