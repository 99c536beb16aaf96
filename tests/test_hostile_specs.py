"""Hostile specs through the command line (issue 12, spec side).

Every file in ``tests/hostile/specs/`` (see its README) is copied into a fresh folder
and run through ``python -m vsidgen.cli`` in a subprocess with that folder as working
directory, a wall-clock limit and an address-space limit. Asserted for each case and
command: the payload's ``SENTINEL`` file does not exist, the case's files are unchanged,
the exit status is the expected one, and a refused spec gets a one-message error that
names the spec file with line (and column) and shows no traceback. The I/O corpus (data
files, results directories) lives beside it in ``tests/hostile/io/``.
"""

from __future__ import annotations

import hashlib
import os
import pathlib
import re
import shutil
import subprocess
import sys

import pytest

# one worker runs the whole module: its module-scoped fixtures are computed once
pytestmark = pytest.mark.xdist_group("test_hostile_specs")

ROOT = pathlib.Path(__file__).resolve().parents[1]
CORPUS = ROOT / "tests" / "hostile" / "specs"
CASES = sorted(CORPUS.glob("*.yaml"))

#: per command; generous for a loaded 2-core CI machine (a refused spec takes ~2-8 s)
TIME_LIMIT_S = 120
#: address-space limit of the child; JAX starts and simulates well within it
MEMORY_LIMIT = 4 << 30

SIM_ARGS = ["--input", "de=doublet:amplitude=0.02", "--duration", "1", "--dt", "0.1"]


def _header(path: pathlib.Path) -> dict:
    out = {"commands": ["check"], "expect-exit": 2, "expect-line": None, "setup": []}
    for line in path.read_text(encoding="utf-8").splitlines():
        m = re.match(r"# ([a-z-]+): (.*)$", line)
        if not m:
            break
        key, value = m.groups()
        if key == "commands":
            out["commands"] = value.split()
        elif key in ("expect-exit", "expect-line"):
            out[key] = int(value)
        elif key == "setup":
            out["setup"].append(value.split())
    return out


def _limits():  # runs in the child before exec
    import resource

    resource.setrlimit(resource.RLIMIT_AS, (MEMORY_LIMIT, MEMORY_LIMIT))


def _snapshot(folder: pathlib.Path) -> dict[str, str]:
    """sha256 of every regular file below ``folder`` except the outputs vsidgen may write."""
    out = {}
    for p in sorted(folder.rglob("*")):
        rel = p.relative_to(folder).as_posix()
        if rel.startswith("generated/") or rel in ("generated", "out.csv"):
            continue
        if p.is_symlink():
            out[rel] = "link:" + os.readlink(p)
        elif p.is_file():
            out[rel] = hashlib.sha256(p.read_bytes()).hexdigest()
        elif p.is_dir():
            out[rel] = "dir"
        else:
            out[rel] = "special"
    return out


def _setup(work: pathlib.Path, steps) -> None:
    for step in steps:
        kind, name = step[0], step[1]
        target = work / name
        if kind == "mkfifo":
            os.mkfifo(target)
        elif kind == "mkdir":
            target.mkdir()
        elif kind == "symlink":
            target.symlink_to(step[2])
        elif kind == "bigfile":
            with open(target, "wb") as fh:
                fh.write(b"name: big\n" + b"#" * int(step[2]) + b"\n")
        else:  # pragma: no cover - a typo in a case header
            raise AssertionError(f"unknown setup step {step}")


def run_cli(args, cwd: pathlib.Path) -> subprocess.CompletedProcess:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    env.pop("VSIDGEN_DEBUG", None)
    return subprocess.run([sys.executable, "-m", "vsidgen.cli", *args], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=TIME_LIMIT_S,
                          preexec_fn=_limits)


def _command(cmd: str, spec: str) -> list[str]:
    if cmd == "build":
        return ["build", spec, "--out", "generated"]
    if cmd == "simulate":
        return ["simulate", spec, "--out", "out.csv", *SIM_ARGS]
    return [cmd, spec]


def _run_case(case: pathlib.Path, base: pathlib.Path) -> dict:
    """Copy the corpus to ``base/work``, run the case's commands there, record everything."""
    header = _header(case)
    work = base / "work"
    shutil.copytree(CORPUS, work, symlinks=True)
    _setup(work, header["setup"])
    before = _snapshot(work)
    runs = []
    for cmd in header["commands"]:
        try:
            proc = run_cli(_command(cmd, case.name), work)
            outcome = (proc.returncode, proc.stdout, proc.stderr)
        except subprocess.TimeoutExpired:
            outcome = (None, "", f"timed out after {TIME_LIMIT_S} s")
        generated = work / "generated"
        runs.append({"cmd": cmd, "outcome": outcome,
                     "sentinel": (work / "SENTINEL").exists() or (base / "SENTINEL").exists(),
                     "changed": _snapshot(work) != before,
                     "generated": sorted(p.name for p in generated.iterdir())
                     if generated.is_dir() else []})
    return {"header": header, "runs": runs, "work": work}


@pytest.fixture(scope="module")
def corpus_results(tmp_path_factory):
    """Every case run once, two subprocesses at a time (each in its own folder)."""
    from concurrent.futures import ThreadPoolExecutor

    bases = {case: tmp_path_factory.mktemp(case.stem) for case in CASES}
    with ThreadPoolExecutor(max_workers=2) as pool:
        futures = {case: pool.submit(_run_case, case, bases[case]) for case in CASES}
        return {case: f.result() for case, f in futures.items()}


@pytest.mark.parametrize("case", CASES, ids=[c.stem for c in CASES])
def test_hostile_spec(case, corpus_results):
    result = corpus_results[case]
    header = result["header"]
    for run in result["runs"]:
        cmd = run["cmd"]
        code, stdout, stderr = run["outcome"]
        out = stdout + stderr
        assert code is not None, f"{case.name}: {cmd} {stderr}"
        assert not run["sentinel"], f"{case.name}: payload ran ({cmd})"
        assert "Traceback" not in out and "internal error" not in out, f"{cmd}: {out}"
        assert "\x1b" not in out, f"{cmd}: a terminal escape sequence reached the output"
        assert code == header["expect-exit"], f"{cmd} -> {code}: {out}"
        if header["expect-exit"] == 2:
            m = re.search(r"^(.+?):(\d+)(?::(\d+))?: error: ", stderr, re.M)
            assert m, f"{cmd}: no located error: {out}"
            assert pathlib.Path(m.group(1)).name == case.name, f"{cmd}: wrong file: {out}"
            if header["expect-line"] is not None:
                assert int(m.group(2)) == header["expect-line"], f"{cmd}: wrong line: {out}"
            assert "root:" not in out and "PATH=" not in out, "foreign file content echoed"
            assert len(stderr) < 4000, f"{cmd}: message too long ({len(stderr)})"
            assert run["generated"] == [], f"{cmd} wrote {run['generated']}"
        assert not run["changed"], f"{case.name}: files changed by {cmd}"
    if "simulate" in header["commands"] and header["expect-exit"] == 0:
        lines = (result["work"] / "out.csv").read_text().splitlines()
        assert len(lines) == 12, lines[:3]


HOSTILE_FILE_NAMES = [
    'quote"name.yaml',
    "apostrophe'name.yaml",
    'x"; import os; os.system("touch SENTINEL"); y=".yaml',
    "line\nimport os; os.system('touch SENTINEL')\n#.yaml",
    "back\\slash \u2028 sep\r.yaml",
    "\"\"\"triple.yaml",
]


def test_hostile_spec_file_names(tmp_path):
    """Specs whose file names hold quotes, line breaks and code build and simulate safely,
    and each module records its file name exactly (``SPEC_PATH``)."""
    import ast

    work = tmp_path / "work"
    work.mkdir()
    text = (CORPUS / "bases" / "payload_base.yaml").read_text(encoding="utf-8")
    for i, fname in enumerate(HOSTILE_FILE_NAMES):
        (work / fname).write_text(text.replace("name: payload_base", f"name: file_name_{i}"),
                                  encoding="utf-8")
    proc = run_cli(["build", *HOSTILE_FILE_NAMES, "--out", "generated"], work)
    assert proc.returncode == 0 and "Traceback" not in proc.stderr, proc.stderr
    proc = run_cli(_command("simulate", HOSTILE_FILE_NAMES[3]), work)
    assert proc.returncode == 0 and "Traceback" not in proc.stderr, proc.stderr
    assert not (work / "SENTINEL").exists()
    for i, fname in enumerate(HOSTILE_FILE_NAMES):
        tree = ast.parse((work / "generated" / f"file_name_{i}.py").read_text(encoding="utf-8"))
        assigned = {t.id: n.value for n in tree.body if isinstance(n, ast.Assign)
                    for t in n.targets if isinstance(t, ast.Name)}
        assert ast.literal_eval(assigned["SPEC_PATH"]) == fname


def test_corpus_covers_the_issue():
    """The corpus keeps a case for every spec-side finding of issue 12 (and issue 17)."""
    names = {c.stem for c in CASES}
    for required in ("payload_every_field", "extends_payload_base", "alias_bomb",
                     "extends_dev_zero", "extends_etc_passwd", "extends_fifo",
                     "chained_definitions_20", "int_power_overflow", "float_product_overflow",
                     "exp_overflow", "long_model_name", "unit_newline", "name_trailing_newline",
                     "nested_power", "description_tagged_list", "reserved_name_jnp"):
        assert required in names, required
