"""A constant outside the range of a column that records the same quantity is warned of
(``DataWarningCode.CONSTANT_OUTSIDE_RECORD``): a trim airspeed from another flight, a unit slip."""

from __future__ import annotations

import numpy as np
import pytest

from vsidgen.data import load_record
from vsidgen.spec import compile_spec
from vsidgen.spec.dataunits import DataWarningCode, column_stem

SPEC = """
name: const_range
states:
  q: {{unit: rad/s}}
inputs:
  de: {{unit: rad}}
outputs:
  q: {{unit: rad/s}}
constants:
  V: {{value: {V}, unit: m/s}}
  mass: {{value: 5000, unit: kg}}
parameters:
  Mq: {{unit: 1/s}}
  Mde: {{unit: 1/s^2}}
drift:
  q: Mq*q + Mde*de*V/70{mass_use}
observations:
  q: q
noise:
  process: {{states: [q], estimate: true}}
data:
  time: t_s
  inputs: {{de: de_rad}}
  outputs: {{q: q_radps}}
"""


def _case(tmp_path, *, V=60.0, speed_col="v_mps", speed=None, mass_use=""):
    spec = tmp_path / "s.yaml"
    spec.write_text(SPEC.format(V=V, mass_use=mass_use))
    n = 50
    t = 0.1 * np.arange(n)
    rng = np.random.default_rng(0)
    v = 72.0 + np.sin(t) if speed is None else speed
    cols = {"t_s": t, "de_rad": 0.01 * np.sin(2 * t), "q_radps": rng.normal(0, 0.01, n),
            speed_col: v, "mass_kg": np.full(n, 5000.0)}
    lines = [",".join(cols)] + [",".join(c[k] if isinstance(c[k], str) else repr(float(c[k]))
                                         for c in cols.values()) for k in range(n)]
    data = tmp_path / "r.csv"
    data.write_text("\n".join(lines) + "\n")
    rec = load_record(compile_spec(spec), data)
    return [w for w in rec.warnings if w.code is DataWarningCode.CONSTANT_OUTSIDE_RECORD]


@pytest.mark.parametrize("column, stem", [("v_mps", "v"), ("mass_kg", "mass"), ("V (kts)", "V"),
                                          ("alpha_deg_s", "alpha"), ("t_s", "t"),
                                          ("airspeed", "airspeed"), ("p_radps2", "p"),
                                          ("rho_kgpm3", "rho"), ("ixx_kgm2", "ixx"),
                                          ("qbar_pa", "qbar")])
def test_column_stem(column, stem):
    assert column_stem(column) == stem


def test_constant_outside_the_recorded_range_is_named(tmp_path):
    w = _case(tmp_path, V=60.0)
    assert len(w) == 1 and w[0].channel == "V"
    assert "`V` = 60 m/s" in w[0].message and "`v_mps`" in w[0].message
    assert "mean 72" in w[0].hint and "inputs" in w[0].hint


def test_constant_inside_the_range_is_not(tmp_path):
    assert _case(tmp_path, V=72.0) == []


def test_column_in_other_units_is_converted(tmp_path):
    # 140 kt ≈ 72 m/s: V = 72 m/s lies inside, V = 140 m/s (the knots typed as m/s) does not
    kts = 140.0 + np.sin(0.1 * np.arange(50))
    assert _case(tmp_path, V=72.0, speed_col="v_kts", speed=kts) == []
    w = _case(tmp_path, V=140.0, speed_col="v_kts", speed=kts)
    assert len(w) == 1 and "converted from knot" in w[0].message


def test_unused_constant_and_other_dimensions_are_left_alone(tmp_path):
    # `mass` is unused (already warned of as unused); a column `v_deg` has another dimension
    assert _case(tmp_path, V=60.0, speed_col="v_deg") == []
    w = _case(tmp_path, V=72.0, mass_use=" + 0*mass")
    assert w == []                       # 5000 kg lies in the (constant) recorded mass


def test_a_text_column_named_like_a_constant_does_not_break_loading(tmp_path):
    w = _case(tmp_path, V=60.0, speed=np.array(["fast"] * 50, dtype=object))
    assert w == []


def test_a_constant_written_to_fewer_digits_than_the_column_is_inside(tmp_path):
    """`Iyy: 32920.6` against a column that records 32920.6156 throughout was warned "outside
    the range (32920.6 … 32920.6)" (session 44, a new user). A constant agrees with the
    record to the digits it is written with (half a unit of its last digit); 32920.5 does
    not."""
    from vsidgen.spec.dataunits import written_half_digit

    assert written_half_digit(32920.6) == pytest.approx(0.05)
    assert written_half_digit(0.001) == pytest.approx(5e-4)
    flat = np.full(50, 72.0156)
    assert _case(tmp_path, V=72.0, speed=flat) == []
    assert len(_case(tmp_path, V=71.9, speed=flat)) == 1
