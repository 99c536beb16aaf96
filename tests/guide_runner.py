"""Run the console blocks of a markdown guide (used by tests/test_authoring_guide.py).

A block is a fenced ``console`` code block; its lines starting with ``$ `` are
commands (run by bash with ``vsidgen`` = ``python -m vsidgen.cli`` of this
checkout), the lines after a command up to the next command are its output as
measured. ``# exit status N`` at the end of a command gives its expected exit
status (default 0). Outputs are compared after normalisation: durations
(``12.3 s``) are masked and numbers compared with a relative tolerance.
"""

from __future__ import annotations

import dataclasses
import math
import os
import pathlib
import re
import subprocess
import sys

ROOT = pathlib.Path(__file__).resolve().parent.parent
_BLOCK = re.compile(r"^```console\n(.*?)^```", re.S | re.M)
_EXIT = re.compile(r"#\s*exit status (\d+)\s*$")
_TIME = re.compile(r"\b\d+(?:\.\d+)?(?= s\b)")
_NUM = re.compile(r"[-+−]?(?:\d+\.\d*|\.\d+|\d+)(?:[eE][-+]?\d+)?")


@dataclasses.dataclass(frozen=True)
class Step:
    command: str
    expected_output: str
    exit_status: int

    @property
    def fits(self) -> bool:
        """Whether the step runs the estimator (slow: JAX compilation and a fit)."""
        return bool(re.search(r"\bvsidgen (fit|report|diagnose)\b", self.command)) \
            and self.exit_status != 2


def steps(markdown: str) -> list[Step]:
    out = []
    for block in _BLOCK.findall(markdown):
        cmd, lines = None, []
        for line in block.splitlines():
            if line.startswith("$ "):
                if cmd is not None:
                    out.append(_step(cmd, lines))
                cmd, lines = line[2:], []
            else:
                lines.append(line)
        if cmd is not None:
            out.append(_step(cmd, lines))
    return out


def _step(cmd: str, lines: list[str]) -> Step:
    m = _EXIT.search(cmd)
    status = int(m.group(1)) if m else 0
    return Step(cmd, "\n".join(lines).rstrip(), status)


def run(step: Step, cwd: pathlib.Path, *, timeout: float = 1800) -> tuple[int, str]:
    env = dict(os.environ, PYTHONPATH=str(ROOT), COLUMNS="100", PYTHONUNBUFFERED="1")
    script = (f'vsidgen() {{ "{sys.executable}" -m vsidgen.cli "$@"; }}\n'
              f"{step.command}\n")
    proc = subprocess.run(["bash", "-c", script], cwd=cwd, env=env, stdout=subprocess.PIPE,
                          stderr=subprocess.STDOUT, text=True, timeout=timeout)
    text = proc.stdout
    return proc.returncode, "\n".join(l.rstrip() for l in text.rstrip().splitlines())


def _normalise(text: str) -> tuple[str, list[float]]:
    text = _TIME.sub("<T>", text)
    nums = [float(x.replace("−", "-")) for x in _NUM.findall(text)]
    return _NUM.sub("<N>", text), nums


def same_output(expected: str, actual: str, *, rel: float = 1e-3, abs_: float = 1e-9) -> str | None:
    """None when ``actual`` matches ``expected`` (see the module docstring), else why not."""
    se, ne = _normalise(expected)
    sa, na = _normalise(actual)
    if se != sa:
        return f"text differs:\n--- guide\n{expected}\n--- measured\n{actual}"
    for a, b in zip(ne, na):
        if not math.isclose(a, b, rel_tol=rel, abs_tol=abs_):
            return f"number {b} differs from the guide's {a}:\n{actual}"
    return None
