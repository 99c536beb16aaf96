"""Benchmark of ``vsidgen diagnose`` on records from an independent simulator (no inverse crime).

The records come from :mod:`sim` (numpy/scipy physics written independently of vsidgen's
catalogue: continuous-time RK4 at 2 ms, inputs that vary between samples, Dryden turbulence,
quantised noisy sensors). Each case conceals one physical effect (or none) and runs the
``vsidgen diagnose`` command line on the spec a user would fit (``specs/hfb320.yaml``,
``specs/attas_sp.yaml``, ``benchmarks/independent/specs/lat_beta.yaml``), in a subprocess,
with a wall-clock limit. It prints, per case, the effect named first, its estimate, 2ΔELBO
and the wall time; then a confusion matrix (true effect × effect named first), the detection
rate per effect and magnitude, and the false-positive rate on the null cases.

Usage::

    python benchmarks/independent/run.py --quick            # 8 short cases (shared 2-core box)
    python benchmarks/independent/run.py --all --jobs 8     # full matrix (3 seeds), elsewhere
    python benchmarks/independent/run.py --list
    python benchmarks/independent/run.py --cases hfb_q_bias_0.005_s0 ... [--oracle]

``--oracle`` reruns a case whose true effect was not named with the catalogue restricted to the
true effect class (``--effects ID``): that separates "not identifiable in this record" from
"the search did not rank it". The script never imports vsidgen (only runs its CLI).
"""

from __future__ import annotations

import argparse
import concurrent.futures as cf
import dataclasses
import json
import os
import pathlib
import subprocess
import sys
import time

HERE = pathlib.Path(__file__).resolve().parent
ROOT = HERE.parents[1]
sys.path.insert(0, str(HERE))

import sim  # noqa: E402

SPEC = {"hfb": ROOT / "specs" / "hfb320.yaml", "sp": ROOT / "specs" / "attas_sp.yaml",
        "lat": HERE / "specs" / "lat_beta.yaml",
        # a user's body-axis model of the same aircraft (u, w, q, θ; α a definition)
        "hfbb": HERE / "specs" / "hfb_body.yaml"}
SIMULATE = {"hfb": sim.simulate_hfb, "sp": sim.simulate_sp, "lat": sim.simulate_lat,
            "hfbb": sim.simulate_hfb}

#: effect named first that counts as the true effect: (effect id, target) pairs; target None = any
TRUE_LABELS = {
    ("hfb", "de_delay"): {("transport_delay", "input:de"), ("control_delay", "input:de")},
    ("hfb", "de_lag"): {("actuator_lag", "input:de")},
    ("hfb", "alpha_vane"): {("sensor_position", "output:alpha")},
    ("hfb", "az_position"): {("sensor_position", "output:az"), ("sensor_position", "output:ax")},
    ("hfb", "q_bias"): {("sensor_bias", "output:q")},
    ("hfb", "alpha_scale"): {("sensor_scale", "output:alpha")},
    # the lift coefficient's derivative (every user of CL: the alpha equation, ax, az), or a
    # free term in the alpha equation alone
    ("hfb", "missing_CLde"): {("coefficient_derivative", "definition:CL"),
                              ("missing_derivative", "drift:alpha")},
    # the lift coefficient's break or square (every user of CL), or a term of the α equation
    ("hfb", "lift_stall"): {("coefficient_nonlinear", "definition:CL"),
                            ("nonlinear_aero", "drift:alpha")},
    ("hfb", "lift_square"): {("coefficient_nonlinear", "definition:CL"),
                             ("nonlinear_aero", "drift:alpha")},
    ("hfb", "gust"): {("unmodelled_wind", None)},
    # the engine's response is a lag of the recorded thrust (the catalogue's engine lag), or
    # a first-order mode driven by it
    ("hfb", "thrust_lag"): {("actuator_lag", "input:thrust"), ("missing_dynamics", None)},
    ("sp", "phugoid"): {("speed_dynamics", None), ("missing_dynamics", None)},
    ("sp", "de_delay"): {("transport_delay", "input:de"), ("control_delay", "input:de")},
    ("lat", "beta_vane"): {("sensor_position", "output:beta")},
    ("lat", "ay_position"): {("sensor_position", "output:ay")},
    ("lat", "da_delay"): {("transport_delay", "input:da"), ("control_delay", "input:da")},
    ("lat", "dr_lag"): {("actuator_lag", "input:dr")},
    ("lat", "p_bias"): {("sensor_bias", "output:p")},
    ("lat", "n_beta_cubic"): {("nonlinear_aero", "drift:r")},
    # the body-axis model: lift reaches u̇, ẇ and both accelerometers through CL
    ("hfbb", "missing_CLde"): {("coefficient_derivative", "definition:CL"),
                               ("missing_derivative", "drift:w")},
    ("hfbb", "lift_stall"): {("coefficient_nonlinear", "definition:CL"),
                             ("nonlinear_aero", "drift:w")},
    ("hfbb", "lift_square"): {("coefficient_nonlinear", "definition:CL"),
                              ("nonlinear_aero", "drift:w")},
    ("hfbb", "alpha_vane"): {("sensor_position", "output:alpha")},
    ("hfbb", "de_delay"): {("transport_delay", "input:de"), ("control_delay", "input:de")},
}
#: catalogue effect class of each true effect (for --oracle)
ORACLE_EFFECT = {"de_delay": "transport_delay", "de_lag": "actuator_lag",
                 "alpha_vane": "sensor_position", "az_position": "sensor_position",
                 "q_bias": "sensor_bias", "alpha_scale": "sensor_scale",
                 "missing_CLde": "coefficient_derivative", "lift_stall": "coefficient_nonlinear",
                 "lift_square": "coefficient_nonlinear", "n_beta_cubic": "nonlinear_aero",
                 "gust": "unmodelled_wind", "thrust_lag": "actuator_lag", "phugoid": "speed_dynamics",
                 "beta_vane": "sensor_position", "ay_position": "sensor_position",
                 "da_delay": "transport_delay", "dr_lag": "actuator_lag", "p_bias": "sensor_bias"}
UNIT = {"de_delay": "s", "de_lag": "s", "alpha_vane": "m", "az_position": "m",
        "q_bias": "rad/s", "alpha_scale": "1", "missing_CLde": "1/rad", "lift_stall": "1/rad",
        "lift_square": "1/rad²", "n_beta_cubic": "1/s²/rad³",
        "gust": "m/s", "thrust_lag": "s", "phugoid": "× physical", "beta_vane": "m", "ay_position": "m",
        "da_delay": "s", "dr_lag": "s", "p_bias": "rad/s", "none": ""}

MAGNITUDES = {
    "hfb": {"none": [0.0], "de_delay": [0.05, 0.15, 0.3], "de_lag": [0.05, 0.15],
            "alpha_vane": [3.0, 10.0], "az_position": [2.0, 8.0], "q_bias": [0.001, 0.005],
            "alpha_scale": [0.03, 0.1], "missing_CLde": [0.15, 0.5], "lift_stall": [1.0, 4.0],
            "lift_square": [2.0, 8.0],
            "gust": [0.5, 2.0], "thrust_lag": [0.5, 2.0]},
    "sp": {"none": [0.0], "phugoid": [0.4, 1.0, 5.0], "de_delay": [0.04, 0.12]},
    "lat": {"none": [0.0], "beta_vane": [3.0, 8.0], "ay_position": [1.0, 4.0],
            "da_delay": [0.04, 0.12], "dr_lag": [0.05, 0.15], "p_bias": [0.0005, 0.002],
            "n_beta_cubic": [10.0, 40.0]},
    "hfbb": {"none": [0.0], "missing_CLde": [0.15, 0.5], "lift_stall": [1.0, 4.0],
             "lift_square": [2.0, 8.0], "alpha_vane": [3.0, 10.0], "de_delay": [0.05]},
}


@dataclasses.dataclass(frozen=True)
class Case:
    model: str
    effect: str
    magnitude: float
    seed: int

    @property
    def name(self) -> str:
        return f"{self.model}_{self.effect}_{self.magnitude:g}_s{self.seed}"


def all_cases(seeds=(0, 1, 2)) -> list[Case]:
    return [Case(m, e, mag, s) for m, effs in MAGNITUDES.items() for e, mags in effs.items()
            for mag in mags for s in seeds]


QUICK = [Case("sp", "none", 0.0, 0), Case("sp", "de_delay", 0.12, 0),
         Case("sp", "phugoid", 1.0, 0), Case("lat", "none", 0.0, 0),
         Case("lat", "beta_vane", 8.0, 0), Case("hfb", "none", 0.0, 0),
         Case("hfb", "missing_CLde", 0.5, 0), Case("hfb", "q_bias", 0.005, 0)]


def make_record(case: Case, work: pathlib.Path) -> pathlib.Path:
    cols, truth = SIMULATE[case.model](effect=case.effect, magnitude=case.magnitude,
                                       seed=case.seed)
    path = work / f"{case.name}.csv"
    sim.write_csv(path, cols)
    (work / f"{case.name}.truth.json").write_text(json.dumps(truth, indent=1))
    return path


def run_diagnose(case: Case, csv: pathlib.Path, out: pathlib.Path, *, time_limit: float,
                 max_candidates: int, max_rounds: int, effects=None, workers: int = 1,
                 extra=()) -> dict:
    cmd = [sys.executable, "-m", "vsidgen.cli", "diagnose", str(SPEC[case.model]), str(csv),
           "--out", str(out), "--max-candidates", str(max_candidates),
           "--max-rounds", str(max_rounds), "--workers", str(workers), "--quiet",
           # the CLI's own limit first (findings written, stop reason `time_limit`); the
           # subprocess timeout is the backstop for a run that does not stop by itself
           "--time-limit", f"{time_limit:g}"]
    if effects:
        cmd += ["--effects", *effects]
    cmd += list(extra)
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    t0 = time.time()
    try:
        proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True,
                              timeout=time_limit + 300)
        rc, last = proc.returncode, (proc.stdout.strip().splitlines() or [""])[-1]
        err = proc.stderr.strip()[-400:] if rc else ""
        # the run's own account (stages, refits, times) beside its findings
        out.mkdir(parents=True, exist_ok=True)
        (out / "diagnose.log").write_text(proc.stdout + ("\n--- stderr ---\n" + proc.stderr
                                                         if proc.stderr else ""))
    except subprocess.TimeoutExpired:
        rc, last, err = None, "", f"time limit {time_limit:g} s"
    wall = time.time() - t0
    doc = None
    fj = out / "findings.json"
    if fj.exists():
        try:
            doc = json.loads(fj.read_text())
        except ValueError:
            doc = None
    return {"rc": rc, "wall_s": wall, "cli_last_line": last, "error": err, "doc": doc}


def classify(case: Case, res: dict) -> dict:
    """Outcome of one case from its findings.json."""
    doc = res["doc"]
    out = {"case": case.name, "model": case.model, "effect": case.effect,
           "magnitude": case.magnitude, "seed": case.seed, "wall_s": round(res["wall_s"], 1),
           "rc": res["rc"], "cli_last_line": res["cli_last_line"], "error": res["error"]}
    if doc is None:
        out.update(named="(no result)", outcome="timeout" if res["rc"] is None else "error")
        return out
    inconclusive = doc.get("conclusion", "").startswith("INCONCLUSIVE")
    # a run stopped by its limit (or killed while a refit ran) accepted nothing in its
    # unfinished round: "nothing" there is not a result
    stop = (doc.get("stop") or {}).get("reason", "completed")
    out["stop"] = stop
    noise = (doc.get("noise_model") or {}).get("adopted")
    out["noise_model"] = (None if not noise else
                          "correlated process noise (" + ", ".join(
                              f"ρ {c['rho']:+.2f}" for c in noise.get("correlations") or []
                              if c.get("rho") is not None) + f"; Λ {noise['statistic']:.4g})")
    gust = (doc.get("noise_gust") or {}).get("adopted")
    if gust:
        # the noise-model stage's second alternative (turbulence in the air-relative velocity)
        g = "air-relative gust (" + ", ".join(
            x["gust_state"] for x in doc["noise_gust"].get("gusts") or []) + \
            f"; Λ {gust['statistic']:.4g})"
        out["noise_model"] = g if out["noise_model"] is None else f"{out['noise_model']}; {g}"
    adopted = (doc.get("numerics") or {}).get("adopted")
    # a modelling-numerics finding is not a physical effect: reported, never counted as one
    out["numerics"] = adopted["setting"]["text"] if adopted else None
    turb = doc.get("noise_turbulence") or []
    if turb:
        # coloured turbulence accepted in a round (a gust state): a noise-model finding
        t = "coloured turbulence (" + ", ".join(
            f"{f['key']}, Λ {f['evidence']['statistic']:.4g}" for f in turb) + ")"
        out["noise_model"] = t if out["noise_model"] is None else f"{out['noise_model']}; {t}"
    findings = doc.get("findings") or []
    if case.effect == "gust":
        # the concealed effect is the turbulence itself: its gust state is what is named
        findings = sorted(findings + turb, key=lambda f: f["rank"])
    if findings:
        f = findings[0]
        out["named"] = f"{f['effect']}:{f['target']}"
        out["named_key"] = f.get("key")
        out["statistic"] = f["evidence"].get("statistic")
        out["threshold"] = f["evidence"].get("threshold")
        out["estimates"] = {k: (v.get("estimate"), v.get("std_error"), v.get("unit"))
                            for k, v in f.get("parameters", {}).items()}
        out["alternatives"] = [f"{a.get('effect')}:{a.get('target')}"
                               for a in f.get("alternatives") or []]
    else:
        out["named"] = ("inconclusive" if inconclusive
                        else "nothing" if stop == "completed" else f"nothing yet ({stop})")
    out["n_findings"] = len(findings)
    trials = [t for r in doc.get("rounds", []) for t in r.get("trials", [])]
    out["refitted"] = [(t.get("key"), t.get("statistic"), t.get("converged")) for t in trials]
    if case.effect == "none":
        out["outcome"] = ("false positive" if findings
                          else "ok" if stop == "completed" else "unfinished")
        return out
    labels = TRUE_LABELS[(case.model, case.effect)]

    def hit(eff_target: str) -> bool:
        eff, tgt = eff_target.split(":", 1)
        return any(eff == e and (t is None or tgt == t) for e, t in labels)

    if findings and hit(out["named"]):
        out["outcome"] = "ok"
    elif findings and any(hit(a) for a in out["alternatives"]):
        out["outcome"] = "ambiguous"
    elif findings:
        out["outcome"] = "wrong"
    else:
        out["outcome"] = ("inconclusive" if inconclusive
                          else "missed" if stop == "completed" else "unfinished")
    return out


def run_case(case: Case, args) -> dict:
    work = pathlib.Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    csv = make_record(case, work)
    res = run_diagnose(case, csv, work / case.name, time_limit=args.time_limit,
                       max_candidates=args.max_candidates, max_rounds=args.max_rounds,
                       workers=args.workers, extra=["--gust-noise"] if args.gust_noise else [])
    row = classify(case, res)
    if args.oracle and case.effect != "none" and row["outcome"] != "ok":
        ores = run_diagnose(case, csv, work / (case.name + "_oracle"),
                            time_limit=args.time_limit, max_candidates=args.max_candidates,
                            max_rounds=1, effects=[ORACLE_EFFECT[case.effect]],
                            workers=args.workers,
                            extra=["--gust-noise"] if args.gust_noise else [])
        orow = classify(case, ores)
        row["oracle"] = {"named": orow["named"], "statistic": orow.get("statistic"),
                         "threshold": orow.get("threshold"), "estimates": orow.get("estimates"),
                         "refitted": orow.get("refitted"), "wall_s": orow["wall_s"]}
    (work / f"{case.name}.result.json").write_text(json.dumps(row, indent=1, default=str))
    return row


def _fmt_est(est: dict | None) -> str:
    if not est:
        return "–"
    parts = []
    for k, (v, se, unit) in est.items():
        if v is None:
            continue
        parts.append(f"{k} {v:.4g}" + (f" ± {se:.2g}" if se is not None else "")
                     + (f" {unit}" if unit and unit != "1" else ""))
    return "; ".join(parts) or "–"


def report(rows: list[dict]) -> str:
    lines = ["| case | truth | numerics / noise model adopted | named first | estimate | 2ΔELBO (threshold) "
             "| outcome | wall |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        truth = "none" if r["effect"] == "none" else \
            f"{r['effect']} {r['magnitude']:g} {UNIT[r['effect']]}"
        stat = "–" if r.get("statistic") is None else \
            f"{r['statistic']:.4g} ({r['threshold']:.3g})"
        named = r["named"] + (" (alt: " + ", ".join(r["alternatives"]) + ")"
                              if r.get("alternatives") else "")
        adopted = "; ".join(x for x in (r.get("numerics"), r.get("noise_model")) if x) or "–"
        lines.append(f"| {r['case']} | {truth} | {adopted} | {named} | "
                     f"{_fmt_est(r.get('estimates'))} | {stat} | {r['outcome']} | "
                     f"{r['wall_s']:.0f} s |")
        if r.get("oracle"):
            o = r["oracle"]
            ostat = "–" if o.get("statistic") is None else \
                f"{o['statistic']:.4g} ({o['threshold']:.3g})"
            lines.append(f"|  ↳ oracle (`--effects {ORACLE_EFFECT[r['effect']]}`) | | | "
                         f"{o['named']} | {_fmt_est(o.get('estimates'))} | {ostat} | | "
                         f"{o['wall_s']:.0f} s |")
    # confusion matrix: true effect × effect named first
    truths = sorted({r["effect"] if r["effect"] == "none" else f"{r['model']}:{r['effect']}"
                     for r in rows})
    named = sorted({r["named"].split(":")[0] for r in rows})
    lines += ["", "Confusion matrix (rows: true effect; columns: effect class named first):", "",
              "| true \\ named | " + " | ".join(named) + " |",
              "|---" * (len(named) + 1) + "|"]
    for tr in truths:
        sel = [r for r in rows if (r["effect"] if r["effect"] == "none"
                                   else f"{r['model']}:{r['effect']}") == tr]
        cnt = [sum(1 for r in sel if r["named"].split(":")[0] == n) for n in named]
        lines.append(f"| {tr} | " + " | ".join(str(c) if c else "·" for c in cnt) + " |")
    # detection rate vs magnitude
    lines += ["", "Detection rate (true effect named first) per effect and magnitude:", ""]
    groups: dict = {}
    for r in rows:
        if r["effect"] != "none":
            groups.setdefault((r["model"], r["effect"], r["magnitude"]), []).append(r)
    for (m, e, mag), sel in sorted(groups.items()):
        ok = sum(r["outcome"] == "ok" for r in sel)
        amb = sum(r["outcome"] == "ambiguous" for r in sel)
        lines.append(f"* {m} {e} {mag:g} {UNIT[e]}: {ok}/{len(sel)}"
                     + (f" (+{amb} ambiguous)" if amb else ""))
    nulls = [r for r in rows if r["effect"] == "none"]
    if nulls:
        fp = sum(r["outcome"] == "false positive" for r in nulls)
        unf = sum(r["outcome"] == "unfinished" for r in nulls)
        lines.append(f"\nFalse positives on null cases: {fp}/{len(nulls) - unf} finished"
                     + (f" ({unf} unfinished: stopped by the time limit before the end of "
                        "round 1, nothing accepted)" if unf else ""))
    tot = sum(r["wall_s"] for r in rows)
    lines.append(f"Total diagnose wall time: {tot:.0f} s over {len(rows)} cases")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    g = ap.add_mutually_exclusive_group()
    g.add_argument("--quick", action="store_true", help=f"{len(QUICK)} short cases (default)")
    g.add_argument("--all", action="store_true", help="every effect × magnitude × 3 seeds")
    g.add_argument("--cases", nargs="+", metavar="NAME", help="cases by name (see --list)")
    ap.add_argument("--list", action="store_true", help="list the cases and exit")
    ap.add_argument("--seeds", type=int, default=3, help="seeds per case with --all (default 3)")
    ap.add_argument("--jobs", type=int, default=1, help="cases run in parallel (default 1)")
    ap.add_argument("--time-limit", type=float, default=1800.0,
                    help="wall-clock limit per diagnose run, s (default 1800)")
    ap.add_argument("--max-candidates", type=int, default=3)
    ap.add_argument("--max-rounds", type=int, default=1)
    ap.add_argument("--workers", type=int, default=1,
                    help="dask workers per diagnose run (default 1: cases run in parallel "
                         "with --jobs, each serially)")
    ap.add_argument("--gust-noise", action="store_true",
                    help="pass --gust-noise to diagnose (the air-relative gust alternative)")
    ap.add_argument("--oracle", action="store_true",
                    help="rerun a missed/wrong case restricted to the true effect class")
    ap.add_argument("--work", default=str(ROOT / "benchmarks" / "independent" / "work"),
                    help="records and diagnose output (default benchmarks/independent/work)")
    ap.add_argument("--json", help="write the per-case results here")
    ap.add_argument("--report-only", action="store_true",
                    help="print the tables from the results already in --work (no runs)")
    args = ap.parse_args(argv)
    full = all_cases(tuple(range(args.seeds)))
    if args.list:
        for c in full:
            print(c.name, "(quick)" if c in QUICK else "")
        return 0
    if args.cases:
        by_name = {c.name: c for c in full + QUICK}
        unknown = [n for n in args.cases if n not in by_name]
        if unknown:
            print(f"unknown case(s): {', '.join(unknown)}; see --list", file=sys.stderr)
            return 2
        cases = [by_name[n] for n in args.cases]
    else:
        cases = full if args.all else QUICK
    if args.report_only:
        work = pathlib.Path(args.work)
        rows = []
        for c in cases:
            res = work / f"{c.name}.result.json"
            fj = work / c.name / "findings.json"
            if res.exists() and fj.exists():   # classified again from the findings
                old = json.loads(res.read_text())
                doc = json.loads(fj.read_text())
                row = classify(c, {"doc": doc, "rc": old.get("rc"), "wall_s": old["wall_s"],
                                   "cli_last_line": old.get("cli_last_line", ""),
                                   "error": old.get("error", "")})
                rows.append({**row, **({"oracle": old["oracle"]} if old.get("oracle") else {})})
            elif res.exists():
                rows.append(json.loads(res.read_text()))
            elif fj.exists():
                doc = json.loads(fj.read_text())   # a run whose driver was stopped
                rows.append(classify(c, {"doc": doc, "rc": 0, "wall_s": doc["wall_time_s"],
                                         "cli_last_line": "", "error": ""}))
        print(report(rows))
        return 0
    rows: list[dict] = []
    with cf.ThreadPoolExecutor(max_workers=max(1, args.jobs)) as ex:
        futs = {ex.submit(run_case, c, args): c for c in cases}
        for fut in cf.as_completed(futs):
            r = fut.result()
            rows.append(r)
            print(f"{r['case']}: {r['named']} -> {r['outcome']} ({r['wall_s']:.0f} s)",
                  flush=True)
    order = {c.name: i for i, c in enumerate(cases)}
    rows.sort(key=lambda r: order[r["case"]])
    print()
    print(report(rows))
    if args.json:
        pathlib.Path(args.json).write_text(json.dumps(rows, indent=1, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
