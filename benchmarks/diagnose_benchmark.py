"""Benchmark of ``vsidgen diagnose`` on synthetic data with one concealed effect at a time.

For each case a *truth* spec is built from a catalogue candidate of the base
spec (the concealed effect, with its true parameter values), data are simulated
with textbook turbulence (process noise) and sensor noise on realistic
maneuvers (3-2-1-1 + doublet), and ``run_diagnose`` is run on the *base* spec.
No-effect cases (data from the base spec itself) must give empty findings.

Usage::

    python benchmarks/diagnose_benchmark.py [--cases NAME ...] [--out DIR] [--list]

Prints a table: case, true effect, effect named first, parameter recovered vs
truth, 2ΔELBO of the first finding, false positives, outcome. Outcomes: ``ok``
(true effect named first, nothing else found; a no-effect case: nothing found),
``ambiguous`` (a different effect explains the data within the ambiguity margin of
the first finding — reported by diagnose as ``alternatives`` — and the true effect
is the first or one of the alternatives), ``spurious`` (true effect named first, but a later
round accepted another effect as well), ``wrong`` (another effect named),
``missed`` (nothing found), ``false positive`` (a no-effect case with a finding).
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
# HFB-320: Jategaonkar test case 4 output-error estimates (textbook programs, record hfb320_1_10)
HFB_THETA = dict(CD0=0.117758, CDV=-0.0517459, CDAL=0.234846, CL0=-0.204711, CLV=0.363549,
                 CLAL=3.21232, CM0=0.134413, CMV=-0.0139045, CMAL=-1.00241, CMQ=-27.057,
                 CMDE=-1.43707)
# light turbulence (process noise, unit/sqrt(s)) and typical flight-test sensor noise
HFB_NOISE = dict(process={"V": 0.05, "alpha": 0.002, "theta": 0.0005, "q": 0.003},
                 measurement={"V": 0.1, "alpha": 0.001, "theta": 0.001, "q": 0.001, "qdot": 0.005,
                              "ax": 0.05, "az": 0.05})
HFB_THRUST = 11500.0
#: record lengths (s); the maneuvers end by 6 s (3-2-1-1) and 17 s (doublet)
DURATION = {"attas": 25.0, "hfb": 30.0}


@dataclasses.dataclass(frozen=True)
class Case:
    name: str
    base: str                       # "attas_sp" | "attas_sp_noMQ" (reduced base spec) | "hfb320"
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
    Case("clean_hfb320", "hfb320", None, {}, "no effect (nonlinear 4-state model, 7 outputs)"),
    Case("hfb_alpha_bias", "hfb320", "sensor_bias:alpha", {"D_BIAS_alpha": 0.01},
         "alpha vane bias 0.57 deg"),
    Case("hfb_alpha_scale", "hfb320", "sensor_scale:alpha", {"D_SCALE_alpha": 0.1},
         "alpha vane upwash / scale factor +10 %"),
    Case("hfb_alpha_vane", "hfb320", "sensor_position:alpha:q", {"D_POS_alpha_q": 8.4},
         "alpha vane 8.4 m ahead of the CG (alpha - 8.4 q/V, about -0.08 s q at 105 m/s)"),
    Case("hfb_alpha_skew", "hfb320", "time_skew:alpha", {"D_SKEW_alpha": 0.1},
         "alpha channel 100 ms late"),
    # attas_sp sensor cases: expected NOT identifiable there (absorbed by Z0/M0 or a state scaling)
    Case("alpha_vane_offset", "attas_sp", "sensor_position:alpha:q", {"D_POS_alpha_q": -0.08},
         "alpha vane 8 m ahead of the CG (not identifiable in attas_sp)"),
    Case("q_bias", "attas_sp", "sensor_bias:q", {"D_BIAS_q": 0.005},
         "q gyro bias (absorbed by Z0/M0 in this model: expected not identifiable)"),
]

#: the cases of the documented table (every catalogue entry at least once, two no-effect cases)
DEFAULT_CASES = ("clean_attas", "missing_Mq", "alpha2_in_q", "de_lag", "de_delay", "alphadot_q",
                 "missing_mode", "wind_alpha", "clean_hfb320", "hfb_alpha_bias",
                 "hfb_alpha_scale", "hfb_alpha_vane", "hfb_alpha_skew")


def write_base(name: str, work: pathlib.Path) -> pathlib.Path:
    spec = ROOT / "specs" / "attas_sp.yaml"
    if name == "hfb320":
        return ROOT / "specs" / "hfb320.yaml"
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
    from vsidgen.data.simulate import doublet, three_two_one_one
    return (three_two_one_one(t, amplitude=0.03, start=2.0, unit=0.4)
            + doublet(t, amplitude=0.02, start=12.0, width=1.0 + 0.1 * seed))


def hfb_trim(model, theta: dict):
    """Trimmed (alpha, theta, de) of the HFB-320 at V0 and the benchmark thrust (q = 0)."""
    import jax.numpy as jnp
    from scipy.optimize import fsolve

    from vsidgen.model import theta_vector

    p = jnp.asarray(theta_vector(model, theta))
    V0 = 104.67

    def res(z):
        a, th, de = z
        f = model.drift(jnp.asarray([V0, a, th, 0.0]), jnp.asarray([de, HFB_THRUST]), p)
        f = np.asarray(f, float)
        return [f[0], f[1], f[3]]

    a, th, de = fsolve(res, [0.1, 0.1, 0.0])
    return {"V": V0, "alpha": float(a), "theta": float(th), "q": 0.0}, float(de)


def hfb_maneuver(t, seed, de0):
    from vsidgen.data.simulate import doublet, three_two_one_one
    return de0 + (three_two_one_one(t, amplitude=0.02, start=2.0, unit=0.6)
                  + doublet(t, amplitude=0.015, start=14.0, width=1.2 + 0.1 * seed))


def make_case(case: Case, work: pathlib.Path, *, seeds=(1,), duration: float | None = None,
              dt: float | None = None, validate_seed: int | None = None):
    """Write base spec, truth spec and data; returns (base_spec, data, validate, truth_theta)."""
    from vsidgen.model import load_model
    from vsidgen.data.simulate import simulate_to_csv

    work.mkdir(parents=True, exist_ok=True)
    hfb = case.base == "hfb320"
    duration = duration or (DURATION["hfb"] if hfb else DURATION["attas"])
    dt = dt or (0.05 if hfb else 0.04)
    base = write_base(case.base, work)
    theta = dict(HFB_THETA if hfb else ATTAS_THETA)
    if case.base == "attas_sp_noMQ":
        theta.pop("MQ")
    truth_spec = base
    noise = HFB_NOISE if hfb else ATTAS_NOISE
    states_noise = dict(noise["process"])
    x0 = None
    de0 = 0.0
    if hfb:
        x0, de0 = hfb_trim(load_model(base, generated_dir=work / "generated"), theta)
    if case.key is not None:
        info = model_info(base, dt=dt)
        t = np.arange(0, duration, dt)
        u = hfb_maneuver(t, 0, de0) if hfb else maneuver(t, 0)
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
        xs = {s: (x0 or {}).get(s, 0.0) for s in model.state_names}
        if hfb:
            de = hfb_maneuver(t, sd, de0)
            for s_ in model.state_names:   # added lag/delay states start at the input
                if s_.startswith("D_de_"):
                    xs[s_] = de0
            u = {"de": de, "thrust": np.full_like(t, HFB_THRUST)}
        else:
            u = {"de": maneuver(t, sd)}
        p = work / f"{case.name}_s{sd}.csv"
        simulate_to_csv(model, p, theta=theta, t=t, u=u, x0=xs,
                        process_std=states_noise, measurement_std=noise["measurement"],
                        seed=sd)
        paths.append(p)
    val = paths[len(seeds):]
    return base, paths[:len(seeds)], val, {k: v for k, v in theta.items() if k.startswith("D_")}


def outcome(case_key: str | None, findings) -> str:
    """Classify a diagnose result against the concealed effect (see the module docstring)."""
    if case_key is None:
        return "ok" if not findings else "false positive"
    if not findings:
        return "missed"
    true_effect = case_key.split(":")[0]
    first = findings[0]
    alts = {a["effect"] for a in first.get("alternatives") or []}
    other = alts - {first["effect"]}
    if first["effect"] == true_effect:
        if any(f["effect"] != true_effect for f in findings[1:]):
            return "spurious"
        return "ambiguous" if other else "ok"
    return "ambiguous" if true_effect in alts else "wrong"


def oracle_refit(case: Case, res, work: pathlib.Path, *, max_iter: int, alpha: float = 0.01):
    """Refit the *true* candidate alone against diagnose's base fit (the search skipped).

    Separates "not identifiable in this record" (the true effect's own refit is not
    significant at diagnose's first Holm level α/m) from "the search did not rank it"
    (it is). Returns a dict with Λ vs the nested reference, the threshold, the estimates.
    """
    from scipy import stats

    from vsidgen.discrepancy.fitstate import refit_converged
    from vsidgen.discrepancy.search import lr_test, model_info_of, staged_refit

    base = res.base
    info = model_info_of(base)
    cands = {c.key: c for c in propose(info)}
    key = case.key
    if key not in cands:   # hinge keys carry data break points: take the same kind/variable
        stem = key.rsplit(":", 1)[0]
        key = next((k for k in cands if k.startswith(stem)), None)
        if key is None:
            return {"oracle": f"{case.key} not proposed"}
    c = cands[key]
    m = next((r.get("n_candidates") or r.get("n_examined") for r in res.document["rounds"]),
             None) or len(cands)
    ro = staged_refit(c, base, info, work / "oracle" / "oracle.yaml", f"oracle_{_san(case.name)}",
                      generated_dir=work / "oracle" / "generated", max_iter=max_iter)
    lam, p = lr_test(ro.elbo_ref, ro.state.elbo, c.n_free)
    thr = float(stats.chi2.isf(alpha / m, max(c.n_free, 1)))
    est = {n: float(v) for n, v in zip(ro.state.model.parameter_names, ro.state.fit.theta)
           if n in {q.name for q in c.parameters}}
    return {"oracle_key": key, "oracle_stat": lam, "oracle_threshold": thr, "oracle_m": m,
            "oracle_converged": refit_converged(ro.state.fit), "oracle_est": est,
            "oracle_wall_s": round(ro.wall_s, 1)}


def _san(name: str) -> str:
    return "".join(ch if ch.isalnum() else "_" for ch in name)


def run_case(case: Case, work: pathlib.Path, *, max_rounds=3, max_candidates=8, max_iter=200,
             validate=False, screen=False, oracle=True):
    from vsidgen.discrepancy import run_diagnose

    base, data, val, truth = make_case(case, work, validate_seed=7 if validate else None)
    t0 = time.perf_counter()
    res = run_diagnose(base, data, validate=val, out=work / "diagnose", max_rounds=max_rounds,
                       max_candidates=max_candidates, max_iter=max_iter, screen=screen)
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
    trials = [t for r in res.document["rounds"] for t in r.get("trials", [])]
    unconv = sum(1 for t in trials if t.get("converged") is False)
    out = outcome(case.key, res.findings)
    alts = ", ".join(f"{a['key']} ({a['statistic']:.4g})"
                     for a in (first.get("alternatives") or [])) if first else ""
    orc = {}
    if oracle and case.key is not None and out != "ok":
        orc = oracle_refit(case, res, work, max_iter=max_iter)
    return {**orc, "case": case.name, "true": case.key or "none", "named_first": named,
            "outcome": out, "alternatives": alts,
            "named_key": first["key"] if first else "-", "param": rec, "2dELBO": gain,
            "false_pos": fp, "n_findings": len(res.findings), "wall_s": round(wall, 1),
            "refits": len(trials), "unconverged": unconv,
            "ok": out == "ok"}


def _oracle_text(r: dict) -> str:
    """The oracle refit as text: Λ vs threshold, converged, estimates."""
    if "oracle" in r:
        return r["oracle"]
    if "oracle_stat" not in r:
        return ""
    est = ", ".join(f"{k}={v:.4g}" for k, v in r["oracle_est"].items())
    sig = "significant" if r["oracle_stat"] > r["oracle_threshold"] else "not significant"
    conv = "" if r["oracle_converged"] else ", NOT converged"
    return (f"Λ={r['oracle_stat']:.4g} vs {r['oracle_threshold']:.3g} ({sig}{conv}; {est})")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="*", default=None)
    ap.add_argument("--out", default=None)
    ap.add_argument("--list", action="store_true")
    ap.add_argument("--max-candidates", type=int, default=8, help="as the CLI (default 8)")
    ap.add_argument("--max-rounds", type=int, default=3, help="as the CLI (default 3)")
    ap.add_argument("--max-iter", type=int, default=200, help="as the CLI (default 200)")
    ap.add_argument("--screen", action="store_true",
                    help="score-test pre-screen of every candidate (diagnose --screen)")
    ap.add_argument("--duration", nargs=2, type=float, default=None, metavar=("ATTAS", "HFB"),
                    help="record lengths in s (default 25 30)")
    ap.add_argument("--validate", action="store_true", help="also simulate a validation record")
    ap.add_argument("--no-oracle", action="store_true",
                    help="skip the oracle refit of the true effect in cases not found")
    args = ap.parse_args(argv)
    if args.list:
        for c in CASES:
            print(f"{c.name:18s} {c.key or 'none':30s} {c.note}")
        return 0
    if args.duration:
        DURATION["attas"], DURATION["hfb"] = args.duration
    wanted = DEFAULT_CASES if args.cases is None else args.cases
    cases = [c for c in CASES if c.name in wanted]
    root = pathlib.Path(args.out or tempfile.mkdtemp(prefix="vsidgen_diag_bench_"))
    rows = []
    for c in cases:
        print(f"--- {c.name}", file=sys.stderr, flush=True)
        try:
            rows.append(run_case(c, root / c.name, validate=args.validate,
                                 max_rounds=args.max_rounds,
                                 max_candidates=args.max_candidates, max_iter=args.max_iter,
                                 screen=args.screen, oracle=not args.no_oracle))
        except Exception as err:  # noqa: BLE001 - report and go on
            rows.append({"case": c.name, "true": c.key or "none", "named_first": f"ERROR {err}",
                         "outcome": "error", "alternatives": "",
                         "named_key": "-", "param": "-", "2dELBO": "-", "false_pos": "-",
                         "n_findings": "-", "wall_s": "-", "ok": False})
            import traceback
            traceback.print_exc()
        r = rows[-1]
        print(f"{r['case']:18s} true={r['true']:28s} first={r['named_key']:28s} "
              f"{r['param']}  2dELBO={r['2dELBO']} FP={r['false_pos']} {r['outcome']} "
              f"alt=[{r.get('alternatives', '')}] {_oracle_text(r)} "
              f"({r['wall_s']} s)", flush=True)
    print("\n| case | true effect | named first | parameter (est vs truth) | 2ΔELBO | false pos. "
          "| alternatives (2ΔELBO) | refits (unconv.) | outcome | true effect refitted alone | wall |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['case']} | {r['true']} | {r['named_key']} | {r['param']} | {r['2dELBO']} | "
              f"{r['false_pos']} | {r.get('alternatives') or '–'} | "
              f"{r.get('refits', '-')} ({r.get('unconverged', '-')}) | "
              f"{r['outcome']} | {_oracle_text(r) or '–'} | {r['wall_s']} s |")
    counts = {}
    for r in rows:
        counts[r["outcome"]] = counts.get(r["outcome"], 0) + 1
    print(f"\n{sum(bool(r['ok']) for r in rows)}/{len(rows)} cases ok; "
          + ", ".join(f"{k}: {v}" for k, v in sorted(counts.items())) + f"; work dir {root}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
