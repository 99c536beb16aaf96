"""Physical parameterisations of the diagnose catalogue: sensor positions in metres with the
model's own airspeed (local air velocity v + ω × r; specific force a + ω̇ × r)."""

from __future__ import annotations

import pathlib

import pytest
import sympy

from vsidgen.discrepancy.base import model_info, propose

ROOT = pathlib.Path(__file__).resolve().parents[1]
HFB = ROOT / "specs" / "hfb320.yaml"
ATTAS = ROOT / "specs" / "attas_sp.yaml"
LAT = ROOT / "benchmarks" / "independent" / "specs" / "lat_beta.yaml"


def _candidate(spec, key):
    info = model_info(spec, dt=0.05)
    return info, next(c for c in propose(info) if c.key == key)


def _observation(spec, cand, output, tmp_path):
    from vsidgen.symbolic import compile_spec

    p = tmp_path / "cand.yaml"
    p.write_text(cand.spec_yaml(spec, name="cand_pos", candidate_path=p))
    sym = compile_spec(p)
    i = [v.name for v in sym.outputs].index(output)
    return sym, sym.observations_expanded()[i]


def _subs(sym, values):
    names = {s.name: s for s in sym.observations_expanded()[0].free_symbols}
    for e in sym.observations_expanded() + sym.drift_expanded():
        names.update({s.name: s for s in e.free_symbols})
    return {names[k]: v for k, v in values.items() if k in names}


def test_alpha_vane_lever_arm_in_metres_with_the_model_airspeed(tmp_path):
    _, c = _candidate(HFB, "sensor_position:alpha:q")
    (p,) = c.parameters
    assert p.unit == "m" and "ahead of the CG" in p.description
    sym, h = _observation(HFB, c, "alpha", tmp_path)
    vals = {"alpha": 0.1, "q": 0.05, "V": 100.0, "theta": 0.0, p.name: 8.0}
    got = float(h.xreplace(_subs(sym, vals)))
    # a vane 8 m ahead of the CG pitching up at 0.05 rad/s at 100 m/s reads 0.004 rad less
    assert got == pytest.approx(0.1 - 8.0 * 0.05 / 100.0, abs=1e-15)


def test_beta_vane_on_a_nose_boom_uses_the_trim_speed_constant(tmp_path):
    _, c = _candidate(LAT, "sensor_position:beta:r")
    (p,) = c.parameters
    assert p.unit == "m"
    sym, h = _observation(LAT, c, "beta", tmp_path)
    vals = {"beta": 0.02, "r": 0.1, "V0": 100.0, p.name: 6.0}
    got = float(h.xreplace(_subs(sym, vals)))
    # v + r x: a yaw rate to the right raises the sideslip seen ahead of the CG
    assert got == pytest.approx(0.02 + 6.0 * 0.1 / 100.0, abs=1e-15)


def test_accelerometer_ahead_of_the_cg_reads_minus_x_qdot(tmp_path):
    _, c = _candidate(HFB, "sensor_position:az:q")
    (p,) = c.parameters
    assert p.unit == "m" and "ahead of the CG" in p.description
    sym, h = _observation(HFB, c, "az", tmp_path)
    slope = sympy.diff(h, [s for s in h.free_symbols if s.name == p.name][0])
    i_q = [v.name for v in sym.states].index("q")
    assert sympy.simplify(slope + sym.drift_expanded()[i_q]) == 0   # ∂az/∂x = −q̇


def test_vane_without_an_airspeed_keeps_seconds():
    _, c = _candidate(ATTAS, "sensor_position:alpha:q")
    assert c.parameters[0].unit == "s"
