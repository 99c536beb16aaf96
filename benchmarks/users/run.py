"""New users' models on the real flight records: does `vsidgen fit` work on what users write?

Each spec in this folder was written by a first-time user of vsidgen (sessions 17-23), from the
flight records' README and constants files only, the way such a user writes a model: body or
wind axes, dimensional or nondimensional derivatives, measured signals as inputs (airspeed,
density, mass, pitch attitude), data-map expressions, bounds and initial values, lever arms
from the constants file. None is tuned to vsidgen; several found defects that were fixed (the
spec's first comment, docs/diagnose.md and the session notes say which).

``python benchmarks/users/run.py [--only NAME ...] [--work DIR] [--json FILE]`` runs
``vsidgen fit SPEC ESTIMATION... --validate VALIDATION... --out DIR`` for each model (command
line, as a user does, in a scratch folder so that nothing is written into the repository) and
prints a table: exit status, convergence, ELBO, iterations, validation ELBO, wall time, the
warnings' codes. The records are read from ``$VSIDGEN_FLIGHT_DATA`` (default
``../shared/data/flight`` beside the repository); they are third-party data and are not
copied here. ``tests/test_user_models.py`` checks every spec and fits some of them.
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import pathlib
import subprocess
import sys
import tempfile
import time

HERE = pathlib.Path(__file__).resolve().parent
ROOT = HERE.parents[1]

#: name (= spec file stem) -> (estimation records, validation records, what the user did)
MODELS: dict[str, tuple[tuple[str, ...], tuple[str, ...], str]] = {
    "otter_coef": (("totter_lon_020213f1_018",), ("totter_lon_020213f1_017",),
                   "short period with C_L, C_m coefficients, measured V and q-bar"),
    "tu144_coef": (("tu144_lon_f20_4d",), ("tu144_lon_f20_4f",),
                   "first model: short period with lift and moment coefficients"),
    "my_twin_otter": (("totter_lon_020213f1_019",), (),
                      "linear short period with dimensional derivatives"),
    "my_otter_lat": (("totter_lat_f1_014",), ("totter_lat_f1_017",),
                     "lateral-directional, nondimensional derivatives"),
    "attas_roll": (("attas_ail1",), ("attas_ail2",),
                   "roll-only model, aileron from a data-map expression"),
    "otter_roll_yaw": (("totter_lat_f1_014",), ("totter_lat_f1_017",),
                       "roll and yaw rates from aileron and rudder"),
    "tu144_pitch": (("tu144_lon_f20_4d",), ("tu144_lon_f20_4f",),
                    "pitch model driven by the measured airspeed"),
    "otter_body": (("totter_lon_020213f1_018",), ("totter_lon_020213f1_017",),
                   "body axes (u, w): states no output measures directly"),
    "attas_lat4": (("attas_ail1", "attas_rud1"), ("attas_ail2",),
                   "lateral, gravity term of beta-dot left out"),
    "otter_slow": (("totter_lon_data",), (),
                   "low-speed body-axis model, q-bar from the air data"),
    "attas_lon": (("attas_elv1",), ("attas_elv2",),
                  "wind-axis point mass, two thrust columns and measured density"),
    "otter_latdim": (("totter_lat_f1_017",), ("totter_lat_f1_014",),
                     "dimensional lateral derivatives, a_y without a bias"),
    "otter_sp_mass": (("totter_lon_9752ed20",), (),
                      "mass and inertia per sample as inputs, abs(), bounds and initial values"),
    "attas_lat_arm": (("attas_ail1", "attas_rud1"), ("attas_ail2",),
                      "lateral with the accelerometer at its lever arm, da from an expression"),
    "tu144_mine": (("tu144_lon_f20_4f",), ("tu144_lon_f20_4d",),
                   "short period in the recorded variables without trim terms"),
    "otter_pitch": (("totter_lon_020213f1_019",), ("totter_lon_020213f1_018",),
                    "short period and pitch attitude, a_z from the lift derivatives, no trim "
                    "constants and no a_z bias"),
    "hfb_sp": (("hfb320_1_10",), (),
               "first HFB-320 model: the short period alone (alpha, q, constants) on a record "
               "whose phugoid is excited"),
    "otter_lon_nl": (("totter_lon_020213f1_018",), ("totter_lon_020213f1_017",),
                     "nonlinear V, alpha, q, theta with coefficients, two thrust inputs, "
                     "density as an input"),
    "hfb_sp_deg": (("hfb320_1_10",), (),
                   "the first HFB-320 short-period model written in degrees"),
    "attas_sp_deg": (("attas_elv1",), ("attas_elv2",),
                     "short period and vertical accelerometer written in degrees, the "
                     "records' radians converted by the data map"),
    "attas_pitch_deg": (("attas_elv1",), ("attas_elv2",),
                        "angle of attack and pitch rate in degrees, own names, no noise "
                        "section (session 38's diagnose 'lag' of 9e-5 s)"),
    "otter_lat_nolr": (("totter_lat_f1_014",), ("totter_lat_f1_017",),
                       "lateral in degrees without the roll-due-to-yaw-rate term L_r"),
    "tu144_nz_deg": (("tu144_lon_f20_4d",), ("tu144_lon_f20_4f",),
                     "short period in degrees with a normal acceleration of its own "
                     "derivatives, without the pitch-rate term"),
    "attas_yaw_v": (("attas_rud1",), ("attas_rud2",),
                    "lateral with a side-velocity state, beta a definition, phi' = p, "
                    "without N_p"),
    "hfb_cz_nondim": (("hfb320_1_10",), (),
                      "coefficient form with mass, area and density as fixed parameters, "
                      "measured V as input, theta' = q without process noise, n_z output"),
    "attas_latdeg": (("attas_ail1", "attas_rud1"), ("attas_ail2", "attas_rud2"),
                     "lateral in degrees with A/B-matrix names, measured beta as input"),
    "twotter_lat_longnames": (("totter_lat_f1_014",), ("totter_lat_f1_017",),
                              "lateral with long descriptive names, bounds and a fixed "
                              "parameter"),
    "otter_lon_coef": (("totter_lon_020213f1_017",), ("totter_lon_020213f1_018",),
                       "short period and attitude in lift and moment coefficients with the "
                       "aircraft constants, g/V cos(theta - alpha), an a_z output"),
    "otter_pitch_degrees": (("totter_lon_020213f1_019",), ("totter_lon_020213f1_018",),
                            "short period and attitude in degrees throughout, g/V cos(theta - "
                            "alpha) through d2r, an a_z output"),
    "attas_sp_us": (("attas_elv1",), ("attas_elv2",),
                    "short period in degrees, the reference airspeed in knots and the vertical "
                    "accelerometer in g"),
}


def flight_data_dir() -> pathlib.Path:
    env = os.environ.get("VSIDGEN_FLIGHT_DATA")
    return pathlib.Path(env) if env else ROOT.parent / "shared" / "data" / "flight"


def fit_command(name: str, data: pathlib.Path, out: pathlib.Path) -> list[str]:
    est, val, _ = MODELS[name]
    cmd = [sys.executable, "-m", "vsidgen", "fit", str(HERE / f"{name}.yaml"),
           *(str(data / f"{r}.csv") for r in est), "--out", str(out)]
    if val:
        cmd += ["--validate", *(str(data / f"{r}.csv") for r in val)]
    return cmd


def run_one(name: str, data: pathlib.Path, work: pathlib.Path, *, timeout: float = 1800.0) -> dict:
    """Fit one model from the command line in ``work`` (its own folder for generated code)."""
    wd = work / name
    wd.mkdir(parents=True, exist_ok=True)
    out = wd / "fit"
    t0 = time.perf_counter()
    try:
        p = subprocess.run(fit_command(name, data, out), cwd=wd, capture_output=True, text=True,
                           timeout=timeout)
        rc, err = p.returncode, p.stderr
    except subprocess.TimeoutExpired:
        rc, err = None, f"timed out after {timeout:g} s"
    row = {"model": name, "rc": rc, "wall_s": time.perf_counter() - t0, "stderr_tail": err[-2000:]}
    res = out / "results.json"
    if res.exists():
        r = json.loads(res.read_text())
        row.update(converged=bool(r.get("converged")), elbo=r.get("elbo"),
                   iterations=r.get("iterations"),
                   validation_elbo=(r.get("validation") or {}).get("elbo"),
                   warnings=dict(collections.Counter(w.get("code", "?") for w in r.get("warnings", []))))
    return row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--only", nargs="+", choices=sorted(MODELS), default=None)
    ap.add_argument("--work", type=pathlib.Path, default=None, help="scratch folder (default: a temporary one)")
    ap.add_argument("--json", type=pathlib.Path, default=None, help="write the rows here")
    args = ap.parse_args(argv)
    data = flight_data_dir()
    if not data.is_dir():
        print(f"flight records not found at {data} (set VSIDGEN_FLIGHT_DATA)", file=sys.stderr)
        return 2
    names = args.only or list(MODELS)
    with tempfile.TemporaryDirectory() as td:
        work = args.work or pathlib.Path(td)
        rows = []
        print(f"{'model':16s} {'rc':>3s} {'conv':>5s} {'ELBO':>10s} {'it.':>5s} {'val. ELBO':>10s} "
              f"{'wall s':>7s}  warnings")
        for n in names:
            r = run_one(n, data, work)
            rows.append(r)
            ve = r.get("validation_elbo")
            print(f"{n:16s} {str(r['rc']):>3s} {str(r.get('converged', '-')):>5s} "
                  f"{r.get('elbo') or float('nan'):10.1f} {r.get('iterations') or 0:5d} "
                  f"{ve if ve is not None else float('nan'):10.1f} {r['wall_s']:7.1f}  "
                  f"{', '.join(f'{k} {v}' for k, v in (r.get('warnings') or {}).items())}", flush=True)
        if args.json:
            args.json.write_text(json.dumps(rows, indent=1))
    return 0 if all(r["rc"] in (0, 1) for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
