"""Data file formats: CSV text and MATLAB ``.mat`` files (v4/v5/v7 and v7.3).

The data map of a spec names *columns*; in a CSV file a column is a header
field. In a MATLAB file a column reference is one of

* ``name``          a variable holding a vector (N, N×1 or 1×N), e.g. ``de`` or ``t``;
* ``name(:,k)``     column ``k`` (1-based, as in MATLAB) of an N×m matrix, e.g.
  ``fdata(:,3)`` for SIDPAC's ``fdata`` or ``Z(:,2)`` for FVSysID's ``Z``;
* ``s.field``       a vector field of a struct ``s`` (nested: ``s.a.b``), and
  ``s.field(:,k)``;
* ``colname``       a named column of a matrix ``X`` that has a companion cell
  array (or char matrix) of column names ``X_names`` with one name per column
  of ``X``, e.g. ``X = [t de alpha]`` and ``X_names = {'t','de','alpha'}``.

A plain name that is a variable wins over a named matrix column. Version 4–7
files are read with :func:`scipy.io.loadmat`, version 7.3 files (HDF5) with
:mod:`h5py` (MATLAB stores arrays column-major, so HDF5 datasets are
transposed back). Anything that is neither CSV text nor a MAT file is
rejected with a :class:`~vsidgen.errors.DataError` listing the supported
formats (never a decoding error).
"""

from __future__ import annotations

import enum
import pathlib
import re
from collections.abc import Sequence

import numpy as np

from ..errors import DataError

SUPPORTED = ("CSV (comma-separated text with one header row of column names), "
             "MATLAB .mat v4/v5/v7 (scipy.io.loadmat) and v7.3 (HDF5, h5py)")

_HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"
_SELECT_RE = re.compile(r"^\s*([A-Za-z_][\w.]*)\s*\(\s*:\s*,\s*(\d+)\s*\)\s*$")


class DataFormat(enum.Enum):
    """Format of a data file, from its content (not its extension)."""

    CSV = "csv"
    MAT = "mat"          # MATLAB v4-v7 (scipy.io.loadmat)
    MAT73 = "mat-v7.3"   # MATLAB v7.3 = HDF5 (h5py)


def detect_format(path: pathlib.Path) -> DataFormat:
    """Format of ``path`` from its first bytes.

    MAT v5/v7 files start with the text ``MATLAB 5.0 MAT-file``; v7.3 files
    are HDF5 (signature at byte 0 or 512, after MATLAB's 512-byte header).
    Files named ``*.mat`` without either header are taken as MAT v4. Text
    that decodes as UTF-8 and has no NUL byte is CSV. Everything else raises
    DataError naming the supported formats.
    """
    try:
        with open(path, "rb") as fh:
            head = fh.read(65536)
    except FileNotFoundError:
        raise DataError("file not found", path=path,
                        hint="check the path (relative paths are taken from the current "
                             "directory)") from None
    except IsADirectoryError:
        raise DataError("is a directory, not a data file", path=path) from None
    except OSError as exc:
        raise DataError(f"cannot read file: {exc.strerror or exc}", path=path) from None
    if head.startswith(b"MATLAB 5.0 MAT-file") or head.startswith(b"MATLAB 7.0 MAT-file"):
        if head[:128].find(b"MATLAB 7.3") >= 0 or head[512:520] == _HDF5_MAGIC:
            return DataFormat.MAT73
        return DataFormat.MAT
    if head.startswith(b"MATLAB 7.3") or head[:8] == _HDF5_MAGIC or head[512:520] == _HDF5_MAGIC:
        return DataFormat.MAT73
    if path.suffix.lower() == ".mat":
        return DataFormat.MAT  # v4 has no text header; scipy decides
    if b"\0" not in head:
        try:
            head.decode("utf-8")
            return DataFormat.CSV
        except UnicodeDecodeError as exc:
            if exc.start >= len(head) - 4:  # a multi-byte character cut by the 64 KiB window
                return DataFormat.CSV
            if _legacy_text(head):
                line = head[:exc.start].count(b"\n") + 1
                raise DataError(
                    f"not UTF-8 text: byte 0x{head[exc.start]:02x} at line {line} (the file "
                    "looks like text in a legacy 8-bit encoding such as Windows-1252 or "
                    "Latin-1)", path=path,
                    hint="save it as CSV UTF-8 (Excel: 'CSV UTF-8 (Comma delimited)'; "
                         "iconv -f cp1252 -t utf-8)") from None
    if head[:2] in (b"\xff\xfe", b"\xfe\xff") or _utf16_without_bom(head):
        raise DataError("text in UTF-16 (the encoding of Excel's 'Unicode Text' and of "
                        "PowerShell's redirection), not UTF-8", path=path,
                        hint="save it as CSV UTF-8 (iconv -f utf-16 -t utf-8, or Excel: "
                             "'CSV UTF-8 (Comma delimited)')")
    kind = _guess_binary(head)
    raise DataError(f"not a supported data file{kind}", path=path,
                    hint=f"supported formats: {SUPPORTED}")


def _utf16_without_bom(head: bytes) -> bool:
    """Whether bytes read as UTF-16 text without a byte-order mark: every other byte NUL
    (ASCII text in UTF-16) over the first 64 bytes, and the decoded text printable."""
    h = head[:64 - (len(head[:64]) % 2)]
    if len(h) < 8:
        return False
    for zeros, chars in ((h[1::2], h[0::2]), (h[0::2], h[1::2])):
        if all(b == 0 for b in zeros) and all(32 <= b < 127 or b in (9, 10, 13) for b in chars):
            return True
    return False


def _legacy_text(head: bytes) -> bool:
    """Whether bytes that are not UTF-8 read as text in an 8-bit code page: no control
    characters but tab, CR and LF, and printable ASCII for at least 90 % of the bytes."""
    if any(b < 32 and b not in (9, 10, 13) for b in head) or 127 in head:
        return False
    return sum(32 <= b < 127 or b in (9, 10, 13) for b in head) >= 0.9 * len(head)


def _guess_binary(head: bytes) -> str:
    if head.startswith(b"PK\x03\x04"):
        return " (a ZIP container, e.g. an Excel .xlsx: save the sheet as CSV)"
    if head.startswith(b"\xd0\xcf\x11\xe0"):
        return " (an old Office file, e.g. Excel .xls: save the sheet as CSV)"
    if head.startswith(b"\x93NUMPY"):
        return " (a NumPy .npy file)"
    return " (binary content)"


# --------------------------------------------------------------------------- MAT v4-v7

def _load_v5(path: pathlib.Path) -> dict:
    import scipy.io

    try:
        raw = scipy.io.loadmat(str(path), simplify_cells=True)
    except NotImplementedError:  # scipy's answer to v7.3 files it cannot read
        raise DataError("MAT v7.3 file not readable", path=path,
                        hint=f"supported formats: {SUPPORTED}") from None
    except Exception as exc:  # scipy raises ValueError, TypeError, ... on corrupt files
        raise DataError(f"not a readable MATLAB .mat file ({type(exc).__name__}: {exc})",
                        path=path, hint=f"supported formats: {SUPPORTED}") from None
    return {k: v for k, v in raw.items() if not k.startswith("__")}


# --------------------------------------------------------------------------- MAT v7.3

def _h5_value(f, obj):
    """A MATLAB object of a v7.3 file as Python: ndarray, str, list (cell) or dict (struct)."""
    import h5py

    if isinstance(obj, h5py.Group):
        return {k: _h5_value(f, obj[k]) for k in obj.keys() if not k.startswith("#")}
    cls = obj.attrs.get("MATLAB_class", b"")
    cls = cls.decode() if isinstance(cls, bytes) else str(cls)
    if obj.attrs.get("MATLAB_empty", 0):
        return np.zeros(0)
    data = obj[()]
    if cls == "char":
        arr = np.asarray(data, dtype=np.uint16)
        if arr.ndim == 2 and arr.shape[0] > 1 and arr.shape[1] > 1:
            return ["".join(map(chr, row)).rstrip() for row in arr.T]  # char matrix: one per row
        return "".join(map(chr, arr.ravel()))
    if cls == "cell" or (isinstance(data, np.ndarray) and data.dtype.kind == "O"):
        return [_h5_value(f, f[ref]) for ref in np.asarray(data).T.ravel()]
    arr = np.asarray(data)
    if arr.dtype.names and {"real", "imag"} <= set(arr.dtype.names):
        arr = arr["real"]
    if arr.ndim >= 2:
        arr = arr.T  # MATLAB is column-major
    return np.squeeze(arr) if arr.ndim == 2 and 1 in arr.shape else arr


class _H5Vars(dict):
    """Top-level variables of a v7.3 file, converted lazily (only those the data map names)."""

    def __init__(self, f):
        super().__init__()
        self._f = f
        self._names = [k for k in f.keys() if not k.startswith("#")]

    def keys(self):
        return list(self._names)

    def __contains__(self, key):
        return key in self._names

    def __iter__(self):
        return iter(self._names)

    def __getitem__(self, key):
        if not dict.__contains__(self, key):
            dict.__setitem__(self, key, _h5_value(self._f, self._f[key]))
        return dict.__getitem__(self, key)

    def items(self):
        return [(k, self[k]) for k in self._names]


# --------------------------------------------------------------------------- column references

def _is_names(v) -> bool:
    if isinstance(v, str):
        return False
    if isinstance(v, (list, tuple)):
        return all(isinstance(x, str) for x in v) and len(v) > 0
    if isinstance(v, np.ndarray) and v.ndim == 1 and v.size > 0:
        return v.dtype.kind in "US" or (v.dtype.kind == "O" and all(isinstance(x, str) for x in v))
    return False


def _walk(variables, dotted: str):
    parts = dotted.split(".")
    if parts[0] not in variables:
        return None
    v = variables[parts[0]]
    for p in parts[1:]:
        if not isinstance(v, dict) or p not in v:
            return None
        v = v[p]
    return v


def _numeric(v, ref: str, path) -> np.ndarray | None:
    if isinstance(v, (dict, str, list, tuple)) or v is None:
        return None
    arr = np.asarray(v)
    if arr.dtype.kind not in "biuf":
        return None
    return arr.astype(np.float64)


def _names_of(variables) -> list[str]:
    out: list[str] = []

    def add(prefix, v, depth):
        if isinstance(v, dict) and depth < 4:
            for k, x in v.items():
                add(f"{prefix}.{k}", x, depth + 1)
            return
        arr = _numeric(v, prefix, None)
        if arr is None:
            return
        if arr.ndim == 2 and min(arr.shape) > 1:
            out.append(f"{prefix}(:,1..{arr.shape[1]})")
        else:
            out.append(prefix)

    for k in variables.keys():
        add(k, variables[k], 0)
    for k in variables.keys():
        if k.endswith("_names") and k[:-6] in variables and _is_names(variables[k]):
            out += [str(n).strip() for n in variables[k]]
    return out


def _named_columns(variables) -> dict[str, tuple[str, int]]:
    """{column name: (matrix variable, 0-based column)} from ``X`` + ``X_names`` pairs."""
    out: dict[str, tuple[str, int]] = {}
    for k in variables.keys():
        if not (k.endswith("_names") and k[:-6] in variables):
            continue
        names = variables[k]
        if not _is_names(names):
            continue
        for j, nm in enumerate(names):
            out.setdefault(str(nm).strip(), (k[:-6], j))
    return out


def _resolve(variables, ref: str, path, named, taken=None) -> np.ndarray:
    m = _SELECT_RE.match(ref)
    col = None
    base = ref.strip()
    if m:
        base, col = m.group(1), int(m.group(2))
    v = _walk(variables, base)
    if v is None and m is None and base in named:
        var, j = named[base]
        matrix = _numeric(variables[var], var, path)
        if matrix is None or matrix.ndim != 2 or matrix.shape[1] <= j:
            raise DataError(f"`{var}_names` names {len(variables[var + '_names'])} columns but "
                            f"`{var}` is not a matrix with that many columns", path=path,
                            column=ref, hint="give one name per column of the matrix")
        return matrix[:, j]
    if v is None:
        from ..suggest import column_hint

        hint = column_hint(ref, _names_of(variables), taken)
        if not (hint and hint.startswith("did you mean")):
            hint = (hint + "; " if hint else "") + "variables in the file: " + \
                ", ".join(_names_of(variables)[:15])
        raise DataError(f"variable '{ref}' not found", path=path, column=ref, hint=hint)
    arr = _numeric(v, base, path)
    if arr is None:
        raise DataError(f"variable '{base}' is not numeric ({type(v).__name__})", path=path,
                        column=ref, hint="map channels to numeric vectors or matrix columns")
    if col is not None:
        if arr.ndim == 1:
            arr = arr[:, None]
        if arr.ndim != 2 or not 1 <= col <= arr.shape[1]:
            raise DataError(f"column {col} of '{base}' does not exist (shape "
                            f"{'x'.join(map(str, arr.shape))})", path=path, column=ref,
                            hint="columns are numbered from 1, as in MATLAB")
        return arr[:, col - 1]
    if arr.ndim == 0:
        raise DataError(f"variable '{base}' is a scalar, not a time history", path=path,
                        column=ref)
    if arr.ndim != 1:
        raise DataError(f"variable '{base}' is a {'x'.join(map(str, arr.shape))} matrix",
                        path=path, column=ref,
                        hint=f"select a column, e.g. `{base}(:,1)` (1-based), or store the "
                             f"column names in a cell array `{base}_names`")
    return arr


def read_mat_columns(path: pathlib.Path, refs: Sequence[str], fmt: DataFormat, *,
                     taken=None) -> dict[str, np.ndarray]:
    """Columns ``refs`` (see the module docstring) of a MAT file as float64 vectors.

    Raises:
        DataError: unreadable file, missing variable (with close names), a
            reference to a matrix without a column, columns of unequal length.
    """
    if fmt is DataFormat.MAT73:
        import h5py

        try:
            f = h5py.File(str(path), "r")
        except OSError as exc:
            raise DataError(f"not a readable MAT v7.3 (HDF5) file ({exc})", path=path,
                            hint=f"supported formats: {SUPPORTED}") from None
        with f:
            variables = _H5Vars(f)
            named = _named_columns(variables)
            cols = {r: _resolve(variables, r, path, named, taken) for r in refs}
    else:
        variables = _load_v5(path)
        named = _named_columns(variables)
        cols = {r: _resolve(variables, r, path, named, taken) for r in refs}
    lengths = {r: c.shape[0] for r, c in cols.items()}
    if len(set(lengths.values())) > 1:
        first = refs[0]
        odd = next(r for r in refs if lengths[r] != lengths[first])
        raise DataError(f"'{odd}' has {lengths[odd]} samples but '{first}' has {lengths[first]}",
                        path=path, column=odd, hint="all channels of a record need one value per "
                                                    "time stamp")
    return cols


__all__ = ["DataFormat", "SUPPORTED", "detect_format", "read_mat_columns"]
