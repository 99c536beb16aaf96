"""A lift derivative left out of the coefficient model, found where it was left out.

The record comes from the independent simulator (``benchmarks/independent/sim.py``: numpy
body-axis HFB-320 physics, RK4 at 2 ms, inputs moving between samples, Dryden gusts,
quantised sensors; it shares no code with vsidgen) with the lift due to elevator
``CL_δe = 0.5 /rad`` that ``specs/hfb320.yaml`` does not have. Lift enters the α equation
and both accelerometers, so the physical candidate is a derivative of the *coefficient*
``CL`` (``coefficient_derivative:CL:de``), not a free term in one equation or a sensor effect
(before this effect existed, diagnose named an accelerometer position: issue 15).
"""

from __future__ import annotations

import pathlib
import sys

import pytest

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "benchmarks" / "independent"))
import sim  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parents[1]
TRUTH = 0.5


@pytest.mark.slow  # a whole HFB-320 diagnose round: 1294 s on the loaded 2-core machine (passed)
def test_missing_lift_derivative_is_named_on_the_coefficient(tmp_path):
    from vsidgen.discrepancy import run_diagnose

    cols, _ = sim.simulate_hfb(effect="missing_CLde", magnitude=TRUTH, seed=0)
    csv = tmp_path / "rec.csv"
    sim.write_csv(csv, cols)
    res = run_diagnose(ROOT / "specs" / "hfb320.yaml", [csv], out=tmp_path / "out", max_rounds=1,
                       max_candidates=3, effects=["coefficient_derivative", "missing_derivative",
                                                  "sensor_position", "time_skew"],
                       workers=1)
    assert res.findings, res.document["conclusion"]
    f = res.findings[0]
    assert f["key"] == "coefficient_derivative:CL:de", [g["key"] for g in res.findings]
    est = f["parameters"]["D_CL_de"]
    assert est["unit"] == "1/(rad)"
    assert abs(est["estimate"] - TRUTH) < 3 * est["std_error"], est
