"""Hostile and careless input on the I/O side (issue 12), each case through the CLI.

Every case runs ``python -m vsidgen.cli ...`` in a subprocess with a temporary
working directory holding a folder of the user's files (a spec, records, notes),
under a wall-clock timeout and an address-space limit (``RLIMIT_AS``), and asserts:

* exit status 2 and a message on stderr that names the file and, for data
  values, the column and the sample; no ``Traceback`` and no ``internal error``;
* nothing was executed (no ``SENTINEL`` file appears; several inputs carry code
  that would create it);
* no file of the user's changed: content hash, permission bits and the set of
  entries of every file and folder under the temporary directory are the same
  before and after.

The cases are refused before any fitting, so the corpus stays cheap. Static inputs
are in ``tests/hostile/io/``; devices, pipes, oversized files, symbolic links and
crafted results directories are made here. Crash recovery of the results-directory
swap (item 9) is tested by killing a child process between the two renames.
"""

from __future__ import annotations

import hashlib
import json
import os
import pathlib
import resource
import shutil
import stat
import subprocess
import sys
import textwrap

import numpy as np
import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
HOSTILE = ROOT / "tests" / "hostile" / "io"
SPEC = ROOT / "specs" / "attas_sp.yaml"
DATA = ROOT / "data" / "attas_sp_synthetic.csv"
#: address-space limit of every child (JAX starts well below it; measured: under 2 GB)
MEMORY_LIMIT = 3 << 30
TIMEOUT_S = 120


def _limit_memory():
    resource.setrlimit(resource.RLIMIT_AS, (MEMORY_LIMIT, MEMORY_LIMIT))


def run_cli(args, cwd, env_extra=None, timeout=TIMEOUT_S):
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    env["VSIDGEN_CACHE_DIR"] = ""
    env.pop("VSIDGEN_DEBUG", None)
    env.update(env_extra or {})
    return subprocess.run([sys.executable, "-m", "vsidgen.cli", *map(str, args)], cwd=cwd,
                          env=env, capture_output=True, text=True, timeout=timeout,
                          preexec_fn=_limit_memory)


def snapshot(root: pathlib.Path) -> dict:
    """{relative path: (kind, permission bits, sha256 | link target)} of everything under root."""
    out = {}
    for dirpath, dirs, files in os.walk(root, followlinks=False):
        for name in dirs + files:
            p = pathlib.Path(dirpath) / name
            st = os.lstat(p)
            rel = p.relative_to(root).as_posix()
            mode = stat.S_IMODE(st.st_mode)
            if stat.S_ISLNK(st.st_mode):
                out[rel] = ("link", mode, os.readlink(p))
            elif stat.S_ISREG(st.st_mode):
                out[rel] = ("file", mode, hashlib.sha256(p.read_bytes()).hexdigest())
            elif stat.S_ISDIR(st.st_mode):
                out[rel] = ("dir", mode, None)
            else:
                out[rel] = ("special", mode, stat.S_IFMT(st.st_mode))
    out["."] = ("dir", stat.S_IMODE(os.lstat(root).st_mode), None)
    return out


@pytest.fixture
def user_dir(tmp_path):
    """A folder of the user's: spec, records, notes (mode 0750), and the hostile inputs."""
    u = tmp_path / "user"
    u.mkdir()
    shutil.copy(SPEC, u / "attas_sp.yaml")
    shutil.copy(DATA, u / "flight.csv")
    (u / "notes.txt").write_text("my notes\n")
    os.chmod(u, 0o750)
    shutil.copytree(HOSTILE, tmp_path / "hostile")
    return tmp_path


def expect_refused(proc, *texts):
    err = proc.stderr
    assert proc.returncode == 2, (proc.returncode, err[-3000:], proc.stdout[-1000:])
    assert "Traceback" not in err and "internal error" not in err, err
    for t in texts:
        assert t in err, (t, err)


def _case(tmp: pathlib.Path, args, *texts, env=None):
    before = snapshot(tmp)
    proc = run_cli(args, tmp, env)
    expect_refused(proc, *texts)
    assert not (tmp / "SENTINEL").exists()
    after = snapshot(tmp)
    assert after == before, {k: (before.get(k), after.get(k))
                             for k in set(before) | set(after) if before.get(k) != after.get(k)}
    return proc


# --------------------------------------------------------------------------- data files

DATA_CASES = [
    # (file under hostile/, expected texts in the message)
    ("input_1e308.csv", ["input_1e308.csv", "column 'de_rad'", "sample 17", "1e+308"]),
    ("output_1e308.csv", ["output_1e308.csv", "column 'alpha_rad'", "sample 23"]),
    ("output_neg_inf.csv", ["output_neg_inf.csv", "column 'q_radps'", "sample 5", "-inf"]),
    ("input_nan.csv", ["input_nan.csv", "column 'de_rad'", "sample 9"]),
    ("time_1e300.csv", ["time_1e300.csv", "column 't_s'", "sample 0"]),
    ("time_step_1e-300.csv", ["time_step_1e-300.csv", "column 't_s'", "sample period 1e-300 s"]),
    ("time_epoch_1e300_step.csv", ["time_epoch_1e300_step.csv", "column 't_s'"]),
    ("time_nan.csv", ["time_nan.csv", "column 't_s'", "sample 12"]),
    ("code_in_cell.csv", ["code_in_cell.csv", "column 'alpha_rad'", "sample 3", "non-numeric"]),
    ("code_in_header.csv", ["code_in_header.csv", "'alpha_rad' (for output `alpha`) is not in the file"]),
    ("binary_garbage.csv", ["binary_garbage.csv"]),
]


@pytest.mark.parametrize("name,texts", DATA_CASES, ids=[c[0] for c in DATA_CASES])
def test_fit_refuses_bad_record(user_dir, name, texts):
    proc = _case(user_dir, ["fit", "user/attas_sp.yaml", f"hostile/{name}", "--out", "res",
                            "--quiet"], *texts)
    assert "np.float64" not in proc.stderr


def test_fit_refuses_csv_syntax_beyond_the_parser_limits(user_dir):
    """Fields longer than the csv module's limit, in the header and in a data row."""
    header = "t_s,de_rad,alpha_rad,q_radps"
    rows = [f"{k * 0.04:.2f},0.01,0.03,0.002" for k in range(20)]
    (user_dir / "long_header.csv").write_text(header + ",x" * 3 + "," + "a" * 300_000 + "\n"
                                              + "\n".join(rows) + "\n")
    _case(user_dir, ["fit", "user/attas_sp.yaml", "long_header.csv", "--out", "res", "--quiet"],
          "long_header.csv", "header row cannot be read")
    bad = list(rows)
    bad[6] = '0.24,0.01,"' + "7" * 300_000 + '",0.002'
    (user_dir / "long_quoted_cell.csv").write_text(header + "\n" + "\n".join(bad) + "\n")
    _case(user_dir, ["fit", "user/attas_sp.yaml", "long_quoted_cell.csv", "--out", "res",
                     "--quiet"], "long_quoted_cell.csv", "sample 6", "file line 8")
    _case(user_dir, ["check", "user/attas_sp.yaml", "--data", "long_header.csv"],
          "long_header.csv")


def test_fit_refuses_devices_pipes_directories(user_dir):
    os.mkfifo(user_dir / "pipe.csv")
    for data, text in (("/dev/zero", "character device"), ("pipe.csv", "named pipe"),
                       ("user", "is a directory"), ("missing.csv", "not found")):
        _case(user_dir, ["fit", "user/attas_sp.yaml", data, "--out", "res", "--quiet"], data, text)
    _case(user_dir, ["fit", "user/attas_sp.yaml", "user/flight.csv", "--validate", "/dev/zero",
                     "--out", "res", "--quiet"], "/dev/zero", "character device")
    _case(user_dir, ["simulate", "user/attas_sp.yaml", "--inputs-from", "/dev/zero",
                     "--out", "sim.csv"], "/dev/zero", "character device")
    _case(user_dir, ["check", "user/attas_sp.yaml", "--data", "/dev/zero"], "/dev/zero",
          "character device")
    _case(user_dir, ["check", "user/attas_sp.yaml", "--data", "pipe.csv"], "pipe.csv",
          "named pipe")


def test_fit_refuses_files_over_the_size_limit(user_dir):
    big = user_dir / "big.csv"
    with open(big, "wb") as fh:  # sparse: 3 MiB of nothing on disk
        fh.truncate(3 << 20)
    _case(user_dir, ["fit", "user/attas_sp.yaml", "big.csv", "--out", "res", "--quiet"],
          "big.csv", "3 MiB", "limit of 1 MiB", "VSIDGEN_MAX_DATA_BYTES",
          env={"VSIDGEN_MAX_DATA_BYTES": "1M"})
    _case(user_dir, ["fit", "user/attas_sp.yaml", "big.csv", "--out", "res", "--quiet"],
          "VSIDGEN_MAX_DATA_BYTES", "byte count", env={"VSIDGEN_MAX_DATA_BYTES": "lots"})


# --------------------------------------------------------------------------- arguments, outputs

def test_fit_never_writes_into_a_folder_of_the_users(user_dir):
    """Item 2: the folder holding the spec, records and notes is refused as --out."""
    proc = _case(user_dir, ["fit", "user/attas_sp.yaml", "user/flight.csv", "--out", "user",
                            "--quiet"], "user", "not a vsidgen results directory", "--overwrite")
    assert "notes.txt" in proc.stderr


def test_arguments_checked_before_any_computation(user_dir):
    """Item 5: each is refused before the fit (the fit would take seconds: time bound 60 s)."""
    (user_dir / "afile").write_text("x")
    base = ["fit", "user/attas_sp.yaml", "user/flight.csv", "--quiet"]
    _case(user_dir, base + ["--out", "res", "--reference", "nope.json"], "nope.json", "not found")
    _case(user_dir, base + ["--out", "res", "--reference", "/dev/zero"], "/dev/zero")
    _case(user_dir, base + ["--out", "res", "--validate", "nope.csv"], "nope.csv", "not found")
    _case(user_dir, base + ["--out", "afile"], "afile", "not a directory")
    _case(user_dir, base + ["--out", "afile/res"], "afile", "not a directory")
    _case(user_dir, base + ["--out", "res", "--max-iter", "0"], "--max-iter")
    os.symlink("user", user_dir / "link")
    _case(user_dir, base + ["--out", "link"], "link", "symbolic link")
    _case(user_dir, ["diagnose", "user/attas_sp.yaml", "user/flight.csv", "--out", "user",
                     "--quiet"], "user", "not a vsidgen results directory")
    _case(user_dir, ["diagnose", "user/attas_sp.yaml", "nope.csv", "--out", "d", "--quiet"],
          "nope.csv", "not found")
    # an address dask cannot parse, a seed numpy refuses (both were internal errors, exit 3)
    _case(user_dir, ["diagnose", "user/attas_sp.yaml", "user/flight.csv", "--out", "d",
                     "--scheduler", "tcp://[::1", "--quiet"], "cannot start or reach")
    _case(user_dir, ["simulate", "user/attas_sp.yaml", "--out", "s.csv", "--seed", "-1",
                     "--input", "de=doublet:amplitude=0.02"], "--seed")
    # non-finite values (NaN x0 was reported as a divergence at sample 0)
    _case(user_dir, ["simulate", "user/attas_sp.yaml", "--out", "s.csv", "--x0", "alpha=nan",
                     "--duration", "2", "--dt", "0.1"], "--x0", "must be finite")
    _case(user_dir, ["simulate", "user/attas_sp.yaml", "--out", "s.csv", "--quantize",
                     "alpha=-1", "--duration", "2", "--dt", "0.1"], "--quantize", "> 0")


@pytest.mark.skipif(hasattr(os, "geteuid") and os.geteuid() == 0,
                    reason="root may write into read-only folders")
def test_out_inside_read_only_parent(user_dir):
    ro = user_dir / "ro"
    ro.mkdir()
    os.chmod(ro, 0o555)
    try:
        _case(user_dir, ["fit", "user/attas_sp.yaml", "user/flight.csv", "--out", "ro/res",
                         "--quiet"], "ro", "not writable")
    finally:
        os.chmod(ro, 0o755)


def test_simulate_never_writes_over_what_it_reads(user_dir):
    """Item 8: --out naming the --inputs-from record, the spec, or through a link."""
    base = ["simulate", "user/attas_sp.yaml", "--inputs-from", "user/flight.csv"]
    _case(user_dir, base + ["--out", "user/flight.csv"], "user/flight.csv", "reads")
    _case(user_dir, base + ["--out", "user/attas_sp.yaml"], "reads")
    os.symlink("user/flight.csv", user_dir / "alias.csv")
    _case(user_dir, base + ["--out", "alias.csv"], "alias.csv", "symbolic link")
    _case(user_dir, base + ["--out", "user"], "user", "is a directory")
    # a link to any file is refused: the rename would replace the link (session 44)
    (user_dir / "other.csv").write_text("mine\n")
    os.symlink("other.csv", user_dir / "lnk.csv")
    _case(user_dir, base + ["--out", "lnk.csv"], "lnk.csv", "symbolic link")
    assert (user_dir / "lnk.csv").is_symlink() and (user_dir / "other.csv").read_text() == "mine\n"


def test_simulate_refuses_records_it_could_not_hold(user_dir):
    """`--duration 1e7 --dt 0.1` (1e8 samples, within the old bound) and a multisine of 1e8
    components ended in MemoryError, exit 3; a maneuver option given twice was taken
    silently (session 44, red team)."""
    assert run_cli(["build", "user/attas_sp.yaml"], user_dir, None).returncode == 0
    base = ["simulate", "user/attas_sp.yaml", "--out", "s.csv"]
    _case(user_dir, base + ["--duration", "1e7", "--dt", "0.1",
                            "--input", "de=doublet:amplitude=0.02"], "--duration", "fit reads")
    _case(user_dir, base + ["--duration", "10", "--dt", "0.1",
                            "--input", "de=multisine:amplitude=0.01,n=100000000"], "from 1 to 1000")
    _case(user_dir, base + ["--duration", "10", "--dt", "0.1",
                            "--input", "de=doublet:amplitude=1,amplitude=2"], "given twice")
    assert not (user_dir / "s.csv").exists()


# --------------------------------------------------------------------------- results directories

def _results_dir(d: pathlib.Path, signals_name: str = "signals_r.csv") -> pathlib.Path:
    """A minimal crafted results directory whose results.json names ``signals_name``."""
    d.mkdir()
    res = {"spec": {"name": "m"}, "model": {"states": [], "outputs": [], "inputs": []},
           "parameters": {}, "records": {"estimation": [{"name": "r", "dt": 0.1}]},
           "signals": {"r": signals_name}}
    (d / "results.json").write_text(json.dumps(res))
    return d


SECRET = "TOP-SECRET-CONTENT-1234"


@pytest.mark.parametrize("kind", ["absolute", "dotdot", "symlink", "results_symlink",
                                  "results_dev_zero", "signals_fifo"])
def test_report_reads_only_inside_the_results_directory(user_dir, kind):
    """Item 4: paths from a crafted results.json never leave DIR; foreign content never shown."""
    secret = user_dir / "secret.csv"
    secret.write_text(f"t_s,{SECRET}\n1,2\n")
    if kind == "absolute":
        d = _results_dir(user_dir / "res", str(secret))
        texts = ["not a relative file name"]
    elif kind == "dotdot":
        d = _results_dir(user_dir / "res", "../secret.csv")
        texts = ["'..' is not allowed"]
    elif kind == "symlink":
        d = _results_dir(user_dir / "res")
        os.symlink(secret, d / "signals_r.csv")
        texts = ["signals_r.csv", "leaves the results directory"]
    elif kind == "results_symlink":
        d = user_dir / "res"
        d.mkdir()
        os.symlink(secret, d / "results.json")
        texts = ["results.json", "leaves the results directory"]
    elif kind == "results_dev_zero":
        d = user_dir / "res"
        d.mkdir()
        os.symlink("/dev/zero", d / "results.json")
        texts = ["results.json"]
    else:
        d = _results_dir(user_dir / "res")
        os.mkfifo(d / "signals_r.csv")
        texts = ["signals_r.csv", "named pipe"]
    proc = _case(user_dir, ["report", "res"], *texts)
    assert SECRET not in proc.stderr + proc.stdout


def test_report_never_replaces_a_file_it_did_not_write(user_dir):
    from report_fixture import write_results_dir

    d = write_results_dir(user_dir / "res", n_samples=40, validation=False, n_outputs=1)
    (d / "report.html").write_text("<p>my own page</p>")
    _case(user_dir, ["report", "res"], "report.html", "--overwrite")
    _case(user_dir, ["report", "res", "--out", "res/results.json"], "reads")
    _case(user_dir, ["report", "res", "--out", "user/notes.txt"], "notes.txt", "--overwrite")


# --------------------------------------------------------------------------- what works

def test_simulate_accepts_epoch_time_stamps_like_fit(tmp_path):
    """Item 7: one time-column reader; the record's grid is 0.04 s from its first stamp."""
    out = tmp_path / "sim.csv"
    proc = run_cli(["simulate", SPEC, "--inputs-from", HOSTILE / "epoch_time.csv", "--out", out],
                   tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    lines = out.read_text().splitlines()
    assert len(lines) == 41
    t = [float(r.split(",")[0]) for r in lines[1:]]
    assert abs(t[-1] / (39 * 0.04) - 1) < 1e-6 and abs(t[1] / t[-1] - 1 / 39) < 1e-12


# --------------------------------------------------------------------------- crash recovery (item 9)

_CRASH = textwrap.dedent("""
    import os, sys, pathlib
    import vsidgen.atomic as atomic
    target = pathlib.Path(sys.argv[1]); when = sys.argv[2]
    calls = []
    real_rename = os.rename
    def rename(a, b):
        calls.append((a, b))
        real_rename(a, b)
        if when == "between" and str(a) == str(target):
            os._exit(9)              # killed after DIR -> .DIR.old-*, before .DIR.tmp-* -> DIR
    atomic.os.rename = rename
    with atomic.atomic_directory(target) as tmp:
        (tmp / "results.json").write_text('{"run": 2}')
        if when == "body":
            os._exit(9)              # killed while writing
""")


def _first_run(d: pathlib.Path) -> None:
    proc = subprocess.run([sys.executable, "-c", _CRASH.replace("when == \"between\"", "False")
                           .replace("when == \"body\"", "False"), str(d), "none"],
                          env={**os.environ, "PYTHONPATH": str(ROOT)}, capture_output=True,
                          text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert json.loads((d / "results.json").read_text()) == {"run": 2}
    (d / "results.json").write_text('{"run": 1}')


def _crash(d: pathlib.Path, when: str) -> None:
    proc = subprocess.run([sys.executable, "-c", _CRASH, str(d), when],
                          env={**os.environ, "PYTHONPATH": str(ROOT)}, capture_output=True,
                          text=True, timeout=60)
    assert proc.returncode == 9, proc.stderr


def _leftovers(parent: pathlib.Path) -> list[str]:
    return sorted(p.name for p in parent.iterdir() if p.name.startswith(".res."))


def _next_run(tmp_path):
    """A later command for the same --out (refused on its data, after the recovery)."""
    return run_cli(["fit", SPEC, HOSTILE / "input_1e308.csv", "--out", "res", "--quiet"], tmp_path)


def test_crash_between_renames_is_completed_by_the_next_run(tmp_path):
    d = tmp_path / "res"
    _first_run(d)
    os.chmod(d, 0o750)
    _crash(d, "between")
    assert not d.exists()
    names = _leftovers(tmp_path)
    assert any(".old-" in n for n in names) and any(".tmp-" in n for n in names)
    proc = _next_run(tmp_path)
    expect_refused(proc, "input_1e308.csv", "sample 17")
    assert "interrupted" in proc.stderr and "now in place" in proc.stderr
    assert json.loads((d / "results.json").read_text()) == {"run": 2}
    assert stat.S_IMODE(d.stat().st_mode) == 0o750
    assert _leftovers(tmp_path) == []


def test_crash_between_renames_without_complete_results_restores_the_old(tmp_path):
    d = tmp_path / "res"
    _first_run(d)
    _crash(d, "between")
    for p in tmp_path.glob(".res.tmp-*"):
        (p / ".vsidgen-results.json").unlink()  # incomplete new results: as a crash during
        (p / ".vsidgen-building").touch()       # the build leaves them, marker still there
    proc = _next_run(tmp_path)
    expect_refused(proc, "input_1e308.csv")
    assert "previous results were restored" in proc.stderr
    assert json.loads((d / "results.json").read_text()) == {"run": 1}
    assert _leftovers(tmp_path) == []


def test_killed_run_leftover_is_removed_and_results_kept(tmp_path):
    d = tmp_path / "res"
    _first_run(d)
    _crash(d, "body")
    assert any(".tmp-" in n for n in _leftovers(tmp_path))
    proc = _next_run(tmp_path)
    expect_refused(proc, "input_1e308.csv")
    assert "removed the unfinished results" in proc.stderr
    assert json.loads((d / "results.json").read_text()) == {"run": 1}
    assert _leftovers(tmp_path) == []


# --------------------------------------------------------------------------- spreadsheet exports

def _export(path: pathlib.Path, kind: str) -> pathlib.Path:
    """The shipped record as a spreadsheet program may export it."""
    lines = DATA.read_text().splitlines()
    if kind == "bom":               # Excel's "CSV UTF-8": a byte-order mark before the header
        path.write_bytes(b"\xef\xbb\xbf" + ("\n".join(lines) + "\n").encode())
    elif kind == "semicolon":       # a European locale: semicolons and decimal commas
        path.write_text("\n".join(ln.replace(",", ";").replace(".", ",") for ln in lines) + "\n")
    elif kind == "cp1252":          # a legacy code page: a degree sign in a column name
        head = lines[0].replace("alpha_rad", "alpha_rad (\u00b0)")
        path.write_bytes(("\n".join([head] + lines[1:]) + "\n").encode("cp1252"))
    elif kind == "utf16":           # Excel's "Unicode Text", PowerShell's `>`: UTF-16 with a BOM
        path.write_bytes(("\n".join(lines) + "\n").encode("utf-16"))
    elif kind == "utf16be":         # UTF-16 without a byte-order mark
        path.write_bytes(("\n".join(lines) + "\n").encode("utf-16-be"))
    return path


@pytest.mark.parametrize("command", ["check", "fit"])
def test_spreadsheet_exports(tmp_path, command):
    """A byte-order mark is read as the UTF-8 it marks; semicolon-separated and legacy
    8-bit text are refused with what the file is and how to save it, before any fit."""
    def run(kind):
        f = _export(tmp_path / f"{kind}.csv", kind)
        args = (["check", SPEC, "--data", f] if command == "check"
                else ["fit", SPEC, f, "--out", tmp_path / f"out_{kind}", "--quiet",
                      "--max-iter", "1"])
        return run_cli(args, tmp_path)

    semi = run("semicolon")
    expect_refused(semi, "semicolon.csv", "comma-separated")
    legacy = run("cp1252")
    expect_refused(legacy, "cp1252.csv", "not UTF-8 text", "line 1", "CSV UTF-8")
    for kind in ("utf16", "utf16be"):
        expect_refused(run(kind), f"{kind}.csv", "UTF-16", "CSV UTF-8")
    if command == "check":
        bom = run("bom")
        assert bom.returncode == 0, bom.stderr[-2000:]
        assert "ok (attas_sp" in bom.stdout + bom.stderr


def test_numpy_savetxt_header_is_read_and_comment_lines_are_refused(tmp_path):
    """A header written by ``numpy.savetxt(..., header=...)`` (``# t_s,de_rad,...``) gives the
    record of the plain file; comment or metadata lines above the header are refused, by
    ``check`` and ``fit``, with the line and what to do (they were read as the header and
    the message named a column ``# t_s`` or a non-numeric '# date' cell)."""
    from vsidgen.data import load_record
    from vsidgen.spec import compile_spec

    lines = DATA.read_text().splitlines()
    saved = tmp_path / "savetxt.csv"
    saved.write_text("# " + lines[0] + "\n" + "\n".join(lines[1:]) + "\n")
    model = compile_spec(SPEC)
    a, b = load_record(model, DATA), load_record(model, saved)
    np.testing.assert_array_equal(a.u, b.u)
    np.testing.assert_array_equal(a.y, b.y)
    assert a.dt == b.dt and a.y.shape == b.y.shape
    ok = run_cli(["check", SPEC, "--data", saved], tmp_path)
    assert ok.returncode == 0, ok.stderr[-2000:]

    meta = tmp_path / "meta.csv"
    meta.write_text("\n# flight 12, run 3\n# exported 2026-11-27\n" + "\n".join(lines) + "\n")
    for args in (["check", SPEC, "--data", meta],
                 ["fit", SPEC, meta, "--out", tmp_path / "out", "--quiet", "--max-iter", "1"]):
        proc = run_cli(args, tmp_path)
        expect_refused(proc, "meta.csv", "line 2 is a comment", "'# flight 12,",
                       "delete the comment or metadata lines")
    assert not (tmp_path / "out").exists()


def test_huge_integers_and_deep_nesting_in_json_inputs_are_refused_cleanly(user_dir):
    """A 400-digit integer (OverflowError where it became a float), a 5001-digit one (Python's
    int-string limit) and 100000 nested arrays (RecursionError) in a file given with
    --init-from or --reference: a message and exit 2, never an internal error (session 43)."""
    from report_fixture import write_results_dir

    u = user_dir / "user"
    write_results_dir(user_dir / "res", n_samples=40, validation=False, n_outputs=1)
    big = "1" + "0" * 400
    (u / "init.json").write_text('{"parameters": {"Z0": {"estimate": %s}}}' % big)
    _case(user_dir, ["fit", "user/attas_sp.yaml", "user/flight.csv", "--out", "o",
                     "--init-from", "user/init.json"], "Z0", "not a finite number")
    for name, body, text in (("r400", '{"parameters": {"Z0": {"estimate": %s}}}' % big, None),
                             ("r5001", '{"parameters": {"Z0": {"estimate": 1%s}}}' % ("0" * 5000), None),
                             ("deep", '{"a": ' + "[" * 100000 + "]" * 100000 + "}", "nested too deeply")):
        (u / f"{name}.json").write_text(body)
        proc = run_cli(["report", "res", "--reference", f"user/{name}.json", "--out", f"rep_{name}"],
                       user_dir)
        assert proc.returncode in (0, 2), (name, proc.returncode, proc.stderr[-2000:])
        assert "Traceback" not in proc.stderr and "internal error" not in proc.stderr, proc.stderr
        if text:
            expect_refused(proc, text)
    res = user_dir / "res" / "results.json"
    res.write_text(res.read_text().replace('"elbo": ', '"elbo": %s, "elbo_was": ' % big, 1))
    proc = run_cli(["report", "res", "--out", "rep_big"], user_dir)
    assert proc.returncode in (0, 2) and "internal error" not in proc.stderr, proc.stderr[-2000:]


@pytest.mark.parametrize("where", ["file_as_generated", "out_is_file", "dev_null"])
def test_an_output_path_blocked_by_a_file_is_refused_cleanly(user_dir, where):
    """A file where vsidgen creates a folder (./generated, --out) or a device as --out:
    exit 2 naming the path, not an internal error (FileExistsError, session 43)."""
    u = user_dir / "user"
    if where == "file_as_generated":
        (u / "generated").write_text("mine\n")
        proc = run_cli(["build", "attas_sp.yaml"], u)
        expect_refused(proc, "generated", "not a folder")
        assert (u / "generated").read_text() == "mine\n"
    elif where == "out_is_file":
        expect_refused(run_cli(["build", "attas_sp.yaml", "-o", "notes.txt"], u), "notes.txt")
        assert (u / "notes.txt").read_text() == "my notes\n"
    else:
        expect_refused(run_cli(["build", "attas_sp.yaml", "-o", "/dev/null"], u), "/dev/null")
