"""Limits on the files vsidgen reads (``docs/security.md``, "Limits").

Every file named on the command line (records, results, reference estimates) is
checked with :func:`check_input_file` before it is opened for reading: it must be
a regular file (not a directory, device such as ``/dev/zero``, pipe or socket) no
larger than a limit. The limits can be changed with environment variables whose
values are byte counts with an optional binary suffix (``K``, ``M``, ``G``, ``T``):

=========================  ==============================  ==========
variable                   applies to                      default
=========================  ==============================  ==========
``VSIDGEN_MAX_DATA_BYTES``  CSV records (fit, diagnose,     2 GiB
                            check --data, simulate
                            --inputs-from)
``VSIDGEN_MAX_JSON_BYTES``  results.json, findings.json,    256 MiB
                            reference estimates, signals
                            CSV files of a results
                            directory, --params-from
=========================  ==============================  ==========
"""

from __future__ import annotations

import os
import pathlib
import re
import stat

from .errors import DataError, VsidgenError

#: most integration sub-steps per sample: they are unrolled into the compiled transition
#: (a spec or --substeps of 10^8 compiled for ever); rk4 is the cure for a coarse step
MAX_SUBSTEPS = 64
DATA_LIMIT_ENV = "VSIDGEN_MAX_DATA_BYTES"
DEFAULT_DATA_LIMIT = 2 << 30
JSON_LIMIT_ENV = "VSIDGEN_MAX_JSON_BYTES"
DEFAULT_JSON_LIMIT = 256 << 20

_SUFFIX = {"": 1, "K": 1 << 10, "M": 1 << 20, "G": 1 << 30, "T": 1 << 40}


def _limit(env: str, default: int) -> int:
    text = os.environ.get(env, "").strip()
    if not text:
        return default
    m = re.fullmatch(r"(\d+)\s*([KMGT]?)(?:i?B)?", text, flags=re.IGNORECASE)
    if not m:
        raise VsidgenError(f"environment variable {env}={text!r}: expected a byte count such "
                           "as 2G, 500M or 1048576")
    value = int(m.group(1)) * _SUFFIX[m.group(2).upper()]
    if value <= 0:
        raise VsidgenError(f"environment variable {env}={text!r}: the limit must be positive")
    return value


def data_limit() -> int:
    """Largest CSV record read, in bytes (``$VSIDGEN_MAX_DATA_BYTES``, default 2 GiB)."""
    return _limit(DATA_LIMIT_ENV, DEFAULT_DATA_LIMIT)


def json_limit() -> int:
    """Largest results/reference file read, in bytes (``$VSIDGEN_MAX_JSON_BYTES``, default 256 MiB)."""
    return _limit(JSON_LIMIT_ENV, DEFAULT_JSON_LIMIT)


def human_bytes(n: int) -> str:
    """``2147483648`` -> ``'2 GiB'`` (exact multiples shown without decimals)."""
    for unit, size in (("TiB", 1 << 40), ("GiB", 1 << 30), ("MiB", 1 << 20), ("KiB", 1 << 10)):
        if n >= size:
            v = n / size
            return f"{v:.0f} {unit}" if v == int(v) else f"{v:.1f} {unit}"
    return f"{n} bytes"


def check_input_file(path: str | os.PathLike, *, what: str = "file", kind: str = "data",
                     data_error: bool = True) -> pathlib.Path:
    """Refuse a path that is not a readable regular file within the size limit.

    Args:
        path: the file named by the user.
        what: how to call it in messages ("data file", "reference file", ...).
        kind: ``"data"`` (limit :func:`data_limit`) or ``"json"`` (:func:`json_limit`).
        data_error: raise :class:`DataError` (else :class:`VsidgenError`).

    The checks use :func:`os.stat` (which follows symbolic links, so a link to
    ``/dev/zero`` is refused like ``/dev/zero`` itself) and never open the file.

    Raises:
        DataError | VsidgenError: missing, not a regular file, or too large (exit 2).
    """
    path = pathlib.Path(path)
    limit = data_limit() if kind == "data" else json_limit()
    env = DATA_LIMIT_ENV if kind == "data" else JSON_LIMIT_ENV

    def fail(msg: str, hint: str = ""):
        if data_error:
            raise DataError(msg, path=path, hint=hint or None)
        raise VsidgenError(f"{path}: error: {msg}" + (f"\n  hint: {hint}" if hint else ""))

    try:
        st = os.stat(path)
    except FileNotFoundError:
        fail(f"{what} not found",
             "check the path (relative paths are taken from the current directory)")
    except (OSError, ValueError) as exc:
        fail(f"cannot access {what}: {getattr(exc, 'strerror', None) or exc}")
    if stat.S_ISDIR(st.st_mode):
        fail(f"{what} is a directory, not a file")
    if not stat.S_ISREG(st.st_mode):
        kind_name = ("a character device" if stat.S_ISCHR(st.st_mode) else
                     "a block device" if stat.S_ISBLK(st.st_mode) else
                     "a named pipe (FIFO)" if stat.S_ISFIFO(st.st_mode) else
                     "a socket" if stat.S_ISSOCK(st.st_mode) else "not a regular file")
        fail(f"{what} is {kind_name}, not a regular file",
             "vsidgen reads only regular files (no devices, pipes or sockets)")
    if st.st_size > limit:
        fail(f"{what} is {human_bytes(st.st_size)}, more than the limit of {human_bytes(limit)}",
             f"set {env} (e.g. {env}=8G) to read larger files")
    if not os.access(path, os.R_OK):
        fail(f"{what} is not readable (permission denied)")
    return path


__all__ = ["DATA_LIMIT_ENV", "DEFAULT_DATA_LIMIT", "DEFAULT_JSON_LIMIT", "JSON_LIMIT_ENV",
           "check_input_file", "data_limit", "human_bytes", "json_limit"]


def _json_int(text: str):
    """A JSON integer: an int up to 18 digits, else a float (inf beyond its range), so that
    a 400-digit number is an ordinary out-of-range value for the reader's checks, not an
    OverflowError where it is converted (nor Python's 4300-digit int limit)."""
    return int(text) if len(text) <= 18 else float(text)


def _json_int_strict(text: str):
    """A JSON integer of a file vsidgen wrote: it writes none longer than 18 digits."""
    if len(text) > 18:
        raise ValueError(f"an integer of {len(text)} digits")
    return int(text)


def parse_json(text: str, *, strict_ints: bool = False):
    """``json.loads`` for files users hand to vsidgen (results.json, references, manifests).

    Integers too long for a float become ±inf or floats (:func:`_json_int`), or, with
    ``strict_ints`` (a file vsidgen wrote, which holds none), raise ``ValueError``; a document
    nested beyond the interpreter's recursion limit raises ``ValueError`` like any other
    invalid JSON (``json.JSONDecodeError`` is a ``ValueError`` too).
    """
    import json

    try:
        return json.loads(text, parse_int=_json_int_strict if strict_ints else _json_int)
    except RecursionError:
        raise ValueError("JSON nested too deeply") from None
