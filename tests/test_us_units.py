"""Spec units of US flight-test practice: knots, g, pound-force, slug, pound, nautical miles.

Reference: the factors to SI are the exact definitions (1 kt = 1852/3600 m/s, g = 9.80665 m/s²,
1 lbf = 4.4482216152605 N, 1 lb = 0.45359237 kg, 1 slug = 1 lbf·s²/ft), and pint, which the data
map uses, must agree with them (a column converted to a spec unit and the estimator's unit
factors use the same numbers).
"""
from __future__ import annotations

import math

import pytest

from vsidgen.spec import compile_spec
from vsidgen.spec.dataunits import _quantity_unit
from vsidgen.spec.units import coherent, is_conversion_factor, parse_unit, same

EXACT = {"kt": 1852.0 / 3600.0, "g": 9.80665, "lbf": 4.4482216152605, "lb": 0.45359237,
         "slug": 4.4482216152605 / 0.3048, "nmi": 1852.0, "kt/s": 1852.0 / 3600.0,
         "lbf*ft": 4.4482216152605 * 0.3048, "slug*ft^2": 4.4482216152605 / 0.3048 * 0.3048 ** 2}


@pytest.mark.parametrize("unit", sorted(EXACT))
def test_factor_is_the_definition_and_pint_agrees(unit):
    f, shown = coherent(unit)
    assert f == pytest.approx(EXACT[unit], rel=1e-12)
    q = (1.0 * _quantity_unit(unit)).to_base_units()
    assert q.magnitude == pytest.approx(EXACT[unit], rel=1e-9)
    assert same(parse_unit(unit), parse_unit(shown))


def test_conversion_factors_to_compound_coherent_units_are_recognised():
    assert is_conversion_factor("m/s/kt") and is_conversion_factor("kt/(m/s)")
    assert is_conversion_factor("m/s^2/g") and not is_conversion_factor("kt")


SPEC = """\
name: us_{tag}
states:
  alpha: {{unit: deg}}
  q: {{unit: deg/s}}
inputs:
  de: {{unit: deg}}
outputs:
  alpha: {{unit: deg}}
  nz: {{unit: g}}
constants:
  V: {{value: 250.0, unit: kt}}
  KT: {{value: 0.514444, unit: {ktu}}}
  D2R: {{value: 0.0174533, unit: rad/deg}}
  G0: {{value: 9.80665, unit: m/s^2/g}}
parameters:
  ZAL: {{unit: 1/s}}
  MAL: {{unit: 1/s^2}}
  MQ: {{unit: 1/s}}
  MDE: {{unit: 1/s^2}}
drift:
  alpha: ZAL*alpha + q
  q: MAL*alpha + MQ*q + MDE*de
observations:
  alpha: alpha
  nz: V*KT*D2R*ZAL*alpha/G0
data:
  time: t
  inputs: {{de: de}}
  outputs: {{alpha: alpha, nz: nz}}
"""


def test_a_reference_speed_in_knots_used_through_its_factor_is_not_warned(tmp_path):
    """V in kt times a kt → m/s factor is right as written (the constant was warned by its
    unit's name alone); written without the factor it is wrong and warned."""
    ok = tmp_path / "ok.yaml"
    ok.write_text(SPEC.format(tag="ok", ktu="m/s/kt"))
    assert [w.code for w in compile_spec(ok).warnings if w.code == "noncoherent_unit"] == []
    bad = tmp_path / "bad.yaml"
    bad.write_text(SPEC.format(tag="bad", ktu="1").replace("V*KT*D2R", "V*D2R"))
    warned = compile_spec(bad).warnings
    assert any(w.code == "noncoherent_unit" and "constant `V` is 250 kt" in str(w) for w in warned)
    assert any(w.code == "unit_scale" and "observation of `nz`" in str(w) for w in warned)
