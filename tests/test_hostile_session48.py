"""Hostile inputs found by the session-48 red team (the defects that have no nearer home)."""

from __future__ import annotations

import math
import re

import pytest
from test_hostile_session47 import DATA, SPEC, _in_tmp, _run  # noqa: F401  (autouse fixture)


@pytest.mark.parametrize("col, expr, factor", [
    ("e", "exp(1)*e", math.e),            # the printer writes E as `e`: it computed e·e
    ("reduce", "min(reduce, 1)", 1.0),    # Min prints as reduce(minimum, …): not callable
    ("arcsin", "asin(arcsin)", None),     # asin prints as arcsin
])
def test_a_column_named_like_a_numpy_printer_name_is_read_as_the_column(tmp_path, capsys,
                                                                          col, expr, factor):
    spec = tmp_path / "s.yaml"
    spec.write_text(SPEC.replace("    de: de_rad", f'    de: {{expr: "{expr}"}}', 1))
    csv = tmp_path / "d.csv"
    csv.write_text("\n".join([DATA[0].replace("de_rad", col), *DATA[1:]]) + "\n")
    code, out, err = _run(capsys, "check", str(spec), "--data", str(csv))
    assert code == 0, err
    de = [float(r.split(",")[1]) for r in DATA[1:]]
    lo, hi = re.search(r"input de: (\S+) \.\. (\S+) rad", out).groups()
    want = [math.asin(v) for v in de] if factor is None else [factor * v for v in de]
    if col == "reduce":
        want = [min(v, 1.0) for v in de]
    assert float(lo) == pytest.approx(min(want), rel=1e-5)
    assert float(hi) == pytest.approx(max(want), rel=1e-5)
