"""The installed package works outside the checkout.

Builds a wheel of this checkout, installs it (without dependencies, which the running
interpreter already has) into a fresh virtual environment created *outside* the
repository, and runs the console script there, in a working directory that holds only a
copy of one spec and its records: ``build`` (the model template must ship inside the
package), ``fit --report`` (the report templates too) and ``diagnose --help``.
"""

from __future__ import annotations

import os
import pathlib
import shutil
import subprocess
import sys
import venv

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]


def _run(cmd, *, cwd, env=None, timeout=600):
    proc = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    assert proc.returncode == 0, f"{cmd} exited {proc.returncode}\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
    return proc


def _pip_has_vsidgen(cwd) -> bool:
    return subprocess.run([sys.executable, "-m", "pip", "show", "-q", "vsidgen"], cwd=cwd,
                          capture_output=True).returncode == 0


def test_wheel_installs_and_runs_outside_checkout(tmp_path):
    if shutil.which("git") is None:
        pytest.skip("git is needed to copy the tracked files")
    # build from the tracked files only (no stale build/ or egg-info of the checkout)
    src = tmp_path / "src"
    _run(["git", "worktree", "list"], cwd=ROOT)  # a git checkout
    files = _run(["git", "ls-files", "-z"], cwd=ROOT).stdout.split("\0")
    for rel in filter(None, files):
        p = ROOT / rel
        dest = src / rel
        dest.parent.mkdir(parents=True, exist_ok=True)
        if p.is_symlink():
            os.symlink(os.readlink(p), dest)
        elif p.is_file():
            shutil.copy2(p, dest)
    wheels = tmp_path / "wheels"
    _run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q",
          "-w", str(wheels), str(src)], cwd=tmp_path)
    (wheel,) = wheels.glob("vsidgen-*.whl")

    installed_before = _pip_has_vsidgen(tmp_path)
    env_dir = tmp_path / "venv"
    venv.EnvBuilder(system_site_packages=True, with_pip=False, symlinks=True).create(env_dir)
    py = env_dir / "bin" / "python"
    exe = env_dir / "bin" / "vsidgen"
    # pip of the running interpreter installs into the new environment's prefix;
    # --ignore-installed: without it pip first *uninstalls* the vsidgen of the running
    # environment (the developer's editable install, the one CI's `pip install -e .` made)
    _run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-index",
          "--ignore-installed", "--prefix", str(env_dir), str(wheel)], cwd=tmp_path)
    assert _pip_has_vsidgen(tmp_path) == installed_before, "the running environment's vsidgen was removed"

    work = tmp_path / "user"
    (work / "specs").mkdir(parents=True)
    shutil.copy(ROOT / "specs" / "attas_sp.yaml", work / "specs")
    shutil.copy(ROOT / "data" / "attas_sp_synthetic.csv", work)
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH",)}
    env["PYTHONNOUSERSITE"] = "1"
    # the package imported there is the wheel's, not this checkout's
    where = _run([str(py), "-c", "import vsidgen, pathlib; print(pathlib.Path(vsidgen.__file__).resolve())"],
                 cwd=work, env=env).stdout.strip()
    assert pathlib.Path(where).is_relative_to(env_dir.resolve()), where

    # the console script is run by the environment's interpreter (pip --prefix writes the
    # running interpreter into its shebang line, which does not see the new environment)
    _run([str(py), str(exe), "build", "specs/attas_sp.yaml", "--out", "generated"], cwd=work, env=env)
    assert (work / "generated" / "attas_sp.py").is_file()
    _run([str(py), str(exe), "fit", "specs/attas_sp.yaml", "attas_sp_synthetic.csv", "--out", "res",
          "--report", "--quiet"], cwd=work, env=env)
    assert (work / "res" / "results.json").is_file()
    html = (work / "res" / "report.html").read_text()
    assert "attas_sp" in html and "<img" in html
    assert "diagnose" in _run([str(py), str(exe), "diagnose", "--help"], cwd=work, env=env).stdout
