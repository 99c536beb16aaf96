"""Check a speed (phugoid) finding of `vsidgen diagnose` against the measured airspeed.

The speed candidate (`speed_dynamics`) adds ΔV̇ = X_V ΔV + X_α α − g Δγ with the
flight-path angle Δγ = θ − α (from the first sample) and was fitted on α, q (and az) only.
This script integrates that speed equation with the record's *measured* θ and α (columns the
fit did not use) and the estimated X_V, X_α, and compares the result with the record's
measured airspeed minus its first sample: correlation (raw and with a linear trend removed
from both, for the unknown trim flight-path angle), RMS and range. A high correlation means
the added state is the speed motion itself, not a generic slow mode.

    python benchmarks/real_records/phugoid_check.py FINDINGS.json RECORD.csv
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np


def speed_from_kinematics(t, alpha, theta, *, xv: float, xa: float, g: float) -> np.ndarray:
    """Euler integration of ΔV̇ = X_V ΔV + X_α (α − mean α) − g ((θ − α) − (θ₀ − α₀))."""
    gam = (theta - alpha) - (theta[0] - alpha[0])
    a = alpha - alpha.mean()
    dv = np.zeros_like(t)
    for k in range(len(t) - 1):
        dv[k + 1] = dv[k] + (t[k + 1] - t[k]) * (xv * dv[k] + xa * a[k] - g * gam[k])
    return dv


def _detrend(t, x):
    A = np.column_stack([np.ones_like(t), t])
    return x - A @ np.linalg.lstsq(A, x, rcond=None)[0]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("findings")
    ap.add_argument("record")
    ap.add_argument("--airspeed", default="v_mps")
    ap.add_argument("--alpha", default="alpha_rad")
    ap.add_argument("--theta", default="theta_rad")
    ap.add_argument("--g", type=float, default=9.80665, help="gravity, m/s^2")
    a = ap.parse_args(argv)
    doc = json.loads(open(a.findings, encoding="utf-8").read())
    f = next((f for f in doc["findings"] if f["effect"] == "speed_dynamics"), None)
    if f is None:
        print("no speed_dynamics finding in", a.findings)
        return 1
    par = {k: v["estimate"] for k, v in f["parameters"].items()}
    xv = next(v for k, v in par.items() if k.startswith("D_XV"))
    xa = next(v for k, v in par.items() if k.startswith("D_Xalpha"))
    g = a.g
    d = np.genfromtxt(a.record, delimiter=",", names=True)
    t = d["t_s"] - d["t_s"][0]
    v = d[a.airspeed] - d[a.airspeed][0]
    for label, (x1, x2) in (("estimated X_V, X_alpha", (xv, xa)), ("gravity only", (0.0, 0.0))):
        dv = speed_from_kinematics(t, d[a.alpha], d[a.theta], xv=x1, xa=x2, g=g)
        r = float(np.corrcoef(dv, v)[0, 1])
        rd = float(np.corrcoef(_detrend(t, dv), _detrend(t, v))[0, 1])
        print(f"{label:24s} (X_V {x1:.4g} 1/s, X_alpha {x2:.4g} m/s^2/rad): correlation with "
              f"measured ΔV {r:.3f} (detrended {rd:.3f}); RMS {np.std(dv):.3f} vs "
              f"{np.std(v):.3f} m/s; range {np.ptp(dv):.2f} vs {np.ptp(v):.2f} m/s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
