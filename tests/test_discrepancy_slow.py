"""End-to-end ``vsidgen diagnose`` on synthetic ATTAS short-period data (slow: many fits)."""

from __future__ import annotations

import importlib.util
import json
import pathlib

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]


def _bench():
    spec = importlib.util.spec_from_file_location("diagnose_benchmark",
                                                  ROOT / "benchmarks" / "diagnose_benchmark.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.slow
def test_diagnose_names_concealed_missing_derivative(tmp_path):
    b = _bench()
    case = next(c for c in b.CASES if c.name == "missing_Mq")
    row = b.run_case(case, tmp_path / "mq", max_rounds=2, max_candidates=4)
    assert row["named_key"] == "missing_derivative:q:q", row
    doc = json.loads((tmp_path / "mq" / "diagnose" / "findings.json").read_text())
    f = doc["findings"][0]
    assert f["parameters"]["D_q_q"]["estimate"] == pytest.approx(-2.0, abs=0.3)
    assert f["evidence"]["statistic"] > f["evidence"]["threshold"]
    assert pathlib.Path(doc["final_spec"]).is_file()
    assert (tmp_path / "mq" / "diagnose" / "diagnose.html").read_text().count("data:image/png") >= 1


@pytest.mark.slow
def test_diagnose_clean_model_gives_empty_findings(tmp_path):
    b = _bench()
    case = next(c for c in b.CASES if c.name == "clean_attas")
    row = b.run_case(case, tmp_path / "clean", max_rounds=2, max_candidates=4)
    assert row["n_findings"] == 0, row
    doc = json.loads((tmp_path / "clean" / "diagnose" / "findings.json").read_text())
    assert doc["findings"] == [] and "No significant discrepancy" in doc["conclusion"]


@pytest.mark.slow
def test_diagnose_names_actuator_lag_after_staged_refit(tmp_path):
    """The lag candidate adds a state; the staged refit must converge and win (it used to lose)."""
    b = _bench()
    case = next(c for c in b.CASES if c.name == "de_lag")
    row = b.run_case(case, tmp_path / "lag", max_rounds=1, max_candidates=3, max_iter=200)
    assert row["named_key"] == "actuator_lag:de", row
    doc = json.loads((tmp_path / "lag" / "diagnose" / "findings.json").read_text())
    f = doc["findings"][0]
    assert f["parameters"]["D_TAU_de"]["estimate"] == pytest.approx(0.15, abs=0.04)
    assert f["evidence"]["converged"] is True
    for t in doc["rounds"][0]["trials"]:          # no refit ends below its nested reference start
        if t["refit"]["elbo_stage1"] is not None and t["refit"]["elbo_stage0"] is not None:
            assert t["refit"]["elbo_stage1"] >= t["refit"]["elbo_stage0"] - 1e-6
