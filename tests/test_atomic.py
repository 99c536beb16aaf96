"""Results directories (vsidgen.atomic): manifest rules, permissions, failure paths, report CSP.

Hand-made directory trees; the expected outcome of each rule is written out here
(docs/security.md, "Results directories"), not computed with the code under test.
"""

from __future__ import annotations

import base64
import hashlib
import json
import os
import pathlib
import re
import stat

import pytest

from vsidgen import atomic
from vsidgen.atomic import (MANIFEST, DirState, WriteMode, atomic_directory, plan_output_dir,
                            read_manifest, results_in_place)
from vsidgen.errors import VsidgenError


def _write(d: pathlib.Path, files: dict[str, str]) -> None:
    for rel, text in files.items():
        (d / rel).parent.mkdir(parents=True, exist_ok=True)
        (d / rel).write_text(text)


def _tree(d: pathlib.Path) -> dict[str, str]:
    return {p.relative_to(d).as_posix(): p.read_text() for p in sorted(d.rglob("*")) if p.is_file()}


def _run(target, files: dict[str, str], **kw) -> None:
    with atomic_directory(target, **kw) as tmp:
        _write(tmp, files)


def test_new_directory_gets_the_umask_mode_and_a_manifest(tmp_path):
    old = os.umask(0o022)
    try:
        _run(tmp_path / "res", {"results.json": "1"})
    finally:
        os.umask(old)
    d = tmp_path / "res"
    assert stat.S_IMODE(d.stat().st_mode) == 0o755
    doc = json.loads((d / MANIFEST).read_text())
    assert doc["format"] == "vsidgen-results" and doc["files"] == ["results.json"]
    assert doc["complete"] is True
    assert sorted(p.name for p in tmp_path.iterdir()) == ["res"]


def test_replacing_own_results_keeps_the_folder_mode(tmp_path):
    d = tmp_path / "res"
    _run(d, {"results.json": "1", "signals_a.csv": "a"})
    os.chmod(d, 0o751)
    _run(d, {"results.json": "2"})
    assert stat.S_IMODE(d.stat().st_mode) == 0o751
    assert _tree(d) == {MANIFEST: (d / MANIFEST).read_text(), "results.json": "2"}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["res"]


def test_empty_existing_directory_keeps_its_mode(tmp_path):
    d = tmp_path / "res"
    d.mkdir(mode=0o700)
    os.chmod(d, 0o710)
    _run(d, {"results.json": "1"})
    assert stat.S_IMODE(d.stat().st_mode) == 0o710 and (d / "results.json").read_text() == "1"


def test_foreign_directory_refused_then_kept_with_overwrite(tmp_path):
    d = tmp_path / "user"
    _write(d, {"notes.txt": "mine", "sub/data.csv": "x", "results.json": "my own"})
    os.chmod(d, 0o750)
    with pytest.raises(VsidgenError, match="not a vsidgen results directory"):
        plan_output_dir(d)
    plan = plan_output_dir(d, overwrite=True)
    assert plan.state is DirState.FOREIGN and plan.mode is WriteMode.IN_PLACE
    _run(d, {"results.json": "new", "signals_a.csv": "a"}, plan=plan)
    tree = _tree(d)
    assert tree["notes.txt"] == "mine" and tree["sub/data.csv"] == "x"
    assert tree["results.json"] == "new" and tree["signals_a.csv"] == "a"
    assert stat.S_IMODE(d.stat().st_mode) == 0o750
    man = read_manifest(d)
    assert man["files"] == {"results.json", "signals_a.csv"}
    assert man["kept"] == {"notes.txt", "sub/data.csv"}
    # the next run replaces only its own files: a stale signals file goes, notes stay
    with pytest.raises(VsidgenError, match="also holds files vsidgen did not write"):
        plan_output_dir(d)
    _run(d, {"results.json": "third"}, plan=plan_output_dir(d, overwrite=True))
    tree = _tree(d)
    assert "signals_a.csv" not in tree and tree["notes.txt"] == "mine"
    assert tree["results.json"] == "third"


def test_user_file_added_to_results_directory_is_protected(tmp_path):
    d = tmp_path / "res"
    _run(d, {"results.json": "1"})
    (d / "my_notes.txt").write_text("keep me")
    with pytest.raises(VsidgenError, match="my_notes.txt"):
        plan_output_dir(d)


def test_files_read_by_the_command_are_never_replaced(tmp_path):
    d = tmp_path / "res"
    _run(d, {"results.json": "1", "ref.json": "{}"})
    with pytest.raises(VsidgenError, match="reads"):
        plan_output_dir(d, reads=[d / "ref.json"])
    u = tmp_path / "user"
    _write(u, {"results.json": "the record I read"})
    plan = plan_output_dir(u, overwrite=True, reads=[u / "results.json"])
    with pytest.raises(VsidgenError, match="reads that file"):
        _run(u, {"results.json": "new"}, plan=plan)
    assert (u / "results.json").read_text() == "the record I read"


def test_symlink_file_and_crafted_manifest(tmp_path):
    (tmp_path / "real").mkdir()
    os.symlink(tmp_path / "real", tmp_path / "link")
    with pytest.raises(VsidgenError, match="symbolic link"):
        plan_output_dir(tmp_path / "link")
    (tmp_path / "f").write_text("x")
    with pytest.raises(VsidgenError, match="not a directory"):
        plan_output_dir(tmp_path / "f")
    with pytest.raises(VsidgenError, match="not a directory"):
        plan_output_dir(tmp_path / "f" / "res")
    # a manifest that names paths outside the directory is no manifest at all
    d = tmp_path / "crafted"
    _write(d, {"a.txt": "a", MANIFEST: json.dumps({"format": "vsidgen-results",
                                                   "files": ["../f", "a.txt"]})})
    assert read_manifest(d) is None
    assert plan_output_dir(d, overwrite=True).state is DirState.FOREIGN


def test_failure_inside_the_body_leaves_everything(tmp_path):
    d = tmp_path / "res"
    _run(d, {"results.json": "1"})
    before = _tree(d)
    with pytest.raises(RuntimeError):
        with atomic_directory(d) as tmp:
            (tmp / "results.json").write_text("2")
            raise RuntimeError("boom")
    assert _tree(d) == before and sorted(p.name for p in tmp_path.iterdir()) == ["res"]


def test_failed_second_rename_restores_the_old_directory(tmp_path, monkeypatch):
    d = tmp_path / "res"
    _run(d, {"results.json": "1"})
    real = os.rename

    def rename(a, b):
        if ".tmp-" in str(a):
            raise OSError("disk full")
        real(a, b)

    monkeypatch.setattr(atomic.os, "rename", rename)
    with pytest.raises(OSError):
        _run(d, {"results.json": "2"})
    assert (d / "results.json").read_text() == "1"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["res"]


def test_leftovers_of_a_live_process_are_left_alone(tmp_path):
    d = tmp_path / "res"
    _run(d, {"results.json": "1"})
    live = tmp_path / f".res.tmp-{os.getppid()}-abcd1234"
    live.mkdir()
    assert atomic.recover(d) == ()
    assert live.exists()


def test_diagnose_style_in_place_run_marks_incomplete_until_done(tmp_path):
    d = tmp_path / "diag"
    _write(d, {"notes.txt": "mine"})
    plan = plan_output_dir(d, overwrite=True)
    owns = ("candidates", "findings.json")
    with pytest.raises(RuntimeError):
        with results_in_place(plan, command="diagnose", owns=owns) as out:
            _write(out, {"candidates/a.yaml": "a"})
            assert json.loads((out / MANIFEST).read_text())["complete"] is False
            raise RuntimeError("killed")
    man = read_manifest(d)
    assert man["files"] == {"candidates/a.yaml"} and man["kept"] == {"notes.txt"}
    with results_in_place(plan_output_dir(d, overwrite=True), command="diagnose",
                          owns=owns) as out:
        _write(out, {"findings.json": "{}"})
    assert set(_tree(d)) == {"notes.txt", "findings.json", MANIFEST}
    assert read_manifest(d)["files"] == {"findings.json"}


def test_files_added_after_a_killed_in_place_run_stay_the_users(tmp_path):
    """A diagnose killed mid-run leaves an incomplete manifest; files the user puts there
    afterwards are not vsidgen's (they were deleted by the next fit, even with
    --overwrite): only the names the run declared are claimed."""
    d = tmp_path / "dC"
    with pytest.raises(RuntimeError):
        with results_in_place(plan_output_dir(d), command="diagnose",
                              owns=("candidates", "findings.json")) as out:
            _write(out, {"candidates/a.yaml": "a", ".findings.json.x1y2": "partial"})
            raise RuntimeError("killed")
    _write(d, {"notes.txt": "my notes", "mydata/x.csv": "1,2"})
    man = read_manifest(d)
    assert man["files"] == {"candidates/a.yaml", ".findings.json.x1y2"}
    with pytest.raises(VsidgenError):          # mixed: refused without --overwrite
        plan_output_dir(d)
    _run(d, {"results.json": "1"}, overwrite=True)
    assert {"notes.txt", "mydata/x.csv", "results.json"} <= set(_tree(d))
    assert "candidates/a.yaml" not in _tree(d)
    assert (d / "notes.txt").read_text() == "my notes"
    # an older incomplete manifest that declares nothing claims nothing
    (d / MANIFEST).write_text(json.dumps({**json.loads((d / MANIFEST).read_text()),
                                          "complete": False, "files": []}))
    assert read_manifest(d)["files"] == set()


# --------------------------------------------------------------------------- report page


def test_report_csp_hashes_its_only_script_and_names_the_final_directory(tmp_path):
    from report_fixture import write_results_dir

    from vsidgen.report import write_report

    d = write_results_dir(tmp_path / ".res.tmp-1-abc", n_samples=40, validation=False,
                          n_outputs=1)
    page = write_report(d, display_dir="results/final").read_text()
    csp = re.search(r'Content-Security-Policy" content="([^"]*)"', page).group(1)
    script_src = re.search(r"script-src ([^;]*)", csp).group(1).split()
    assert "'unsafe-inline'" not in script_src and len(script_src) == 1
    scripts = re.findall(r"<script>(.*?)</script>", page, flags=re.S)
    assert len(scripts) == 1 and "<script" not in page.replace("<script>", "", 1)
    digest = base64.b64encode(hashlib.sha256(scripts[0].encode("utf-8")).digest()).decode()
    assert script_src[0] == f"'sha256-{digest}'"
    assert "vsidgen report of <code>results/final</code>" in page
    assert ".res.tmp-" not in page.split("<footer>")[1]


def test_diagnose_section_escapes_every_inserted_value():
    from vsidgen.discrepancy.findings import report_section

    evil = "<img src=x onerror=alert(1)>"
    doc = {"conclusion": evil, "findings": [{
        "rank": evil, "title": evil, "target": evil, "explanation": evil, "effect": "e",
        "added_terms": {"drift": {"q": evil}}, "parameters": {},
        "evidence": {"elbo_before": 1.0, "elbo_after": 2.0, "statistic": 2.0, "dof": evil,
                     "threshold": 1.0, "alpha": evil, "n_candidates": evil}}]}
    html = report_section(doc)
    assert "<img" not in html and "onerror=alert(1)&gt;" in html


def test_a_link_given_as_an_output_file_is_refused_and_left_alone(tmp_path):
    """`report --out /dev/stdout --overwrite` replaced the system's /dev/stdout link with the
    report, and `simulate -o link.csv` replaced a link with a 0600 file: the rename replaces
    the link itself (session 44, red team). Links are refused, by the output check and by
    the atomic writers themselves; the link and what it points to are unchanged."""
    target = tmp_path / "real.csv"
    target.write_text("mine\n")
    link = tmp_path / "link.csv"
    link.symlink_to(target)
    with pytest.raises(VsidgenError, match="symbolic link"):
        atomic.check_output_file(link)
    for write in (lambda: atomic.write_text_atomic(link, "new"),
                  lambda: atomic.write_bytes_atomic(link, b"new")):
        with pytest.raises(VsidgenError, match="symbolic link"):
            write()
    assert link.is_symlink() and target.read_text() == "mine\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["link.csv", "real.csv"]
    with pytest.raises(VsidgenError, match="link to a file"):
        plan_output_dir(link)


def test_a_second_run_into_the_same_directory_is_refused_while_the_first_writes(tmp_path):
    """Two fits into one `-o` at once both said "results in DIR" and the first one's results
    were gone (session 44). The first holds a lock until its results are written; the
    second is refused before computing, naming the first's process; once the first ends
    (here: killed, as a crash), the directory can be written again and no lock is left."""
    import subprocess
    import sys
    import time

    d = tmp_path / "res"
    code = ("import sys, time; from vsidgen.atomic import plan_output_dir; "
            f"plan_output_dir({str(d)!r}); print('held', flush=True); time.sleep(60)")
    holder = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(VsidgenError, match=f"another vsidgen run \\(process {holder.pid}\\)"):
            plan_output_dir(d)
    finally:
        holder.kill()
        holder.wait()
    _run(d, {"results.json": "1"})
    assert _tree(d)["results.json"] == "1"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["res"]
    # in one process, a second plan of the same directory is its own (the API called twice)
    plan_output_dir(d)
    plan_output_dir(d)
    atomic.release(d)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["res"]


def test_written_files_get_the_mode_a_user_expects(tmp_path):
    """Every results file, report and generated module was created 0600 (mkstemp) whatever
    the umask, so colleagues could not read a report (session 44, a new user). A new file
    gets 0666 less the umask; a replaced file keeps its mode."""
    old = os.umask(0o022)
    try:
        new = atomic.write_text_atomic(tmp_path / "new.txt", "x")
        assert stat.S_IMODE(new.stat().st_mode) == 0o644
        kept = tmp_path / "kept.txt"
        kept.write_text("a")
        os.chmod(kept, 0o640)
        atomic.write_bytes_atomic(kept, b"b")
        assert stat.S_IMODE(kept.stat().st_mode) == 0o640 and kept.read_bytes() == b"b"
        _run(tmp_path / "res", {"results.json": "1"})
        assert stat.S_IMODE((tmp_path / "res" / MANIFEST).stat().st_mode) == 0o644
    finally:
        os.umask(old)
