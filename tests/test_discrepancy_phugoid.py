"""Physical candidates with the aircraft's flight conditions: the speed (phugoid) dynamics a
short-period model leaves out, flow vanes in metres with the record's airspeed, and
accelerometer lever arms with the full rigid-body kinematics.

References are independent of the candidates' terms: numpy cross products for the
accelerometer kinematics, a numpy simulation (RK4 on a 10× finer grid, inputs varying
between samples) of the exact vane geometry α_vane = atan2(V sin α − x q, V cos α), and the
textbook linear longitudinal equations for the speed candidate. The real-record tests are slow.
"""

from __future__ import annotations

import dataclasses
import math
import pathlib
import textwrap

import numpy as np
import pytest
import sympy

from vsidgen.discrepancy.base import model_info, propose
from vsidgen.discrepancy.catalogue import SpeedDynamics, _arm_terms
from vsidgen.discrepancy.flightconst import flight_conditions, flight_conditions_of
from vsidgen.spec.expr import parse_expression

ROOT = pathlib.Path(__file__).resolve().parents[1]
ATTAS = ROOT / "specs" / "attas_sp.yaml"
TOTTER = ROOT / "specs" / "totter_sp.yaml"
G = 9.80665


class _Rec:
    def __init__(self, path):
        self.path = pathlib.Path(path)


def _write_csv(path, cols: dict[str, np.ndarray]):
    names = list(cols)
    data = np.column_stack([cols[n] for n in names])
    np.savetxt(path, data, delimiter=",", header=",".join(names), comments="", fmt="%.12g")


# ---------------------------------------------------------------------------
# flight conditions
# ---------------------------------------------------------------------------

def test_flight_conditions_from_record_and_constants_file(tmp_path):
    (tmp_path / "plane.constants.yaml").write_text(textwrap.dedent("""\
        aircraft: Test plane
        data_files: [plane_a.csv]
        gravity: {g_ftps2: 32.174}
        geometry: {noseboom_wrt_cg_m: {x: 7.5, y: 0.0, z: -0.2}}
        reference_models: {sp: {Vo_ftps: 200.0}}
        """))
    t = np.arange(50) * 0.1
    _write_csv(tmp_path / "plane_a.csv", {"t_s": t, "v_mps": 60.0 + 0.1 * np.sin(t)})
    _write_csv(tmp_path / "plane_b.csv", {"t_s": t, "de_rad": 0 * t})
    fc = flight_conditions([_Rec(tmp_path / "plane_a.csv")])
    assert fc.aircraft == "Test plane"
    assert fc.airspeed.value == pytest.approx(np.mean(60.0 + 0.1 * np.sin(t)), rel=1e-12)
    assert "v_mps" in fc.airspeed.source
    assert fc.gravity.value == pytest.approx(32.174 * 0.3048, rel=1e-12)
    assert fc.sensors["noseboom"] == (7.5, 0.0, -0.2)
    # no airspeed column: the constants file's trim speed (found by the file's stem)
    fb = flight_conditions([_Rec(tmp_path / "plane_b.csv")])
    assert fb.airspeed.value == pytest.approx(200.0 * 0.3048, rel=1e-12)
    # a spec constant g wins; a model with its own airspeed needs no number
    fs = flight_conditions([_Rec(tmp_path / "plane_a.csv")], spec_constants={"g": 9.81},
                           own_speed="V")
    assert fs.gravity.value == 9.81 and fs.airspeed is None
    # nothing known: standard gravity, no airspeed
    fn = flight_conditions([])
    assert fn.gravity.value == G and fn.airspeed is None


# ---------------------------------------------------------------------------
# accelerometer kinematics against numpy cross products
# ---------------------------------------------------------------------------

def test_accelerometer_arm_terms_are_the_rigid_body_kinematics():
    rng = np.random.default_rng(0)
    w, wd = rng.normal(size=3), rng.normal(size=3)
    sym = {n: sympy.Symbol(n, real=True) for n in ("p", "q", "r", "pd", "qd", "rd")}
    vals = dict(zip(("p", "q", "r", "pd", "qd", "rd"), [*w, *wd]))
    axes = "xyz"
    for i, arm in enumerate(axes):
        e = np.eye(3)[i]
        ref = np.cross(wd, e) + np.cross(w, np.cross(w, e))
        for j, axis in enumerate(axes):
            terms = _arm_terms(arm, axis, {"p": "p", "q": "q", "r": "r"},
                               {"p": "pd", "q": "qd", "r": "rd"})
            got = sum(float(parse_expression(tx, sym).xreplace(
                {sym[k]: v for k, v in vals.items()})) for tx in terms)
            assert got == pytest.approx(ref[j], abs=1e-12), (arm, axis, terms)
    # a longitudinal model (q only): ax reads −x q² from an arm ahead, az reads −x q̇
    assert _arm_terms("x", "x", {"q": "q"}, {"q": "qd"}) == ["-q**2"]
    assert _arm_terms("x", "z", {"q": "q"}, {"q": "qd"}) == ["-(qd)"]


# ---------------------------------------------------------------------------
# vane in metres with the record's airspeed (the spec has none)
# ---------------------------------------------------------------------------

def _smooth_input(t, dt, seed):
    """A 3-2-1-1 multistep with rounded edges plus a small doublet train: varies between
    samples (no zero-order hold in the truth)."""
    steps = np.zeros_like(t)
    edges = [(1.0, 4.0, 1.0), (4.0, 6.0, -1.0), (6.0, 7.0, 1.0), (7.0, 8.0, -1.0)]
    for a, b, s in edges:
        steps += s * (0.5 * (np.tanh((t - a) / 0.08) - np.tanh((t - b) / 0.08)))
    rng = np.random.default_rng(seed)
    return 0.03 * steps + 0.004 * np.sin(2 * math.pi * 0.7 * t + rng.uniform(0, 6.28))


def _rk4(f, x0, t_fine, u_of_t):
    X = np.empty((len(t_fine), len(x0)))
    x = np.array(x0, float)
    h = t_fine[1] - t_fine[0]
    for k, tk in enumerate(t_fine):
        X[k] = x
        k1 = f(x, u_of_t(tk))
        k2 = f(x + 0.5 * h * k1, u_of_t(tk + 0.5 * h))
        k3 = f(x + 0.5 * h * k2, u_of_t(tk + 0.5 * h))
        k4 = f(x + h * k3, u_of_t(tk + h))
        x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return X


SP = dict(Za=-1.2, Zde=-0.15, Ma=-4.0, Mq=-1.5, Mde=-6.0)

#: short-period model with the kinematic q term of the α equation (coefficient 1) and no
#: airspeed. With a free Z_q (attas_sp) a vane offset is not identifiable: α' = α − k q
#: maps the model onto itself (Z_α − k M_α, 1 + Z_q + k(Z_α − M_q) − k² M_α, ...).
SP_SPEC = textwrap.dedent("""\
    name: sp_kin
    states:
      alpha: {unit: rad}
      q: {unit: rad/s}
    inputs:
      de: {unit: rad}
    outputs:
      alpha: {unit: rad}
      q: {unit: rad/s}
    parameters:
      Z0: {unit: rad/s}
      Za: {unit: 1/s}
      Zde: {unit: 1/s}
      M0: {unit: rad/s^2}
      Ma: {unit: 1/s^2}
      Mq: {unit: 1/s}
      Mde: {unit: 1/s^2}
    drift:
      alpha: Z0 + Za*alpha + q + Zde*de
      q: M0 + Ma*alpha + Mq*q + Mde*de
    observations:
      alpha: alpha
      q: q
    noise:
      process: {states: [alpha, q], structure: diagonal, estimate: true}
      measurement:
        alpha: {floor: auto}
        q: {floor: auto}
    data:
      time: t_s
      inputs: {de: de_rad}
      outputs: {alpha: alpha_rad, q: q_radps}
    """)


def _fit_candidate(cand, base_spec, info, csv, tmp_path):
    from vsidgen.data import load_record
    from vsidgen.estimator import FitOptions, fit
    from vsidgen.model import load_model

    p = tmp_path / "cand.yaml"
    p.write_text(cand.spec_yaml(base_spec, name="cand_phys", candidate_path=p, info=info)
                 + "integrator: {method: rk4, substeps: 1, inputs: foh}\n")
    m = load_model(p, generated_dir=tmp_path / "gen")
    rec = load_record(m, csv)
    res = fit(m, [rec], options=FitOptions(deterministic="quasi", deterministic_std=1e-3))
    return m, res


def _estimate(m, res, name):
    i = list(m.parameter_names).index(name)
    return float(res.theta[i]), float(res.std_errors[i])


def test_alpha_vane_offset_recovered_in_metres_from_exact_geometry(tmp_path):
    dt, n, V, x_vane = 0.04, 400, 80.0, 12.0
    t = np.arange(n) * dt
    sub = 10
    t_f = np.arange(n * sub) * (dt / sub)

    def u_of(tt):
        return _smooth_input(np.asarray(tt), dt, 1)

    def f(x, u):
        a, q = x
        return np.array([SP["Za"] * a + q + SP["Zde"] * u, SP["Ma"] * a + SP["Mq"] * q
                         + SP["Mde"] * u])

    X = _rk4(f, [0.0, 0.0], t_f, u_of)[::sub]
    a, q = X[:, 0] + 0.05, X[:, 1]              # trim α 0.05 rad
    rng = np.random.default_rng(7)
    a_vane = np.arctan2(V * np.sin(a) - x_vane * q, V * np.cos(a))
    csv = tmp_path / "vane_rec.csv"
    _write_csv(csv, {"t_s": t, "de_rad": u_of(t),
                     "alpha_rad": a_vane + 4e-4 * rng.normal(size=n),
                     "q_radps": q + 1e-3 * rng.normal(size=n),
                     "v_mps": V + 0.2 * rng.normal(size=n)})
    spec = tmp_path / "sp_kin.yaml"
    spec.write_text(SP_SPEC)
    info = model_info(spec, dt=dt)
    info = dataclasses.replace(info, flight=flight_conditions_of(info, [_Rec(csv)]))
    cand = next(c for c in propose(info) if c.key == "sensor_position:alpha:q")
    (p,) = cand.parameters
    assert p.unit == "m" and "v_mps" in cand.info["airspeed_source"]
    m, res = _fit_candidate(cand, spec, info, csv, tmp_path)
    est, se = _estimate(m, res, p.name)
    assert res.converged, res.status
    assert abs(est - x_vane) < 3 * se and se < 0.1 * x_vane, (est, se)


# ---------------------------------------------------------------------------
# the speed (phugoid) dynamics
# ---------------------------------------------------------------------------

def test_speed_candidate_is_the_linearised_longitudinal_model(tmp_path):
    """Its equations are the textbook linear longitudinal model, with the path angle closed
    two ways: from the model's α equation (γ̇ = q − α̇, air-relative α) and from the attitude
    (Δθ̇ = q, γ = Δθ − α, inertial α)."""
    from vsidgen.spec import compile_spec

    info = model_info(TOTTER, dt=0.01)
    air, att = SpeedDynamics().applies_to(info)
    assert air.key == "speed_dynamics:alpha:q" and att.key == "speed_dynamics:alpha:q:attitude"
    assert air.info["closure"] == "air" and att.info["closure"] == "attitude"
    for c in (air, att):
        assert c.effect == "speed_dynamics" and c.target == "drift:alpha"
        units = {p.name: p.unit for p in c.parameters}
        assert units == {"D_XV": "1/s", "D_Xalpha": "(m/s^2)/(rad)", "D_ZV": "(rad)/m",
                         "D_MV": "(rad/s)/m"}
        assert all(p.initial == 0.0 and not p.fixed for p in c.parameters)
    g = sympy.Float(G, 15)
    for c, ang in ((air, "D_dgamma"), (att, "D_dtheta")):
        path = tmp_path / f"speed_{ang}.yaml"
        path.write_text(c.spec_yaml(TOTTER, name="speed", candidate_path=path, info=info))
        sym = compile_spec(path)
        names = [v.name for v in sym.states]
        drift = dict(zip(names, sym.drift_expanded()))
        obs = dict(zip([v.name for v in sym.outputs], sym.observations_expanded()))
        s = {x.name: x for e in list(drift.values()) + list(obs.values()) for x in e.free_symbols}
        a, q, de, dV, x = (s[k] for k in ("alpha", "q", "de", "D_dV", ang))
        Z0, Za, Zde, Vo = (s[k] for k in ("Z0", "Za", "Zde", "Vo"))
        XV, Xa, ZV, MV = (s[k] for k in ("D_XV", "D_Xalpha", "D_ZV", "D_MV"))
        M0, Ma, Mq, Mde, az0 = (s[k] for k in ("M0", "Ma", "Mq", "Mde", "az0"))
        hand_alpha = Z0 + Za * a + q + Zde * de + ZV * dV
        assert sympy.simplify(drift["alpha"] - hand_alpha) == 0
        assert sympy.simplify(drift["q"] - (M0 + Ma * a + Mq * q + Mde * de + MV * dV)) == 0
        if ang == "D_dgamma":
            # flight-path angle: γ̇ = θ̇ − α̇ = q − α̇ (the α equation without its noise)
            assert sympy.simplify(drift["D_dV"] - (XV * dV + Xa * a - g * x)) == 0
            assert sympy.simplify(drift[ang] - (q - hand_alpha)) == 0
        else:
            # gravity along the flight path γ = θ − α, θ̇ = q
            assert sympy.simplify(drift["D_dV"] - (XV * dV + Xa * a - g * (x - a))) == 0
            assert sympy.simplify(drift[ang] - q) == 0
        # vertical specific force Z/m = V₀(α̇ − q) without the bias: gains V₀ Z_V ΔV
        assert sympy.simplify(obs["az"] - (Vo * (Za * a + Zde * de + ZV * dV) + az0)) == 0


def test_speed_candidate_needs_alpha_and_q_and_no_speed_state():
    lat = model_info(ROOT / "specs" / "attas_lat.yaml", dt=0.04)
    assert SpeedDynamics().applies_to(lat) == []
    hfb = model_info(ROOT / "specs" / "hfb320.yaml", dt=0.1)     # has a V state
    assert SpeedDynamics().applies_to(hfb) == []


MEASURED_SPEED_SPEC = textwrap.dedent("""
    name: pitch_measured_speed
    states:
      alpha: {unit: rad}
      q: {unit: rad/s}
      theta: {unit: rad}
    inputs:
      de: {unit: rad}
      V: {unit: m/s, description: measured true airspeed}
    outputs:
      alpha: {unit: rad}
      q: {unit: rad/s}
    constants:
      rho: {value: 0.46, unit: kg/m^3}
      g: {value: 9.81, unit: m/s^2}
    parameters:
      CLa: {unit: 1/rad}
      Cma: {unit: 1/rad}
      Cmq: {unit: 1/rad}
      Cmde: {unit: 1/rad}
    definitions:
      qbar: 0.5*rho*V**2
    drift:
      alpha: q - qbar*0.004*CLa*alpha/V + g*cos(theta - alpha)/V
      q: qbar*0.0008*(Cma*alpha + Cmq*q*10/V + Cmde*de)
      theta: q
    observations:
      alpha: alpha
      q: q
    data:
      time: t_s
      inputs: {de: de_rad, V: v_mps}
      outputs: {alpha: alpha_rad, q: q_radps}
    """)


def test_a_model_driven_by_the_measured_airspeed_has_its_speed_dynamics(tmp_path):
    """A new user's pitch model that takes the measured airspeed as an input: the speed
    variations are in the model already (no speed-dynamics candidate), and the vane position
    uses that airspeed sample by sample (not the record's mean)."""
    spec = tmp_path / "pitch.yaml"
    spec.write_text(MEASURED_SPEED_SPEC)
    info = model_info(spec, dt=0.04)
    assert SpeedDynamics().applies_to(info) == []
    vane = next(c for c in propose(info) if c.key == "sensor_position:alpha:q")
    (term,) = vane.add_terms["observations"].values()
    assert "/V" in term.replace(" ", "").replace("(V)", "V"), term
    assert "the model's V" in vane.explanation


# ---------------------------------------------------------------------------
# real records (slow; the records are not in the repository)
# ---------------------------------------------------------------------------

def _diagnose(spec, records, out, **kw):
    import json

    from vsidgen.discrepancy import run_diagnose

    run_diagnose(spec, records, out=out, max_rounds=1, numerics=False, workers=1, **kw)
    return json.loads((out / "findings.json").read_text())


@pytest.mark.slow
def test_twin_otter_short_period_names_the_missing_speed_dynamics(flight_data_dir, tmp_path):
    doc = _diagnose(TOTTER, [flight_data_dir / "totter_lon_9752ed20.csv"], tmp_path / "d",
                    effects=["speed_dynamics"], max_candidates=2, min_score=0.0)
    (f,) = doc["findings"]
    # either closure of the path angle (both refitted; since the profiled speed screen,
    # session 33, both reach 2ΔELBO ≈ 2270–2290 and the data do not separate them)
    assert f["key"] in ("speed_dynamics:alpha:q", "speed_dynamics:alpha:q:attitude")
    assert f["title"] == "speed (phugoid) dynamics missing"
    ev = f["evidence"]
    assert ev["statistic"] > ev["threshold"] and ev["converged"]
    par = f["parameters"]
    assert par["D_ZV"]["unit"] == "(rad)/m"
    # lift grows with speed: Z_V = −2g/V₀² (lift ∝ V² in trim) at the spec's Vo = 56.5227 m/s,
    # −0.00614 rad/m; within 3 standard errors
    zv, se = par["D_ZV"]["estimate"], par["D_ZV"]["std_error"]
    assert abs(zv - (-2 * G / 56.5227 ** 2)) < 3 * se
    assert doc["final"]["elbo"] > doc["base"]["elbo"]


@pytest.mark.slow
@pytest.mark.parametrize("spec_name, unit, rad_per_unit", [
    ("hfb_sp", "(rad)/m", 1.0), ("hfb_sp_deg", "(deg)/m", math.pi / 180)])
def test_new_users_hfb320_short_period_names_the_missing_speed_dynamics(
        flight_data_dir, tmp_path, spec_name, unit, rad_per_unit):
    """A new user's short-period model (α, q with constants; benchmarks/users/hfb_sp.yaml, and
    the same model written in degrees, hfb_sp_deg.yaml) on the real HFB-320 record whose
    phugoid is excited (V 104.6–113.1 m/s). Before the profiled speed screen (session 33) both
    speed refits stalled (2ΔELBO 62 and 97) and a generic slow mode was named; in degrees,
    before the screen's gravity term was per degree (session 34), both stalled at 79 and 134.
    Now the speed dynamics lead, with Z_V of the size lift ∝ V² gives, in the model's unit."""
    spec = ROOT / "benchmarks" / "users" / f"{spec_name}.yaml"
    doc = _diagnose(spec, [flight_data_dir / "hfb320_1_10.csv"], tmp_path / "d",
                    effects=["speed_dynamics"], max_candidates=2, min_score=0.0,
                    noise_model=False)
    (f,) = doc["findings"]
    assert f["key"].startswith("speed_dynamics:alpha:q")
    ev = f["evidence"]
    assert ev["statistic"] > 10 * ev["threshold"]
    zv = f["parameters"]["D_ZV"]
    assert zv["unit"] == unit
    # −2g/V₀² at the record's mean airspeed 109.2 m/s: −0.00164 rad/m (the refits: −0.00194
    # and −0.00182 rad/m)
    ratio = zv["estimate"] * rad_per_unit / (-2 * G / 109.2 ** 2)
    assert 0.5 < ratio < 2.0
    assert doc["final"]["elbo"] > doc["base"]["elbo"]


@pytest.mark.slow
def test_attas_alpha_vane_on_the_noseboom(flight_data_dir, tmp_path):
    """With the accelerometer (which fixes the inertial α̇ − q) the α vane's position comes
    out in metres ahead of the CG near the noseboom of attas.constants.yaml (13.08 m); the
    finding holds on the validation record."""
    spec = ROOT / "benchmarks" / "real_records" / "attas_sp_az.yaml"
    doc = _diagnose(spec, [flight_data_dir / "attas_elv1.csv"], tmp_path / "d",
                    validate=[flight_data_dir / "attas_elv2.csv"],
                    effects=["sensor_position"], max_candidates=2)
    f = next(f for f in doc["findings"] if f["key"] == "sensor_position:alpha:q")
    x = f["parameters"]["D_POS_alpha_q"]
    assert x["unit"] == "m" and 9.0 < x["estimate"] < 15.0 and x["std_error"] < 1.0
    assert "13.08" in f["explanation"]
    assert f["evidence"]["validation_elbo_after"] > f["evidence"]["validation_elbo_before"]


@pytest.mark.slow
def test_attas_alpha_vane_in_metres_from_a_model_written_in_degrees(flight_data_dir, tmp_path):
    """A new user's ATTAS short period in degrees (benchmarks/users/attas_sp_deg.yaml: α, δe
    in deg, q in deg/s, the records' radians converted by the data map): the vane position is
    in metres, the same as the radian model's (11.49 ± 0.33 m, session 34: 11.49 ± 0.33 m,
    2ΔELBO 749.3, 52 s)."""
    spec = ROOT / "benchmarks" / "users" / "attas_sp_deg.yaml"
    doc = _diagnose(spec, [flight_data_dir / "attas_elv1.csv"], tmp_path / "d",
                    validate=[flight_data_dir / "attas_elv2.csv"],
                    effects=["sensor_position"], max_candidates=3, noise_model=False)
    f = next(f for f in doc["findings"] if f["key"] == "sensor_position:alpha:q")
    x = f["parameters"]["D_POS_alpha_q"]
    assert x["unit"] == "m" and abs(x["estimate"] - 11.49) < 3 * x["std_error"] < 1.5
    assert "13.08" in f["explanation"]


def test_an_output_modelling_a_force_gets_its_missing_derivatives(tmp_path):
    """An output equation with parameters of its own (a new user's a_y = V(Y_β β + Y_δr δr))
    gets a derivative candidate for every state and input it lacks; an output built on a
    coefficient definition shared with the drift, or a direct measurement, does not."""
    from vsidgen.discrepancy.catalogue import OutputDerivative
    from vsidgen.spec import compile_spec

    spec = tmp_path / "lat4.yaml"
    spec.write_text(textwrap.dedent("""
        name: lat4_user
        states:
          beta: {unit: rad}
          p: {unit: rad/s}
          r: {unit: rad/s}
          phi: {unit: rad}
        inputs:
          da: {unit: rad}
          dr: {unit: rad}
        outputs:
          beta: {unit: rad}
          p: {unit: rad/s}
          r: {unit: rad/s}
          ay: {unit: m/s^2}
        constants:
          V: {value: 100.0, unit: m/s}
        parameters:
          Yb: {unit: 1/s}
          Ydr: {unit: 1/s}
          Lp: {unit: 1/s}
          Nr: {unit: 1/s}
          Lda: {unit: 1/s^2}
          Ndr: {unit: 1/s^2}
        drift:
          beta: Yb*beta - r + Ydr*dr + 9.81/V*phi
          p: Lp*p + Lda*da
          r: Nr*r + Ndr*dr
          phi: p
        observations:
          beta: beta
          p: p
          r: r
          ay: V*(Yb*beta + Ydr*dr)
        data:
          time: t_s
          inputs: {da: da_rad, dr: dr_rad}
          outputs: {beta: beta_rad, p: p_radps, r: r_radps, ay: ay_mps2}
        """))
    info = model_info(spec, dt=0.04)
    cands = {c.key: c for c in OutputDerivative().applies_to(info)}
    assert set(cands) == {f"output_derivative:ay:{v}" for v in ("p", "r", "phi", "da")}
    c = cands["output_derivative:ay:r"]
    (p,) = c.parameters
    assert p.unit == "m/s^2/(rad/s)" and p.initial == 0.0 and c.target == "output:ay"
    assert c.info["regressor"] == "rate:r" and "not a sensor effect" in c.explanation
    # the candidate's spec: a_y gains D·r, nothing else changes; at D = 0 it is the model
    path = tmp_path / "cand.yaml"
    path.write_text(c.spec_yaml(spec, name="cand", candidate_path=path, info=info))
    sym, base = compile_spec(path), compile_spec(spec)
    obs = dict(zip([v.name for v in sym.outputs], sym.observations_expanded()))
    obs0 = dict(zip([v.name for v in base.outputs], base.observations_expanded()))
    d, r = sympy.Symbol(p.name, real=True), sympy.Symbol("r", real=True)
    diff = sympy.simplify(obs["ay"].subs({s: sympy.Symbol(s.name, real=True)
                                           for s in obs["ay"].free_symbols})
                          - obs0["ay"].subs({s: sympy.Symbol(s.name, real=True)
                                             for s in obs0["ay"].free_symbols}))
    assert sympy.simplify(diff - d * r) == 0
    assert [str(e) for e in sym.drift_expanded()] == [str(e) for e in base.drift_expanded()]
    # a shared coefficient definition (lat_beta: a_y = V0·Yside) or no output force: none
    lat = model_info(ROOT / "benchmarks" / "independent" / "specs" / "lat_beta.yaml", dt=0.04)
    assert OutputDerivative().applies_to(lat) == []
    assert OutputDerivative().applies_to(model_info(ROOT / "specs" / "hfb320.yaml", dt=0.1)) == []


# ---------------------------------------------------------------------------
# the profiled speed screen: its signals against an independent simulation
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("a", [0.0, -0.2, 0.05])
def test_lag_response_is_the_exact_response_to_a_piecewise_linear_signal(a):
    from scipy.integrate import solve_ivp

    from vsidgen.discrepancy.score import lag_response

    rng = np.random.default_rng(3)
    dt, n = 0.1, 120
    t = np.arange(n) * dt
    s = np.cumsum(rng.normal(size=n)) * 0.1
    ref = solve_ivp(lambda tt, y: a * y + np.interp(tt, t, s), (0.0, t[-1]), [0.0], t_eval=t,
                    rtol=1e-11, atol=1e-13, max_step=dt / 4).y[0]
    np.testing.assert_allclose(lag_response(s, dt, a), ref, rtol=0, atol=1e-8 * np.abs(ref).max())


@pytest.mark.parametrize("closure", ["attitude", "air"])
def test_speed_channels_combine_to_the_speed_equation_along_the_path(closure):
    """ΔV = κ F[α − α₀] − g F[γ_rel] + c F[1] (score.speed_channels) against an RK4 simulation
    (10 sub-steps, α and q linear between samples) of the candidate's own speed equation at
    its nesting point: ΔV̇ = X_V ΔV + X_α α − g γ, with γ = Δθ − α, Δθ̇ = q (attitude) or
    γ̇ = q − f_α(x, u) (air-relative), ΔV(0) = 0."""
    import types

    import jax.numpy as jnp

    from vsidgen.discrepancy.score import speed_channels, speed_path

    dt, n = 0.1, 300
    t = np.arange(n) * dt
    al = 0.1 + 0.02 * np.sin(0.7 * t) + 0.01 * np.sin(2.3 * t)
    q = 0.03 * np.cos(0.5 * t) - 0.01 * np.sin(1.9 * t)
    de = 0.01 * np.sign(np.sin(0.4 * t))
    mu = np.column_stack([al, q])
    za, zde, z0 = -0.8, -0.1, 0.05

    def drift(x, u, th):
        return jnp.stack([z0 + za * x[0] + x[1] + zde * u[0], -2.0 * x[0] - 1.2 * x[1]])
    model = types.SimpleNamespace(state_names=("alpha", "q"), drift=drift)
    rec = types.SimpleNamespace(y=np.zeros((n, 2)), t=t, dt=dt, u=de[:, None])
    current = types.SimpleNamespace(model=model, records=[rec], fit=types.SimpleNamespace(
        decision={"records": [{"mu": mu}]}, theta=np.zeros(1)))
    cand = types.SimpleNamespace(info={"states": ("alpha", "q"), "closure": closure})
    xv, xa, gam0 = -0.05, 3.0, 0.02
    F = speed_channels(speed_path(cand, current), xv)[0]

    # independent reference: RK4 with α, q (and f_α) linear between samples
    fa = z0 + za * al + q + zde * de
    rate = q if closure == "attitude" else q - fa

    def f(z, inp):
        a_t, r_t = inp
        gam = (z[1] - a_t) if closure == "attitude" else z[1]
        return np.array([xv * z[0] + xa * a_t - G * gam, r_t])
    # γ(0) = gam0: Δθ(0) = gam0 + α₀ (attitude), γ(0) = gam0 (air)
    start = [0.0, gam0 + al[0] if closure == "attitude" else gam0]
    t_fine = np.arange((n - 1) * 10 + 1) * (dt / 10)
    out = _rk4(f, start, t_fine, lambda tt: (np.interp(tt, t, al), np.interp(tt, t, rate)))[::10, 0]
    kappa = xa + G if closure == "attitude" else xa
    c = kappa * al[0] - G * gam0 - (G * al[0] if closure == "attitude" else 0.0)
    dv = kappa * F[0] - G * F[1] + c * F[2]
    # the screen's path angle is linear between samples, the reference's quadratic (q linear):
    # an O(T²) difference, 0.3 % of the speed's range here; a wrong sign or coefficient of
    # any of the three signals is 100 %
    np.testing.assert_allclose(dv, np.array(out), rtol=0, atol=5e-3 * np.ptp(out))



def _longitudinal_record(path, *, coupling: float, seed: int):
    """Independent numpy simulation of the linear longitudinal model (ΔV, α, q, θ) — RK4 on a
    10× finer grid, the elevator linear between samples, turbulence on α and q — with the
    speed coupling Z_V = −2g/V₀² × ``coupling`` and M_V = 0.002 × ``coupling``."""
    rng = np.random.default_rng(seed)
    dt, n, sub, v0 = 0.05, 1000, 10, 60.0
    t = np.arange(n) * dt
    de = np.zeros(n)
    for t0, w, amp in ((1, 1, 0.03), (2, 1, -0.03), (8, 6, 0.02), (25, 1, -0.03),
                       (26, 1, 0.03), (35, 8, -0.02)):
        de[(t >= t0) & (t < t0 + w)] = amp
    zv, mv = -2 * G / v0 ** 2 * coupling, 0.002 * coupling
    xv, xa, za, zde, ma, mq, mde = -0.02, 3.0 - G, -1.5, -0.2, -8.0, -2.5, -10.0

    def f(x, d):
        dv, a, q, th = x
        return np.array([xv * dv + xa * a - G * (th - a), za * a + q + zde * d + zv * dv,
                         ma * a + mq * q + mde * d + mv * dv, q])
    h = dt / sub
    x = np.zeros(4)
    X = np.empty((n, 4))
    for k in range(n):
        X[k] = x
        d0, d1 = de[k], de[min(k + 1, n - 1)]
        for j in range(sub):
            da, dm, db = (d0 + (d1 - d0) * (j + s) / sub for s in (0.0, 0.5, 1.0))
            k1 = f(x, da)
            k2 = f(x + h / 2 * k1, dm)
            k3 = f(x + h / 2 * k2, dm)
            k4 = f(x + h * k3, db)
            x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
            x[1:3] += np.array([0.002, 0.004]) * math.sqrt(h) * rng.standard_normal(2)
    _write_csv(path, {"t_s": t, "de_rad": de,
                      "alpha_rad": X[:, 1] + 0.0005 * rng.standard_normal(n),
                      "q_radps": X[:, 2] + 0.0005 * rng.standard_normal(n)})


@pytest.mark.parametrize("coupling", [0.0, 1.0])
def test_speed_screen_finds_a_left_out_phugoid_and_is_quiet_without_one(tmp_path, coupling):
    """The profiled speed screen (score.screen_speed) on a short-period model fitted to records
    of an independent four-state simulation: significant (p < 1e-6) when the speed couples
    into α and q as lift does (−2g/V₀²), and not (p > 1e-3) when it does not — the statistic is
    χ²₆ under the null, Bonferroni over the grid of speed dampings."""
    from vsidgen.discrepancy.refit import REFIT_DETERMINISTIC_STD
    from vsidgen.discrepancy.score import screen_speed
    from vsidgen.discrepancy.search import fit_spec, model_info_of, filter_start

    spec = tmp_path / "sp.yaml"
    spec.write_text(SP_SPEC)
    csv = tmp_path / "rec.csv"
    _longitudinal_record(csv, coupling=coupling, seed=11)
    st = fit_spec(spec, [csv], generated_dir=tmp_path / "gen", max_iter=300)
    cands = SpeedDynamics().applies_to(model_info_of(st))
    res = screen_speed(cands, st, det_std=REFIT_DETERMINISTIC_STD)
    att = res["speed_dynamics:alpha:q:attitude"]
    assert att.dof == 6 and att.multiplicity == len(att.profile) >= 5
    if coupling:
        assert att.statistic is not None and att.log10p > 6
        started = filter_start(next(c for c in cands if c.key.endswith("attitude")), att)
        init = {p.name: p.initial for p in started.parameters}
        # the refit starts at the profile's speed damping, the couplings at nesting
        assert init["D_XV"] == att.step["D_XV"] <= 0 and init["D_ZV"] == init["D_MV"] == 0.0
    else:
        for r in res.values():
            assert r.statistic is None or r.log10p < 3


def test_speed_finding_is_checked_against_the_lift_speed_coupling():
    """Effect.check_estimates of the speed class: Z_V against −2g/V₀² with V₀ the spec's own
    airspeed constant (m/s); near it the finding says "a phugoid", far from it (18 s.e., a
    tenth) that the candidate may absorb another slow mismatch; α in degrees: Z_V in deg/m,
    compared in rad/m; no sentence for an angle without an angle unit."""
    info = model_info(TOTTER, dt=0.02)
    eff = SpeedDynamics()
    att = next(c for c in eff.applies_to(info) if c.info["closure"] == "attitude")
    ref = -2 * G / 56.5227 ** 2
    near = eff.check_estimates(att, {"D_ZV": (0.97 * ref, 0.00029)})
    far = eff.check_estimates(att, {"D_ZV": (0.12 * ref, 0.0003)})
    assert f"{ref:.4g}" in near and "the speed coupling of a phugoid" in near
    assert "not the phugoid's speed coupling" in far
    assert eff.check_estimates(att, {}) == ""
    def unit(u, **info):
        return dataclasses.replace(att, parameters=att.parameters[:2] + (dataclasses.replace(
            att.parameters[2], unit=u),) + att.parameters[3:], info={**att.info, **info})
    deg = eff.check_estimates(unit("(deg)/m", angle_radians=math.pi / 180),
                              {"D_ZV": (0.97 * ref * 180 / math.pi, 0.00029 * 180 / math.pi)})
    assert deg == near
    assert eff.check_estimates(unit("(1)/m"), {"D_ZV": (ref, 0.0003)}) == ""
