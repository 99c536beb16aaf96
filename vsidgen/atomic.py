"""Atomic writes and results directories that never destroy what the user had.

Every file vsidgen writes for the user (generated modules, records, results, reports)
goes through these helpers: a temporary file or directory beside the target, then a
rename.

Results directories (``fit --out``, ``diagnose --out``, the report written into one)
carry a manifest, :data:`MANIFEST` (``.vsidgen-results.json``), listing the files
vsidgen wrote there. The rules (``docs/security.md``, "Results directories"):

* an absent or empty directory, or one whose every file is listed in its manifest
  (a *vsidgen results directory*), is replaced as a whole: the new results are built
  in ``.DIR.tmp-<pid>-<token>`` beside it and swapped in with two renames
  (``DIR -> .DIR.old-<pid>-<token>``, ``.DIR.tmp-... -> DIR``); the new directory
  gets the old one's permission bits, and a new one the mode ``mkdir`` gives
  (0777 less the umask);
* a non-empty directory without a manifest, or a results directory that also holds
  files vsidgen did not write, is refused (exit status 2, before any computation)
  unless the user passes ``--overwrite``; even then only vsidgen's own files are
  written into it one by one (each with :func:`os.replace`) and the files of the
  previous run listed in its manifest are removed; every other file stays as it was;
* a symbolic link, a file, or a directory whose parent is not writable is refused;
* a run that was killed or crashed leaves ``.DIR.tmp-*`` / ``.DIR.old-*``; the next
  run for ``DIR`` restores or completes the swap (a temporary directory holding a
  manifest is complete, the manifest being its last file) and removes the leftovers,
  and says so on stderr. Leftovers of a process that is still running are left alone.
"""

from __future__ import annotations

import atexit
import contextlib
import dataclasses
import enum
import json
import os
import pathlib
import re
import secrets
import shutil
import stat
import sys
import tempfile
from collections.abc import Iterable, Iterator
from typing import TextIO

from .errors import VsidgenError, printable_lines

#: name of the manifest file of a results directory
MANIFEST = ".vsidgen-results.json"
MANIFEST_FORMAT = "vsidgen-results"
MANIFEST_VERSION = 1

#: directories of this process that are being built or swapped (never "stale")
_ACTIVE: set[str] = set()


class DirState(enum.Enum):
    """What an output directory holds before a run."""

    ABSENT = "absent"
    EMPTY = "empty"
    OWNED = "owned"        # every file listed in its manifest
    MIXED = "mixed"        # a manifest, and files vsidgen did not write
    FOREIGN = "foreign"    # files and no (valid) manifest


class WriteMode(enum.Enum):
    """How new results reach the output directory."""

    SWAP = "swap"          # built beside it, swapped in by two renames
    IN_PLACE = "in-place"  # vsidgen's files moved in one by one; other files kept


@dataclasses.dataclass(frozen=True)
class OutputPlan:
    """A checked output directory (see :func:`plan_output_dir`).

    Attributes:
        target: the directory.
        state: what it held when checked.
        mode: how the results will be written.
        previous: files (relative POSIX paths) vsidgen wrote there before.
        kept: files that are not vsidgen's and stay untouched.
        mode_bits: permission bits of the existing directory (None when absent).
        recovered: what the leftover clean-up did (one line each, for stderr).
        reads: resolved paths of the files the command reads.
    """

    target: pathlib.Path
    state: DirState
    mode: WriteMode
    previous: frozenset[str] = frozenset()
    kept: frozenset[str] = frozenset()
    mode_bits: int | None = None
    recovered: tuple[str, ...] = ()
    reads: tuple[pathlib.Path, ...] = ()


# --------------------------------------------------------------------------- manifest

def _safe_relative(rel: object) -> bool:
    """A manifest entry: a relative POSIX path without ``..``, ``.`` or empty parts."""
    if not isinstance(rel, str) or not rel or "\x00" in rel or rel.startswith("/"):
        return False
    parts = rel.split("/")
    return all(p not in ("", ".", "..") for p in parts) and "\\" not in rel


def listing(directory: pathlib.Path) -> set[str]:
    """Every entry under ``directory`` that is not a directory (relative POSIX paths).

    Symbolic links are listed as entries and never followed; empty
    subdirectories are not listed.
    """
    out: set[str] = set()
    for root, dirs, files in os.walk(directory, followlinks=False):
        rel_root = pathlib.Path(root).relative_to(directory)
        for d in list(dirs):
            if os.path.islink(os.path.join(root, d)):
                out.add((rel_root / d).as_posix())
        for f in files:
            out.add((rel_root / f).as_posix())
    return out


def foreign_entries(directory: pathlib.Path, allowed: Iterable[str]) -> set[str]:
    """Entries under ``directory`` that a swap must not remove: files (and links) not in
    ``allowed``, and directories that hold none of ``allowed`` (an empty folder, shown with a
    trailing ``/``), which :func:`listing` does not list."""
    allowed = set(allowed)
    needed = {"/".join(a.split("/")[:i]) for a in allowed for i in range(1, a.count("/") + 1)}
    out: set[str] = set()
    for root, dirs, files in os.walk(directory, followlinks=False):
        rel_root = pathlib.Path(root).relative_to(directory)
        for d in list(dirs):
            rel = (rel_root / d).as_posix()
            if os.path.islink(os.path.join(root, d)):
                if rel not in allowed:
                    out.add(rel)
            elif rel not in needed:
                out.add(rel + "/")
                dirs.remove(d)        # everything below it is foreign too: named once
        for f in files:
            rel = (rel_root / f).as_posix()
            if rel not in allowed:
                out.add(rel)
    return out


def read_manifest(directory: str | os.PathLike) -> dict | None:
    """The manifest of ``directory`` or None (absent, unreadable or malformed).

    The returned mapping has ``files`` (a set of the files vsidgen wrote); for an
    incomplete run (``complete`` false) these are all files except ``kept``.
    """
    directory = pathlib.Path(directory)
    path = directory / MANIFEST
    try:
        if path.is_symlink() or not path.is_file() or path.stat().st_size > 1 << 20:
            return None
        from .limits import parse_json

        doc = parse_json(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError):
        return None
    if not (isinstance(doc, dict) and doc.get("format") == MANIFEST_FORMAT
            and isinstance(doc.get("files"), list) and isinstance(doc.get("kept", []), list)):
        return None
    if not all(_safe_relative(f) for f in doc["files"] + doc.get("kept", [])):
        return None
    files = set(doc["files"])
    kept = set(doc.get("kept", []))
    if not doc.get("complete", True):
        # an unfinished run may have written any path it declared (``owns``: top-level
        # names, and their temporary files); nothing else is assumed to be vsidgen's, so a
        # file the user put there after a crash is kept (an older manifest without ``owns``
        # claims nothing)
        owns = doc.get("owns", [])
        if not (isinstance(owns, list) and all(isinstance(o, str) and _safe_relative(o)
                                               for o in owns)):
            owns = []
        files |= {f for f in listing(directory) - kept - {MANIFEST} if _owned(f, owns)}
        return {**doc, "files": files, "kept": kept, "owns": owns}
    return {**doc, "files": files, "kept": kept}


def _owned(rel: str, owns: Iterable[str]) -> bool:
    """Is ``rel`` (a relative POSIX path) one of the declared names, below one, or the
    temporary file of one (``.NAME.xxxx``, :func:`atomic_text_file`)?"""
    top = rel.split("/", 1)[0]
    return any(top == o or top.startswith(f".{o}.") for o in owns)


def _manifest_text(files: Iterable[str], *, command: str, complete: bool = True,
                   kept: Iterable[str] = (), owns: Iterable[str] = ()) -> str:
    from . import __version__

    doc = {"format": MANIFEST_FORMAT, "version": MANIFEST_VERSION,
           "vsidgen_version": __version__, "command": command, "complete": complete,
           "files": sorted(set(files) - {MANIFEST}), "kept": sorted(set(kept))}
    if not complete:
        doc["owns"] = sorted(set(owns))
    return json.dumps(doc, indent=1) + "\n"


def add_to_manifest(directory: str | os.PathLike, names: Iterable[str]) -> None:
    """List ``names`` (relative paths) as vsidgen's in the manifest of ``directory``, if any."""
    directory = pathlib.Path(directory)
    doc = read_manifest(directory)
    if doc is None:
        return
    write_text_atomic(directory / MANIFEST, _manifest_text(
        doc["files"] | set(names), command=str(doc.get("command", "")),
        complete=bool(doc.get("complete", True)), kept=doc["kept"] - set(names),
        owns=doc.get("owns", ())))


# --------------------------------------------------------------------------- leftovers

_LEFTOVER = re.compile(r"^\.(?P<name>.+)\.(?P<kind>tmp|old)-(?P<pid>\d+)-[0-9a-f]{8}$")

#: marker file of a results directory being built (``.DIR.tmp-*``): a leftover without it,
#: and without a manifest, is not vsidgen's and is never touched
BUILDING = ".vsidgen-building"


def _pid_alive(pid: int | None) -> bool:
    if pid is None:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OSError):
        return True
    return True


def _ours(path: pathlib.Path, kind: str) -> bool:
    """Whether a directory named like a leftover is one vsidgen left: a ``tmp`` holds the
    :data:`BUILDING` marker or a manifest (it was complete); an ``old`` was a results
    directory that was replaced — one with a manifest, or an empty one. A user's folder
    that only looks like one (``.out.old-123-0badcafe`` with their files) is not
    (red team, session 47: such folders were deleted, or moved into ``--out``)."""
    try:
        if kind == "tmp":
            return any((path / n).is_file() and not (path / n).is_symlink()
                       for n in (BUILDING, MANIFEST))
        return read_manifest(path) is not None or not any(path.iterdir())
    except OSError:
        return False


def _stale(path: pathlib.Path, pid: int | None) -> bool:
    if str(path) in _ACTIVE:
        return False
    if pid == os.getpid():
        return True
    return not _pid_alive(pid)


def recover(target: str | os.PathLike) -> tuple[str, ...]:
    """Finish or undo an interrupted swap of ``target`` and remove stale leftovers.

    * ``target`` missing and a backup ``.target.old-*`` present (a crash between the
      two renames): a complete ``.target.tmp-*`` (one holding its manifest) is moved
      into place, else the backup is restored;
    * every other stale ``.target.tmp-*`` / ``.target.old-*`` is removed.

    Leftovers of a process that is still alive are not touched. Returns one line per
    action (for stderr).
    """
    target = pathlib.Path(target)
    parent = target.parent if str(target.parent) else pathlib.Path(".")
    msgs: list[str] = []
    try:
        entries = list(parent.iterdir())
    except OSError:
        return ()
    tmps, olds = [], []
    for p in entries:
        m = _LEFTOVER.match(p.name)
        if not m or m.group("name") != target.name or p.is_symlink() or not p.is_dir():
            continue
        pid = int(m.group("pid"))
        if not _stale(p, pid) or not _ours(p, m.group("kind")):
            continue
        (tmps if m.group("kind") == "tmp" else olds).append(p)
    tmps.sort(key=lambda p: p.stat().st_mtime)
    olds.sort(key=lambda p: p.stat().st_mtime)
    if not os.path.lexists(target) and olds:
        complete = [t for t in tmps if (t / MANIFEST).is_file() and not (t / MANIFEST).is_symlink()]
        if complete:
            os.rename(complete[-1], target)
            with contextlib.suppress(OSError):      # a crash between manifest and marker
                (target / BUILDING).unlink()
            tmps.remove(complete[-1])
            msgs.append(f"{target}: an earlier run was interrupted while replacing its results; "
                        "its new results were complete and are now in place")
        else:
            os.rename(olds[-1], target)
            olds.remove(olds[-1])
            msgs.append(f"{target}: an earlier run was interrupted while replacing its results; "
                        "the previous results were restored")
    for p in tmps + olds:
        shutil.rmtree(p, ignore_errors=True)
        what = "unfinished results" if p in tmps else "backup of replaced results"
        msgs.append(f"{parent / p.name}: removed the {what} left by an interrupted run")
    return tuple(msgs)


def _leftover_path(target: pathlib.Path, kind: str) -> pathlib.Path:
    parent = target.parent if str(target.parent) else pathlib.Path(".")
    return parent / f".{target.name}.{kind}-{os.getpid()}-{secrets.token_hex(4)}"


# --------------------------------------------------------------------------- checks

def _nearest_existing(path: pathlib.Path) -> pathlib.Path:
    p = path.absolute()
    while not os.path.lexists(p) and p != p.parent:
        p = p.parent
    return p


def _writable_dir(path: pathlib.Path) -> bool:
    return path.is_dir() and os.access(path, os.W_OK | os.X_OK)


def _resolved(paths: Iterable[str | os.PathLike]) -> tuple[pathlib.Path, ...]:
    out = []
    for p in paths:
        if p is None:
            continue
        try:
            out.append(pathlib.Path(p).resolve())
        except (OSError, RuntimeError):
            continue
    return tuple(out)


def check_output_file(path: str | os.PathLike, *, reads: Iterable[str | os.PathLike] = (),
                      option: str = "--out") -> pathlib.Path:
    """Check that a single output file can be written and is none of the files read.

    Raises:
        VsidgenError: ``path`` is a directory or another non-regular file, a file the
            command reads, or its folder cannot be created or written.
    """
    path = pathlib.Path(path)
    if str(path) in ("", "."):
        raise VsidgenError(f"{option} '{path}': not a file name")
    if path.name in (MANIFEST, BUILDING):
        # `report DIR -o DIR/.vsidgen-results.json --overwrite` replaced the manifest, and the
        # folder was no longer vsidgen's (red team, session 47)
        raise VsidgenError(f"{path}: error: {option} names the file vsidgen keeps its results "
                           "directories' records in; give another file name")
    if path.is_symlink():
        raise VsidgenError(_link_refusal(path, option))
    if os.path.lexists(path):
        if path.is_dir():
            raise VsidgenError(f"{path}: error: {option} is a directory; give a file name")
        if not path.is_file():
            raise VsidgenError(f"{path}: error: {option} exists and is not a regular file "
                               "(a device, pipe or socket); give a file name")
        for r in reads:
            try:
                same = os.path.samefile(path, r)
            except OSError:
                same = False
            if same:
                raise VsidgenError(f"{path}: error: {option} is a file this command reads "
                                   f"({r}); write the output to another file")
    _check_parent_writable(path, option)
    return path


def _link_refusal(path: pathlib.Path, option: str = "") -> str:
    """The message refusing to write over a symbolic link: the file would be renamed over
    the link itself (``report --out /dev/stdout`` replaced the system's link with the report;
    session 44), never written into what it points to."""
    try:
        target = os.readlink(path)
    except OSError:
        target = "?"
    what = f"{option} " if option else ""
    return (f"{path}: error: {what}is a symbolic link (to {target}); vsidgen writes a new file "
            "and renames it into place, which would replace the link, not write into what it "
            "points to\n  hint: give a path that is not a link (the file it points to, or a "
            "new name)")


def _check_parent_writable(path: pathlib.Path, option: str) -> pathlib.Path:
    """The parent of ``path`` (its nearest existing ancestor must be a writable folder)."""
    parent = path.parent if str(path.parent) else pathlib.Path(".")
    base = _nearest_existing(parent)
    if not base.is_dir():
        raise VsidgenError(f"{path}: error: cannot create {option}: {base} is not a directory")
    if not _writable_dir(base):
        raise VsidgenError(f"{path}: error: cannot write {option}: the folder {base} is not "
                           "writable")
    return parent


def plan_output_dir(target: str | os.PathLike, *, overwrite: bool = False,
                    reads: Iterable[str | os.PathLike] = (), option: str = "--out",
                    recover_leftovers: bool = True) -> OutputPlan:
    """Check an output directory before any computation and decide how to write it.

    See the module docstring for the rules. ``reads`` are the files the command
    reads: none of them may be replaced or removed by the new results.

    Raises:
        VsidgenError: the directory cannot or must not be written (exit status 2).
    """
    target = pathlib.Path(target)
    if str(target) in ("", ".", "..") or target.name in ("", ".", ".."):
        raise VsidgenError(f"{option} '{target}': give a directory name (not '.' or '..'); "
                           "the results directory is replaced as a whole")
    if target.is_symlink():
        if target.is_dir():
            raise VsidgenError(f"{target}: error: {option} is a symbolic link; give the "
                               "directory it points to (vsidgen does not replace links)")
        raise VsidgenError(f"{target}: error: {option} is a symbolic link to a file, not a "
                           "results directory; give a new directory name (vsidgen does not "
                           "replace links)")
    if os.path.lexists(target) and not target.is_dir():
        raise VsidgenError(f"{target}: error: {option} exists and is not a directory; "
                           "choose another directory")
    parent = _check_parent_writable(target, option)
    _claim(target, option)
    try:
        return _plan_claimed(target, parent, overwrite=overwrite, reads=reads, option=option,
                             recover_leftovers=recover_leftovers)
    except BaseException:
        release(target)
        raise


def _plan_claimed(target: pathlib.Path, parent: pathlib.Path, *, overwrite: bool, reads,
                  option: str, recover_leftovers: bool) -> OutputPlan:
    """:func:`plan_output_dir` once the directory is this process's to write."""
    if parent.is_dir():
        # permission bits can say yes where the file system says no (root in /sys or /proc):
        # the results would be computed and then not written (session 44)
        probe = _leftover_path(target, "tmp")
        try:
            os.mkdir(probe)
            os.rmdir(probe)
        except OSError as exc:
            raise VsidgenError(f"{target}: error: {option} cannot be created in {parent} "
                               f"({exc.strerror})") from None
    recovered = recover(target) if (recover_leftovers and parent.is_dir()) else ()
    reads_r = _resolved(reads)
    if not target.exists():
        return OutputPlan(target, DirState.ABSENT, WriteMode.SWAP, recovered=recovered,
                          reads=reads_r)
    if not os.access(target, os.W_OK | os.X_OK):
        raise VsidgenError(f"{target}: error: {option} is not writable")
    mode_bits = stat.S_IMODE(target.stat().st_mode)
    files = listing(target)
    tres = target.resolve()
    inside = [r for r in reads_r if r == tres or tres in r.parents]
    if not files:
        return OutputPlan(target, DirState.EMPTY, WriteMode.SWAP, mode_bits=mode_bits,
                          recovered=recovered, reads=reads_r)
    manifest = read_manifest(target)
    if manifest is not None:
        ours = manifest["files"] & files
        # an empty folder is the user's too: a swap would remove it (listing skips it)
        others = (files - ours - {MANIFEST}) | {
            e for e in foreign_entries(target, ours | {MANIFEST})
            if e.endswith("/") and not any(f.startswith(e) for f in files)}
        state = DirState.OWNED if not others else DirState.MIXED
    else:
        ours, others, state = set(), files, DirState.FOREIGN
    if state is DirState.OWNED:
        if inside:
            raise VsidgenError(f"{target}: error: {option} holds {inside[0]}, which this command "
                               "reads; the results directory is replaced as a whole, so write "
                               "the results to another directory")
        return OutputPlan(target, state, WriteMode.SWAP, previous=frozenset(ours),
                          mode_bits=mode_bits, recovered=recovered, reads=reads_r)
    if not overwrite:
        shown = ", ".join(sorted(others)[:5]) + (", ..." if len(others) > 5 else "")
        what = ("is not empty and is not a vsidgen results directory" if state is DirState.FOREIGN
                else "also holds files vsidgen did not write")
        raise VsidgenError(
            f"{target}: error: {option} {what} ({len(others)} file"
            f"{'s' if len(others) != 1 else ''}: {shown})\n"
            f"  hint: choose a new or empty directory, or pass --overwrite to write vsidgen's "
            f"files into it (other files are kept; files with the same names as vsidgen's "
            f"are replaced)")
    return OutputPlan(target, state, WriteMode.IN_PLACE, previous=frozenset(ours),
                      kept=frozenset(o for o in others if not o.endswith("/")),
                      mode_bits=mode_bits, recovered=recovered, reads=reads_r)


#: output directories this process writes: their lock files' descriptors
_LOCKS: dict[str, int] = {}


def _lock_path(target: pathlib.Path) -> pathlib.Path:
    return target.parent / f".{target.name}.lock"


def _claim(target: pathlib.Path, option: str) -> None:
    """Hold an exclusive lock on ``target`` (``flock`` of ``.NAME.lock`` beside it, removed
    when released) until the results are written or the process ends: two runs into one ``--out`` both reported
    success and the first one's results were gone (session 44). The kernel releases the
    lock of a process that dies, so a crash leaves no stale lock. Where the folder above
    ``target`` does not exist yet, or the system has no ``flock``, nothing is locked."""
    try:
        import fcntl
    except ImportError:          # pragma: no cover - not POSIX
        return
    key = os.path.abspath(target)
    if key in _LOCKS or not target.parent.is_dir():
        return
    path = _lock_path(target)
    for _ in range(5):
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0), 0o644)
        except OSError:
            return               # a read-only folder is refused by the checks that follow
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            try:
                holder = os.read(fd, 32).decode("ascii", "replace").strip() or "?"
            except OSError:
                holder = "?"
            os.close(fd)
            raise VsidgenError(f"{target}: error: another vsidgen run (process {holder}) is "
                               f"writing {option} {target}\n  hint: wait for it to end, or write "
                               "to another directory") from None
        try:
            same = os.fstat(fd).st_ino == os.stat(path, follow_symlinks=False).st_ino
        except OSError:
            same = False
        if same and not _lock_file_text(fd):
            os.close(fd)
            raise VsidgenError(f"{path}: error: this file is in the way of the lock vsidgen "
                               f"keeps beside {option} {target} while it writes, and it is not "
                               "one of vsidgen's lock files (which hold a process id); it is "
                               "left as it is\n  hint: rename or move it, or write to another "
                               "directory")
        if same:                 # not a file its holder removed between our open and lock
            os.ftruncate(fd, 0)
            os.write(fd, f"{os.getpid()}\n".encode())
            _LOCKS[key] = fd
            return
        os.close(fd)


def _lock_file_text(fd: int) -> bool:
    """Whether the open file ``fd`` is empty or holds a process id and a newline, as the lock
    files of :func:`_claim` do (a user's ``.out.lock`` was truncated and deleted: red team,
    session 47)."""
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode) or st.st_size > 32:
            return False
        text = os.pread(fd, 33, 0)
    except OSError:
        return False
    return re.fullmatch(rb"(\d+\n?)?", text) is not None


@atexit.register
def _release_all() -> None:
    """At exit, the locks of runs that ended before writing (a refused spec) are removed."""
    for key in list(_LOCKS):
        release(key)


def release(target: str | os.PathLike) -> None:
    """Release this process's lock on an output directory (:func:`_claim`), if it holds one."""
    key = os.path.abspath(target)
    fd = _LOCKS.pop(key, None)
    if fd is not None:
        with contextlib.suppress(OSError):
            os.unlink(_lock_path(pathlib.Path(key)))     # removed while still held
        with contextlib.suppress(OSError):
            os.close(fd)


def print_recovered(plan: OutputPlan, stream=None) -> None:
    """Print what :func:`recover` did (stderr by default)."""
    stream = stream if stream is not None else sys.stderr
    for line in plan.recovered:
        print(printable_lines(f"note: {line}"), file=stream)


# --------------------------------------------------------------------------- writing

def _commit_swap(tmp: pathlib.Path, plan: OutputPlan, command: str = "fit") -> None:
    target = plan.target
    if plan.mode_bits is not None:
        os.chmod(tmp, plan.mode_bits)
    if not os.path.lexists(target):
        os.rename(tmp, target)
        return
    # checked again: the directory was planned before the computation, which may have run
    # for an hour; whatever appeared in it meanwhile is the user's and stays (session 48)
    extra = (foreign_entries(target, set(plan.previous) | {MANIFEST})
             if target.is_dir() and not target.is_symlink() else {target.name})
    if extra:
        _commit_beside(tmp, plan, extra, command)
        return
    old = _leftover_path(target, "old")
    _ACTIVE.add(str(old))
    try:
        os.rename(target, old)
        try:
            os.rename(tmp, target)
        except BaseException:
            os.rename(old, target)
            raise
        shutil.rmtree(old, ignore_errors=True)
    finally:
        _ACTIVE.discard(str(old))


def _commit_beside(tmp: pathlib.Path, plan: OutputPlan, extra: set[str], command: str) -> None:
    """The swap's target gained entries during the run (``extra``): keep them. The results
    are moved in file by file beside them when none has a name the results use; otherwise
    they are kept in a new sibling directory, which the error names."""
    target = plan.target
    shown = ", ".join(sorted(extra)[:5]) + (", ..." if len(extra) > 5 else "")
    new = listing(tmp) - {MANIFEST, BUILDING}
    files = {e for e in extra if not e.endswith("/")}
    clash = {e for e in extra for n in new if n == e or n.startswith(e.rstrip("/") + "/")}
    if target.is_dir() and not target.is_symlink() and not clash:
        print(printable_lines(f"note: {target}: {len(extra)} entr{'y' if len(extra) == 1 else 'ies'} "
                              f"appeared during the run ({shown}); kept, the results written "
                              "beside them"), file=sys.stderr)
        _commit_in_place(tmp, dataclasses.replace(plan, mode=WriteMode.IN_PLACE,
                                                  kept=frozenset(files)), command)
        return
    keep = target.parent / f"{target.name}.results-{secrets.token_hex(4)}"
    os.rename(tmp, keep)
    raise VsidgenError(
        f"{target}: error: {target} changed during the run ({shown}: not vsidgen's, and in the "
        f"way of the results); it is left as it is and the results are in {keep}\n"
        "  hint: move them where you want them; do not write into a results directory while "
        "vsidgen is writing it")


def _remove_entry(path: pathlib.Path) -> None:
    if path.is_symlink() or path.is_file():
        with contextlib.suppress(FileNotFoundError):
            path.unlink()


def _commit_in_place(tmp: pathlib.Path, plan: OutputPlan, command: str) -> None:
    target = plan.target
    new = sorted(listing(tmp) - {MANIFEST, BUILDING})
    tres = target.resolve()
    for rel in new:
        dest = tres / rel
        if any(r == dest for r in plan.reads):
            raise VsidgenError(f"{target / rel}: error: this command reads that file and would "
                               "replace it; write the results to another directory")
        if dest.is_dir() and not dest.is_symlink():
            raise VsidgenError(f"{target / rel}: error: is a directory, where vsidgen writes a "
                               "file; move it or choose another --out")
        if any(p.is_symlink() for p in [dest, *dest.parents] if tres in p.parents or p == tres):
            raise VsidgenError(f"{target / rel}: error: a symbolic link is in the way of a file "
                               "vsidgen writes; move it or choose another --out")
    for rel in new:
        dest = target / rel
        dest.parent.mkdir(parents=True, exist_ok=True)
        os.replace(tmp / rel, dest)
    for rel in sorted(plan.previous - set(new)):
        if rel not in plan.kept:
            _remove_entry(target / rel)
    write_text_atomic(target / MANIFEST, _manifest_text(new, command=command,
                                                        kept=plan.kept - set(new)))


@contextlib.contextmanager
def atomic_directory(target: str | os.PathLike, *, plan: OutputPlan | None = None,
                     overwrite: bool = False, command: str = "fit") -> Iterator[pathlib.Path]:
    """Yield a fresh temporary directory whose files become the results in ``target``.

    On an exception (or KeyboardInterrupt) the temporary directory is removed and
    ``target`` is left exactly as it was. On success the manifest is written and the
    results are swapped in (or, for a directory holding other files and
    ``overwrite``, moved in file by file); see the module docstring. ``plan`` is the
    result of :func:`plan_output_dir` when the caller checked the directory before
    computing (recommended); otherwise it is checked here.
    """
    if plan is None:
        plan = plan_output_dir(target, overwrite=overwrite)
        print_recovered(plan)
    target = plan.target
    parent = target.parent if str(target.parent) else pathlib.Path(".")
    try:
        parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise VsidgenError(f"{target}: error: cannot create the folder {parent} "
                           f"({exc.strerror})") from None
    tmp = _leftover_path(target, "tmp")
    _ACTIVE.add(str(tmp))
    try:
        try:
            os.mkdir(tmp)
        except OSError as exc:
            # e.g. a folder root may "write" by its permission bits but the file system
            # refuses (/sys, /proc): the message names the directory asked for (session 44)
            raise VsidgenError(f"{target}: error: cannot create the results directory there "
                               f"({exc.strerror})") from None
        try:
            (tmp / BUILDING).touch()     # inside: a failed touch still removes tmp
            yield tmp
            if plan.mode is WriteMode.SWAP:
                write_text_atomic(tmp / MANIFEST, _manifest_text(listing(tmp) - {BUILDING},
                                                                 command=command))
                (tmp / BUILDING).unlink()
                _commit_swap(tmp, plan, command)
            else:
                _commit_in_place(tmp, plan, command)
        finally:
            if os.path.lexists(tmp):
                shutil.rmtree(tmp, ignore_errors=True)
    finally:
        _ACTIVE.discard(str(tmp))
        release(target)


@contextlib.contextmanager
def results_in_place(plan: OutputPlan, *, command: str,
                     owns: Iterable[str] = ()) -> Iterator[pathlib.Path]:
    """Write results directly into ``plan.target`` (a long job such as ``diagnose``).

    The files vsidgen wrote there before (its manifest) are removed first, other
    files are kept; the manifest marks the run incomplete until it ends, so a
    crashed run still leaves a vsidgen results directory that the next run can
    replace. Not atomic: a failed run leaves partial results, marked incomplete.
    ``owns``: the top-level names the run may write (files or folders); an incomplete
    manifest claims only those, so files added after a crash stay the user's.
    """
    target = plan.target
    target.mkdir(parents=True, exist_ok=True)
    kept = set(plan.kept)
    for rel in sorted(plan.previous):
        _remove_entry(target / rel)
    write_text_atomic(target / MANIFEST, _manifest_text((), command=command, complete=False,
                                                        kept=kept, owns=owns))
    try:
        yield target
        files = listing(target) - kept - {MANIFEST}
        write_text_atomic(target / MANIFEST, _manifest_text(files, command=command, kept=kept))
    finally:
        release(target)


def _umask() -> int:
    """The process's umask, read without changing it (``os.umask`` sets it, and a thread
    creating a file meanwhile would get mode 0666): Linux's /proc, else the usual 022."""
    try:
        with open("/proc/self/status", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    return 0o022


def _publish_mode(tmp: str, path: pathlib.Path) -> None:
    """Give the temporary file the mode the user expects before it is renamed into place:
    the replaced file's, or a new file's (0666 less the umask). ``mkstemp`` creates 0600,
    so every report and results file was unreadable to colleagues (session 44)."""
    try:
        mode = stat.S_IMODE(os.stat(path).st_mode)
    except OSError:
        mode = 0o666 & ~_umask()
    with contextlib.suppress(OSError):
        os.chmod(tmp, mode)


@contextlib.contextmanager
def atomic_text_file(path: str | os.PathLike) -> Iterator[TextIO]:
    """A UTF-8 text file (``\\n`` line ends) that appears at ``path`` only when the block ends.

    What is written goes to a temporary file beside ``path`` (parent folders created),
    which :func:`os.replace` moves into place when the block ends without an exception, so
    a reader sees the old file or the whole new one, never a part; on an exception the
    temporary file is removed and ``path`` is left as it was.
    """
    path = pathlib.Path(path)
    if path.is_symlink():
        raise VsidgenError(_link_refusal(path))
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        # backslashreplace: a file name that is not UTF-8 reaches text as surrogates
        # (`\udcfe`), which UTF-8 cannot encode (`fit --report` with such a record or spec
        # name was an internal error after the fit, its results lost; session 46)
        with os.fdopen(fd, "w", encoding="utf-8", errors="backslashreplace",
                       newline="\n") as fh:
            yield fh
        _publish_mode(tmp, path)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def write_text_atomic(path: str | os.PathLike, text: str) -> pathlib.Path:
    """Write ``text`` to ``path`` atomically (:func:`atomic_text_file`)."""
    with atomic_text_file(path) as fh:
        fh.write(text)
    return pathlib.Path(path)


def write_bytes_atomic(path: str | os.PathLike, data: bytes) -> pathlib.Path:
    """Write ``data`` to ``path`` atomically: a temporary file beside it, then
    :func:`os.replace` (as :func:`atomic_text_file`; parent folders created)."""
    path = pathlib.Path(path)
    if path.is_symlink():
        raise VsidgenError(_link_refusal(path))
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
        _publish_mode(tmp, path)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    return path


__all__ = ["MANIFEST", "DirState", "OutputPlan", "WriteMode", "add_to_manifest",
           "atomic_directory", "atomic_text_file", "check_output_file", "listing", "plan_output_dir",
           "print_recovered", "read_manifest", "recover", "release", "results_in_place",
           "write_bytes_atomic", "write_text_atomic"]
