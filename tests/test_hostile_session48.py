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


@pytest.mark.parametrize("desc", ["angle $\\frac{$ of attack", "a $\\deg$ b", "one $ alone",
                                  "$" + "{" * 60 + "x" + "}" * 60 + "$"])
def test_a_dollar_in_a_description_is_text_in_the_report_figures(tmp_path, desc):
    """Descriptions are free text; the figures drew them through matplotlib's mathtext, so
    `$\\frac{$` made `fit --report` fail after the fit (exit 3, the results lost)."""
    import json

    from report_fixture import write_results_dir

    from vsidgen.report import write_report

    d = write_results_dir(tmp_path / "fit", validation=False, n_samples=100, n_outputs=1)
    res = json.loads((d / "results.json").read_text())
    for group in ("states", "outputs"):
        for v in res["model"][group]:
            v["description"] = desc
    (d / "results.json").write_text(json.dumps(res))
    assert write_report(d).is_file()


def test_a_report_that_fails_keeps_the_fit_results(tmp_path, capsys, monkeypatch):
    """A defect in the report (any exception) no longer discards the converged fit: the
    results directory is written without the report, the command says so, exit status 3."""
    from vsidgen import report as report_pkg

    def broken(*a, **k):
        raise ValueError("mathtext blew up")

    monkeypatch.setattr(report_pkg, "write_report", broken)
    spec = tmp_path / "s.yaml"
    spec.write_text(SPEC)
    csv = tmp_path / "d.csv"
    csv.write_text("\n".join(DATA[:201]) + "\n")
    from vsidgen.cli import main
    code = main(["fit", str(spec), str(csv), "-o", str(tmp_path / "out"), "--max-iter", "5",
                 "--report"])
    err = capsys.readouterr().err
    assert code == 3 and "the report could not be written (ValueError: mathtext blew up)" in err
    assert (tmp_path / "out" / "results.json").is_file()
    assert not (tmp_path / "out" / "report.html").exists()


def test_files_that_appear_in_the_output_during_a_run_are_kept(tmp_path):
    """The output directory was checked once, before the computation; at the end the swap
    removed whatever had appeared in it meanwhile (a user's notes, an empty folder)."""
    from vsidgen.atomic import atomic_directory, plan_output_dir

    out = tmp_path / "out"
    plan = plan_output_dir(out)
    with atomic_directory(out, plan=plan) as d:
        (d / "results.json").write_text("new")
        out.mkdir()
        (out / "notes.txt").write_text("mine")
        (out / "later").mkdir()
    assert (out / "notes.txt").read_text() == "mine" and (out / "later").is_dir()
    assert (out / "results.json").read_text() == "new"
    # the next run still replaces its own results and keeps the user's
    plan = plan_output_dir(out, overwrite=True)
    with atomic_directory(out, plan=plan) as d:
        (d / "results.json").write_text("newer")
    assert (out / "notes.txt").read_text() == "mine"
    assert (out / "results.json").read_text() == "newer"


def test_a_file_in_the_way_of_the_results_is_kept_and_the_results_too(tmp_path):
    from vsidgen.atomic import atomic_directory, plan_output_dir
    from vsidgen.errors import VsidgenError

    out = tmp_path / "out"
    plan = plan_output_dir(out)
    with pytest.raises(VsidgenError, match="changed during the run") as exc:
        with atomic_directory(out, plan=plan) as d:
            (d / "results.json").write_text("new")
            out.mkdir()
            (out / "results.json").write_text("the user's")
    assert (out / "results.json").read_text() == "the user's"
    (kept,) = tmp_path.glob("out.results-*")
    assert (kept / "results.json").read_text() == "new" and str(kept) in str(exc.value)


def test_an_empty_folder_in_a_results_directory_is_not_removed_without_overwrite(tmp_path):
    from vsidgen.atomic import DirState, atomic_directory, plan_output_dir
    from vsidgen.errors import VsidgenError

    out = tmp_path / "out"
    with atomic_directory(out, plan=plan_output_dir(out)) as d:
        (d / "results.json").write_text("1")
    (out / "mine").mkdir()
    with pytest.raises(VsidgenError, match="mine/"):
        plan_output_dir(out)
    plan = plan_output_dir(out, overwrite=True)
    assert plan.state is DirState.MIXED
    with atomic_directory(out, plan=plan) as d:
        (d / "results.json").write_text("2")
    assert (out / "mine").is_dir() and (out / "results.json").read_text() == "2"


def test_file_names_with_escapes_do_not_reach_stdout(tmp_path, capsys):
    """`check`'s ok line and `report`'s "wrote" line printed the spec's and the results
    directory's names raw (stdout now passes every line through ``printable``)."""
    from report_fixture import write_results_dir

    esc = "\x1b]0;PWNED\x07"
    spec = tmp_path / f"s{esc}.yaml"
    spec.write_text(SPEC)
    code, out, _ = _run(capsys, "check", str(spec))
    assert code == 0 and "\\x1b]0;PWNED\\x07.yaml: ok" in out
    d = write_results_dir(tmp_path / f"res{esc}", validation=False, n_samples=100, n_outputs=1)
    code, out, _ = _run(capsys, "report", str(d))
    assert code == 0 and "wrote" in out and "\\x1b" in out


def test_a_long_description_is_cut_in_figure_titles():
    from vsidgen.report.html import FIGURE_TEXT_CHARS, _short

    assert _short("angle of attack") == "angle of attack"
    cut = _short("$x^{a}_{b}$ " * 16000)
    assert len(cut) == FIGURE_TEXT_CHARS and cut.endswith("…")


@pytest.mark.parametrize("drift, defs", [
    ("max(ZAL, ZQ, ZDE, MAL, MQ)*alpha + q", ""),
    ("mx*alpha + q", "definitions:\n  m1: max(ZAL, ZQ, ZDE)\n  mx: max(m1, MAL, MQ)\n"),
])
def test_a_min_or_max_of_many_arguments_is_refused_at_once(tmp_path, capsys, drift, defs):
    """max of 8 parameters took `check` 49 s and `build` of 50 more than 5 minutes (sympy's
    piecewise derivatives); more than four arguments, nested ones flattened, are refused."""
    text = SPEC
    line = next(x for x in text.splitlines() if x.strip().startswith("alpha:")
                and "q" in x and "ZAL" in x)
    text = text.replace(line, f"  alpha: {drift}", 1)
    if defs:
        text = text.replace("drift:\n", defs + "drift:\n", 1)
    spec = tmp_path / "s.yaml"
    spec.write_text(text)
    code, _, err = _run(capsys, "check", str(spec))
    assert code == 2 and "min/max of 5 arguments" in err and "(at most 4)" in err, err
