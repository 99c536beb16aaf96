"""Hostile inputs found by the session-47 red team that reach the terminal: a record's column
names, its file name, and the names in a data map were printed raw, so a terminal escape in a
CSV header (ESC [2J clears the screen; OSC sequences set the title or write the clipboard)
reached the terminal through "did you mean" hints, warnings, errors and `check`'s ranges.
(The other defects of that red team have their tests beside the code they touch:
test_generated_bytecode, test_atomic_leftovers_session47, test_domain_start,
test_diagnose_resilience.)"""

from __future__ import annotations

import pathlib

import pytest

from vsidgen.cli import main

ROOT = pathlib.Path(__file__).resolve().parents[1]
SPEC = (ROOT / "specs" / "attas_sp.yaml").read_text()
DATA = (ROOT / "data" / "attas_sp_synthetic.csv").read_text().splitlines()
ESC = "\x1b[2J\x1b]0;pwned\x07"


@pytest.fixture(autouse=True)
def _in_tmp(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)


def _run(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    assert "Traceback" not in err and "internal error" not in err, err
    assert "\x1b" not in out and "\x07" not in out, out
    assert "\x1b" not in err and "\x07" not in err, err
    return code, out, err


def _column(name):
    """The data map's column of alpha (as the shipped spec names it)."""
    for line in SPEC.splitlines():
        if line.strip().startswith("alpha:") and "alpha_" in line:
            return line.split(":", 1)[1].strip()
    raise AssertionError("no alpha column in the spec's data map")


def test_a_column_name_with_escapes_is_escaped_in_did_you_mean(tmp_path, capsys):
    col = _column("alpha")
    header = DATA[0].replace(col, col + ESC)
    csv = tmp_path / "esc.csv"
    csv.write_text("\n".join([header, *DATA[1:]]) + "\n")
    spec = tmp_path / "s.yaml"
    spec.write_text(SPEC)
    code, _, err = _run(capsys, "check", str(spec), "--data", str(csv))
    assert code == 2 and "\\x1b[2J" in err


def test_a_data_file_name_with_escapes_is_escaped_in_errors_and_warnings(tmp_path, capsys):
    rows = [DATA[0], DATA[1].replace(DATA[1].split(",")[1], "nan", 1), *DATA[2:]]
    csv = tmp_path / f"f{ESC}bad.csv"
    csv.write_text("\n".join(rows) + "\n")
    spec = tmp_path / "s.yaml"
    spec.write_text(SPEC)
    code, out, err = _run(capsys, "check", str(spec), "--data", str(csv))
    assert "\\x1b" in out + err


def test_a_mapped_column_with_escapes_is_escaped_in_check_ranges(tmp_path, capsys):
    col = _column("alpha")
    spec = tmp_path / "s.yaml"
    spec.write_text(SPEC.replace(f"alpha: {col}", f'alpha: "{col}\\e[2J"', 1))
    csv = tmp_path / "d.csv"
    csv.write_text("\n".join([DATA[0].replace(col, col + "\x1b[2J"), *DATA[1:]]) + "\n")
    code, out, _ = _run(capsys, "check", str(spec), "--data", str(csv))
    assert code == 0 and "\\x1b[2J" in out


# ---------------------------------------------------------------------------
# simulate options and data-map expressions (red team, session 47)
# ---------------------------------------------------------------------------

def _spec(tmp_path, old=None, new=None):
    text = SPEC if old is None else SPEC.replace(old, new, 1)
    assert old is None or old in SPEC
    p = tmp_path / "s.yaml"
    p.write_text(text)
    return p


SIM = ["--duration", "5", "--dt", "0.04", "--input", "de=step:amplitude=0.01"]


def test_a_quantisation_step_below_the_values_resolution_is_refused(tmp_path, capsys):
    out = tmp_path / "q.csv"
    code, _, err = _run(capsys, "simulate", str(_spec(tmp_path)), "-o", str(out), *SIM,
                        "--measurement-std", "alpha=0.001", "--quantize", "alpha=1e-320")
    assert code == 2 and "below the resolution" in err and "RuntimeWarning" not in err
    assert not out.exists()


def test_a_record_too_short_to_fit_is_said(tmp_path, capsys):
    code, _, err = _run(capsys, "simulate", str(_spec(tmp_path)), "-o", str(tmp_path / "s.csv"),
                        "--duration", "0.05", "--dt", "0.04", "--input", "de=step:amplitude=0.01")
    assert code == 0 and "2 samples: a fit needs at least 10" in err


@pytest.mark.parametrize("maneuver", ["doublet:amplitude=0.01,width=-1",
                                      "doublet:amplitude=0.01,width=0",
                                      "3211:amplitude=0.01,unit=-0.5"])
def test_a_manoeuvre_of_no_duration_is_refused(tmp_path, capsys, maneuver):
    code, _, err = _run(capsys, "simulate", str(_spec(tmp_path)), "-o", str(tmp_path / "m.csv"),
                        "--duration", "5", "--dt", "0.04", "--input", f"de={maneuver}")
    assert code == 2 and "must be a positive number of seconds" in err


def test_an_unknown_output_lists_outputs_that_are_also_states(tmp_path, capsys):
    code, _, err = _run(capsys, "simulate", str(_spec(tmp_path)), "-o", str(tmp_path / "x.csv"),
                        *SIM, "--measurement-std", "alpah=1")
    assert code == 2 and "did you mean `alpha`?" in err and "outputs: alpha, q" in err
    assert "none" not in err


def test_a_data_map_expression_outside_its_domain_is_named(tmp_path, capsys):
    col = [ln.split(":", 1)[1].strip() for ln in SPEC.splitlines()
           if ln.strip().startswith("de:") and "de_" in ln][0]
    spec = _spec(tmp_path, f"de: {col}", f'de: {{expr: "log({col} - 1)"}}')
    data = ROOT / "data" / "attas_sp_synthetic.csv"
    code, _, err = _run(capsys, "check", str(spec), "--data", str(data))
    assert code == 2 and "the data map's expression for input `de`" in err
    assert "missing" not in err
    code, _, err = _run(capsys, "fit", str(spec), str(data), "-o", str(tmp_path / "r"),
                        "--quiet")
    assert code == 2 and "is undefined (NaN) at these values" in err
    assert "empty" not in err and "all NaN" not in err


# ---------------------------------------------------------------------------
# spec sizes and shapes (red team, session 47)
# ---------------------------------------------------------------------------

def test_a_long_flat_sum_is_not_nested(tmp_path, capsys):
    """A polynomial of 80 terms was refused as "nested too deeply" (Python parses a + b + ...
    as a left-leaning tree)."""
    terms = " + ".join(f"{i + 1}e-3*alpha**{i % 5 + 1}" for i in range(80))
    spec = _spec(tmp_path, "q: M0 + MAL*alpha", f"q: M0 + MAL*alpha + MAL*({terms})")
    code, _, err = _run(capsys, "check", str(spec))
    assert code == 0, err
    deep = "sin(" * 70 + "alpha" + ")" * 70        # real nesting is still bounded
    spec = _spec(tmp_path, "q: M0 + MAL*alpha", f"q: M0 + MAL*{deep}")
    code, _, err = _run(capsys, "check", str(spec))
    assert code == 2 and "nested too deeply" in err


def test_too_many_states_are_refused_at_the_first_one_too_many(tmp_path, capsys):
    lines = ["name: big", "states:"] + [f"  x{i}: {{unit: '1'}}" for i in range(101)]
    lines += ["inputs:", "  u: {unit: '1'}", "outputs:", "  y: {unit: '1'}",
              "parameters:", "  a: {unit: 1/s}", "drift:"]
    lines += [f"  x{i}: -a*x{i} + u" for i in range(101)]
    lines += ["observations:", "  y: x0", "data:", "  time: t", "  inputs: {u: u}",
              "  outputs: {y: y}"]
    spec = tmp_path / "big.yaml"
    spec.write_text("\n".join(lines) + "\n")
    code, _, err = _run(capsys, "check", str(spec))
    assert code == 2 and "more than 100 states" in err and "big.yaml:103:" in err, err


@pytest.mark.parametrize("value", ["5", "true", "0.1"])
def test_a_state_given_a_value_instead_of_a_mapping_is_refused(tmp_path, capsys, value):
    spec = _spec(tmp_path, "  alpha: {", f"  alpha: {value}\n  alpha_unused_: {{")
    code, _, err = _run(capsys, "check", str(spec))
    assert code == 2 and "must be a mapping" in err and f"not the value" in err, err


def test_fleet_record_names_never_name_the_fleet_s_own_files():
    from vsidgen.atomic import MANIFEST
    from vsidgen.fitjob.fleet import _dir_names

    names = _dir_names(["..csv", "fleet.json.csv", f"{MANIFEST}.csv", "a.csv", "d/a.csv",
                        "a_2.csv", ".hidden.csv"])
    assert len(set(names)) == len(names)
    assert not any(n.startswith(".") or n in ("fleet.json", MANIFEST) for n in names), names
    assert names[3:6] == ["a", "a_2", "a_2_2"]


# ---------------------------------------------------------------------------
# silently accepted nonsense (red team, session 47)
# ---------------------------------------------------------------------------

def test_sat_with_its_limits_reversed_is_refused(tmp_path, capsys):
    spec = _spec(tmp_path, "MDE*de", "MDE*sat(de, 0.1, -0.1)")
    code, _, err = _run(capsys, "check", str(spec))
    assert code == 2 and "lower limit 0.1 is above the upper limit" in err


def test_an_initial_value_that_underflows_is_refused(tmp_path, capsys):
    text = SPEC.replace("parameters:\n", "parameters:\n  K: {initial: 1e-400}\n", 1)
    text = text.replace("MDE*de", "MDE*de + K*q", 1)
    (tmp_path / "s.yaml").write_text(text)
    code, _, err = _run(capsys, "check", str(tmp_path / "s.yaml"))
    assert code == 2 and "`1e-400` is too small" in err


def test_min_score_nan_is_refused(tmp_path, capsys):
    code, _, err = _run(capsys, "diagnose", str(_spec(tmp_path)),
                        str(ROOT / "data" / "attas_sp_synthetic.csv"), "-o", str(tmp_path / "d"),
                        "--min-score", "nan", "--quiet")
    assert code == 2 and "--min-score must be a finite number" in err
    assert not (tmp_path / "d").exists()


def test_report_never_writes_over_the_manifest(tmp_path, capsys):
    from vsidgen.atomic import MANIFEST, atomic_directory

    d = tmp_path / "res"
    with atomic_directory(d) as tmp:
        (tmp / "results.json").write_text("{}")
    before = (d / MANIFEST).read_text()
    code, _, err = _run(capsys, "report", str(d), "-o", str(d / MANIFEST), "--overwrite")
    assert code == 2 and "keeps its results" in err
    assert (d / MANIFEST).read_text() == before


def test_a_bidi_override_in_a_comment_is_refused(tmp_path, capsys):
    spec = _spec(tmp_path, "q: M0 + MAL*alpha", "q: M0 + MAL*alpha # \u202e comment")
    code, _, err = _run(capsys, "check", str(spec))
    assert code == 2 and "U+202E" in err and "\u202e" not in err
