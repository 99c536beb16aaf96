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
