"""Folders and files beside ``--out`` that only look like vsidgen's leftovers or lock are the
user's and are never deleted, moved or truncated (red team, session 47: ``.out.old-mybackup``
and ``.out.tmp-keep`` were deleted by a run refused on its data, ``.out.old-v1`` was moved
into a missing ``out``, and a user's ``.out.lock`` was truncated and deleted)."""

from __future__ import annotations

import pathlib
import subprocess
import sys

import pytest

from vsidgen import atomic
from vsidgen.atomic import MANIFEST, atomic_directory, plan_output_dir
from vsidgen.errors import VsidgenError


def _mine(d: pathlib.Path, text="mine") -> pathlib.Path:
    d.mkdir()
    (d / "notes.txt").write_text(text)
    return d


def _dead_pid() -> int:
    """The id of a process that has ended."""
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_folders_named_like_leftovers_without_vsidgen_marks_are_kept(tmp_path):
    out = tmp_path / "out"
    keep = [_mine(tmp_path / ".out.old-mybackup"), _mine(tmp_path / ".out.tmp-keep"),
            # the exact pattern of a leftover, of a dead process, but the user's files
            _mine(tmp_path / f".out.old-{_dead_pid()}-0badcafe"),
            _mine(tmp_path / f".out.tmp-{_dead_pid()}-0badcafe")]
    assert atomic.recover(out) == ()
    assert not out.exists()                       # nothing moved into place
    for d in keep:
        assert (d / "notes.txt").read_text() == "mine"
    # a whole run for that --out keeps them too
    with atomic_directory(out) as tmp:
        (tmp / "results.json").write_text("1")
    for d in keep:
        assert (d / "notes.txt").read_text() == "mine"


def test_real_leftovers_are_still_recovered(tmp_path):
    out = tmp_path / "out"
    pid = _dead_pid()
    old = tmp_path / f".out.old-{pid}-0123abcd"      # a replaced results directory
    old.mkdir()
    (old / "results.json").write_text("1")
    (old / MANIFEST).write_text(atomic._manifest_text(["results.json"], command="fit"))
    tmp = tmp_path / f".out.tmp-{pid}-4567cdef"      # a build cut short
    tmp.mkdir()
    (tmp / atomic.BUILDING).touch()
    (tmp / "results.json").write_text("2")
    msgs = atomic.recover(out)
    assert (out / "results.json").read_text() == "1" and not tmp.exists()
    assert any("restored" in m for m in msgs)


def test_no_building_marker_in_the_results(tmp_path):
    out = tmp_path / "out"
    with atomic_directory(out) as tmp:
        assert (tmp / atomic.BUILDING).is_file()
        (tmp / "results.json").write_text("1")
    assert sorted(p.name for p in out.iterdir()) == sorted([MANIFEST, "results.json"])
    assert "building" not in (out / MANIFEST).read_text()


def test_a_users_lock_named_file_is_refused_not_truncated(tmp_path):
    out = tmp_path / "out"
    lock = tmp_path / ".out.lock"
    lock.write_text("my notes, not a lock\n")
    with pytest.raises(VsidgenError, match="not one of vsidgen's lock files"):
        plan_output_dir(out)
    assert lock.read_text() == "my notes, not a lock\n"
    atomic._release_all()
    assert lock.read_text() == "my notes, not a lock\n"


def test_a_stale_lock_of_a_crashed_run_is_reused(tmp_path):
    out = tmp_path / "out"
    (tmp_path / ".out.lock").write_text(f"{_dead_pid()}\n")
    with atomic_directory(out) as tmp:
        (tmp / "results.json").write_text("1")
    assert (out / "results.json").read_text() == "1"
    assert not (tmp_path / ".out.lock").exists()
