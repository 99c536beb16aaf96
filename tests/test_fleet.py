"""``vsidgen fleet``: one results directory per record, fitted on a 2-worker LocalCluster."""

from __future__ import annotations

import json
import pathlib

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
SPEC = ROOT / "specs" / "attas_sp.yaml"
RECS = [ROOT / "data" / "attas_sp_synthetic.csv", ROOT / "data" / "attas_sp_synthetic_val.csv"]


@pytest.mark.slow
def test_fleet_on_two_workers_matches_single_fits_and_isolates_a_bad_record(tmp_path, capsys,
                                                                            monkeypatch):
    from vsidgen.cli import main
    from vsidgen.fitjob import run_fit

    monkeypatch.setenv("VSIDGEN_CACHE_DIR", "")
    bad = tmp_path / "bad.csv"
    bad.write_text("t_s,nothing\n0,1\n0.04,2\n")
    out = tmp_path / "fleet"
    rc = main(["fleet", str(SPEC), *map(str, RECS), str(bad), str(RECS[0]), "--out", str(out),
               "--workers", "2", "--max-iter", "4", "--quiet"])
    assert rc == 2                                   # one record had bad input
    doc = json.loads((out / "fleet.json").read_text())
    assert doc["complete"] and "2 worker" in doc["engine"]
    rows = {r["record"]: r for r in doc["records"]}
    assert list(rows) == ["attas_sp_synthetic", "attas_sp_synthetic_val", "bad",
                          "attas_sp_synthetic_2"]
    assert rows["bad"]["status"] == "bad_input" and "column" in rows["bad"]["error"]
    for name, rec in (("attas_sp_synthetic", RECS[0]), ("attas_sp_synthetic_val", RECS[1]),
                      ("attas_sp_synthetic_2", RECS[0])):
        r = rows[name]
        # 4 per noise start, and 4 more for the highest start stopped at its limit when no start
        # converged (estimator.fit._start_to_continue; the bound predates it)
        assert r["status"] == "not_converged" and 4 <= r["iterations"] <= 16
        res = json.loads((out / name / "results.json").read_text())
        assert res["elbo"] == pytest.approx(r["elbo"], rel=1e-12)
        assert res["records"]["estimation"][0]["path"].endswith(rec.name)
    # the same fit in this process, independently of the engine
    ref = run_fit(SPEC, [RECS[1]], out=tmp_path / "single", max_iter=4)
    assert rows["attas_sp_synthetic_val"]["elbo"] == pytest.approx(ref.results["elbo"], rel=1e-9)
    text = capsys.readouterr().out
    assert "4 records, 0 converged" in text and "bad: bad_input" in text


def test_fleet_bad_records_only_serial(tmp_path, capsys):
    """No fit can start: every record is reported as bad input, fleet.json is complete, exit 2;
    a bad spec is an error before anything runs."""
    from vsidgen.cli import main

    bad = tmp_path / "bad.csv"
    bad.write_text("t_s,nothing\n0,1\n0.04,2\n")
    out = tmp_path / "fleet"
    assert main(["fleet", str(SPEC), str(bad), str(bad), "--out", str(out), "--workers", "1",
                 "--quiet"]) == 2
    doc = json.loads((out / "fleet.json").read_text())
    assert doc["complete"] and [r["status"] for r in doc["records"]] == ["bad_input"] * 2
    assert [r["record"] for r in doc["records"]] == ["bad", "bad_2"]
    spec = tmp_path / "broken.yaml"
    spec.write_text("name: broken\nstates: [\n")
    assert main(["fleet", str(spec), str(bad), "--out", str(tmp_path / "f2")]) == 2
    assert not (tmp_path / "f2").exists()
    assert main(["fleet", str(SPEC), str(bad), "--out", str(tmp_path / "f3"),
                 "--workers", "0"]) == 2


def test_fleet_follows_the_results_directory_rules(tmp_path, capsys):
    """A folder with the user's files (their own fleet.json among them) is refused without
    --overwrite, and with it only vsidgen's files are written (the user's stay); options a
    fit refuses are refused too. Records with bad input: no fit runs (fast)."""
    from vsidgen.cli import main

    bad = tmp_path / "bad.csv"
    bad.write_text("t_s,nothing\n0,1\n0.04,2\n")
    user = tmp_path / "user"
    user.mkdir()
    (user / "fleet.json").write_text("my own notes")
    (user / "notes.txt").write_text("keep me")
    argv = ["fleet", str(SPEC), str(bad), "--out", str(user), "--workers", "1", "--quiet"]
    assert main(argv) == 2
    assert "not a vsidgen results directory" in capsys.readouterr().err
    assert (user / "fleet.json").read_text() == "my own notes"
    assert main(argv + ["--overwrite"]) == 2          # bad input, but the run took place
    assert (user / "notes.txt").read_text() == "keep me"
    assert json.loads((user / "fleet.json").read_text())["records"][0]["status"] == "bad_input"
    for opt in (["--max-iter", "0"], ["--substeps", "0"]):
        assert main(["fleet", str(SPEC), str(bad), "--out", str(tmp_path / "o"), "--workers",
                     "1", "--quiet", *opt]) == 2
        assert not (tmp_path / "o").exists()


@pytest.mark.slow
def test_fleet_passes_overrides_and_noise_start_to_every_fit(tmp_path, capsys):
    """--fix, --method, --noise-start reach each record's fit (the results say so, and equal a
    single `run_fit` with the same settings); an unknown --fix name is refused before any fit."""
    from vsidgen import Overrides
    from vsidgen.cli import main
    from vsidgen.fitjob import run_fit
    from vsidgen.spec.overrides import Method

    out = tmp_path / "fleet"
    rc = main(["fleet", str(SPEC), str(RECS[1]), "--out", str(out), "--workers", "1", "--max-iter", "3",
               "--fix", "ZQ=0", "--method", "output-error", "--noise-start", "data", "--quiet"])
    res = json.loads((out / "attas_sp_synthetic_val" / "results.json").read_text())
    assert rc == (0 if res["converged"] else 1)
    assert res["overrides"]["fix"] == {"ZQ": 0.0} and res["overrides"]["method"] == "output-error"
    assert res["parameters"]["ZQ"]["fixed"] and res["parameters"]["ZQ"]["estimate"] == 0.0
    ref = run_fit(SPEC, [RECS[1]], out=tmp_path / "single", max_iter=3, noise_start="data",
                  overrides=Overrides(fix={"ZQ": 0.0}, method=Method.OUTPUT_ERROR))
    assert res["elbo"] == pytest.approx(ref.results["elbo"], rel=1e-9)
    capsys.readouterr()
    assert main(["fleet", str(SPEC), str(RECS[1]), "--out", str(tmp_path / "f2"), "--workers", "1",
                 "--fix", "NOPE=1", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "NOPE" in err and not (tmp_path / "f2" / "attas_sp_synthetic_val").exists()
