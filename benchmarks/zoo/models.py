"""Model zoo: true parameters, hand-written numpy dynamics and an independent simulator.

Nothing here uses vsidgen: the dynamics are written out by hand from the equations in
the zoo specs (``*.yaml`` beside this file), integrated with classical RK4 on a fine grid
(``fine`` steps per sample, inputs held over the sample), and the process noise is added
as Brownian increments on that fine grid (Euler–Maruyama over the fine step: the
continuous-time intensity G, dw = √h N(0, 1)). Measurement noise is Gaussian, added
to the outputs at the sample times and then converted to the CSV units of the spec's
data map (degrees, feet, g).
"""

from __future__ import annotations

import dataclasses
import math
import pathlib

import numpy as np

HERE = pathlib.Path(__file__).resolve().parent
DEG = math.pi / 180.0
G0 = 9.80665
FT = 0.3048


@dataclasses.dataclass(frozen=True)
class ZooModel:
    """One zoo case: spec, truth, hand-written dynamics and the record layout."""

    name: str
    spec: str                      # file name beside this module
    truth: dict                    # parameter -> true value (SI, as in the spec)
    drift: object                  # f(x, u, p) -> xdot (numpy)
    output: object                 # h(x, u, p) -> y (numpy, SI)
    x0: tuple
    proc_std: tuple                # continuous-time intensity per state (state unit/√s); 0 = none
    meas_std: tuple                # per output (SI)
    inputs: object                 # inputs(t) -> (N, nu) array (SI)
    dt: float
    n: int
    time_col: str
    input_cols: tuple              # (column, scale): CSV value = SI / scale
    output_cols: tuple
    description: str = ""


def simulate(m: ZooModel, seed: int, *, n: int | None = None, fine: int = 20):
    """Simulated record (t, u SI, y SI, x) of model ``m`` with its true parameters."""
    rng = np.random.default_rng(seed)
    n = m.n if n is None else n
    t = np.arange(n) * m.dt
    u = m.inputs(t, rng)
    p = m.truth
    x = np.array(m.x0, float)
    gs = np.array(m.proc_std, float)
    h = m.dt / fine
    X = np.empty((n, len(x)))
    for k in range(n):
        X[k] = x
        uk = u[k]
        for _ in range(fine):
            k1 = m.drift(x, uk, p)
            k2 = m.drift(x + 0.5 * h * k1, uk, p)
            k3 = m.drift(x + 0.5 * h * k2, uk, p)
            k4 = m.drift(x + h * k3, uk, p)
            x = x + h / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4) + math.sqrt(h) * gs * rng.normal(size=len(x))
    Y = np.array([m.output(X[k], u[k], p) for k in range(n)])
    Y = Y + np.array(m.meas_std) * rng.normal(size=Y.shape)
    return t, u, Y, X


def write_csv(m: ZooModel, path, seed: int, *, n: int | None = None) -> pathlib.Path:
    """Simulate and write the record in the CSV units of the spec's data map."""
    t, u, y, _ = simulate(m, seed, n=n)
    cols = [m.time_col] + [c for c, _ in m.input_cols] + [c for c, _ in m.output_cols]
    data = np.column_stack([t] + [u[:, i] / s for i, (_, s) in enumerate(m.input_cols)]
                           + [y[:, j] / s for j, (_, s) in enumerate(m.output_cols)])
    path = pathlib.Path(path)
    np.savetxt(path, data, delimiter=",", header=",".join(cols), comments="", fmt="%.10g")
    return path


# ----------------------------------------------------------------------------- input signals
def _pulses(t, start, width, amps):
    """Sequence of rectangular pulses (a 3-2-1-1 is widths 3,2,1,1 with amplitudes +,-,+,-)."""
    out = np.zeros_like(t)
    t0 = start
    for w, a in zip(width, amps):
        out[(t >= t0) & (t < t0 + w)] = a
        t0 += w
    return out


def _lat_inputs(scale=1.0):
    def f(t, rng):
        da = _pulses(t, 1.0, [0.9, 0.6, 0.3, 0.3], [4, -4, 4, -4]) * DEG * scale
        da += _pulses(t, 14.0, [1.0, 1.0], [-3, 3]) * DEG * scale
        dr = _pulses(t, 7.0, [1.2, 0.8, 0.4, 0.4], [5, -5, 5, -5]) * DEG * scale
        dr += _pulses(t, 20.0, [1.5, 1.5], [4, -4]) * DEG * scale
        return np.column_stack([da, dr])
    return f


def _lon_inputs(t, rng):
    de = _pulses(t, 1.0, [1.5, 1.0, 0.5, 0.5], [-2, 2, -2, 2]) * DEG
    de += _pulses(t, 10.0, [1.0, 1.0], [1.5, -1.5]) * DEG
    return de[:, None]


# ----------------------------------------------------------------------------- lateral (4 states)
def _lat4_f(x, u, p):
    beta, pr, r, phi = x
    da, dr = u
    return np.array([
        p["Yb"] * beta + p["Ydr"] * dr - r + G0 / 50.0 * phi,
        p["Lb"] * beta + p["Lp"] * pr + p["Lr"] * r + p["Lda"] * da + p["Ldr"] * dr,
        p["Nb"] * beta + p["Np"] * pr + p["Nr"] * r + p["Nda"] * da + p["Ndr"] * dr,
        pr,
    ])


def _lat4_h(x, u, p):
    beta, pr, r, phi = x
    return np.array([beta, pr, r, phi, 50.0 * (p["Yb"] * beta + p["Ydr"] * u[1])])


LAT_TRUTH = {"Yb": -0.25, "Ydr": 0.06, "Lb": -15.0, "Lp": -7.5, "Lr": 2.0, "Lda": 22.0, "Ldr": 1.5,
             "Nb": 8.0, "Np": -0.6, "Nr": -1.2, "Nda": -1.0, "Ndr": -6.0}
_DEGC = [("beta_deg", DEG), ("p_dps", DEG), ("r_dps", DEG), ("phi_deg", DEG), ("ay_g", 1.0 / G0)]
# CSV value = SI / scale_csv, where scale_csv is the spec's `scale` (SI per CSV unit)
_DEGC = [(c, s if c != "ay_g" else G0) for c, s in _DEGC]

LAT4 = ZooModel(
    name="lat4", spec="lat4.yaml", truth=LAT_TRUTH, drift=_lat4_f, output=_lat4_h,
    x0=(0.0, 0.0, 0.0, 0.02), proc_std=(0.004, 0.03, 0.01, 0.0),
    meas_std=(0.2 * DEG, 0.3 * DEG, 0.2 * DEG, 0.3 * DEG, 0.02 * G0 / 10),
    inputs=_lat_inputs(), dt=0.02, n=1250, time_col="time",
    input_cols=(("da_deg", DEG), ("dr_deg", DEG)), output_cols=tuple(_DEGC),
    description="lateral, linear, 4 states, φ without process noise, accelerometer, degrees/g, 50 Hz")

def _lat4_nobeta_h(x, u, p):
    return _lat4_h(x, u, p)[1:]


LAT4_NOBETA = dataclasses.replace(
    LAT4, name="lat4_nobeta", spec="lat4_nobeta.yaml", output=_lat4_nobeta_h,
    proc_std=(0.004, 0.03, 0.01, 0.002), meas_std=LAT4.meas_std[1:], dt=0.1, n=300,
    output_cols=tuple(_DEGC[1:]),
    description="lateral, linear, 4 states, unmeasured sideslip with process noise, 10 Hz")


# ----------------------------------------------------------------------------- short period, output error
def _sp_f(x, u, p):
    a, q = x
    return np.array([p["Za"] * a + q + p["Zde"] * u[0], p["Ma"] * a + p["Mq"] * q + p["Mde"] * u[0]])


def _sp_h(x, u, p):
    return np.array([x[0], x[1], -70.0 * (p["Za"] * x[0] + p["Zde"] * u[0])])


SP_OE = ZooModel(
    name="sp_oe", spec="sp_oe.yaml", truth={"Za": -1.2, "Zde": -0.1, "Ma": -9.0, "Mq": -2.5, "Mde": -12.0},
    drift=_sp_f, output=_sp_h, x0=(0.0, 0.0), proc_std=(0.0, 0.0),
    meas_std=(0.1 * DEG, 0.2 * DEG, 0.03 * G0), inputs=_lon_inputs, dt=0.04, n=500, time_col="t",
    input_cols=(("de_deg", DEG),), output_cols=(("alpha_deg", DEG), ("q_dps", DEG), ("az_g", G0)),
    description="short period, linear, 2 states, output error (no process noise), 25 Hz")


SP_PN = dataclasses.replace(
    SP_OE, name="sp_pn", spec="sp_pn.yaml", proc_std=(0.004, 0.02), n=400,
    description="short period, linear, 2 states, process noise on both, 25 Hz")


# ----------------------------------------------------------------------------- nonlinear longitudinal
LON_C = dict(RHO=1.1, S=16.0, CBAR=1.5, MASS=1000.0, IY=1800.0)
LON_TRUTH = {"CD0": 0.03, "CDa": 0.3, "CL0": 0.25, "CLa": 5.0, "Cm0": 0.02, "Cma": -0.8, "Cmq": -12.0,
             "Cmde": -1.2}
_DE_TRIM = (0.02 - 0.8 * 0.0122) / 1.2


def _lon_f(x, u, p):
    V, a, th, q = x
    de, thr = u
    c = LON_C
    qbar = 0.5 * c["RHO"] * V * V
    CL = p["CL0"] + p["CLa"] * a
    CD = p["CD0"] + p["CDa"] * a
    Cm = p["Cm0"] + p["Cma"] * a + p["Cmq"] * q * c["CBAR"] / (2 * V) + p["Cmde"] * de
    return np.array([
        -qbar * c["S"] * CD / c["MASS"] + thr * math.cos(a) / c["MASS"] - G0 * math.sin(th - a),
        -qbar * c["S"] * CL / (c["MASS"] * V) + q + G0 * math.cos(th - a) / V,
        q,
        qbar * c["S"] * c["CBAR"] * Cm / c["IY"],
    ])


def _lon_h(x, u, p):
    V, a, th, q = x
    qbar = 0.5 * LON_C["RHO"] * V * V
    return np.array([V, a, th, q, qbar * LON_C["S"] * (p["CL0"] + p["CLa"] * a) / LON_C["MASS"]])


def _lon4_inputs(t, rng):
    de = _DE_TRIM + _lon_inputs(t, rng)[:, 0]
    thr = 1065.0 + _pulses(t, 18.0, [4.0], [300.0])
    return np.column_stack([de, thr])


LON4 = ZooModel(
    name="lon4", spec="lon4.yaml", truth=LON_TRUTH, drift=_lon_f, output=_lon_h,
    x0=(60.0, 0.0122, 0.0122, 0.0), proc_std=(0.05, 0.003, 0.01, 0.0),
    meas_std=(0.3 * FT, 0.15 * DEG, 0.15 * DEG, 0.2 * DEG, 0.03 * G0), inputs=_lon4_inputs, dt=0.05, n=600,
    time_col="t", input_cols=(("de_deg", DEG), ("thrust_N", 1.0)),
    output_cols=(("V_fps", FT), ("alpha_deg", DEG), ("theta_deg", DEG), ("q_dps", DEG), ("az_g", G0)),
    description="longitudinal, nonlinear, 4 states, θ without process noise, accelerometer, ft/s and degrees, 20 Hz")

# ----------------------------------------------------------------------------- variants with noise on every state
LAT4_PN = dataclasses.replace(
    LAT4, name="lat4_pn", spec="lat4_pn.yaml", proc_std=(0.004, 0.03, 0.01, 0.002), dt=0.04, n=600,
    description="lateral, linear, 4 states, process noise on every state, accelerometer, degrees/g, 25 Hz")

KT = 1852.0 / 3600.0
LON4_PN = dataclasses.replace(
    LON4, name="lon4_pn", spec="lon4_pn.yaml", proc_std=(0.05, 0.003, 0.003, 0.01),
    output_cols=(("V_kt", KT),) + LON4.output_cols[1:],
    description="longitudinal, nonlinear, 4 states, process noise on every state, knots and degrees, 20 Hz")


# ----------------------------------------------------------------------------- short period with attitude
def _sp3_f(x, u, p):
    a, q, th = x
    return np.array([p["Za"] * a + p["Zq"] * q + p["Zde"] * u[0], p["Ma"] * a + p["Mq"] * q + p["Mde"] * u[0], q])


def _sp3_h(x, u, p):
    a, q, th = x
    return np.array([a, q, th, -45.0 * (p["Za"] * a + (p["Zq"] - 1.0) * q + p["Zde"] * u[0])])


SP3_PN = ZooModel(
    name="sp3_pn", spec="sp3_pn.yaml",
    truth={"Za": -1.0, "Zq": 0.95, "Zde": -0.08, "Ma": -6.0, "Mq": -2.0, "Mde": -10.0},
    drift=_sp3_f, output=_sp3_h, x0=(0.0, 0.0, 0.0), proc_std=(0.003, 0.02, 0.002),
    meas_std=(0.15 * DEG, 0.2 * DEG, 0.1 * DEG, 0.03 * G0), inputs=_lon_inputs, dt=0.025, n=480,
    time_col="time_s", input_cols=(("elev_deg", DEG),),
    output_cols=(("aoa_deg", DEG), ("q_dps", DEG), ("theta_deg", DEG), ("nz_g", G0)),
    description="short period with attitude, linear, 3 states, process noise on every state, 40 Hz")

# ----------------------------------------------------------------------------- longitudinal, no alpha vane
def _lon4_now_f(x, u, p):
    uu, w, q, th = x
    de = u[0]
    return np.array([
        p["Xu"] * uu + p["Xw"] * w - G0 * th,
        p["Zu"] * uu + p["Zw"] * w + 50.0 * q + p["Zde"] * de,
        p["Mw"] * w + p["Mq"] * q + p["Mde"] * de,
        q,
    ])


def _lon4_now_h(x, u, p):
    uu, w, q, th = x
    return np.array([uu, q, th, p["Zu"] * uu + p["Zw"] * w + p["Zde"] * u[0]])


LON4_NOW = ZooModel(
    name="lon4_now", spec="lon4_now.yaml",
    truth={"Xu": -0.04, "Xw": 0.1, "Zu": -0.35, "Zw": -2.0, "Zde": -6.0, "Mw": -0.15, "Mq": -3.0, "Mde": -12.0},
    drift=_lon4_now_f, output=_lon4_now_h, x0=(0.0, 0.0, 0.0, 0.0), proc_std=(0.05, 0.1, 0.01, 0.002),
    meas_std=(0.15, 0.2 * DEG, 0.15 * DEG, 0.03 * G0), inputs=_lon_inputs, dt=0.05, n=600, time_col="t",
    input_cols=(("de_deg", DEG),),
    output_cols=(("du_kt", KT), ("q_dps", DEG), ("theta_deg", DEG), ("az_g", G0)),
    description="longitudinal, linear, 4 states, unmeasured vertical velocity with process noise, knots/deg/g, 20 Hz")


# ----------------------------------------------------------------------------- coupled lon + lat, 8 states
SIX8_V0 = 60.0
SIX8_TRUTH = {"Xu": -0.04, "Xa": 4.0, "Zu": -0.3, "Za": -1.3, "Zde": -0.12, "Mu": 0.003, "Ma": -7.0,
              "Mq": -2.8, "Mde": -11.0, **LAT_TRUTH}


def _six8_f(x, u, p):
    uu, a, q, th, beta, pr, r, phi = x
    de, da, dr = u
    V0 = SIX8_V0
    return np.array([
        p["Xu"] * uu + p["Xa"] * a - G0 * th,
        p["Zu"] * uu / V0 + p["Za"] * a + p["Zde"] * de + q,
        p["Mu"] * uu + p["Ma"] * a + p["Mq"] * q + p["Mde"] * de,
        q,
        p["Yb"] * beta + p["Ydr"] * dr - r + G0 / V0 * phi,
        p["Lb"] * beta + p["Lp"] * pr + p["Lr"] * r + p["Lda"] * da + p["Ldr"] * dr,
        p["Nb"] * beta + p["Np"] * pr + p["Nr"] * r + p["Nda"] * da + p["Ndr"] * dr,
        pr,
    ])


def _six8_h(x, u, p):
    uu, a, q, th, beta, pr, r, phi = x
    de, da, dr = u
    V0 = SIX8_V0
    az = -V0 * (p["Zu"] * uu / V0 + p["Za"] * a + p["Zde"] * de)
    ay = V0 * (p["Yb"] * beta + p["Ydr"] * dr)
    return np.array([V0 + uu, a, q, th, beta, pr, r, phi, az, ay])


def _six8_inputs(t, rng):
    de = _lon_inputs(t, rng)[:, 0]
    lat = _lat_inputs()(t - 12.0, rng)
    return np.column_stack([de, lat])


SIX8 = ZooModel(
    name="six8", spec="six8.yaml", truth=SIX8_TRUTH, drift=_six8_f, output=_six8_h,
    x0=(0.0,) * 8, proc_std=(0.2, 0.003, 0.02, 0.0, 0.004, 0.03, 0.01, 0.0),
    meas_std=(0.15, 0.15 * DEG, 0.2 * DEG, 0.1 * DEG, 0.2 * DEG, 0.3 * DEG, 0.2 * DEG, 0.2 * DEG,
              0.02 * G0, 0.01 * G0),
    inputs=_six8_inputs, dt=0.02, n=2000, time_col="t",
    input_cols=(("elev_deg", DEG), ("ail_deg", DEG), ("rud_deg", DEG)),
    output_cols=(("ias_kt", KT), ("aoa_deg", DEG), ("q_dps", DEG), ("theta_deg", DEG), ("aos_deg", DEG),
                 ("p_dps", DEG), ("r_dps", DEG), ("phi_deg", DEG), ("nz_g", G0), ("ny_g", G0)),
    description="coupled longitudinal + lateral, linear, 8 states, θ and φ without process noise, "
                "knots, degrees and g through units, 50 Hz")

SIX8_RK4 = dataclasses.replace(SIX8, name="six8_rk4", spec="six8_rk4.yaml",
                               description=SIX8.description + "; RK4")

MODELS = {m.name: m for m in (SP_PN, SP_OE, LAT4_NOBETA, LON4, LAT4, LAT4_PN, LON4_PN, SP3_PN, SIX8, LON4_NOW, SIX8_RK4)}
