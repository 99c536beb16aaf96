"""CLI: build / check / show exit codes and output."""

import argparse
import pathlib
import subprocess
import sys

import pytest

from vsidgen.cli import main
from vsidgen.errors import SpecError
from vsidgen.data.check import check_first_sample
from vsidgen.spec import compile_spec

SPECS = pathlib.Path(__file__).parent / "specs"

CSV = "t_s,de_rad,v_mps,alpha_deg,az_mps2\n0.0,0.01,100.0,3.0,-9.7\n0.1,0.01,100.1,3.1,-9.8\n"


def test_build_and_up_to_date(tmp_path, capsys):
    assert main(["build", str(SPECS / "base.yaml"), "--out", str(tmp_path)]) == 0
    out = capsys.readouterr()
    assert "wrote:" in out.out and (tmp_path / "base.py").exists()
    assert "unused constant `V0`" in out.err
    assert main(["build", str(SPECS / "base.yaml"), "--out", str(tmp_path)]) == 0
    assert "up to date:" in capsys.readouterr().out
    assert main(["build", str(SPECS / "base.yaml"), "--out", str(tmp_path), "--force"]) == 0
    assert "wrote:" in capsys.readouterr().out


def test_check_ok(capsys):
    assert main(["check", str(SPECS / "child.yaml")]) == 0
    out = capsys.readouterr()
    assert "ok (child: 3 states" in out.out


def test_check_bad_spec_reports_location_without_traceback(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: bad\nstates:\n  V: {}\ndrift:\n  V: -V + alfa\n")
    proc = subprocess.run([sys.executable, "-m", "vsidgen.cli", "check", str(bad)],
                          capture_output=True, text=True)
    assert proc.returncode == 2
    assert f"{bad}:5:11: error: unknown symbol `alfa`" in proc.stderr
    assert "Traceback" not in proc.stderr and proc.stdout == ""


def test_check_missing_file_and_usage(capsys):
    assert main(["check", "does/not/exist.yaml"]) == 2
    assert "spec file not found" in capsys.readouterr().err
    assert main(["frobnicate"]) == 2
    assert main(["--help"]) == 0


def test_show_plain_and_latex(capsys):
    assert main(["show", str(SPECS / "base.yaml")]) == 0
    out = capsys.readouterr().out
    assert "dV/dt = -SBYM*qbar*(CD0 + 0.1*CL**2)" in out
    assert "qbar = RHO*V**2/2" in out and "V [m/s]" in out
    assert main(["show", "--latex", str(SPECS / "base.yaml")]) == 0
    latex = capsys.readouterr().out
    assert latex.startswith("\\begin{align}") and "\\dot{V}" in latex


def _record(n=20, *, dt=0.1):
    """A CSV record of n samples for tests/specs/base.yaml."""
    rows = [f"{k * dt:.3f},0.01,{100 + 0.1 * k:.2f},{3 + 0.01 * k:.3f},-9.7" for k in range(n)]
    return "t_s,de_rad,v_mps,alpha_deg,az_mps2\n" + "\n".join(rows) + "\n"


def test_check_with_data(tmp_path, capsys):
    csv = tmp_path / "rec.csv"
    csv.write_text(CSV)
    assert check_first_sample(compile_spec(SPECS / "base.yaml"), csv) == []
    assert main(["check", str(SPECS / "base.yaml"), "--data", str(csv)]) == 2  # 2 samples
    assert "too few samples" in capsys.readouterr().err
    csv.write_text(_record())
    assert main(["check", str(SPECS / "base.yaml"), "--data", str(csv)]) == 0
    # the record positionally, as `fit` takes it; not both ways at once
    csv.write_text(CSV)
    assert main(["check", str(SPECS / "base.yaml"), str(csv)]) == 2
    assert "too few samples" in capsys.readouterr().err
    assert main(["check", str(SPECS / "base.yaml"), str(csv), "--data", str(csv)]) == 2
    assert "not allowed with argument" in capsys.readouterr().err


@pytest.mark.parametrize("edit, message", [
    (lambda rows: rows[:8] + [rows[8].replace("0.01,", ",", 1)] + rows[9:],
     "missing value in input 'de'"),
    (lambda rows: rows[:12] + rows[13:], "non-uniform sampling"),
    (lambda rows: rows[:5] + [rows[6], rows[5]] + rows[7:], "time is not increasing"),
])
def test_check_data_reads_the_whole_record(tmp_path, capsys, edit, message):
    lines = _record().splitlines()
    csv = tmp_path / "rec.csv"
    csv.write_text("\n".join([lines[0]] + edit(lines[1:])) + "\n")
    assert main(["check", str(SPECS / "base.yaml"), "--data", str(csv)]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err


def test_check_data_nonfinite_drift_later_in_the_record(tmp_path, capsys):
    (tmp_path / "base.yaml").write_text((SPECS / "base.yaml").read_text())
    kid = tmp_path / "kid.yaml"
    kid.write_text("name: kid\nextends: base.yaml\nadd_terms:\n  drift: {alpha: 0.01*log(V)}\n")
    lines = _record().splitlines()
    lines[15] = lines[15].replace(",101.40,", ",0.00,")  # V = 0 at sample 14 -> log(V) = -inf
    csv = tmp_path / "rec.csv"
    csv.write_text("\n".join(lines) + "\n")
    assert main(["check", str(kid), "--data", str(csv)]) == 2
    err = capsys.readouterr().err
    assert "sample 14 (t = 1.4 s)" in err and "drift of `alpha`" in err


def test_check_data_nonfinite_drift(tmp_path):
    csv = tmp_path / "rec.csv"
    csv.write_text(CSV.replace("0.0,0.01,100.0", "0.0,0.01,0.0"))  # V = 0 -> log(V) = -inf
    (tmp_path / "base.yaml").write_text((SPECS / "base.yaml").read_text())
    kid = tmp_path / "kid.yaml"
    kid.write_text("name: kid\nextends: base.yaml\nadd_terms:\n  drift: {alpha: 0.01*log(V)}\n")
    assert check_first_sample(compile_spec(tmp_path / "base.yaml"), csv) == []
    with pytest.raises(SpecError) as ei:
        check_first_sample(compile_spec(kid), csv)
    assert "drift of `alpha`" in ei.value.message and "drift of `V`" not in ei.value.message
    assert ei.value.line == 29 and ei.value.path.name == "base.yaml"
    assert main(["check", str(kid), "--data", str(csv)]) == 2


def test_check_data_missing_column(tmp_path, capsys):
    csv = tmp_path / "rec.csv"
    csv.write_text(CSV.replace("de_rad", "de_rd"))
    assert main(["check", str(SPECS / "base.yaml"), "--data", str(csv)]) == 2
    err = capsys.readouterr().err
    assert "column `de_rad`" in err and "did you mean `de_rd`?" in err


def test_channel_expression_evaluated(tmp_path):
    csv = tmp_path / "rec.csv"
    csv.write_text("t_s,u1_mps2,p_right_rad,p_left_rad,y1_m,y2_rad,y3\n0,0.1,0.3,0.1,0.5,0.2,0.1\n")
    assert check_first_sample(compile_spec(SPECS / "nonlinear.yaml"), csv) == []


def test_show_prints_what_is_fitted_besides_the_equations(tmp_path, capsys):
    """Integrator, sub-steps, input hold and delays, and the noise settings, after the equations."""
    d = tmp_path / "specs"
    d.mkdir()
    spec = d / "settings.yaml"
    spec.write_text("""\
name: settings
integrator: {method: rk4, substeps: 2, inputs: foh}
states:
  alpha: {unit: rad}
  q: {unit: rad/s}
  theta: {unit: rad}
inputs:
  de: {unit: rad, delay: 0.08}
outputs:
  alpha: {unit: rad}
  q: {unit: rad/s}
parameters:
  Za: {unit: 1/s}
drift:
  alpha: Za*alpha + q
  q: de
  theta: q
observations:
  alpha: alpha
  q: q
noise:
  process:
    states: [alpha, q]
    structure: full
    degenerate: [q]
    floor: {alpha: 0.001}
  measurement:
    alpha: {estimate: false, std: 0.002}
    q: {floor: 0}
data:
  time: t
  inputs: {de: de}
  outputs: {alpha: a, q: q}
""")
    assert main(["show", str(spec)]) == 0
    out = capsys.readouterr().out
    settings = out[out.index("\nsettings:"):]
    assert out.index("outputs:") < out.index("\nsettings:")
    for text in ("integrator: rk4, 2 sub-steps per sample; inputs: first-order hold",
                 "input delay: de 0.08 s",
                 "process noise: alpha, q (full lower-triangular G, correlated, estimated)",
                 "floor: alpha 0.001 [rad/sqrt(s)]",
                 "degenerate (no independent noise, G_ii = 0): q",
                 "without process noise (fitted in the limit of vanishing noise): theta",
                 "alpha: fixed, std 0.002 [rad], floor auto", "q: estimated, no floor"):
        assert text in settings, (text, settings)


def test_every_out_option_has_the_short_form_o():
    """``-o`` is ``--out`` for every command that writes (users type it out of habit)."""
    from vsidgen.cli import make_parser

    p = make_parser()
    sub = next(a for a in p._actions if isinstance(a, argparse._SubParsersAction))
    with_out = 0
    for name, sp in sub.choices.items():
        opts = {s for a in sp._actions for s in a.option_strings}
        if "--out" in opts:
            with_out += 1
            assert "-o" in opts, name
    assert with_out >= 4


BODY_AXIS = """\
name: body
states: {u: {unit: m/s}, w: {unit: m/s}}
inputs: {de: {unit: rad}}
outputs: {V: {unit: m/s}, alpha: {unit: rad}}
parameters: {Xu: {unit: 1/s}, Zw: {unit: 1/s}, Zde: {unit: m/s^2/rad}}
definitions:
  Vt: sqrt(u**2 + w**2)
drift:
  u: Xu*u*u/Vt
  w: Zw*w + Zde*de + LOGTERM
observations:
  V: Vt
  alpha: atan2(w, u)
data:
  time: t_s
  inputs: {de: de_rad}
  outputs: {V: v_mps, alpha: alpha_rad}
"""


def test_check_with_data_evaluates_at_the_fits_start(tmp_path, capsys):
    """States no output measures directly (body-axis u, w under V, α) start where the fit
    starts them, solved from the outputs: u = w = 0 would make u²/√(u² + w²) 0/0, but
    `check --data` now agrees with the fit and passes; an equation that is not finite there
    either is still an error naming it, the sample and the start."""
    import math

    rows = [f"{0.05 * k:.2f},{0.01 * math.sin(k / 5):.5f},{60 + 0.1 * k:.2f},"
            f"{0.05 + 0.001 * k:.4f}" for k in range(40)]
    csv = tmp_path / "rec.csv"
    csv.write_text("t_s,de_rad,v_mps,alpha_rad\n" + "\n".join(rows) + "\n")
    spec = tmp_path / "body.yaml"
    spec.write_text(BODY_AXIS.replace(" + LOGTERM", ""))
    assert main(["check", str(spec), "--data", str(csv)]) == 0, capsys.readouterr().err
    assert "0 warnings" in capsys.readouterr().out
    spec.write_text(BODY_AXIS.replace("LOGTERM", "Zw*w*log(u/Vt - 2)"))
    assert main(["check", str(spec), "--data", str(csv)]) == 2
    err = capsys.readouterr().err
    assert "non-finite value at sample 0" in err and "drift of `w`" in err
    assert "the fit's start" in err


def test_python_m_vsidgen_is_the_command_line():
    """`python -m vsidgen` runs the same command line as the `vsidgen` script (exit codes too)."""
    ok = subprocess.run([sys.executable, "-m", "vsidgen", "check", str(SPECS / "child.yaml")],
                        capture_output=True, text=True)
    assert ok.returncode == 0 and "ok (child: 3 states" in ok.stdout
    bad = subprocess.run([sys.executable, "-m", "vsidgen", "check", str(SPECS / "missing.yaml")],
                         capture_output=True, text=True)
    assert bad.returncode == 2 and "Traceback" not in bad.stderr


def test_build_never_replaces_another_specs_module_or_a_foreign_file(tmp_path, capsys):
    """A user's spec named like a shipped one, built from the repository's folder, wrote
    ./generated/<name>.py over the repository's module (session 43, a new user's HFB-320 spec
    named `hfb320`). A module generated from another spec, or a file vsidgen did not write,
    is left as it is (exit 2, the spec's `name:` line and a hint); this spec's own module is
    rebuilt as before."""
    repo = tmp_path / "repo"
    (repo / "specs").mkdir(parents=True)
    text = (SPECS / "base.yaml").read_text(encoding="utf-8")
    (repo / "specs" / "base.yaml").write_text(text, encoding="utf-8")
    gen = repo / "generated"
    assert main(["build", str(repo / "specs" / "base.yaml"), "--out", str(gen)]) == 0
    shipped = (gen / "base.py").read_bytes()
    mine = tmp_path / "mine" / "base.yaml"
    mine.parent.mkdir()
    mine.write_text(text.replace("V0", "V1"), encoding="utf-8")
    capsys.readouterr()
    assert main(["build", str(mine), "--out", str(gen)]) == 2
    err = capsys.readouterr().err
    assert "generated from another spec ('specs/base.yaml')" in err and "another `name:`" in err
    assert (gen / "base.py").read_bytes() == shipped
    assert main(["build", str(mine), "--out", str(gen), "--force"]) == 2   # force rebuilds, never clobbers
    assert (gen / "base.py").read_bytes() == shipped
    # a file of the user's own with the model's name
    own = tmp_path / "own"
    own.mkdir()
    (own / "base.py").write_text("x = 1\n", encoding="utf-8")
    assert main(["build", str(mine), "--out", str(own)]) == 2
    assert "not a module vsidgen generated" in capsys.readouterr().err
    assert (own / "base.py").read_text(encoding="utf-8") == "x = 1\n"
    # the spec's own module, changed spec: rebuilt
    (repo / "specs" / "base.yaml").write_text(text.replace("description: small", "description: a small"),
                                             encoding="utf-8")
    assert main(["build", str(repo / "specs" / "base.yaml"), "--out", str(gen)]) == 0
    assert "wrote:" in capsys.readouterr().out
