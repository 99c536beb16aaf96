"""Atomic writes: readers never see a partial file, and failures leave old files intact.

Every file vsidgen writes for the user (generated modules, records, results, reports)
goes through these two helpers: a temporary file or directory beside the target,
then :func:`os.replace`.
"""

from __future__ import annotations

import contextlib
import os
import pathlib
import shutil
import tempfile
from collections.abc import Iterator

from .errors import VsidgenError


@contextlib.contextmanager
def atomic_directory(target: str | os.PathLike) -> Iterator[pathlib.Path]:
    """Yield a fresh temporary directory that replaces ``target`` on success.

    On an exception (or KeyboardInterrupt) the temporary directory is removed
    and ``target`` is left exactly as it was. Files of ``target`` that the new
    run does not write are not carried over: the directory is the results of
    one run.
    """
    target = pathlib.Path(target)
    parent = target.parent if str(target.parent) else pathlib.Path(".")
    parent.mkdir(parents=True, exist_ok=True)
    if target.exists() and not target.is_dir():
        raise VsidgenError(f"{target}: exists and is not a directory; choose another --out")
    tmp = pathlib.Path(tempfile.mkdtemp(prefix=f".{target.name}.tmp-", dir=parent))
    try:
        yield tmp
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    old = None
    if target.exists():
        old = pathlib.Path(tempfile.mkdtemp(prefix=f".{target.name}.old-", dir=parent))
        old.rmdir()
        os.replace(target, old)
    try:
        os.replace(tmp, target)
    except BaseException:
        if old is not None:
            os.replace(old, target)
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def write_text_atomic(path: str | os.PathLike, text: str) -> pathlib.Path:
    """Write ``text`` to ``path`` through a temporary file and ``os.replace``."""
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8", newline="\n") as fh:
            fh.write(text)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    return path
