"""Which variable is α, β, p, q, r, V, az — by name or, for names users invent, by the
description they give (``a: {description: angle of attack}``).

The catalogue, locate and the findings' texts ask these roles; a model whose states are named
``aa``/``pr`` but described as angle of attack and pitch rate must get the same candidates
as the same model written with ``alpha``/``q``.
"""
from __future__ import annotations

import re

import numpy as np
import pytest

from vsidgen.discrepancy.base import model_info, propose, roles_of, variable_role
from vsidgen.discrepancy.locate import state_regressors

USER_SPEC = """\
name: my_sp
states:
  aa: {unit: rad, description: Angle of attack}
  pr: {unit: rad/s, description: body pitch rate}
inputs:
  de: {unit: rad, description: elevator}
outputs:
  aa_vane: {unit: rad, description: angle-of-attack vane}
  pr_gyro: {unit: rad/s, description: pitch rate gyro}
  nzacc: {unit: m/s^2, description: normal acceleration at the CG}
constants:
  V0: {value: 110.0, unit: m/s}
parameters:
  Z0: {}
  ZAL: {}
  ZQ: {}
  ZDE: {}
  M0: {}
  MAL: {}
  MQ: {}
  MDE: {}
drift:
  aa: Z0 + ZAL*aa + (1 + ZQ)*pr + ZDE*de
  pr: M0 + MAL*aa + MQ*pr + MDE*de
observations:
  aa_vane: aa
  pr_gyro: pr
  nzacc: V0*(ZAL*aa + ZDE*de)
data:
  time: t
  inputs: {de: de}
  outputs: {aa_vane: aa, pr_gyro: pr, nzacc: nz}
"""
RENAME = [("aa_vane", "alpha"), ("pr_gyro", "q"), ("nzacc", "az"), ("aa", "alpha"), ("pr", "q")]


def _canonical(text: str) -> str:
    for a, b in RENAME:
        text = re.sub(rf"(?<![A-Za-z0-9_]){a}(?![A-Za-z0-9_])", b, text)
    return text


@pytest.mark.parametrize("name, description, role", [
    ("alpha", "", "alpha"), ("AoA", "", "alpha"), ("alpha_rad", "", "alpha"),
    ("alfa_deg", "", "alpha"), ("a", "angle of attack", "alpha"),
    ("a", "Angle-of-attack, rad", "alpha"), ("x1", "incidence", "alpha"),
    ("b", "sideslip angle", "beta"), ("Q", "", "q"), ("w", "body-axis pitch rate", "q"),
    ("x3", "yaw rate (gyro)", "r"), ("s", "true airspeed", "V"), ("VTAS", "", "V"),
    ("n", "normal acceleration", "az"), ("ay_b", "", "ay"),
    # a rate, a command or a trim value of the quantity is not the quantity
    ("a", "angle of attack rate", None), ("x1", "pitch rate command", None),
    ("x", "trim angle of attack", None), ("az_cmd", "", None), ("u", "body x velocity", None),
    ("x", "", None),
])
def test_variable_role(name, description, role):
    assert variable_role(name, description) == role


def test_roles_unique_and_names_first():
    class V:
        def __init__(self, name, description=""):
            self.name, self.description = name, description
    # the state named alpha wins over one only described as angle of attack
    r = roles_of([V("a2", "angle of attack (second vane)"), V("alpha"), V("pr", "pitch rate")])
    assert r == {"alpha": "alpha", "pr": "q"}


def test_user_names_get_the_canonical_candidates(tmp_path):
    user = tmp_path / "user_sp.yaml"
    user.write_text(USER_SPEC)
    canon = tmp_path / "canon_sp.yaml"
    canon.write_text(_canonical(USER_SPEC))
    a, b = model_info(user, dt=0.04), model_info(canon, dt=0.04)
    assert a.state_roles == {"aa": "alpha", "pr": "q"}
    assert a.output_roles == {"aa_vane": "alpha", "pr_gyro": "q", "nzacc": "az"}
    keys_user = {_canonical(c.key) for c in propose(a)}
    keys_canon = {c.key for c in propose(b)}
    assert keys_user == keys_canon
    effects = {c.effect for c in propose(a)}
    # what a name-only reading missed on this model
    assert {"sensor_position", "speed_dynamics", "unsteady_aero", "unmodelled_wind"} <= effects


def test_locate_regressors_follow_roles():
    rng = np.random.default_rng(0)
    X, U = rng.standard_normal((200, 2)), rng.standard_normal((200, 1))
    Xd, Ud = rng.standard_normal((200, 2)), rng.standard_normal((200, 1))
    seg = [slice(0, 200)]
    by_role = state_regressors(["aa", "pr"], ["de"], X, U, Xd, Ud, dt=0.04, seg=seg,
                               roles={"aa": "alpha", "pr": "q"})
    named = state_regressors(["alpha", "q"], ["de"], X, U, Xd, Ud, dt=0.04, seg=seg)
    assert {_canonical(k) for k in by_role} == set(named)
    for k, v in by_role.items():
        np.testing.assert_allclose(v, named[_canonical(k)])
    # without roles the invented names are no flow angles: no α squares, products, speed proxy
    plain = state_regressors(["aa", "pr"], ["de"], X, U, Xd, Ud, dt=0.04, seg=seg)
    assert "sq:aa" not in plain and "speed:kin" not in plain


def test_a_velocity_component_is_not_the_airspeed():
    """`v` described as the lateral velocity, or beside `u`/`w` (body axes), is a component;
    `V: true airspeed` or a lone `v` is the airspeed."""
    class V:
        def __init__(self, name, description=""):
            self.name, self.description = name, description
    assert variable_role("v", "lateral velocity (body y)") is None
    assert variable_role("V", "true airspeed") == "V"
    assert roles_of([V("v", "side velocity"), V("p"), V("r")]) == {"p": "p", "r": "r"}
    assert roles_of([V("u"), V("v"), V("w"), V("q")]) == {"q": "q"}
    assert roles_of([V("V"), V("alpha"), V("q")]) == {"V": "V", "alpha": "alpha", "q": "q"}


def test_a_trim_speed_constant_named_u_gives_the_vane_in_metres(tmp_path):
    """A new user's lateral model with the trim speed as a constant `U` (and a β vane output
    named `b_vane`, described as the sideslip vane): the vane candidate divides by U and its
    distance is in metres, not seconds."""
    text = USER_SPEC.replace("  V0: {value: 110.0, unit: m/s}", "  U: {value: 110.0, unit: m/s}")
    text = text.replace("V0*(", "U*(")
    spec = tmp_path / "u.yaml"
    spec.write_text(text)
    c = next(c for c in propose(model_info(spec, dt=0.04))
             if c.key == "sensor_position:aa_vane:pr")
    assert c.parameters[0].unit == "m"
    assert c.add_terms["observations"]["aa_vane"].endswith("*pr/U")
