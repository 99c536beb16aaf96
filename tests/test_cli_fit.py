"""`vsidgen simulate` and `vsidgen fit` end to end on the synthetic records shipped in data/.

The true parameter values are those of data/make_synthetic.sh; the fit starts from
null initial guesses and must recover them within 3 standard errors. Bad input must
give a clear message, a non-zero exit status and leave earlier results intact.
"""

import json
import pathlib
import shutil

import numpy as np
import pytest

from vsidgen.cli import main

# one worker runs the whole module: its module-scoped fixtures are computed once
pytestmark = pytest.mark.xdist_group("test_cli_fit")

ROOT = pathlib.Path(__file__).resolve().parents[1]
SPEC = ROOT / "specs" / "attas_sp.yaml"
DATA = ROOT / "data" / "attas_sp_synthetic.csv"
VAL = ROOT / "data" / "attas_sp_synthetic_val.csv"
TRUTH = {"Z0": -0.009, "ZAL": -0.483, "ZQ": 0.104, "ZDE": 0.676,
         "M0": 0.475, "MAL": -4.93, "MQ": -2.01, "MDE": -7.21}
TRUE_PROCESS = {"alpha": 0.005, "q": 0.01}
TRUE_MEAS = {"alpha": 0.0017, "q": 0.0028}


@pytest.fixture(scope="module")
def demo_fit(tmp_path_factory):
    out = tmp_path_factory.mktemp("fit") / "demo"
    rc = main(["fit", str(SPEC), str(DATA), "--validate", str(VAL), "--out", str(out), "--quiet"])
    return rc, out


def test_demo_fit_converges_and_recovers_truth(demo_fit):
    rc, out = demo_fit
    assert rc == 0
    res = json.loads((out / "results.json").read_text())
    assert res["converged"] is True and res["stop_reason"] in ("newton_decrement", "gradient")
    assert res["validation"]["converged"] is True and res["validation"]["elbo"] is not None
    # the validation record at its own noise (θ fixed): never below the fixed-noise smoothing
    val = res["validation"]
    assert val["own_noise_converged"] is True
    assert val["elbo_own_noise"] >= val["elbo"] - 1e-6 * abs(val["elbo"])
    assert res["iterations"] > 0 and res["wall_time_s"] > 0
    for name, truth in TRUTH.items():
        p = res["parameters"][name]
        assert p["fixed"] is False
        assert abs(p["estimate"] - truth) < 3 * p["std_error"], (name, p, truth)
    for name, truth in TRUE_MEAS.items():
        assert abs(res["noise"]["measurement_std"][name] / truth - 1) < 0.15
    for name, truth in TRUE_PROCESS.items():
        assert abs(res["noise"]["process_std"][name] / truth - 1) < 0.3
    corr = np.array(res["correlation"]["matrix"])
    assert corr.shape == (8, 8) and np.allclose(np.diag(corr), 1.0)
    # a converged fit of an identifiable model carries no standard-error flag
    assert res["std_errors_reliable"] is True and res["std_error_issues"] == []


def test_demo_fit_writes_signals_and_validation_metrics(demo_fit):
    _, out = demo_fit
    res = json.loads((out / "results.json").read_text())
    assert set(res["signals"]) == {"attas_sp_synthetic", "attas_sp_synthetic_val"}
    for rec, fname in res["signals"].items():
        header = (out / fname).read_text().splitlines()[0].split(",")
        for col in ("t_s", "alpha_meas", "alpha_smooth", "alpha_sim", "alpha_pred",
                    "q_mu", "q_dot_fd", "q_drift"):
            assert col in header
    val = res["metrics"]["validation"]["attas_sp_synthetic_val"]
    # the smoother tracks the validation record; the free simulation is worse but informative
    assert val["smoother"]["alpha"]["r2"] > 0.9
    assert val["prediction"]["q"]["r2"] > val["simulation"]["q"]["r2"] > 0.5
    assert res["validation"]["elbo"] is not None


def test_simulate_command_round_trip(tmp_path):
    out = tmp_path / "sim.csv"
    rc = main(["simulate", str(SPEC), "--out", str(out), "--param", "MAL=-4.9", "--param", "MQ=-2",
               "--param", "MDE=-7", "--param", "ZAL=-0.5", "--input",
               "de=doublet:amplitude=0.02,start=1,width=1", "--duration", "5", "--dt", "0.04"])
    assert rc == 0
    lines = out.read_text().splitlines()
    assert lines[0].split(",") == ["t_s", "de_rad", "alpha_rad", "q_radps"]
    assert len(lines) == 1 + 126


def _earlier_results(out):
    """A results directory of an earlier run: results.json listed in vsidgen's manifest."""
    out.mkdir(exist_ok=True)
    (out / "results.json").write_text('{"earlier": true}')
    (out / ".vsidgen-results.json").write_text(json.dumps(
        {"format": "vsidgen-results", "version": 1, "files": ["results.json"]}))


def _bad_fit(tmp_path, capsys, csv_text, expect):
    bad = tmp_path / "bad.csv"
    bad.write_text(csv_text)
    out = tmp_path / "res"
    _earlier_results(out)
    rc = main(["fit", str(SPEC), str(bad), "--out", str(out), "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2
    assert "Traceback" not in err
    for text in expect:
        assert text in err, err
    assert json.loads((out / "results.json").read_text()) == {"earlier": True}


def _rows(n, dt=0.04, jitter_at=None):
    lines = ["t_s,de_rad,alpha_rad,q_radps"]
    for k in range(n):
        t = k * dt + (0.5 * dt if k == jitter_at else 0.0)
        lines.append(f"{t},{0.01 * np.sin(k / 5)},{0.03 + 0.001 * k},{0.001 * k}")
    return "\n".join(lines) + "\n"


def test_missing_column(tmp_path, capsys):
    text = _rows(50).replace("q_radps", "q_degps")
    _bad_fit(tmp_path, capsys, text, ["q_radps", "q_degps"])


def test_non_uniform_time(tmp_path, capsys):
    _bad_fit(tmp_path, capsys, _rows(50, jitter_at=20), ["t_s", "sample 20", "non-uniform"])


def test_too_few_samples(tmp_path, capsys):
    _bad_fit(tmp_path, capsys, _rows(4), ["samples"])


def test_all_nan_channel(tmp_path, capsys):
    lines = _rows(50).splitlines()
    lines = [lines[0]] + [",".join(r.split(",")[:3] + ["nan"]) for r in lines[1:]]
    _bad_fit(tmp_path, capsys, "\n".join(lines) + "\n", ["q_radps", "NaN"])


def test_spec_data_mismatch(tmp_path, capsys):
    # a record of another aircraft: none of the mapped channels is there
    text = "t_s,v_mps,theta_rad\n" + "".join(f"{k * 0.1},{100 + k},{0.01 * k}\n" for k in range(50))
    _bad_fit(tmp_path, capsys, text, ["de_rad"])


def test_failed_run_leaves_earlier_results_intact(tmp_path, monkeypatch, capsys):
    """An exception while writing results (here: the report) leaves DIR as it was."""
    out = tmp_path / "res"
    shutil.copytree(ROOT / "data", tmp_path / "data")
    _earlier_results(out)
    import vsidgen.report

    def broken(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(vsidgen.report, "write_report", broken)
    rc = main(["fit", str(SPEC), str(DATA), "--out", str(out), "--quiet", "--report",
               "--max-iter", "3"])
    assert rc == 130
    assert json.loads((out / "results.json").read_text()) == {"earlier": True}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data", "res"]  # no temp dirs left


def test_not_converged_is_reported(tmp_path, capsys):
    out = tmp_path / "res"
    rc = main(["fit", str(SPEC), str(DATA), "--validate", str(VAL), "--out", str(out), "--quiet",
               "--max-iter", "2"])
    captured = capsys.readouterr()
    assert rc == 1
    assert "NOT CONVERGED" in captured.out
    res = json.loads((out / "results.json").read_text())
    assert res["converged"] is False and res["status"]
    assert res["stop_reason"] == "iteration_limit" and res["std_errors_reliable"] is False
    assert [i["code"] for i in res["std_error_issues"]][:1] == ["not_converged"]
    assert "standard errors: UNRELIABLE — not_converged" in captured.out
    # the validation smoothing (two iterations from its start) is flagged in results.json and the CLI line
    assert res["validation"]["converged"] is False and res["validation"]["stop_reason"] == "iteration_limit"
    assert "validation smoothing: NOT CONVERGED" in captured.out
    assert "validation_not_converged" in [w["code"] for w in res["warnings"]]


def test_parameters_entering_only_as_a_sum_are_flagged_in_results_cli_and_report(tmp_path, capsys):
    """ZDE2 added to the alpha equation beside ZDE: only ZDE + ZDE2 is identifiable. results.json,
    the CLI line and the report name the flag and both parameters."""
    (tmp_path / "specs").mkdir()
    spec = tmp_path / "specs" / "attas_sp_split.yaml"   # generated code goes to tmp_path/generated
    spec.write_text(f"extends: {SPEC}\nname: attas_sp_split\n"
                    "parameters:\n  ZDE2: {unit: 1/s, description: second elevator term}\n"
                    "add_terms:\n  drift: {alpha: ZDE2*de}\n")
    out = tmp_path / "res"
    main(["fit", str(spec), str(DATA), "--out", str(out), "--report", "--noise-start", "data",
          "--max-iter", "60"])
    captured = capsys.readouterr()
    res = json.loads((out / "results.json").read_text())
    assert res["std_errors_reliable"] is False
    flagged = [i for i in res["std_error_issues"]
               if i["code"] in ("hessian_not_positive_definite", "near_singular_information")]
    assert flagged and {"ZDE", "ZDE2"} <= set(flagged[0]["parameters"]), res["std_error_issues"]
    assert "standard errors: UNRELIABLE" in captured.out and "ZDE2" in captured.out.split("UNRELIABLE")[1]
    html = (out / "report.html").read_text()
    assert flagged[0]["code"] in html and "ZDE2" in html


def test_the_estimation_record_given_again_for_validation_or_twice_is_warned(tmp_path):
    """A validation record holding the estimation samples (the same file, or a copy under
    another name) measures the fit itself; an estimation record given twice counts its
    evidence twice. Both are named; distinct records raise nothing."""
    from vsidgen.data import load_record, unique_names
    from vsidgen.fitjob.run import repeated_record_warnings
    from vsidgen.spec import compile_spec

    copy = tmp_path / "renamed.csv"
    shutil.copy(DATA, copy)
    sym = compile_spec(SPEC)
    est, val, dup = (load_record(sym, p) for p in (DATA, VAL, copy))
    assert repeated_record_warnings([est], [val]) == []
    got = repeated_record_warnings([est], [val, dup])
    assert [w["code"] for w in got] == ["validation_is_estimation_record"]
    assert got[0]["records"] == ["attas_sp_synthetic", "renamed"]
    both = unique_names([est, load_record(sym, DATA)])
    got = repeated_record_warnings(both, [])
    assert [w["code"] for w in got] == ["estimation_record_repeated"] and "sqrt(2)" in got[0]["message"]


def test_records_with_one_file_name_in_two_folders_keep_both_names(tmp_path):
    """`fit d1/rec.csv --validate d2/rec.csv` wrote both records' signals to one
    `signals_rec.csv`, and results.json named both `rec` (session 44, red team): names are
    made unique across estimation and validation records."""
    from vsidgen.data import load_records
    from vsidgen.spec import compile_spec

    for sub, src in (("d1", DATA), ("d2", VAL)):
        (tmp_path / sub).mkdir()
        shutil.copy(src, tmp_path / sub / "rec.csv")
    est, val = load_records(compile_spec(SPEC), [tmp_path / "d1" / "rec.csv"],
                            [tmp_path / "d2" / "rec.csv"])
    assert [r.name for r in est] == ["rec"] and [r.name for r in val] == ["rec_1"]


def test_a_mistyped_option_gets_the_commands_usage_and_the_nearest_option(capsys):
    """`vsidgen fit … --validation v.csv` printed the top-level usage and no hint (session 44,
    a new user): the command's usage, the argument, and the option meant."""
    from vsidgen.cli import main

    code = main(["fit", str(SPEC), str(DATA), "-o", "never", "--validation", str(VAL)])
    err = capsys.readouterr().err
    assert code == 2 and "usage: vsidgen fit" in err and "did you mean `--validate`?" in err
    assert not pathlib.Path("never").exists()
    code = main(["check", str(SPEC), "--dta", str(DATA)])
    err = capsys.readouterr().err
    assert code == 2 and "did you mean `--data`?" in err
