"""A new user's lateral accelerometer written as a load factor beside a bias in `g` (session 47):
one dimension warning at the observation, with a hint about load factors, and no second
"unit system" warning at the same place that read as contradicting it."""

from vsidgen.spec import compile_spec

SPEC = """\
name: ay_in_g
states:
  beta: {unit: rad}
  r: {unit: rad/s}
inputs:
  dr: {unit: rad}
outputs:
  beta_m: {unit: rad}
  ay_m: {unit: g}
constants:
  V0: {value: 72.0, unit: m/s}
  g0: {value: 9.80665, unit: m/s^2}
parameters:
  Yb: {unit: 1/s}
  Ydr: {unit: 1/s}
  Nr: {unit: 1/s}
  Ndr: {unit: 1/s^2}
  ay0: {unit: g}
definitions:
  side: Yb*beta + Ydr*dr
drift:
  beta: side - r
  r: Nr*r + Ndr*dr
observations:
  beta_m: beta
  ay_m: V0*side/g0 + ay0
data:
  time: t
  inputs: {dr: dr}
  outputs: {beta_m: b, ay_m: ay}
"""


def _warnings(tmp_path, text):
    p = tmp_path / "s.yaml"
    p.write_text(text)
    return compile_spec(p).warnings


def test_one_warning_at_the_observation_with_a_load_factor_hint(tmp_path):
    ws = _warnings(tmp_path, SPEC)
    at_obs = [w for w in ws if w.line == SPEC.splitlines().index("  ay_m: V0*side/g0 + ay0") + 1]
    assert [w.code for w in at_obs] == ["units"], [str(w) for w in at_obs]
    assert "load factor" in at_obs[0].hint and "dimension 1" in at_obs[0].message


def test_scale_warning_kept_where_dimensions_agree(tmp_path):
    # beta in deg beside r in rad/s: same dimension, different unit systems: the scale
    # warning is the only one and stays
    text = SPEC.replace("beta: {unit: rad}\n  r:", "beta: {unit: deg}\n  r:")
    ws = _warnings(tmp_path, text)
    assert any(w.code == "unit_scale" for w in ws), [str(w) for w in ws]
