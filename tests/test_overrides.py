"""--fix/--free/--init/--init-from/--method, role-aware suggestions and extends field merge."""

from __future__ import annotations

import dataclasses
import json
import pathlib

import pytest

from vsidgen.cli import main
from vsidgen.errors import VsidgenError
from vsidgen.spec.overrides import Method, apply_overrides, parse_overrides
from vsidgen.suggest import closest, suggest
from vsidgen.spec import compile_spec

ROOT = pathlib.Path(__file__).resolve().parent.parent
SPEC = ROOT / "specs" / "attas_sp.yaml"
CSV = ROOT / "data" / "attas_sp_synthetic.csv"


def _fixed_child(tmp_path):
    path = tmp_path / "fixed.yaml"
    path.write_text(f"extends: {SPEC}\nname: attas_sp_fixed\nparameters:\n"
                    "  MQ: {initial: -2.5, fixed: true}\n  ZAL: {initial: -0.5}\n")
    return path


def test_fix_equals_a_spec_with_fixed_true(tmp_path):
    sym = compile_spec(SPEC)
    ov = parse_overrides(fix=["MQ=-2.5"], init=["ZAL=-0.5"])
    assert apply_overrides(sym, ov).parameters == compile_spec(_fixed_child(tmp_path)).parameters


@pytest.mark.slow
def test_fit_with_fix_equals_fit_of_the_fixed_spec(tmp_path):
    from vsidgen.data import load_record
    from vsidgen.estimator import FitOptions, fit
    from vsidgen.model import load_model

    out = tmp_path / "res"
    code = main(["fit", str(SPEC), str(CSV), "--out", str(out), "--fix", "MQ=-2.5",
                 "--init", "ZAL=-0.5", "--max-iter", "60", "--quiet"])
    res = json.loads((out / "results.json").read_text())
    assert code == 0 and res["converged"]
    assert res["parameters"]["MQ"] == {**res["parameters"]["MQ"], "estimate": -2.5, "fixed": True,
                                       "std_error": None, "unit": "1/s"}
    assert res["overrides"] == {"fix": {"MQ": -2.5}, "free": [], "init": {"ZAL": -0.5},
                                "init_from": None, "method": "filter-error"}
    sim = res["metrics"]["estimation"]["attas_sp_synthetic"]["simulation"]["alpha"]
    assert sim["fit_percent"] == pytest.approx(100 * (1 - (1 - sim["r2"]) ** 0.5), rel=1e-9)
    # the spec with `fixed: true` changes no equation: its parameters on the same module
    base = load_model(SPEC)
    model = dataclasses.replace(base, parameters=compile_spec(_fixed_child(tmp_path)).parameters)
    ref = fit(model, [load_record(model, CSV)], options=FitOptions(max_iter=60))
    assert res["elbo"] == pytest.approx(ref.elbo, rel=1e-10)
    for name, value in zip(model.parameter_names, ref.theta):
        assert res["parameters"][name]["estimate"] == pytest.approx(value, rel=1e-8, abs=1e-12)
    # --init-from: the estimates become the initial values; the fit starts at its optimum
    out2 = tmp_path / "res2"
    assert main(["fit", str(SPEC), str(CSV), "--out", str(out2), "--init-from",
                 str(out / "results.json"), "--free", "MQ", "--method", "output-error",
                 "--max-iter", "60", "--quiet"]) in (0, 1)
    res2 = json.loads((out2 / "results.json").read_text())
    assert res2["method"]["method"] == "output-error"
    assert res2["overrides"]["init_from"] == str(out / "results.json")
    assert res2["parameters"]["MQ"]["fixed"] is False
    assert all(v < 1e-3 for v in res2["noise"]["process_std"].values()) or \
        res2["noise"]["process_std"] == {}


def test_output_error_removes_process_noise():
    sym = compile_spec(SPEC)
    oe = apply_overrides(sym, parse_overrides(method="output-error"))
    assert oe.process_noise.estimate is False and oe.process_noise.std == {}
    assert parse_overrides().method is Method.FILTER_ERROR


@pytest.mark.parametrize("argv, expected", [
    (["--fix", "MQQ=1"], "did you mean `MQ`?"),
    (["--fix", "alpha=0.1"], "`alpha` is a state, not a parameter"),
    (["--free", "q"], "`q` is a state, not a parameter"),
    (["--init", "de=1"], "`de` is an input, not a parameter"),
    (["--fix", "MQ"], "expected NAME=VALUE"),
    (["--fix", "MQ=abc"], "is not a number"),
    (["--init-from", "/nonexistent/results.json"], "file not found"),
    (["--init-from", "/dev/zero"], "a character device, not a regular file"),
    (["--init-from", "LIST"], "not a vsidgen results.json"),
    (["--init-from", "NAN"], "is not a finite number"),
    (["--init-from", "DEEP"], "not a vsidgen results.json"),
    (["--fix", "MQ=1", "--free", "MQ"], "both --fix and --free"),
])
def test_bad_override_exits_2(tmp_path, capsys, argv, expected):
    # hostile results files (a device would be read without end; a parameter list, a NaN
    # estimate or a 100000-deep nesting raised AttributeError/RecursionError or got in)
    files = {"LIST": json.dumps({"parameters": [1, 2]}),
             "NAN": '{"parameters": {"MQ": {"estimate": NaN}}}',
             "DEEP": "[" * 100000 + "]" * 100000}
    argv = [str(tmp_path / a) if a in files else a for a in argv]
    for name, text in files.items():
        (tmp_path / name).write_text(text)
    code = main(["fit", str(SPEC), str(CSV), "--out", str(tmp_path / "o"), "--quiet"] + argv)
    err = capsys.readouterr().err
    assert code == 2 and expected in err and "Traceback" not in err
    assert not (tmp_path / "o").exists()


def test_simulate_params_from_reads_estimates_like_init_from(tmp_path, capsys):
    names = [p.name for p in compile_spec(SPEC).parameters]
    good, bad = tmp_path / "good.json", tmp_path / "bad.json"
    good.write_text(json.dumps({"parameters": {n: {"estimate": -0.5} for n in names}}))
    bad.write_text(json.dumps({"parameters": {names[0]: {"value": -0.5}}}))
    argv = ["simulate", str(SPEC), "--duration", "2", "--dt", "0.05",
            "--input", "de=doublet:amplitude=0.02,start=0.5,width=0.5"]
    assert main(argv + ["--out", str(tmp_path / "b.csv"), "--params-from", str(bad)]) == 2
    err = capsys.readouterr().err
    assert f"--params-from {bad}: not a vsidgen results.json" in err and "Traceback" not in err
    assert main(argv + ["--out", str(tmp_path / "g.csv"), "--params-from", str(good)]) == 0
    assert main(argv + ["--out", str(tmp_path / "p.csv")] + [f"--param={n}=-0.5" for n in names]) == 0
    assert (tmp_path / "g.csv").read_text() == (tmp_path / "p.csv").read_text()


def test_bounds_checked(tmp_path):
    spec = tmp_path / "b.yaml"
    spec.write_text(f"extends: {SPEC}\nname: b\nparameters:\n  MQ: {{bounds: [-10, 0]}}\n")
    sym = compile_spec(spec)
    with pytest.raises(VsidgenError, match="outside its bounds"):
        apply_overrides(sym, parse_overrides(fix=["MQ=1"]))


def test_role_aware_suggestions():
    # a typo of a derivative name suggests the parameter, not the state it contains
    assert closest("Lbeta", ["Lb", "Lp", "beta", "p"]) == ["Lb"]
    assert suggest("Lbeta", ["Lb", "Lp"], {"beta": "a state"}, role="parameter") == \
        "did you mean `Lb`?"
    assert suggest("beta", ["Lb", "Lp"], {"beta": "a state"}, role="parameter") == \
        "`beta` is a state, not a parameter"


def test_missing_rudder_column_does_not_suggest_the_aileron(tmp_path):
    from vsidgen.suggest import column_hint

    header = ["t_s", "da_deg", "p_degps"]
    taken = {"t_s": "the time", "da_deg": "input `da`", "dr_deg": "input `dr`"}
    hint = column_hint("dr_deg", header, taken)
    assert "did you mean" not in hint and "'da_deg' is already the column of input `da`" in hint
    assert column_hint("dr_deg", header + ["dr_dg"], taken) == "did you mean 'dr_dg'?"


def test_extends_override_keeps_unit_and_description(tmp_path):
    spec = tmp_path / "child.yaml"
    spec.write_text(f"extends: {SPEC}\nname: child\nparameters:\n  MQ: {{bounds: [-10, 0]}}\n")
    parent = {p.name: p for p in compile_spec(SPEC).parameters}["MQ"]
    child = {p.name: p for p in compile_spec(spec).parameters}["MQ"]
    assert (child.unit, child.description) == (parent.unit, parent.description) == \
        ("1/s", "M_q: pitch damping")
    assert (child.lower, child.upper) == (-10, 0)


def test_show_prints_parameter_descriptions(capsys):
    assert main(["show", str(SPEC)]) == 0
    out = capsys.readouterr().out
    assert "M_q: pitch damping" in out


def test_diagnose_override_spec_equals_the_overrides(tmp_path):
    from vsidgen.spec.overrides import write_override_spec

    ov = parse_overrides(fix=["MQ=-2.5"], init=["ZAL=-0.5"], method="output-error")
    path = write_override_spec(SPEC, ov, tmp_path)
    sym = compile_spec(path)
    want = apply_overrides(compile_spec(SPEC), ov)
    assert sym.parameters == want.parameters
    assert sym.process_noise.estimate is False
    assert sym.drift == want.drift and sym.name == "attas_sp_cli"
    with pytest.raises(VsidgenError, match="did you mean `MQ`"):
        write_override_spec(SPEC, parse_overrides(fix=["MQQ=1"]), tmp_path / "x")


def test_a_non_finite_start_says_where_and_why(tmp_path, capsys):
    """--fix MQ=1e200: the ELBO overflows at the start; the message names the parameter (it
    said only 'not finite at the initial point')."""
    code = main(["fit", str(SPEC), str(CSV), "--out", str(tmp_path / "o"), "--quiet",
                 "--fix", "MQ=1e200"])
    err = capsys.readouterr().err
    assert code == 2 and "MQ = 1e+200" in err and "overflow" in err and "Traceback" not in err


@pytest.mark.parametrize("estimate", ["true", '"1e3"', "null", "[1]"])
def test_init_from_refuses_estimates_that_are_not_numbers(tmp_path, estimate):
    """`true` and "1e3" were read as 1.0 and 1000 (float() takes both; session 43)."""
    from vsidgen.errors import VsidgenError
    from vsidgen.spec.overrides import read_estimates

    path = tmp_path / "r.json"
    path.write_text('{"parameters": {"Z0": {"estimate": %s}}}' % estimate)
    with pytest.raises(VsidgenError, match="Z0|not a vsidgen results.json"):
        read_estimates(path)
