"""Benchmark of ``vsidgen diagnose`` on synthetic data with one concealed effect at a time.

For each case a *truth* spec is built from a catalogue candidate of the base
spec (the concealed effect, with its true parameter values), data are simulated
with textbook turbulence (process noise) and sensor noise on realistic
maneuvers (3-2-1-1 + doublet), and ``run_diagnose`` is run on the *base* spec.
No-effect cases (data from the base spec itself) must give empty findings.

Usage::

    python benchmarks/diagnose_benchmark.py [--cases NAME ...] [--out DIR] [--list]

Prints a table: case, true effect, effect named first, parameter recovered vs
truth, 2ΔELBO of the first finding, false positives.
"""

from __future__ import annotations

import argparse
import dataclasses
import pathlib
import sys
import tempfile
import time

import numpy as np
import yaml

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from vsidgen.discrepancy.base import model_info, propose  # noqa: E402
from vsidgen.discrepancy.locate import break_points  # noqa: E402

ATTAS_THETA = dict(Z0=0.0, ZAL=-0.48, ZQ=0.0, ZDE=-0.1, M0=0.0, MAL=-4.9, MQ=-2.0, MDE=-7.2)
ATTAS_NOISE = dict(process={"alpha": 0.002, "q": 0.005}, measurement={"alpha": 0.001, "q": 0.001})


@dataclasses.dataclass(frozen=True)
class Case:
    name: str
    base: str                       # "attas_sp" | "attas_sp_noMQ" (reduced base spec)
    key: str | None                 # candidate key of the concealed effect (None: no effect)
    truth: dict                     # true values of the candidate's parameters
    note: str = ""


CASES = [
    Case("clean_attas", "attas_sp", None, {}, "no effect"),
    Case("missing_Mq", "attas_sp_noMQ", "missing_derivative:q:q", {"D_q_q": -2.0},
         "pitch damping left out of a reduced model"),
    Case("alpha2_in_q", "attas_sp", "nonlinear_aero:q:sq:alpha", {"D_q_alphaalpha": -40.0},
         "quadratic Cm(alpha)"),
    Case("de_lag", "attas_sp", "actuator_lag:de", {"D_TAU_de": 0.15}, "elevator actuator lag"),
    Case("de_delay", "attas_sp", "control_delay:de", {"D_DELAY_de": 0.12}, "elevator delay"),
    Case("alphadot_q", "attas_sp", "unsteady_aero:q:alpha", {"D_q_alphadot": -1.5},
         "Cm_alpha-dot / downwash lag"),
    Case("missing_mode", "attas_sp", "missing_dynamics:q:de",
         {"D_K_MODE_q_de": 3.0, "D_TAU_MODE_q": 2.0}, "slow mode driven by the elevator"),
    Case("wind_alpha", "attas_sp", "unmodelled_wind:alpha", {"D_TAU_WIND_alpha": 1.0},
         "gusts with 1 s correlation time (wind state noise 0.01 rad/sqrt(s))"),
    Case("alpha_vane_offset", "attas_sp", "sensor_position:alpha:q", {"D_POS_alpha_q": -0.08},
         "alpha vane 8 m ahead of the CG at 100 m/s"),
    Case("alpha_skew", "attas_sp", "time_skew:alpha", {"D_SKEW_alpha": 0.08},
         "alpha channel 80 ms late"),
    Case("q_bias", "attas_sp", "sensor_bias:q", {"D_BIAS_q": 0.005},
         "q gyro bias (absorbed by Z0/M0 in this model: expected not identifiable)"),
    Case("q_scale", "attas_sp", "sensor_scale:q", {"D_SCALE_q": 0.1},
         "q gyro scale error (absorbed by a state scaling: expected not identifiable)"),
]


def write_base(name: str, work: pathlib.Path) -> pathlib.Path:
    spec = ROOT / "specs" / "attas_sp.yaml"
    if name == "attas_sp":
        return spec
    if name == "attas_sp_noMQ":
        d = yaml.safe_load(spec.read_text())
        d["name"] = "attas_sp_noMQ"
        del d["parameters"]["MQ"]
        d["drift"]["q"] = "M0 + MAL*alpha + MDE*de"
        p = work / "attas_sp_noMQ.yaml"
        p.write_text(yaml.safe_dump(d, sort_keys=False))
        return p
    raise KeyError(name)


def maneuver(t, seed):
    from vsidgen.simulate import doublet, three_two_one_one
    return (three_two_one_one(t, amplitude=0.03, start=2.0, unit=0.4)
            + doublet(t, amplitude=0.02, start=12.0, width=1.0 + 0.1 * seed))


def make_case(case: Case, work: pathlib.Path, *, seeds=(1,), duration: float = 25.0,
              dt: float = 0.04, validate_seed: int | None = None):
    """Write base spec, truth spec and data; returns (base_spec, data, validate, truth_theta)."""
    from vsidgen.model import load_model
    from vsidgen.simulate import simulate_to_csv

    work.mkdir(parents=True, exist_ok=True)
    base = write_base(case.base, work)
    theta = {k: v for k, v in ATTAS_THETA.items()}
    if case.base == "attas_sp_noMQ":
        theta.pop("MQ")
    truth_spec = base
    states_noise = dict(ATTAS_NOISE["process"])
    if case.key is not None:
        info = model_info(base, dt=dt)
        t = np.arange(0, duration, dt)
        u = maneuver(t, 0)
        info = dataclasses.replace(info, breaks={"de": tuple(break_points(u)),
                                                 "alpha": (("hinge", 0.02),)})
        cands = {c.key: c for c in propose(info)}
        if case.key not in cands:
            raise KeyError(f"{case.key} not proposed for {base}")
        c = cands[case.key]
        truth_spec = work / f"truth_{case.name}.yaml"
        d = c.spec_dict(base, name=f"truth_{case.name}", candidate_path=truth_spec, info=info)
        truth_spec.write_text(yaml.safe_dump(d, sort_keys=False))
        for p in c.parameters:
            theta[p.name] = case.truth.get(p.name, p.initial)
        for s in c.states:
            if s.process_noise:
                states_noise[s.name] = 0.01
    model = load_model(truth_spec, generated_dir=work / "generated")
    paths = []
    all_seeds = list(seeds) + ([validate_seed] if validate_seed is not None else [])
    for sd in all_seeds:
        t = np.arange(0, duration, dt)
        x0 = {s: 0.0 for s in model.state_names}
        p = work / f"{case.name}_s{sd}.csv"
        simulate_to_csv(model, p, theta=theta, t=t, u={"de": maneuver(t, sd)}, x0=x0,
                        process_std=states_noise, measurement_std=ATTAS_NOISE["measurement"],
                        seed=sd)
        paths.append(p)
    val = paths[len(seeds):]
    return base, paths[:len(seeds)], val, {k: v for k, v in theta.items() if k.startswith("D_")}


def run_case(case: Case, work: pathlib.Path, *, max_rounds=2, max_candidates=6, validate=False):
    from vsidgen.discrepancy import run_diagnose

    base, data, val, truth = make_case(case, work, validate_seed=7 if validate else None)
    t0 = time.perf_counter()
    res = run_diagnose(base, data, validate=val, out=work / "diagnose", max_rounds=max_rounds,
                       max_candidates=max_candidates)
    wall = time.perf_counter() - t0
    first = res.findings[0] if res.findings else None
    named = first["effect"] if first else "-"
    rec = "-"
    if first and case.key:
        for name, true in truth.items():
            if name in first["parameters"]:
                p = first["parameters"][name]
                se = p.get("std_error")
                rec = f"{name}={p['estimate']:.4g}±{se:.2g} (true {true:.4g})" if se else \
                    f"{name}={p['estimate']:.4g} (true {true:.4g})"
                break
        else:
            rec = ", ".join(f"{k}={v['estimate']:.4g}" for k, v in first["parameters"].items()) \
                + f" (true {truth})"
    true_effect = case.key.split(":")[0] if case.key else "none"
    if case.key is None:
        fp = len(res.findings)
    else:
        fp = sum(1 for f in res.findings if f["effect"] != true_effect)
    gain = f"{first['evidence']['statistic']:.4g}" if first else "-"
    return {"case": case.name, "true": case.key or "none", "named_first": named,
            "named_key": first["key"] if first else "-", "param": rec, "2dELBO": gain,
            "false_pos": fp, "n_findings": len(res.findings), "wall_s": round(wall, 1),
            "ok": (named == true_effect) if case.key else (not res.findings)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="*", default=None)
    ap.add_argument("--out", default=None)
    ap.add_argument("--list", action="store_true")
    ap.add_argument("--validate", action="store_true", help="also simulate a validation record")
    args = ap.parse_args(argv)
    if args.list:
        for c in CASES:
            print(f"{c.name:18s} {c.key or 'none':30s} {c.note}")
        return 0
    cases = [c for c in CASES if args.cases is None or c.name in args.cases]
    root = pathlib.Path(args.out or tempfile.mkdtemp(prefix="vsidgen_diag_bench_"))
    rows = []
    for c in cases:
        print(f"--- {c.name}", file=sys.stderr, flush=True)
        try:
            rows.append(run_case(c, root / c.name, validate=args.validate))
        except Exception as err:  # noqa: BLE001 - report and go on
            rows.append({"case": c.name, "true": c.key or "none", "named_first": f"ERROR {err}",
                         "named_key": "-", "param": "-", "2dELBO": "-", "false_pos": "-",
                         "n_findings": "-", "wall_s": "-", "ok": False})
        r = rows[-1]
        print(f"{r['case']:18s} true={r['true']:28s} first={r['named_key']:28s} "
              f"{r['param']}  2dELBO={r['2dELBO']} FP={r['false_pos']} ok={r['ok']} "
              f"({r['wall_s']} s)", flush=True)
    print("\n| case | true effect | named first | parameter (est vs truth) | 2ΔELBO | false pos. | ok |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['case']} | {r['true']} | {r['named_key']} | {r['param']} | {r['2dELBO']} | "
              f"{r['false_pos']} | {r['ok']} |")
    print(f"\n{sum(bool(r['ok']) for r in rows)}/{len(rows)} cases as expected; work dir {root}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
