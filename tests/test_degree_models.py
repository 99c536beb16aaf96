"""A model written in degrees gets the physical candidates in physical units: vane and
accelerometer positions in metres, the speed equation in m/s with gravity along the path.

Reference: the same model written in radians. Angles and rates of the degree model are the
radian model's × 180/π; the added terms must then predict the same physical quantity.
"""
from __future__ import annotations

import math

import pytest
import sympy

from vsidgen.discrepancy.base import model_info, propose
from vsidgen.spec import compile_spec

D = 180.0 / math.pi

SPEC = """\
name: sp_{tag}
states:
  alpha: {{unit: {au}, description: angle of attack}}
  q: {{unit: {qu}, description: pitch rate}}
inputs:
  de: {{unit: {au}, description: elevator}}
outputs:
  alpha: {{unit: {au}}}
  q: {{unit: {qu}}}
  az: {{unit: m/s^2, description: normal acceleration}}
constants:
  V0: {{value: 100.0, unit: m/s}}
parameters:
  ZAL: {{}}
  ZQ: {{}}
  ZDE: {{}}
  MAL: {{}}
  MQ: {{}}
  MDE: {{}}
  AZAL: {{}}
drift:
  alpha: ZAL*alpha + (1 + ZQ)*{q_in_alpha} + ZDE*de
  q: MAL*{alpha_in_q} + MQ*q + MDE*{de_in_q}
observations:
  alpha: alpha
  q: q
  az: AZAL*alpha
data:
  time: t
  inputs: {{de: de}}
  outputs: {{alpha: alpha, q: q, az: az}}
"""


def _spec(tmp_path, tag, au, qu):
    """The short-period model with α (and δe) in ``au`` and q in ``qu``; its equations hold
    the same physics in every unit (conversions written where the units differ)."""
    k = D if (au, qu) == ("deg", "rad/s") else 1.0
    text = SPEC.format(tag=tag, au=au, qu=qu,
                       q_in_alpha="q" if k == 1.0 else f"{D!r}*q",
                       alpha_in_q="alpha" if k == 1.0 else f"alpha/{D!r}",
                       de_in_q="de" if k == 1.0 else f"de/{D!r}")
    p = tmp_path / f"{tag}.yaml"
    p.write_text(text)
    return p


def _candidate_model(path, key, tmp_path):
    info = model_info(path, dt=0.02)
    c = next(c for c in propose(info) if c.key == key)
    out = tmp_path / f"{path.stem}_{key.replace(':', '_')}.yaml"
    out.write_text(c.spec_yaml(path, name="cand", candidate_path=out))
    return c, compile_spec(out)


def _eval(sym, expr, values):
    names = {}
    for e in sym.observations_expanded() + sym.drift_expanded():
        names.update({s.name: s for s in e.free_symbols})
    return float(expr.xreplace({names[k]: v for k, v in values.items() if k in names}))


# a physical point: α = 0.05 rad, q = 0.1 rad/s, δe = −0.02 rad; the linear model's
# coefficients (per second) are the same in every consistent unit
RAD = {"alpha": 0.05, "q": 0.1, "de": -0.02}
THETA = {"ZAL": -1.2, "ZQ": -0.05, "ZDE": -0.1, "MAL": -6.0, "MQ": -2.0, "MDE": -9.0,
         "AZAL": -110.0, "V0": 100.0}
UNITS = [("rad", "rad", "rad/s"), ("deg", "deg", "deg/s"), ("mixed", "deg", "rad/s")]


def _point(au, qu):
    return {"alpha": RAD["alpha"] * (D if au == "deg" else 1), "de": RAD["de"] * (D if au == "deg" else 1),
            "q": RAD["q"] * (D if qu == "deg/s" else 1)}


def _position(tmp_path, tag, au, qu, key, output):
    """The position candidate ``key`` of the model in these units: its parameter (in metres)
    and the candidate model's expression of ``output``."""
    c, sym = _candidate_model(_spec(tmp_path, tag, au, qu), key, tmp_path)
    (p,) = c.parameters
    assert p.unit == "m"
    return p, sym, sym.observations_expanded()[[v.name for v in sym.outputs].index(output)]


@pytest.mark.parametrize("tag, au, qu", UNITS)
def test_vane_position_in_metres_in_any_angle_unit(tmp_path, tag, au, qu):
    p, sym, h = _position(tmp_path, tag, au, qu, "sensor_position:alpha:q", "alpha")
    got = _eval(sym, h, {**_point(au, qu), **THETA, p.name: 8.0})
    # a vane 8 m ahead reads α − x q/V, in the vane's unit
    want = (RAD["alpha"] - 8.0 * RAD["q"] / 100.0) * (D if au == "deg" else 1.0)
    assert got == pytest.approx(want, rel=1e-12)


@pytest.mark.parametrize("tag, au, qu", UNITS)
def test_accelerometer_arm_in_metres_in_any_rate_unit(tmp_path, tag, au, qu):
    p, sym, h = _position(tmp_path, tag, au, qu, "sensor_position:az:q", "az")
    x = [s for s in h.free_symbols if s.name == p.name][0]
    slope = _eval(sym, sympy.diff(h, x), {**_point(au, qu), **THETA})
    # ∂az/∂x = −q̇ in rad/s² at the physical point
    qdot = THETA["MAL"] * RAD["alpha"] + THETA["MQ"] * RAD["q"] + THETA["MDE"] * RAD["de"]
    assert slope == pytest.approx(-qdot, rel=1e-12)


@pytest.mark.parametrize("closure", ["", ":attitude"])
@pytest.mark.parametrize("tag, au, qu", UNITS)
def test_speed_equation_in_metres_per_second_in_any_angle_unit(tmp_path, tag, au, qu, closure):
    path = _spec(tmp_path, tag, au, qu)
    c, sym = _candidate_model(path, "speed_dynamics:alpha:q" + closure, tmp_path)
    names = [v.name for v in sym.states]
    dv = next(n for n in names if n.startswith("D_dV"))
    ang = next(n for n in names if n.startswith(("D_dgamma", "D_dtheta")))
    f_dv = sym.drift_expanded()[names.index(dv)]
    f_ang = sym.drift_expanded()[names.index(ang)]
    k = D if au == "deg" else 1.0
    kq = D if qu == "deg/s" else 1.0
    # gravity along the path: ∂ΔV̇/∂(path or attitude angle) = −g per radian
    s_ang = [s for s in f_dv.free_symbols if s.name == ang][0]
    assert float(sympy.diff(f_dv, s_ang)) * k == pytest.approx(-c.info["gravity"], rel=1e-12)
    # the angle state moves with q in α's unit (k/kq per unit of q): the attitude by q itself,
    # the air-relative path angle by q less the α equation's (1 + ZQ) q, i.e. by −ZQ q
    s_q = [s for s in f_ang.free_symbols if s.name == "q"][0]
    dq = _eval(sym, sympy.diff(f_ang, s_q), THETA)
    want = (1.0 if closure else -THETA["ZQ"]) * k / kq
    assert dq == pytest.approx(want, rel=1e-12)


@pytest.mark.parametrize("kind", ["vane", "speed"])
def test_positions_and_speed_equation_in_si_when_the_trim_speed_is_in_knots(tmp_path, kind):
    """V0 written as 194.38 kt (= 100 m/s): the vane's arm over V is in metres and the speed
    candidate's trim airspeed in m/s, exactly as with V0 in m/s (session 45: the arm came out
    in kt·s, 21.36 'm' for an 10.99 m vane on a user's ATTAS model in knots)."""
    kt = 1852.0 / 3600.0
    out = {}
    for tag, v0 in (("ms", "{value: 100.0, unit: m/s}"), ("kt", f"{{value: {100.0 / kt!r}, unit: kt}}")):
        path = _spec(tmp_path, f"v_{tag}", "deg", "deg/s")
        path.write_text(path.read_text().replace("V0: {value: 100.0, unit: m/s}", "V0: " + v0))
        key = "sensor_position:alpha:q" if kind == "vane" else "speed_dynamics"
        info = model_info(path, dt=0.02)
        c = next(c for c in propose(info) if c.key == key or c.key.startswith(key))
        cand = tmp_path / f"cand_{tag}.yaml"
        cand.write_text(c.spec_yaml(path, name=f"cand_{tag}", candidate_path=cand))
        sym = compile_spec(cand)
        vals = {**_point("deg", "deg/s"), **THETA, "V0": 100.0 if tag == "ms" else 100.0 / kt}
        vals.update({q.name: 0.7 for q in c.parameters})
        exprs = sym.observations_expanded() + sym.drift_expanded()
        names = {}
        for e in exprs:
            names.update({s.name: s for s in e.free_symbols})
        vals.update({n: 0.3 for n in names if n not in vals})   # added states (speed perturbation)
        out[tag] = [_eval(sym, e, vals) for e in exprs]
    assert out["kt"] == pytest.approx(out["ms"], rel=1e-12)
