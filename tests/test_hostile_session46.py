"""Hostile and careless inputs found by the session-46 red team (each failed before its fix).

* a model named like a Python keyword (`name: import`) passed `check` and was an internal
  error (exit 3) in `build`;
* a spec text holding a lone surrogate (the YAML escape `"\\ud800"`) passed `check` and
  `build`, then `show` and `fit --report` ended in an internal error (UnicodeEncodeError);
* `show` printed parameter descriptions raw: terminal escapes from the spec reached the
  terminal;
* a file name that is not UTF-8 (a record or spec copied from a Latin-1 file system) made
  `fit --report` and `report` fail after the fit (UnicodeEncodeError), the results lost;
* a number literal below the double range (`1e-999`) silently became 0 and its term
  vanished; hex, octal and binary literals (`0x10`) were read although a spec's numbers
  are plain decimal; full-width or ligature names (`ＭＱ`, `ﬁ`) were read as `MQ`, `fi`;
* `--init-from` a results.json without any of the model's parameters was ignored silently;
* `--fix`/`--init`/`--param NAME=VALUE` and `simulate --input NAME=...` given twice kept
  the last one silently; `--params-from` with a foreign parameter was reported as `--param`.

Every case runs the command line in-process (no fit runs: each is refused before it).
"""

from __future__ import annotations

import contextlib
import io
import os
import pathlib
import shutil
import sys

import pytest

from vsidgen.cli import main

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(pathlib.Path(__file__).parent))

SPEC = (ROOT / "specs" / "attas_sp.yaml").read_text()


@pytest.fixture(autouse=True)
def _in_tmp(tmp_path, monkeypatch):
    """Every command runs in its own folder (./generated is written there, never in the repo)."""
    monkeypatch.chdir(tmp_path)


def _run(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    assert "Traceback" not in err and "internal error" not in err, err
    return code, out, err


def _spec(tmp_path, name="s.yaml", **replace) -> pathlib.Path:
    text = SPEC
    for old, new in replace.items():
        assert old in text, old
        text = text.replace(old, new, 1)
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


def _expr(tmp_path, expr: str) -> pathlib.Path:
    text = SPEC.replace("q: M0 + MAL*alpha + MQ*q + MDE*de", f"q: M0 + MAL*alpha + {expr} + MDE*de")
    path = tmp_path / "e.yaml"
    path.write_text(text, encoding="utf-8")
    return path


@pytest.mark.parametrize("name", ["import", "lambda", "True", "None"])
def test_model_name_that_is_a_python_keyword_is_refused_at_its_line(tmp_path, capsys, name):
    spec = tmp_path / "kw.yaml"
    spec.write_text(SPEC.replace("name: attas_sp", f"name: {name}"))
    for command in ("check", "build"):
        code, _, err = _run(capsys, command, str(spec))
        assert code == 2, err
        assert f"kw.yaml:5:7: error: model name `{name}` is a Python keyword" in err, err
        assert "hint:" in err
    assert not (tmp_path / "generated").exists() or not any((tmp_path / "generated").iterdir())


@pytest.mark.parametrize("where", ["description", "key", "unit_column"])
def test_lone_surrogate_in_spec_text_is_refused_at_its_line(tmp_path, capsys, where):
    if where == "description":
        spec = _spec(tmp_path, **{'"M_q: pitch damping"': '"pitch \\ud800 damping"'})
        line = 28
    elif where == "key":
        spec = _spec(tmp_path, **{"  MDE: {unit: 1/s^2,": '  "M\\udc80DE": {unit: 1/s^2,'})
        line = 29
    else:
        spec = _spec(tmp_path, **{"alpha: alpha_rad": 'alpha: "alpha\\udcffrad"'})
        line = 53
    for command in ("check", "show"):
        code, out, err = _run(capsys, command, str(spec))
        assert code == 2, (out, err)
        assert f"s.yaml:{line}:" in err and "lone surrogate" in err, err


def test_extends_path_with_surrogate_escape_still_works(tmp_path, capsys):
    """An `extends` path is a file name: one that is not UTF-8 arrives as surrogates
    (diagnose writes such specs); it is not refused as text."""
    base = tmp_path / os.fsdecode(b"b\xfe.yaml")
    base.write_text(SPEC)
    child = tmp_path / "child.yaml"
    child.write_text(f'extends: "{os.fsdecode(b"b")}\\udcfe.yaml"\nname: child\n')
    code, out, err = _run(capsys, "check", str(child))
    assert code == 0, err


def test_show_escapes_terminal_control_characters_in_parameter_descriptions(tmp_path, capsys):
    spec = _spec(tmp_path, **{'"M_q: pitch damping"': '"a\\e[2J\\e[31mred\\a\\rX"'})
    code, out, err = _run(capsys, "show", str(spec))
    assert code == 0, err
    assert "\x1b" not in out and "\x07" not in out and "\r" not in out
    assert "a\\x1b[2J\\x1b[31mred\\x07\\rX" in out


def test_text_files_take_file_names_that_are_not_utf8(tmp_path):
    from vsidgen.atomic import write_text_atomic

    path = write_text_atomic(tmp_path / "page.html", "record d" + os.fsdecode(b"\xfd") + "\n")
    assert path.read_text(encoding="utf-8") == "record d\\udcfd\n"


def test_report_of_a_results_directory_whose_name_is_not_utf8(tmp_path, capsys):
    """`fit --report` with a record named `d\\xfd.csv` was an internal error after the fit;
    `report` of such a directory refused its (valid) content."""
    from report_fixture import write_results_dir

    d = tmp_path / os.fsdecode(b"res\xfc")
    write_results_dir(d, n_samples=40, validation=False, n_outputs=1)
    shown = io.StringIO()   # a terminal under a C.UTF-8 locale takes the name (surrogateescape)
    with contextlib.redirect_stdout(shown):
        code, out, err = _run(capsys, "report", str(d))
    assert code == 0, err
    page = (d / "report.html").read_text(encoding="utf-8")
    assert "res\\udcfc" in page


@pytest.mark.parametrize("expr, text", [
    ("MQ*q*1e-999", "`1e-999` is too small"),
    ("MQ*q + 0.000000000000000000000000000000000000000000000000000000000000000000000000000000"
     "000000000000000000000000000000000000000000000000000000000000000000000000000000000000000"
     "000000000000000000000000000000000000000000000000000000000000000000000000000000000000000"
     "000000000000000000000000000000000000000000000000000000000000000000000000000000000000000"
     "0000001", "is too small"),
    ("MQ*q*0x10", "`0x10` is not decimal"),
    ("MQ*q*0o17", "`0o17` is not decimal"),
    ("MQ*q*0B11", "`0B11` is not decimal"),
    ("\uff2d\uff31*q", "name `\uff2d\uff31` is not ASCII (Python would read it as `MQ`)"),
])
def test_number_literals_and_names_that_python_would_change_are_refused(tmp_path, capsys,
                                                                        expr, text):
    code, _, err = _run(capsys, "check", str(_expr(tmp_path, expr)))
    assert code == 2, err
    assert "e.yaml:33:" in err and text in err, err


def test_ligature_name_is_refused_with_the_ascii_spelling(tmp_path, capsys):
    spec = _spec(tmp_path, **{"MQ:  {unit: 1/s,": "fi:  {unit: 1/s,"})
    spec.write_text(spec.read_text().replace("MQ*q", "\ufb01*q"))
    code, _, err = _run(capsys, "check", str(spec))
    assert code == 2 and "Python would read it as `fi`" in err and "U+FB01" in err, err


@pytest.mark.parametrize("expr", ["MQ*q*0.0", "MQ*q*1e-300", "MQ*q*1_000.5", "MQ*q*.5e1"])
def test_plain_decimal_literals_still_work(tmp_path, capsys, expr):
    code, _, err = _run(capsys, "check", str(_expr(tmp_path, expr)))
    assert code == 0, err


def _record(tmp_path) -> pathlib.Path:
    dst = tmp_path / "d.csv"
    lines = (ROOT / "data" / "attas_sp_synthetic.csv").read_text().splitlines()[:41]
    dst.write_text("\n".join(lines) + "\n")
    return dst


def test_init_from_without_any_parameter_of_the_model_is_refused(tmp_path, capsys):
    spec = tmp_path / "attas_sp.yaml"
    shutil.copy(ROOT / "specs" / "attas_sp.yaml", spec)
    other = tmp_path / "other.json"
    other.write_text('{"parameters": {"CD0": {"estimate": 0.1}, "\\u001b[2JX": {"estimate": 1}}}')
    code, out, err = _run(capsys, "fit", str(spec), str(_record(tmp_path)), "-o",
                          str(tmp_path / "res"), "--quiet", "--init-from", str(other))
    assert code == 2, err
    assert "other.json" in err and "none of its parameters is a parameter of model `attas_sp`" in err
    assert "\x1b" not in err
    assert not (tmp_path / "res").exists()


@pytest.mark.parametrize("option", ["--fix", "--init"])
def test_fit_override_given_twice_with_different_values_is_refused(tmp_path, capsys, option):
    spec = tmp_path / "attas_sp.yaml"
    shutil.copy(ROOT / "specs" / "attas_sp.yaml", spec)
    code, _, err = _run(capsys, "fit", str(spec), str(_record(tmp_path)), "-o",
                        str(tmp_path / "res"), "--quiet", option, "MQ=1", option, "MQ=2")
    assert code == 2, err
    assert f"{option} MQ is given twice, with different values (1 and 2)" in err
    assert not (tmp_path / "res").exists()


def test_simulate_options_given_twice_and_params_from_names(tmp_path, capsys):
    spec = tmp_path / "attas_sp.yaml"
    shutil.copy(ROOT / "specs" / "attas_sp.yaml", spec)
    base = ["simulate", str(spec), "-o", str(tmp_path / "s.csv"), "--duration", "2", "--dt", "0.1"]
    code, _, err = _run(capsys, *base, "--input", "de=step:amplitude=0.1",
                        "--input", "de=doublet:amplitude=1")
    assert code == 2 and "--input de is given twice" in err and "'+'" in err, err
    code, _, err = _run(capsys, *base, "--input", "de=step:amplitude=0.1",
                        "--param", "MQ=5", "--param", "MQ=6")
    assert code == 2 and "--param MQ is given twice" in err, err
    foreign = tmp_path / "foreign.json"
    foreign.write_text('{"parameters": {"MQ": {"estimate": -1}, "\\u001b[31mNOPE": '
                       '{"estimate": 1}}}')
    code, _, err = _run(capsys, *base, "--input", "de=step:amplitude=0.1",
                        "--params-from", str(foreign))
    assert code == 2, err
    assert f"--params-from {foreign}:" in err and "unknown parameter" in err, err
    assert "\x1b" not in err
    assert not (tmp_path / "s.csv").exists()
