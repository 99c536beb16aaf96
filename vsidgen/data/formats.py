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

Only the variables the data map needs are read (all of them only to list
close names when a reference is not found). A MAT file is compressed, so its
size says little about what reading it costs: the variables read from one
file may hold at most :func:`vsidgen.limits.data_limit` bytes uncompressed
(``$VSIDGEN_MAX_DATA_BYTES``, 2 GiB by default, the limit on a CSV record),
counted before anything is read -- from the declared shape and type of a v7.3
dataset, from the decompressed length of a compressed v7 variable -- and
structs and cells are read at most :data:`MAX_MAT_NESTING` levels deep, at
most :data:`MAX_MAT_OBJECTS` arrays in all, never following a reference into
a cell or struct that contains it.
"""

from __future__ import annotations

import dataclasses
import enum
import math
import os
import pathlib
import re
import struct
import zlib
from collections.abc import Sequence

import numpy as np

from ..errors import DataError
from ..limits import DATA_LIMIT_ENV, data_limit, human_bytes

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
    if path.suffix.lower() in _NOT_DATA:
        # a spec or a README given as a record was read as a CSV whose first line is a
        # comment (session 44, a new user)
        raise DataError(f"not a supported data file (a {_NOT_DATA[path.suffix.lower()]} file)",
                        path=path, hint=f"give the flight record; supported formats: {SUPPORTED}")
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


#: file name endings that are never a flight record, and what they are
_NOT_DATA = {".yaml": "YAML", ".yml": "YAML", ".json": "JSON", ".md": "Markdown",
             ".html": "HTML", ".htm": "HTML", ".py": "Python", ".ipynb": "notebook",
             ".pdf": "PDF", ".xlsx": "Excel workbook", ".xls": "Excel workbook",
             ".zip": "zip archive", ".gz": "gzip archive"}


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


# --------------------------------------------------------------------------- read limits

#: deepest nesting of cells and structs read from a MAT file (SIDPAC/FVSysID files: 1-3)
MAX_MAT_NESTING = 32
#: most MATLAB arrays (variables, cell elements, struct fields) read from one MAT file
MAX_MAT_OBJECTS = 100_000


class _ReadBudget:
    """What reading one MAT file may still cost: bytes of array data, uncompressed
    (:func:`~vsidgen.limits.data_limit`), and MATLAB arrays (:data:`MAX_MAT_OBJECTS`)."""

    def __init__(self, path):
        self.path = path
        self.limit = data_limit()
        self.left = self.limit
        self.objects = 0

    def take(self, shown: str, nbytes: int, what: str, *, exact: bool = True) -> None:
        """Count ``nbytes`` of variable ``shown`` (``what``: its declared shape and class)
        before it is read; DataError if it would exceed the limit. ``exact``: False when
        ``nbytes`` is only known to be at least that much (decompression stopped)."""
        if nbytes > self.left:
            if nbytes > self.limit:
                room = f"more than the limit of {human_bytes(self.limit)}"
            else:
                room = (f"more than the {human_bytes(self.left)} left of the limit of "
                        f"{human_bytes(self.limit)}")
            size = human_bytes(nbytes) if exact else f"more than {human_bytes(self.left)}"
            raise DataError(
                f"variable '{shown}' ({what}) is {size} uncompressed, {room} on the data read "
                f"from one file", path=self.path,
                hint=f"vsidgen reads at most {DATA_LIMIT_ENV} bytes of uncompressed variables "
                     f"from a MAT file (the limit on a CSV record); set it (e.g. "
                     f"{DATA_LIMIT_ENV}=32G) to read a larger record")
        self.left -= nbytes

    def count(self, shown: str) -> None:
        self.objects += 1
        if self.objects > MAX_MAT_OBJECTS:
            raise DataError(f"more than {MAX_MAT_OBJECTS} MATLAB arrays (cell elements, struct "
                            f"fields) to read, at '{shown}'", path=self.path,
                            hint="store the channels as numeric vectors or matrix columns")


def _too_many_variables(path) -> DataError:
    return DataError(f"more than {MAX_MAT_OBJECTS} variables in the file", path=path,
                     hint="store the channels as numeric vectors or matrix columns")


def _shape_text(shape) -> str:
    return "x".join(str(int(n)) for n in shape) if len(shape) else "1x1"


# --------------------------------------------------------------------------- MAT v4-v7

_MI_MATRIX, _MI_COMPRESSED = 14, 15
#: MATLAB array classes of a MAT v5 array flags element (mxCHAR_CLASS = 4, ...)
_MX_CLASSES = {1: "cell", 2: "struct", 3: "object", 4: "char", 5: "sparse", 6: "double",
               7: "single", 8: "int8", 9: "uint8", 10: "int16", 11: "uint16", 12: "int32",
               13: "uint32", 14: "int64", 15: "uint64"}


@dataclasses.dataclass
class _V5Entry:
    """One top-level variable of a MAT v5/v7 file: where its element is, and its header."""

    name: str
    offset: int        # of the element's data (after its 8-byte tag)
    nbytes: int        # of the element as stored (compressed for miCOMPRESSED)
    compressed: bool
    what: str          # declared shape and class, e.g. "1x300000000 double"


def _v5_header(body: bytes, order: str) -> tuple[str, str] | None:
    """(name, "shape class") from the start of a miMATRIX element's content."""
    off = 0
    parts = []
    for _ in range(3):  # array flags, dimensions, name
        if off + 8 > len(body):
            return None
        mdtype, n = struct.unpack_from(order + "II", body, off)
        if mdtype >> 16:  # small data element: 2-byte length, 2-byte type, 4 bytes of data
            n, start, off = mdtype >> 16, off + 4, off + 8
            if n > 4:
                return None
        else:
            start, off = off + 8, off + 8 + (n + 7) // 8 * 8
        if start + n > len(body):
            return None
        parts.append(body[start:start + n])
    flags, dims, name = parts
    if len(flags) < 4:
        return None
    cls = _MX_CLASSES.get(struct.unpack_from(order + "I", flags)[0] & 0xFF, "unknown")
    shape = struct.unpack(order + f"{len(dims) // 4}i", dims[:len(dims) // 4 * 4])
    return name.decode("latin1") or "__function_workspace__", f"{_shape_text(shape)} {cls}"


def _inflate(fh, offset: int, nbytes: int, *, cap: int, keep: int = 0) -> tuple[int, bytes]:
    """(length, first ``keep`` bytes) of the zlib stream stored at ``offset`` in ``nbytes``
    bytes, decompressed piecewise; the length counting stops once above ``cap``."""
    d = zlib.decompressobj()
    fh.seek(offset)
    left, total, head = nbytes, 0, b""
    while left > 0 and not d.eof:
        buf = fh.read(min(left, 1 << 16))
        if not buf:
            break
        left -= len(buf)
        while buf and not d.eof:
            out = d.decompress(buf, 1 << 20)
            if len(head) < keep:
                head += out[:keep - len(head)]
            total += len(out)
            if total > cap and len(head) >= keep:
                return total, head
            buf = d.unconsumed_tail
    return total, head


def _v5_index(path: pathlib.Path) -> dict[str, _V5Entry] | None:
    """The top-level variables of a MAT v5/v7 file by name (the first of a repeated name, as
    :func:`scipy.io.loadmat` reads with ``variable_names``); None when the file is not v5
    (v4 stores every variable uncompressed, so its size bounds what reading it costs;
    anything else :func:`scipy.io.loadmat` refuses)."""
    try:
        size = os.stat(path).st_size
        with open(path, "rb") as fh:
            head = fh.read(128)
            if len(head) < 128 or 0 in head[:4]:
                return None  # v4 (scipy: a zero in the first four bytes), or too short
            order = "<" if head[126:128] == b"IM" else ">"
            major = head[125] if head[126:127] == b"I" else head[124]
            if major != 1:
                return None
            out: dict[str, _V5Entry] = {}
            pos = 128
            while pos < size:
                fh.seek(pos)
                tag = fh.read(8)
                if len(tag) < 8:
                    break  # scipy reports the truncated file
                mdtype, nbytes = struct.unpack(order + "II", tag)
                if mdtype >> 16 or nbytes == 0:
                    break  # not a variable: scipy reports the corrupt file
                if mdtype == _MI_COMPRESSED:
                    try:
                        _, body = _inflate(fh, pos + 8, nbytes, cap=0, keep=8 + 512)
                    except zlib.error:
                        body = b""
                    header = _v5_header(body[8:], order)
                elif mdtype == _MI_MATRIX:
                    header = _v5_header(fh.read(min(nbytes, 512)), order)
                else:
                    header = None
                if header is not None and header[0] not in out:
                    if len(out) >= MAX_MAT_OBJECTS:
                        raise _too_many_variables(path)
                    stored = min(nbytes, max(size - pos - 8, 0))  # a truncated file has less
                    out[header[0]] = _V5Entry(header[0], pos + 8, stored,
                                              mdtype == _MI_COMPRESSED, header[1])
                pos += 8 + nbytes
            return out
    except OSError as exc:
        raise DataError(f"cannot read file: {exc.strerror or exc}", path=path) from None


def _loadmat(path: pathlib.Path, names: list[str] | None) -> dict:
    import scipy.io

    try:
        raw = scipy.io.loadmat(str(path), simplify_cells=True, variable_names=names)
    except NotImplementedError:  # scipy's answer to v7.3 files it cannot read
        raise DataError("MAT v7.3 file not readable", path=path,
                        hint=f"supported formats: {SUPPORTED}") from None
    except Exception as exc:  # scipy raises ValueError, TypeError, ... on corrupt files
        raise DataError(f"not a readable MATLAB .mat file ({type(exc).__name__}: {exc})",
                        path=path, hint=f"supported formats: {SUPPORTED}") from None
    return {k: v for k, v in raw.items() if not k.startswith("__")}


class _NamedVariables(dict):
    """A MAT file's variables read on demand: ``_names`` lists them, the dict holds those read."""

    def keys(self):
        return list(self._names)

    def __contains__(self, key):
        return key in self._names

    def __iter__(self):
        return iter(self._names)


class _V5Vars(_NamedVariables):
    """Variables of a MAT v4-v7 file, read when first used (each checked against the read
    budget before it is decompressed)."""

    def __init__(self, path: pathlib.Path):
        super().__init__()
        self._path = path
        self._budget = _ReadBudget(path)
        self._index = _v5_index(path)
        if self._index is None:  # v4 (bounded by the file size) or not a MAT file at all
            dict.update(self, _loadmat(path, None))
            self._names = list(dict.keys(self))
        else:
            self._names = [k for k in self._index if not k.startswith("__")]

    def _reserve(self, key) -> None:
        entry = self._index[key]
        if entry.compressed:
            with open(self._path, "rb") as fh:
                try:
                    size, _ = _inflate(fh, entry.offset, entry.nbytes, cap=self._budget.left)
                except zlib.error as exc:
                    raise DataError(f"variable '{key}': corrupt compressed data ({exc})",
                                    path=self._path) from None
        else:
            size = entry.nbytes
        self._budget.count(key)
        self._budget.take(key, size, entry.what, exact=size <= self._budget.left)

    def prefetch(self, keys) -> None:
        """Read the variables ``keys`` that are within the budget in one pass over the file."""
        if self._index is None:
            return
        todo = []
        for key in keys:
            if key in self._names and not dict.__contains__(self, key):
                try:
                    self._reserve(key)
                except DataError:
                    continue
                todo.append(key)
        if todo:
            dict.update(self, _loadmat(self._path, todo))

    def __getitem__(self, key):
        if not dict.__contains__(self, key):
            if key not in self._names:
                raise KeyError(key)
            self._reserve(key)
            raw = _loadmat(self._path, [key])
            if key not in raw:
                raise DataError(f"variable '{key}' could not be read", path=self._path,
                                hint=f"supported formats: {SUPPORTED}")
            dict.__setitem__(self, key, raw[key])
        return dict.__getitem__(self, key)

    def items(self):
        return [(k, self[k]) for k in self._names]


# --------------------------------------------------------------------------- MAT v7.3

class _H5Reader:
    """Converts MATLAB objects of a v7.3 (HDF5) file to Python: ndarray, str, list (cell)
    or dict (struct), within a :class:`_ReadBudget`, at most :data:`MAX_MAT_NESTING`
    levels deep and never into a cell or struct that contains the object (a reference
    or link cycle)."""

    def __init__(self, f, path):
        self.f = f
        self.path = path
        self.budget = _ReadBudget(path)

    def variable(self, name: str):
        return self._value(self.f, name, name, 0, [])

    def _value(self, parent, key, shown: str, depth: int, active: list):
        import h5py

        if depth > MAX_MAT_NESTING:
            raise DataError(f"variable '{shown.split('.')[0].split('{')[0]}' nests cells or "
                            f"structs more than {MAX_MAT_NESTING} levels deep (at '{shown}')",
                            path=self.path,
                            hint="store the channels as numeric vectors or matrix columns")
        if isinstance(key, h5py.Reference):
            if not key:
                raise DataError(f"'{shown}' is a null reference", path=self.path)
            obj = parent[key]
        else:
            link = parent.get(key, getlink=True)
            if isinstance(link, h5py.ExternalLink):
                raise DataError(f"'{shown}' is a link to another file ({link.filename})",
                                path=self.path,
                                hint="vsidgen reads only the data stored in the file itself")
            obj = parent[key]
        if any(obj.id == other for other in active):
            raise DataError(f"'{shown}' refers to a cell or struct that contains it (a "
                            f"reference cycle in variable "
                            f"'{shown.split('.')[0].split('{')[0]}')", path=self.path,
                            hint="the file is damaged or was not written by MATLAB")
        self.budget.count(shown)
        active.append(obj.id)
        try:
            return self._convert(obj, shown, depth, active)
        finally:
            active.pop()

    def _convert(self, obj, shown: str, depth: int, active: list):
        import h5py

        if isinstance(obj, h5py.Group):
            return {k: self._value(obj, k, f"{shown}.{k}", depth + 1, active)
                    for k in obj if not k.startswith("#")}
        cls = obj.attrs.get("MATLAB_class", b"")
        cls = cls.decode(errors="replace") if isinstance(cls, bytes) else str(cls)
        if obj.attrs.get("MATLAB_empty", 0):
            return np.zeros(0)
        shape = obj.shape or ()
        n = math.prod(shape) if obj.shape is not None else 0
        self.budget.take(shown, n * obj.dtype.itemsize,
                         f"{_shape_text(shape[::-1])} {cls or obj.dtype}")
        data = obj[()]
        if cls == "char":
            arr = np.asarray(data).astype("<u2", copy=False)
            if arr.ndim == 2 and arr.shape[0] > 1 and arr.shape[1] > 1:
                return [_utf16(row).rstrip() for row in arr.T]  # char matrix: one per row
            return _utf16(arr.ravel())
        if cls == "cell" or (isinstance(data, np.ndarray) and data.dtype.kind == "O"):
            out = []
            for i, ref in enumerate(np.asarray(data).T.ravel()):
                if isinstance(ref, h5py.Reference):
                    out.append(self._value(self.f, ref, f"{shown}{{{i + 1}}}", depth + 1,
                                           active))
                else:
                    out.append(ref.decode(errors="replace") if isinstance(ref, bytes) else ref)
            return out
        arr = np.asarray(data)
        if arr.dtype.names and {"real", "imag"} <= set(arr.dtype.names):
            arr = arr["real"]
        if arr.ndim >= 2:
            arr = arr.T  # MATLAB is column-major
        return np.squeeze(arr) if arr.ndim == 2 and 1 in arr.shape else arr


def _utf16(units: np.ndarray) -> str:
    """MATLAB char data (UTF-16 code units) as text."""
    return np.ascontiguousarray(units, dtype="<u2").tobytes().decode("utf-16-le",
                                                                    errors="surrogatepass")


class _H5Vars(_NamedVariables):
    """Top-level variables of a v7.3 file, converted lazily (only those the data map names)."""

    def __init__(self, f, path=None):
        super().__init__()
        self._f = f
        self._path = path
        self._reader = _H5Reader(f, path)
        self._names = []
        for k in f:
            if not k.startswith("#"):
                if len(self._names) >= MAX_MAT_OBJECTS:
                    raise _too_many_variables(path)
                self._names.append(k)

    def __getitem__(self, key):
        if not dict.__contains__(self, key):
            try:
                value = self._reader.variable(key)
            except (OSError, ValueError, KeyError, TypeError) as exc:  # h5py on a damaged file
                raise DataError(f"variable '{key}' cannot be read ({type(exc).__name__}: "
                                f"{exc})", path=self._path,
                                hint="the file is damaged or was not written by MATLAB") from None
            dict.__setitem__(self, key, value)
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

    prefetch = getattr(variables, "prefetch", None)
    if prefetch is not None:
        prefetch(variables.keys())
    readable = {}
    for k in variables.keys():
        try:
            readable[k] = variables[k]
        except DataError:  # too large, damaged: named, not read
            out.append(k)
            continue
        add(k, readable[k], 0)
    for k, v in readable.items():
        if k.endswith("_names") and k[:-6] in variables and _is_names(v):
            out += [str(n).strip() for n in v]
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
    matrix_name, _, col_name = base.rpartition(".")
    if v is None and matrix_name and named.get(col_name, ("",))[0] == matrix_name:
        # `fdata.t` for the column `t` that `fdata_names` names: written plain (session 44)
        raise DataError(f"variable '{ref}' not found", path=path, column=ref,
                        hint=f"a column named in `{matrix_name}_names` is written by its name "
                             f"alone: `{col_name}`")
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
            variables = _H5Vars(f, path)
            named = _named_columns(variables)
            cols = {r: _resolve(variables, r, path, named, taken) for r in refs}
    else:
        variables = _V5Vars(path)
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


__all__ = ["DataFormat", "MAX_MAT_NESTING", "MAX_MAT_OBJECTS", "SUPPORTED", "detect_format",
           "read_mat_columns"]
