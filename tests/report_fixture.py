"""Write a realistic, synthetic fit results directory (for report tests).

The directory follows docs/architecture.md ("Results directory"): a
``results.json`` plus one ``signals_<record>.csv`` per record. The signals
come from a small linear HFB-320-like longitudinal model excited by a
3-2-1-1 elevator input; no third-party flight data is used or copied.

Usage::

    from report_fixture import write_results_dir   # tests/ is on sys.path under pytest
    d = write_results_dir(tmp_path / "fit")
"""

from __future__ import annotations

import csv
import json
import pathlib

import numpy as np

STATES = [
    ("V", "m/s", "true airspeed"),
    ("alpha", "rad", "angle of attack"),
    ("theta", "rad", "pitch attitude"),
    ("q", "rad/s", "pitch rate"),
]
INPUTS = [("de", "rad", "elevator deflection"), ("thrust", "N", "total thrust")]
OUTPUTS = [
    ("V", "m/s", "measured true airspeed"),
    ("alpha", "rad", "measured angle of attack"),
    ("theta", "rad", "measured pitch attitude"),
    ("q", "rad/s", "measured pitch rate"),
    ("qdot", "rad/s^2", "measured pitch acceleration"),
    ("ax", "m/s^2", "longitudinal specific force"),
    ("az", "m/s^2", "vertical specific force"),
]
# (name, estimate, std_error, unit, lower, upper, fixed)
PARAMETERS = [
    ("CD0", 0.1215, 0.0031, "1", None, None, False),
    ("CDV", -0.0630, 0.0026, "1", None, None, False),
    ("CDAL", 0.3150, 0.0072, "1/rad", None, None, False),
    ("CL0", -0.0950, 0.0195, "1", None, None, False),
    ("CLV", 0.1510, 0.0165, "1", None, None, False),
    ("CLAL", 4.3100, 0.0467, "1/rad", 0.0, 10.0, False),
    ("CM0", 0.1121, 0.0037, "1", None, None, False),
    ("CMV", 0.0041, 0.0032, "1", None, None, False),
    ("CMAL", -0.9690, 0.0109, "1/rad", None, 0.0, False),
    ("CMQ", -34.30, 0.79, "1/rad", None, None, False),
    ("CMDE", -1.5250, 0.0194, "1/rad", None, None, False),
    ("SIGMAT", 0.0524, float("nan"), "rad", None, None, True),
]
EQUATIONS = {
    "definitions": {
        "qbar": r"\frac{\rho V^{2}}{2}",
        "CD": r"CD_{0} + CDAL \alpha + \frac{CDV V}{V_{0}}",
        "CL": r"CL_{0} + CLAL \alpha + \frac{CLV V}{V_{0}}",
        "Cm": r"CM_{0} + CMAL \alpha + \frac{CMQ CBAR q}{V_{0}} + CMDE de + \frac{CMV V}{V_{0}}",
    },
    "drift": {
        "V": r"- CD SBYM \bar{q} + G_{0} \sin{\left(\alpha - \theta \right)} + "
             r"\frac{thrust \cos{\left(SIGMAT + \alpha \right)}}{RM}",
        "alpha": r"- \frac{CL SBYM \bar{q}}{V} + \frac{G_{0} \cos{\left(\alpha - \theta \right)}}{V}"
                 r" + q - \frac{thrust \sin{\left(SIGMAT + \alpha \right)}}{RM V}",
        "theta": r"q",
        "q": r"Cm SCBYIY \bar{q} + FEIYLT thrust",
    },
    "observations": {
        "V": "V", "alpha": r"\alpha", "theta": r"\theta", "q": "q",
        "qdot": r"Cm SCBYIY \bar{q} + FEIYLT thrust",
        "ax": r"SBYM \bar{q} \left(CL \sin{\left(\alpha \right)} - CD \cos{\left(\alpha \right)}\right)"
              r" + \frac{thrust \cos{\left(SIGMAT \right)}}{RM}",
        # deliberately outside matplotlib's mathtext subset: exercises the <code> fallback
        "az": r"\begin{cases} SBYM \bar{q} CZ - \frac{thrust \sin{\left(SIGMAT \right)}}{RM} \end{cases}",
    },
}
MEAS_STD = {"V": 0.13, "alpha": 0.001, "theta": 0.00045, "q": 0.0006,
            "qdot": 0.0056, "ax": 0.02, "az": 0.14}
PROC_STD = {"V": 0.35, "alpha": 0.0024, "theta": 0.00045, "q": 0.0017}


def _simulate(n: int, dt: float, seed: int, amplitude: float):
    """Linear longitudinal model around trim; returns t, u, x (true), y (true)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * dt
    de = np.full(n, -0.008)
    # 3-2-1-1 elevator input starting at 2 s, then a pulse at 30 s
    unit = max(1, int(round(1.0 / dt)))
    k0 = int(round(2.0 / dt))
    for sign, width in ((1, 3), (-1, 2), (1, 1), (-1, 1)):
        de[k0:k0 + width * unit] += sign * amplitude
        k0 += width * unit
    kp = int(round(min(30.0, 0.5 * n * dt) / dt))
    de[kp:kp + unit] += 1.5 * amplitude
    thrust = 11550.0 + 40.0 * np.sin(2 * np.pi * t / 45.0)
    # state-space matrices (short period + phugoid), deviations from trim
    A = np.array([[-0.012, 3.5, -9.8, 0.0],
                  [-0.0018, -1.0, 0.0, 1.0],
                  [0.0, 0.0, 0.0, 1.0],
                  [0.0005, -5.5, 0.0, -1.4]])
    B = np.array([0.0, -0.09, 0.0, -9.0])
    x0 = np.array([106.0, 0.112, 0.105, 0.0])
    x = np.zeros((n, 4))
    xi = np.zeros(4)
    for k in range(n):
        x[k] = x0 + xi
        w = rng.normal(size=4) * np.array(list(PROC_STD.values())) * np.sqrt(dt)
        xi = xi + dt * (A @ xi + B * (de[k] + 0.008)) + w
    xdot = np.vstack([np.diff(x, axis=0) / dt, np.zeros((1, 4))])
    qdot = xdot[:, 3]
    ax = 0.97 + 0.8 * (x[:, 0] - 106.0) * 0.01 - 9.8 * (x[:, 2] - x[:, 1] - 0.105 + 0.112)
    az = -9.86 - 40.0 * (x[:, 1] - 0.112) - 0.3 * x[:, 3]
    y = np.column_stack([x, qdot, ax, az])
    return t, np.column_stack([de, thrust]), x, y, xdot


def _write_signals(path: pathlib.Path, name: str, n: int, dt: float, seed: int,
                   nan_fraction: float, amplitude: float, outputs: list) -> tuple:
    rng = np.random.default_rng(seed + 1000)
    t, _u, x, y, xdot = _simulate(n, dt, seed, amplitude)
    y = y[:, :len(outputs)]
    sm = np.array([MEAS_STD[o] for o, _, _ in outputs])
    y_meas = y + rng.normal(size=y.shape) * sm
    if nan_fraction > 0:
        mask = rng.random(y.shape) < nan_fraction
        y_meas[mask] = np.nan
    y_smooth = y + rng.normal(size=y.shape) * sm * 0.3
    drift = np.cumsum(rng.normal(size=y.shape) * sm * 0.05, axis=0)
    y_sim = y + drift + 0.5 * sm * np.sin(2 * np.pi * t / 20.0)[:, None]
    y_pred = y + rng.normal(size=y.shape) * sm * 1.1
    mu = x + rng.normal(size=x.shape) * np.array(list(PROC_STD.values())) * 0.05
    mu_std = np.tile(np.array(list(PROC_STD.values())) * 0.3, (n, 1))
    xdot_fd = np.diff(mu, axis=0) / dt
    f_smooth = xdot[:-1] + rng.normal(size=(n - 1, 4)) * np.array(list(PROC_STD.values())) * 0.5

    header = ["t_s"]
    for o, _, _ in outputs:
        header += [f"{o}_meas", f"{o}_smooth", f"{o}_sim", f"{o}_pred"]
    for s, _, _ in STATES:
        header += [f"{s}_mu", f"{s}_mu_std", f"{s}_dot_fd", f"{s}_drift"]
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(header)
        for k in range(n):
            row = [repr(float(t[k]))]
            for j in range(len(outputs)):
                for arr in (y_meas, y_smooth, y_sim, y_pred):
                    v = arr[k, j]
                    row.append("" if np.isnan(v) else repr(float(v)))
            for j in range(len(STATES)):
                row += [repr(float(mu[k, j])), repr(float(mu_std[k, j]))]
                if k < n - 1:
                    row += [repr(float(xdot_fd[k, j])), repr(float(f_smooth[k, j]))]
                else:
                    row += ["", ""]
            w.writerow(row)
    return y_meas, y_smooth, y_sim, y_pred, xdot_fd, f_smooth


def _metrics(meas, pred) -> dict:
    out = {}
    for j, (o, _, _) in enumerate(OUTPUTS[: meas.shape[1]]):
        m, p = meas[:, j], pred[:, j]
        ok = ~(np.isnan(m) | np.isnan(p))
        m, p = m[ok], p[ok]
        rms = float(np.sqrt(np.mean((m - p) ** 2)))
        theil = rms / (np.sqrt(np.mean(m ** 2)) + np.sqrt(np.mean(p ** 2)))
        r2 = 1.0 - float(np.sum((m - p) ** 2) / np.sum((m - m.mean()) ** 2))
        out[o] = {"rms": rms, "theil": float(theil), "r2": r2, "n": int(ok.sum())}
    return out


def _correlation(names: list[str]) -> list[list[float]]:
    """A valid correlation matrix with the textbook's strongly correlated pairs."""
    n = len(names)
    rng = np.random.default_rng(7)
    c = np.eye(n)
    for i, j, r in (("CD0", "CDV", 0.985), ("CL0", "CLV", 0.985), ("CM0", "CMV", -0.975)):
        ii, jj = names.index(i), names.index(j)
        c[ii, jj] = c[jj, ii] = r
    a = rng.normal(size=(n, 3)) * 0.25
    c = c + a @ a.T                       # adding a PSD matrix keeps it positive definite
    d = np.sqrt(np.diag(c))
    c = c / np.outer(d, d)
    return [[round(float(x), 6) for x in row] for row in c]


def write_results_dir(path, *, n_samples: int = 601, dt: float = 0.1, validation: bool = True,
                      warnings: bool = True, std_errors_reliable: bool = True,
                      nan_fraction: float = 0.0, converged: bool = True,
                      with_parameter_reference: bool = True,
                      n_outputs: int | None = None) -> pathlib.Path:
    """Write a complete synthetic results directory at ``path`` and return it.

    Keyword options:
        n_samples, dt: record length and sample period.
        validation: also write a validation record (signals + metrics).
        warnings: include a ``noise_at_floor`` warning in results.json.
        std_errors_reliable: value of the ``std_errors_reliable`` flag.
        nan_fraction: fraction of measured samples set missing (empty CSV cells).
        converged: convergence flag and status text.
        with_parameter_reference: give two parameters a spec reference value.
        n_outputs: keep only the first n outputs (smaller, faster reports).
    """
    path = pathlib.Path(path)
    path.mkdir(parents=True, exist_ok=True)
    outputs = OUTPUTS[:n_outputs] if n_outputs else OUTPUTS
    est_name, val_name = "hfb320_1_10", "hfb320_synthetic_val"
    records = [(est_name, 1, 0.02)] + ([(val_name, 2, 0.025)] if validation else [])
    metrics: dict = {"estimation": {}, "validation": {}}
    signals = {}
    for name, seed, amp in records:
        fname = f"signals_{name}.csv"
        y_meas, y_smooth, y_sim, y_pred, xfd, fs = _write_signals(
            path / fname, name, n_samples, dt, seed, nan_fraction, amp, outputs)
        m = {"smoother": _metrics(y_meas, y_smooth), "simulation": _metrics(y_meas, y_sim),
             "prediction": _metrics(y_meas, y_pred)}
        m["derivative"] = _metrics(xfd, fs)  # state names = first four output names
        metrics["estimation" if name == est_name else "validation"][name] = m
        signals[name] = fname

    free = [p[0] for p in PARAMETERS if not p[6]]
    parameters = {}
    for name, est, se, unit, lo, hi, fixed in PARAMETERS:
        ref = None
        if with_parameter_reference and name in ("CLAL", "CMQ"):
            ref = {"CLAL": 4.32785, "CMQ": -34.7098}[name]
        parameters[name] = {
            "estimate": est, "std_error": None if fixed else se, "fixed": fixed, "unit": unit,
            "lower": lo, "upper": hi, "description": f"coefficient {name}", "reference": ref,
        }
    rec_meta = lambda name: {"name": name, "path": f"synthetic/{name}.csv", "n_samples": n_samples,
                             "dt": dt, "duration_s": round((n_samples - 1) * dt, 9)}
    results = {
        "vsidgen_version": "0.1.0",
        "spec": {"name": "hfb320", "path": "specs/hfb320.yaml",
                 "hash": "3f9a1c0d5e7b2a4968c1f0e3d2b7a6c5948372615049382716a5b4c3d2e1f0a9",
                 "module": "generated/hfb320.py"},
        "model": {
            "states": [{"name": n, "unit": u, "description": d} for n, u, d in STATES],
            "inputs": [{"name": n, "unit": u, "description": d} for n, u, d in INPUTS],
            "outputs": [{"name": n, "unit": u, "description": d} for n, u, d in outputs],
            "equations_latex": EQUATIONS,
        },
        "method": {"estimator": "variational (ELBO)", "integrator": "euler", "substeps": 1,
                   "optimizer": "structured-newton"},
        "records": {"estimation": [rec_meta(est_name)],
                    "validation": [rec_meta(val_name)] if validation else []},
        "parameters": parameters,
        "correlation": {"names": free, "matrix": _correlation(free)},
        "noise": {
            "measurement_std": {o: MEAS_STD[o] for o, _, _ in outputs},
            "process_std": dict(PROC_STD),
            "measurement_floor": {o: (0.00045 if o == "theta" else 1e-5) for o, _, _ in outputs},
            "G": np.diag(list(PROC_STD.values())).tolist(),
            "R": np.diag([MEAS_STD[o] ** 2 for o, _, _ in outputs]).tolist(),
        },
        "elbo": 8123.4,
        "converged": converged,
        "status": ("converged: gradient norm 3e-9 < 1e-6" if converged
                   else "not converged: maximum number of iterations (200) reached"),
        "iterations": 23 if converged else 200,
        "wall_time_s": 4.2,
        "metrics": metrics,
        "validation": ({"elbo": 7950.1, "elbo_own_noise": 7961.25, "own_noise_converged": True}
                       if validation else {"elbo": None}),
        "warnings": ([{"code": "noise_at_floor",
                       "message": "measurement noise std of output 'theta' is at its floor 0.00045 rad",
                       "reliable": False}] if warnings else []),
        "std_errors_reliable": std_errors_reliable,
        "signals": signals,
    }
    tmp = path / "results.json.tmp"
    tmp.write_text(json.dumps(results, indent=1))
    tmp.replace(path / "results.json")
    return path
