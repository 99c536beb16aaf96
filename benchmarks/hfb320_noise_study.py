"""HFB-320: how the pitching-moment estimates depend on the noise model (docs/hfb320.md).

Fits specs/hfb320.yaml to hfb320_1_10 from null initial guesses with

1. the noise estimated (vsidgen's default), Euler and RK4;
2. G and R fixed at the filter-error method's own estimates (its process-noise
   matrix F and its residual covariance R), Euler and RK4;
3. G fixed at F and R fixed at the measurement noise the FEM implies, RK4,

and prints ELBO, CM0, CMV, CMQ, CMDE for each, then the noise table: vsidgen's
estimate, the FEM innovation std √R, and the implied measurement std √R_m, where
R_m solves C P(R_m) Cᵀ + R_m = R (P: steady-state predictor covariance of the
model linearised at the reference's fixed initial state with the FEM's θ and F,
A = exp(J T), Q = T F Fᵀ), by damped fixed-point iteration.

    python benchmarks/hfb320_noise_study.py [--flight ../shared/data/flight]

Takes about 5 minutes on a 2-core machine. Reads the third-party data and reference
results in place; writes only to a temporary directory.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import sys
import tempfile

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
SHOW = ("CM0", "CMV", "CMQ", "CMDE")


def fem_noise_spec(path: pathlib.Path, process: dict, meas_std: dict) -> pathlib.Path:
    """A spec extending specs/hfb320.yaml with every noise std fixed."""
    lines = [f"extends: {ROOT / 'specs' / 'hfb320.yaml'}", f"name: {path.stem}",
             "noise:", "  process:", "    estimate: false", "    std:"]
    lines += [f"      {s}: {float(v)!r}" for s, v in process.items()]
    lines += ["  measurement:"]
    lines += [f"    {o}: {{estimate: false, std: {float(v)!r}}}" for o, v in meas_std.items()]
    path.write_text("\n".join(lines) + "\n")
    return path


def implied_measurement_std(ref: dict, csv: pathlib.Path) -> dict:
    import jax
    import jax.numpy as jnp
    import scipy.linalg as sl

    from vsidgen import load_model, load_record

    jax.config.update("jax_enable_x64", True)
    m = load_model(ROOT / "specs" / "hfb320.yaml")
    rec = load_record(m, csv)
    fem = ref["fem"]
    th = jnp.array([fem["parameters"][p.name]["value"] for p in m.parameters])
    x0 = jnp.asarray([106.023, 0.111685, 0.104887, -0.00332659])  # reference 'numerics': fixed x0
    u0 = jnp.asarray(rec.u[0])
    J = np.asarray(m.drift_jacobian(x0, u0, th)[0])
    C = np.asarray(m.output_jacobian(x0, u0, th)[0])
    T = float(rec.dt)
    A = sl.expm(J * T)
    F = np.diag([fem["process_noise_F_diag"][n] for n in m.state_names])
    Q = T * F @ F.T
    R = np.diag([fem["R_diag"][n] for n in m.output_names])
    Rm = R.copy()
    for _ in range(500):
        P = sl.solve_discrete_are(A.T, C.T, Q, Rm)
        Rm = 0.5 * Rm + 0.5 * np.diag(np.maximum(np.diag(R - C @ P @ C.T), 1e-16))
    return {n: float(np.sqrt(Rm[j, j])) for j, n in enumerate(m.output_names)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--flight", default=os.environ.get("VSIDGEN_FLIGHT_DATA", str(ROOT.parent / "shared" / "data" / "flight")))
    args = ap.parse_args(argv)
    flight = pathlib.Path(args.flight)
    csv = flight / "hfb320_1_10.csv"
    ref_path = flight.parent.parent / "reference" / "hfb320_reference.json"
    if not csv.exists() or not ref_path.exists():
        print(f"needs {csv} and {ref_path}", file=sys.stderr)
        return 2
    ref = json.loads(ref_path.read_text())
    fem = ref["fem"]

    from vsidgen import run_fit

    implied = implied_measurement_std(ref, csv)
    innov = {o: float(np.sqrt(v)) for o, v in fem["R_diag"].items()}
    work = pathlib.Path(tempfile.mkdtemp(prefix="vsidgen_hfb_noise_"))
    s_fem = fem_noise_spec(work / "hfb320_fem_noise.yaml", fem["process_noise_F_diag"], innov)
    s_imp = fem_noise_spec(work / "hfb320_fem_implied.yaml", fem["process_noise_F_diag"], implied)
    runs = [("estimated noise, Euler", ROOT / "specs" / "hfb320.yaml", "euler"),
            ("estimated noise, RK4", ROOT / "specs" / "hfb320.yaml", "rk4"),
            ("FEM F and R fixed, Euler", s_fem, "euler"),
            ("FEM F and R fixed, RK4", s_fem, "rk4"),
            ("FEM F, implied R_m fixed, RK4", s_imp, "rk4")]
    free = None
    for k, (label, spec, integ) in enumerate(runs):
        run_fit(spec, [csv], out=work / str(k), integrator=integ, generated_dir=work / "gen")
        res = json.loads((work / str(k) / "results.json").read_text())
        if free is None:
            free = res
        print(f"{label:32s} converged={res['converged']!s:5s} ELBO {res['elbo']:.2f}  "
              + "  ".join(f"{p} {res['parameters'][p]['estimate']:.4g} ± {res['parameters'][p]['std_error']:.2g}"
                          for p in SHOW), flush=True)
    print(f"{'FEM (reference)':32s} " + "  ".join(
        f"{p} {fem['parameters'][p]['value']:.4g} ± {fem['parameters'][p]['std']:.2g}" for p in SHOW))
    print("\noutput   vsidgen σ (Euler)   FEM √R (innovations)   implied measurement σ   floor")
    for o in free["noise"]["measurement_std"]:
        print(f"{o:7s}  {free['noise']['measurement_std'][o]:<18.3g}  {innov[o]:<21.3g}  {implied[o]:<22.3g}  "
              f"{free['noise']['measurement_floor'][o]:.2g}")
    print("\nstate    vsidgen G (Euler)   FEM F")
    for s, v in free["noise"]["process_std"].items():
        print(f"{s:7s}  {v:<18.3g}  {fem['process_noise_F_diag'][s]:.3g}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
