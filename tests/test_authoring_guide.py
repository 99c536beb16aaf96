"""docs/authoring.md: every command of the guide runs and prints what the guide shows.

The fast steps (check, show, build, simulate, the error examples) run in the
default suite; the fits (and the steps after them) are marked slow. Each run
works in a copy of docs/authoring/, so the repository is not written to.
"""

from __future__ import annotations

import pathlib
import shutil

import numpy as np
import pytest

from guide_runner import run, same_output, steps

ROOT = pathlib.Path(__file__).resolve().parent.parent
GUIDE = ROOT / "docs" / "authoring.md"
STEPS = steps(GUIDE.read_text(encoding="utf-8"))


def _copy(tmp_path) -> pathlib.Path:
    work = tmp_path / "authoring"
    shutil.copytree(ROOT / "docs" / "authoring", work,
                    ignore=shutil.ignore_patterns("generated", "results", "navion_flight.csv"))
    return work


def _check(step, work):
    if step.command.startswith("cd "):
        return
    code, out = run(step, work)
    assert code == step.exit_status, f"{step.command}: exit {code}\n{out}"
    why = same_output(step.expected_output, out)
    assert why is None, f"{step.command}: {why}"


def test_guide_has_every_step():
    cmds = " ".join(s.command for s in STEPS)
    for needed in ("vsidgen check", "vsidgen show", "vsidgen build", "vsidgen simulate",
                   "vsidgen fit", "--data", "--report", "--fix", "# exit status 2"):
        assert needed in cmds
    assert all(s.expected_output for s in STEPS if not s.command.startswith("cd "))
    assert "(docs/authoring.md)" in (ROOT / "README.md").read_text()


def test_guide_fast_steps(tmp_path):
    """check, show, build, simulate and the error examples, in the guide's order."""
    work = _copy(tmp_path)
    for step in STEPS:
        if step.fits:
            continue
        _check(step, work)
    # the simulated record is the one shipped beside the guide
    made = np.genfromtxt(work / "navion_flight.csv", delimiter=",", names=True)
    shipped = np.genfromtxt(ROOT / "docs" / "authoring" / "navion_flight.csv", delimiter=",",
                            names=True)
    assert made.dtype.names == shipped.dtype.names
    for name in made.dtype.names:
        np.testing.assert_allclose(made[name], shipped[name], rtol=1e-9, atol=1e-12)


@pytest.mark.slow
def test_guide_all_steps(tmp_path):
    """Every step including the fits and the report (about a minute per fit on one core)."""
    work = _copy(tmp_path)
    for step in STEPS:
        _check(step, work)
    assert (work / "results" / "navion" / "report.html").is_file()
