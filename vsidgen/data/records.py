"""Flight records: CSV or MATLAB files -> :class:`Record` (t, u, y) through the spec's data map.

File formats and how a MAT file's variables are named in the data map:
:mod:`vsidgen.data.formats`; units declared in the data map: :mod:`vsidgen.spec.dataunits`.

A record is one contiguous, uniformly sampled time history. Each model input
and output is read through a :class:`vsidgen.metadata.ChannelMap`:

* ``column`` map:  ``value = scale * column + offset``
* ``expr`` map:    ``value = scale * expr(columns) + offset`` where ``expr`` is
  a sympy expression (built by the project's whitelist parser) over the
  column symbols; it is evaluated with ``sympy.lambdify(..., "numpy")``.

Checks (each failure is a :class:`vsidgen.errors.DataError` naming the file,
the column and/or the sample = 0-based data row, with a hint):

* the path is not a regular file (a directory, ``/dev/zero``, a pipe) or is
  larger than :func:`vsidgen.limits.data_limit` (2 GiB unless
  ``$VSIDGEN_MAX_DATA_BYTES`` says otherwise): refused before it is opened;
* file missing / unreadable / empty / header only; a mapped column missing
  (close names suggested); a non-numeric cell; ``±inf`` anywhere in a used
  column; a magnitude above :data:`MAX_ABS_VALUE` (1e150) in a used column or a
  mapped channel: squares of such values overflow float64 (1.8e308) long before
  the likelihood is summed, so they can only be corrupt samples; fewer than
  :data:`MIN_SAMPLES` samples;
* time: NaN, non-increasing (duplicated or going back), gaps and
  non-uniform sampling. The sample period is ``T = (t[N-1] - t[0])/(N-1)``;
  every step must satisfy ``|t[k+1] - t[k] - T| <= JITTER * T`` and the
  stamps must stay close to the uniform grid, ``|t[k] - t[0] - kT| <= T/2``.
  ``JITTER = 5 %`` accepts time stamps quantised by the recorder (HFB-320
  steps 0.09999–0.10001 s; ``totter_lon_data.csv`` alternates
  0.009766/0.010010 s, ±2.4 %) but rejects gaps (a missing sample is a 100 %
  step error) and drifting rates. The period must be resolvable at the stamps'
  magnitude: the float64 spacing of the largest stamp, ``ulp(max|t|)``, must be
  at most ``RESOLUTION * T`` (1e-3 T), else the stamps cannot carry the
  ±5 % check (time stamps near 1e300 with T = 1 s, or T = 1e-300 s after a
  large offset); and ``MIN_DT <= T <= MAX_DT`` (1 µs to one day: the time
  column is in seconds, anything outside is a unit mistake);
* inputs cannot be missing: NaN (an empty cell or ``nan``) in an input is an
  error naming the column and sample; outputs may have NaN (= missing
  sample, excluded from the likelihood) but not in every sample; each output
  with gaps gets a warning naming its column, count and first samples.

Reading is fast: the header is read with :mod:`csv`, the numeric block of the
used columns with :func:`numpy.loadtxt` (about 1 s per million rows); if
that fails, empty cells are filled with ``nan`` and numpy is tried again
(missing output samples); only when that fails too (quotes, a bad cell) is the
file parsed cell by cell, which also locates the offending cell.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import math
import os
import pathlib
import re
import warnings
from collections.abc import Mapping, Sequence

import numpy as np

from ..atomic import atomic_text_file
from ..spec.dataunits import plausibility_warnings
from ..errors import DataError, VsidgenError
from .formats import DataFormat, detect_format, read_mat_columns
from ..limits import check_input_file
from ..suggest import column_hint

MIN_SAMPLES = 10
JITTER = 0.05
#: largest magnitude accepted in a used column or channel (float64 squares overflow above 1.3e154)
MAX_ABS_VALUE = 1e150
#: the float64 spacing of the largest time stamp must be at most RESOLUTION * T
RESOLUTION = 1e-3
#: sample periods outside [MIN_DT, MAX_DT] seconds are refused (a unit mistake)
MIN_DT = 1e-6
MAX_DT = 86400.0
_MISSING = {"", "nan", "na", "n/a", "null", "none"}
#: a cell's number as numpy's reader takes it: ASCII digits, point, exponent; inf and nan
_PLAIN_NUMBER = re.compile(r"[+-]?(?:(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?|inf|infinity|nan)",
                           re.IGNORECASE)


@dataclasses.dataclass(frozen=True, eq=False)
class Record:
    """One flight record on a uniform time grid.

    Attributes:
        name: record name (default: the file stem).
        path: the CSV file (None for in-memory records).
        t: (N,) seconds from the record start, ``t_raw - t_raw[0]``.
        dt: the sample period ``T = (t[N-1] - t[0])/(N-1)``.
        u: (N, nu) inputs, float64, never NaN.
        y: (N, ny) outputs, float64; NaN = missing sample.
        input_names, output_names: channel (model input/output) names.
        t_raw: (N,) the original time stamps.
        warnings: :class:`vsidgen.spec.dataunits.DataWarning` records (value ranges
            implausible for a channel's unit), empty when none.
    """

    name: str
    path: pathlib.Path | None
    t: np.ndarray
    dt: float
    u: np.ndarray
    y: np.ndarray
    input_names: tuple[str, ...]
    output_names: tuple[str, ...]
    t_raw: np.ndarray
    warnings: tuple = ()

    @classmethod
    def from_arrays(cls, model, t, u, y, *, name: str = "record") -> "Record":
        """A record from arrays already in the spec's units (no data map applied): ``t``
        (N,) seconds on a uniform grid (the rules of :func:`check_time`), ``u`` (N, nu)
        finite inputs, ``y`` (N, ny) outputs with NaN for missing samples, channels in the
        order of ``model.input_names`` and ``model.output_names``.

        Raises:
            DataError: a shape that does not match the model, a non-finite input, a time
                grid that is not uniform.
        """
        t_raw = np.asarray(t, dtype=np.float64).reshape(-1)
        n = t_raw.shape[0]
        u = np.asarray(u, dtype=np.float64).reshape(n, -1) if np.size(u) else np.zeros((n, 0))
        y = np.asarray(y, dtype=np.float64)
        y = y.reshape(n, -1) if y.ndim == 1 else y
        nu, ny = len(model.input_names), len(model.output_names)
        if n < MIN_SAMPLES:
            raise DataError(f"{n} samples; at least {MIN_SAMPLES} are needed", column="t")
        if u.shape != (n, nu) or y.shape != (n, ny):
            raise DataError(f"u has shape {u.shape} and y {y.shape}; the model needs ({n}, {nu}) "
                            f"inputs {tuple(model.input_names)} and ({n}, {ny}) outputs "
                            f"{tuple(model.output_names)}", column="u" if u.shape != (n, nu) else "y")
        for what, names, arr in (("input", model.input_names, u), ("output", model.output_names, y)):
            # inputs: finite everywhere; outputs: NaN marks a missing sample
            bad = np.isinf(arr) | (np.abs(np.nan_to_num(arr)) > MAX_ABS_VALUE)
            if what == "input":
                bad |= np.isnan(arr)
            if bad.any():
                k, j = (int(v[0]) for v in np.nonzero(bad))
                raise DataError(f"{what} `{names[j]}` is {fmt_number(arr[k, j])}", column=names[j],
                                sample=k, hint=f"values must be finite and below {MAX_ABS_VALUE:g} "
                                "in magnitude (NaN marks a missing output; inputs cannot miss)")
        dt = check_time(t_raw, column="t")
        return cls(str(name), None, t_raw - t_raw[0], dt, u, y, tuple(model.input_names),
                   tuple(model.output_names), t_raw)

    @property
    def n(self) -> int:
        """Number of samples N."""
        return int(self.t.shape[0])

    @property
    def duration(self) -> float:
        """Record length ``t[N-1] - t[0]`` in seconds."""
        return float(self.t[-1] - self.t[0]) if self.n else 0.0


# --------------------------------------------------------------------------- helpers

def _names(model, kind: str) -> tuple[str, ...]:
    attr = getattr(model, f"{kind}_names", None)
    if attr is not None:
        return tuple(attr)
    return tuple(v.name for v in getattr(model, kind + "s"))


def hash_header(header: list[str], following: list[str] | None, path, *, line: int = 1) -> list[str]:
    """The column names of a header row whose first field starts with ``#``.

    ``numpy.savetxt(..., header=...)`` writes ``# t,alpha,q``: when the next non-blank row
    has as many fields and is not a comment itself, that row is the header with the ``#``
    taken off. Anything else is a comment or metadata line above the header, which the
    readers do not skip (one header row, then data): DataError naming the line.
    """
    if not header or not header[0].lstrip().startswith("#"):
        return header
    names = [header[0].lstrip()[1:].strip()] + [c.strip() for c in header[1:]]
    if (len(header) > 1 and names[0] and following is not None
            and len(following) == len(header) and not following[0].lstrip().startswith("#")):
        return names
    text = ",".join(header).strip()
    raise DataError(f"line {line} is a comment ({text[:60]!r}), not the column names",
                    path=path, hint="vsidgen reads the column names from the first line: delete "
                                    "the comment or metadata lines above the header (a header "
                                    "written by numpy.savetxt, '# t,alpha,q', is read as it is)")


def _read_header(path: pathlib.Path) -> list[str]:
    try:
        with open(path, newline="", encoding="utf-8-sig") as fh:
            reader = csv.reader(fh)
            header, line = None, 0
            for row in reader:
                if not any(c.strip() for c in row):
                    continue
                if header is not None:
                    return hash_header(header, row, path, line=line)
                header, line = [c.strip() for c in row], reader.line_num
                if not header[0].startswith("#"):
                    return header
            return hash_header(header, None, path, line=line) if header is not None else []
    except FileNotFoundError:
        raise DataError("file not found", path=path,
                        hint="check the path (relative paths are taken from the current directory)") from None
    except IsADirectoryError:
        raise DataError("is a directory, not a CSV file", path=path) from None
    except UnicodeDecodeError:
        raise DataError("not a text (UTF-8) CSV file", path=path,
                        hint="export the record as comma-separated text with one header row") from None
    except csv.Error as exc:
        raise DataError(f"the header row cannot be read as CSV ({exc})", path=path,
                        hint="export the record as comma-separated text with one header row") from None
    except OSError as exc:
        raise DataError(f"cannot read file: {exc.strerror or exc}", path=path) from None


def cell_value(text: str) -> float:
    """The number in one CSV cell, by the rule of numpy's reader (ASCII digits, a decimal
    point, an exponent; inf and nan); NaN for an empty or missing-marker cell.

    Raises:
        ValueError: anything else. Python's ``float`` would also take ``"1_000"`` and
            full-width or other-script digits, which the fast reader refuses: one rule for
            every cell, whichever reader meets it.
    """
    s = text.strip()
    if s.lower() in _MISSING:
        return math.nan
    if not _PLAIN_NUMBER.fullmatch(s):
        raise ValueError(s)
    return float(s)


def cell_hint(text: str) -> str:
    """What is wrong with a cell :func:`cell_value` refused, in words."""
    import unicodedata

    odd = [ch for ch in dict.fromkeys(text) if not ch.isascii()]
    if odd:
        ch = odd[0]
        return (f"the cell contains U+{ord(ch):04X} {unicodedata.name(ch, 'a non-ASCII character')}: "
                "write numbers with ASCII digits and a decimal point")
    if "_" in text and _PLAIN_NUMBER.fullmatch(text.strip().replace("_", "")):
        return "no digit separators: write 1000.5, not 1_000.5"
    if "," in text:
        return "no decimal commas: write 1.5, not 1,5"
    return "use plain decimal numbers, an empty cell or 'nan' for a missing output sample"


def refuse_units_row(row, header, path) -> None:
    """A DataError when the first data row has no number at all (a units or description row
    under the header, as spreadsheet exports and logging software write): named as such, with
    what to do, rather than as the first cell that is not a number."""
    cells = [c.strip() for c in row if c.strip()]
    if not cells:
        return
    for c in cells:
        try:
            cell_value(c)
            return
        except ValueError:
            pass
    shown = ", ".join(repr(c[:12]) for c in cells[:4]) + (", ..." if len(cells) > 4 else "")
    raise DataError(f"the first row below the header holds no number ({shown}): a units or "
                    "description row?", path=path, column=header[0] if header else None,
                    sample=0,
                    hint="delete that row (file line 2); put units in the column names "
                         "(alpha_rad) or convert them in the spec's data map (unit:, scale:)")


def _parse_cell(text: str, path, column: str, sample: int) -> float:
    try:
        return cell_value(text)
    except ValueError:
        s = text.strip()
        raise DataError(f"non-numeric value {s[:40]!r}", path=path, column=column, sample=sample,
                        hint=f"file line {sample + 2}; {cell_hint(s)}") from None


def _fill_empty_cells(body: str) -> str:
    """Write ``nan`` into empty CSV cells (fast ``str.replace``; blank lines kept)."""
    body = "\n" + body
    body = body.replace(",,", ",nan,").replace(",,", ",nan,")
    body = body.replace(",\r\n", ",nan\r\n").replace(",\n", ",nan\n").replace("\n,", "\nnan,")
    if body.endswith(","):
        body += "nan"
    return body[1:]


def _checked_rows(reader, path, sample):
    """Rows of a csv reader; a CSV syntax error (an over-long field, a stray quote, a NUL)
    becomes a DataError naming the sample and the file line."""
    while True:
        try:
            row = next(reader)
        except StopIteration:
            return
        except csv.Error as exc:
            raise DataError(f"the row cannot be read as CSV ({exc})", path=path, sample=sample(),
                            hint=f"file line {reader.line_num}; use plain comma-separated numbers") from None
        except UnicodeDecodeError:
            raise DataError("not a text (UTF-8) CSV file", path=path, sample=sample(),
                            hint="export the record as comma-separated text") from None
        yield row


def _slow_parse(path: pathlib.Path, header: list[str], idx: list[int]) -> np.ndarray:
    """Cell-by-cell parse (handles empty cells and quotes; locates bad cells)."""
    need = max(idx) + 1
    rows: list[list[float]] = []
    with open(path, newline="", encoding="utf-8-sig") as fh:
        reader = csv.reader(fh)
        started = False
        sample = 0
        for row in _checked_rows(reader, path, lambda: sample):
            if not started:
                if any(c.strip() for c in row):
                    started = True  # the header
                continue
            if not any(c.strip() for c in row):
                continue  # blank line (numpy.loadtxt skips them too)
            if len(row) < need:
                missing = header[len(row)] if len(row) < len(header) else "?"
                raise DataError(
                    f"row has {len(row)} fields but the header has {len(header)}",
                    path=path, column=missing, sample=sample,
                    hint=f"file line {sample + 2} is truncated or uses another delimiter "
                         "(vsidgen reads comma-separated files)")
            if len(row) > len(header) and any(c.strip() for c in row[len(header):]):
                raise DataError(
                    f"row has {len(row)} fields but the header has {len(header)}",
                    path=path, sample=sample,
                    hint=f"file line {sample + 2} has extra values: a decimal comma, or a comma "
                         "inside a value that is not quoted? (vsidgen reads comma-separated files "
                         "with a decimal point)")
            if sample == 0:
                refuse_units_row(row, header, path)
            rows.append([_parse_cell(row[j], path, header[j], sample) for j in idx])
            sample += 1
    return np.asarray(rows, dtype=np.float64).reshape(len(rows), len(idx))


def _uneven_rows(path: pathlib.Path, n_header: int) -> bool:
    """True when a data line has more delimiters than the header (with non-empty extra
    fields, or quotes that need the exact reader): the exact parser then names the row."""
    with open(path, encoding="utf-8-sig") as fh:
        for line in fh:
            if line.strip():
                break
        for line in fh:
            if line.count(",") >= n_header and (line.rstrip("\r\n").rstrip(", \t").count(",")
                                                 >= n_header or '"' in line):
                return True
    return False


def _read_block(path: pathlib.Path, header: list[str], idx: list[int]) -> np.ndarray:
    if _uneven_rows(path, len(header)):
        return _slow_parse(path, header, idx)
    try:
        with open(path, encoding="utf-8-sig") as fh:
            # skip leading blank lines and the header
            for line in fh:
                if line.strip():
                    break
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # "input contained no data": checked by the caller
                data = np.loadtxt(fh, delimiter=",", usecols=idx, dtype=np.float64,
                                  comments=None, ndmin=2)
        return data.reshape(-1, len(idx))
    except (ValueError, IndexError):
        pass
    # middle path: empty cells (missing samples) -> "nan", then numpy again
    try:
        text = path.read_text(encoding="utf-8-sig")
        body = text.lstrip("\r\n").split("\n", 1)[1] if "\n" in text.lstrip("\r\n") else ""
        body = _fill_empty_cells(body)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            data = np.loadtxt(io.StringIO(body), delimiter=",", usecols=idx, dtype=np.float64,
                              comments=None, ndmin=2)
        return data.reshape(-1, len(idx))
    except (ValueError, IndexError):
        return _slow_parse(path, header, idx)


def refuse_other_delimiter(header: list[str], path) -> None:
    """Raise DataError when a CSV header is one field holding another delimiter (a
    semicolon-, tab- or bar-separated export)."""
    if len(header) == 1 and any(d in header[0] for d in ";\t|"):
        raise DataError("the header has a single field: vsidgen reads comma-separated files",
                        path=path, hint="save the record as CSV with commas between values "
                                        "and a decimal point (not semicolons or tabs)")


_TIME_LIKE = re.compile(r"(?i)^(t|time|zeit|tempo)(\b|_|$)|time|_s$|\(s\)$|\[s\]$")


def time_hint(name: str, header: list[str]) -> str:
    """Hint for a time column ``name`` the file lacks: a close spelling, else the columns
    whose names look like a time (``t``, ``t_s``, ``time``, ``... (s)``), then all columns."""
    return _suggest(name, header, time=True)


def _suggest(name: str, header: list[str], taken: Mapping[str, str] | None = None, *,
             time: bool = False) -> str:
    hint = column_hint(name, header, taken)
    if hint and hint.startswith("did you mean"):
        return hint
    if time:
        like = [h for h in header if _TIME_LIKE.search(h)]
        if like:
            hint = (hint + "; " if hint else "") + "time-like columns: " + ", ".join(like[:5])
    shown = ", ".join(header[:60]) + (f", ... ({len(header)} in all)" if len(header) > 60 else "")
    return (hint + "; " if hint else "") + f"columns in the file: {shown}"


def _eval_map(cmap, cols: dict[str, np.ndarray], n: int) -> np.ndarray:
    if cmap.expr is not None:
        import sympy

        expr = cmap.expr
        by_name = {str(s): s for s in expr.free_symbols}
        names = [c for c in cmap.source_columns() if c in by_name]
        # the columns renamed before printing: lambdify puts its arguments' names into the
        # function's namespace, so a column called ``e``, ``reduce`` or ``arcsin`` shadowed a
        # name the NumPy printer emits (``exp(1)*e`` computed e·e: silently wrong input)
        safe = [sympy.Symbol(f"_vsidgen_column_{i}", real=True) for i in range(len(names))]
        expr = expr.xreplace({by_name[c]: v for c, v in zip(names, safe)})
        fn = sympy.lambdify(safe, expr, "numpy")
        with np.errstate(all="ignore"):
            val = np.asarray(fn(*[cols[c] for c in names]), dtype=np.float64)
        val = np.broadcast_to(val, (n,)).copy()
    else:
        val = cols[cmap.source_columns()[0]].copy()
    return np.asarray(cmap.apply(val), dtype=np.float64)


def fmt_number(v) -> str:
    """A number for messages: ``1e+308``, ``0.04``, ``1.7e+09`` (never ``np.float64(...)``)."""
    v = float(v)
    if math.isnan(v):
        return "NaN"
    if math.isinf(v):
        return "inf" if v > 0 else "-inf"
    return f"{v:.6g}"


def _first(mask: np.ndarray) -> int:
    return int(np.flatnonzero(mask)[0])


def check_time(t_raw: np.ndarray, *, path=None, column: str = "t_s") -> float:
    """Validate a time column and return the sample period ``T``.

    See the module docstring for the rules (strictly increasing, jitter up to
    ``JITTER*T`` per step, stamps within ``T/2`` of the uniform grid).
    """
    n = t_raw.shape[0]
    bad = ~np.isfinite(t_raw)
    if bad.any():
        k = _first(bad)
        raise DataError(f"time stamp is {fmt_number(t_raw[k])}", path=path, column=column,
                        sample=k,
                        hint="every sample needs a finite time stamp")
    steps = np.diff(t_raw)
    nonpos = steps <= 0
    if nonpos.any():
        k = _first(nonpos) + 1
        what = "duplicated" if steps[k - 1] == 0 else "goes back"
        # every digit of the stamps (54819.06 was shown as 54819: the row cannot be found
        # by its time; session 44)
        raise DataError(f"time is not increasing: {what} ({float(t_raw[k - 1])!r} -> "
                        f"{float(t_raw[k])!r})",
                        path=path, column=column, sample=k,
                        hint="sort the record by time and remove repeated samples; "
                             "split it where the recording restarts")
    dt = float((t_raw[-1] - t_raw[0]) / (n - 1))
    big = float(np.max(np.abs(t_raw)))
    spacing = float(np.spacing(big))
    if not (math.isfinite(dt) and spacing <= RESOLUTION * dt):
        k = int(np.argmax(np.abs(t_raw)))
        raise DataError(
            f"time stamps of magnitude {fmt_number(big)} s cannot resolve the sample period "
            f"{fmt_number(dt)} s (float64 spacing {fmt_number(spacing)} s there)",
            path=path, column=column, sample=k,
            hint="subtract the start time from the time column (vsidgen needs the sample "
                 "period to be at least 1000 times the rounding step of the stamps)")
    if not (MIN_DT <= dt <= MAX_DT):
        raise DataError(
            f"sample period {fmt_number(dt)} s is outside the accepted range "
            f"{fmt_number(MIN_DT)} s to {fmt_number(MAX_DT)} s",
            path=path, column=column, sample=1,
            hint="declare the time column's unit in the spec (`time: {column: t_ms, unit: ms}`) "
                 "or map another column")
    # each step against the median step (a gap inflates the mean period, which would blame
    # the first regular step instead of the gap)
    typical = float(np.median(steps))
    dev = np.abs(steps - typical)
    tol = JITTER * typical
    if (dev > tol).any():
        k = int(np.argmax(dev > tol)) + 1
        step = float(steps[k - 1])
        kind = "gap" if step > typical else "short step"
        n_lost = round(step / typical) - 1
        lost = (f", about {n_lost} sample{'s' if n_lost != 1 else ''} missing"
                if step > 1.5 * typical else "")
        raise DataError(
            f"non-uniform sampling: {kind} of {step:.6g} s before this sample{lost} "
            f"(median period {typical:.6g} s, tolerance ±{100 * JITTER:.0f} %)",
            path=path, column=column, sample=k,
            hint="vsidgen needs uniformly sampled records: split the file at gaps "
                 "or resample it to a uniform grid")
    drift = np.abs(t_raw - t_raw[0] - dt * np.arange(n))
    if (drift > 0.5 * dt).any():
        k = int(np.argmax(drift))
        raise DataError(
            f"non-uniform sampling: time stamp is {drift[k]:.6g} s off the uniform grid "
            f"of period {dt:.6g} s (the sample rate changes within the record)",
            path=path, column=column, sample=k,
            hint="split the record where the sample rate changes or resample it")
    return dt


# --------------------------------------------------------------------------- public API

def load_record(model, path, *, name: str | None = None) -> Record:
    """Read one flight record (CSV or MATLAB .mat) through ``model.data`` (a DataSpec).

    Args:
        model: a :class:`vsidgen.model.Model` or a SymbolicModel (uses
            ``data``, input and output names).
        path: CSV file with one header row, comma separated, or a MATLAB .mat
            file (:mod:`vsidgen.data.formats`).
        name: record name; default the file stem.

    Returns:
        :class:`Record` with ``u`` in model-input order and ``y`` in
        model-output order.

    Raises:
        DataError: see the module docstring.
    """
    if not hasattr(model, "data"):
        raise DataError(f"load_record needs the compiled spec or the model, got "
                        f"{type(model).__name__} {str(model)[:60]!r}",
                        hint="load_record(vsidgen.load_model('spec.yaml'), 'flight.csv')")
    if not isinstance(path, (str, os.PathLike)):
        raise DataError(f"load_record reads a file; got {type(path).__name__}",
                        hint="give the file's path; for arrays use vsidgen.Record.from_arrays("
                             "model, t, u, y)")
    path = check_input_file(path, what="data file")
    spec = model.data
    in_names, out_names = _names(model, "input"), _names(model, "output")
    in_maps = {c.name: c for c in spec.inputs}
    out_maps = {c.name: c for c in spec.outputs}
    for kind, names, maps in (("input", in_names, in_maps), ("output", out_names, out_maps)):
        for nm in names:
            if nm not in maps:
                raise DataError(f"model {kind} '{nm}' has no data mapping", path=path,
                                hint=f"add `{nm}: <column>` under data.{kind}s in the spec")

    # columns needed, in a stable order: time first
    needed: list[str] = [spec.time]
    for nm in in_names:
        needed += [c for c in in_maps[nm].source_columns() if c not in needed]
    for nm in out_names:
        needed += [c for c in out_maps[nm].source_columns() if c not in needed]

    taken = {spec.time: "the time"}
    for kind, names, maps in (("input", in_names, in_maps), ("output", out_names, out_maps)):
        for nm in names:
            for c in maps[nm].source_columns():
                taken.setdefault(c, f"{kind} `{nm}`")
    fmt = detect_format(path)
    if fmt is DataFormat.CSV:
        cols = _read_csv_columns(path, needed, spec.time, taken)
    else:
        cols = read_mat_columns(path, needed, fmt, taken=taken)
    n = cols[spec.time].shape[0]
    if n == 0:
        raise DataError("no data rows (header only)" if fmt is DataFormat.CSV else
                        "the record is empty", path=path,
                        hint="the file must hold at least "
                             f"{MIN_SAMPLES} samples")
    rec = _finish_record(model, path, name, cols, n, in_names, out_names, in_maps, out_maps)
    if fmt is DataFormat.CSV:
        extra = _constant_warnings(model, path, needed, n)
        if extra:
            rec = dataclasses.replace(rec, warnings=rec.warnings + extra)
    return rec


def _constant_warnings(model, path: pathlib.Path, needed: list[str], n: int) -> tuple:
    """Warnings for constants outside the range of an unmapped column that records the same
    quantity (:func:`vsidgen.spec.dataunits.constant_range_warnings`). Best effort: a column
    that does not parse as numbers is skipped (it is not the record's data)."""
    from ..spec.dataunits import constant_columns, constant_range_warnings

    sym = model if hasattr(model, "drift_expanded") else getattr(model, "symbolic", None)
    if sym is None or not getattr(sym, "constants", ()):
        return ()
    header = _read_header(path)
    matches = constant_columns(sym.constants, header, taken=needed)
    if not matches:
        return ()          # the common case: no column named like a constant, no sympy work
    used = set().union(*(e.free_symbols for e in sym.drift_expanded() + sym.observations_expanded()))
    constants = [c for c in sym.constants if c.symbol in used]   # an unused one is warned of
    matches = {k: v for k, v in matches.items() if k in {c.name for c in constants}}
    values = {}
    for col in sorted({c for cols in matches.values() for c in cols}):
        try:
            v = _read_block(path, header, [header.index(col)])[:, 0]
        except (DataError, ValueError, IndexError):
            continue
        if v.shape[0] == n:
            values[col] = v
    return constant_range_warnings(constants, values, matches, path=path)


def _read_csv_columns(path: pathlib.Path, needed: list[str], time_column: str,
                      taken: Mapping[str, str]) -> dict[str, np.ndarray]:
    header = _read_header(path)
    if not header:
        raise DataError("empty file", path=path,
                        hint="expected one header row of column names followed by data rows")
    refuse_other_delimiter(header, path)
    seen: dict[str, int] = {}
    for j, h in enumerate(header):
        seen.setdefault(h, j)
    for c in needed:
        if c not in seen:
            what = (f"time column '{c}'" if c == time_column
                    else f"column '{c}' (for {taken[c]})" if c in taken else f"column '{c}'")
            raise DataError(f"{what} is not in the file", path=path, column=c,
                            hint=_suggest(c, header, taken, time=c == time_column))
        if header.count(c) > 1:
            raise DataError(f"column '{c}' appears {header.count(c)} times in the header",
                            path=path, column=c, hint="rename the duplicated columns")
    idx = [seen[c] for c in needed]

    block = _read_block(path, header, idx)
    return {c: block[:, j] for j, c in enumerate(needed)}


def _finish_record(model, path, name, cols, n, in_names, out_names, in_maps, out_maps) -> Record:
    spec = model.data
    for c in cols:
        inf = np.isinf(cols[c])
        if inf.any():
            k = _first(inf)
            raise DataError(f"infinite value {fmt_number(cols[c][k])}", path=path, column=c,
                            sample=k,
                            hint="replace overflowed or invalid samples (an empty cell marks a "
                                 "missing output sample)")
        huge = np.abs(cols[c]) > MAX_ABS_VALUE
        if huge.any():
            k = _first(huge)
            raise DataError(f"absurd value {fmt_number(cols[c][k])} (magnitude above "
                            f"{fmt_number(MAX_ABS_VALUE)})", path=path, column=c, sample=k,
                            hint="a corrupt or overflowed sample; fix it, or leave the cell "
                                 "empty if it is an output (a missing sample)")
    if n < MIN_SAMPLES:
        raise DataError(f"too few samples: {n} (at least {MIN_SAMPLES} needed)", path=path,
                        hint="is this the right file? records must be contiguous time histories")

    t_raw = cols[spec.time] * float(getattr(spec, "time_scale", 1.0))
    dt = check_time(t_raw, path=path, column=spec.time)

    def channel(nm, cmap, kind):
        val = _eval_map(cmap, cols, n)
        srcs = cmap.source_columns()
        label = srcs[0] if len(srcs) == 1 and cmap.expr is None else f"{nm} = {cmap.expr}"
        col_for = srcs[0] if len(srcs) == 1 else None
        bad = np.isinf(val) | (np.abs(val) > MAX_ABS_VALUE)
        if bad.any():
            k = _first(bad)
            what = "infinite" if np.isinf(val[k]) else f"absurd ({fmt_number(val[k])})"
            raise DataError(f"{kind} '{nm}' is {what} (from {label})", path=path,
                            column=col_for, sample=k, hint="check the expression and the data")
        nan = np.isnan(val)
        if cmap.expr is not None and nan.any() and (kind == "input" or nan.all()):
            present = np.all([np.isfinite(cols[c]) for c in srcs], axis=0)
            undefined = nan & present
            if undefined.any():
                # every column has a value: the expression itself gave NaN (log or sqrt of a
                # negative value, 0/0), which was reported as a missing value (session 44) or,
                # at every sample, as an empty column (red team, session 47)
                k = _first(undefined)
                vals = ", ".join(f"{c} = {fmt_number(cols[c][k])}" for c in srcs)
                raise DataError(f"{kind} '{nm}' = {cmap.expr} is undefined (NaN) at these "
                                f"values: {vals}"
                                + (" (and at every other sample)" if nan.all() else ""),
                                path=path, column=col_for or nm, sample=k,
                                hint="the expression is not defined there (log or sqrt of a "
                                     "negative value, 0/0); check it and the columns")
        if nan.all():
            raise DataError(f"{kind} channel '{nm}' has no valid sample (all NaN)",
                            path=path, column=col_for or nm,
                            hint="the column is empty; map the channel to another column "
                                 "or remove it from the model")
        if kind == "input" and nan.any():
            k = _first(nan)
            bad = [c for c in srcs if np.isnan(cols[c][k])]
            col = bad[0] if bad else (col_for or nm)
            raise DataError(f"missing value in input '{nm}'", path=path, column=col, sample=k,
                            hint="inputs cannot be missing (only outputs may have empty cells); "
                                 "fill the gap or split the record")
        return val

    u = np.empty((n, len(in_names)))
    delays = {v.name: float(getattr(v, "delay", 0.0) or 0.0) for v in getattr(model, "inputs", ())}
    for i, nm in enumerate(in_names):
        u[:, i] = channel(nm, in_maps[nm], "input")
        if delays.get(nm, 0.0) > 0.0:
            u[:, i] = delay_input(u[:, i], t_raw - t_raw[0], delays[nm])
    y = np.empty((n, len(out_names)))
    for i, nm in enumerate(out_names):
        y[:, i] = channel(nm, out_maps[nm], "output")

    t = t_raw - t_raw[0]
    for a in (t, u, y, t_raw):
        a.setflags(write=False)
    found = (sampling_warnings(dt, spec, path=path) + plausibility_warnings(model, u, y, path=path)
             + missing_output_warnings(out_names, out_maps, y, path=path))
    return Record(name=name if name is not None else path.stem, path=path, t=t, dt=dt,
                  u=u, y=y, input_names=in_names, output_names=out_names, t_raw=t_raw,
                  warnings=found)


#: sample periods above this many seconds are flagged (flight-test records are sampled at
#: 1 Hz or faster: the dynamics identified have time constants of seconds)
SLOW_SAMPLING_DT = 1.0


def sampling_warnings(dt: float, spec, *, path=None) -> tuple:
    """A :class:`DataWarning` when the sample period exceeds :data:`SLOW_SAMPLING_DT`: what a
    time column in milliseconds read as seconds looks like (a 25-Hz record becomes one sample
    every 40 s). Not an error: a slow record of slow dynamics is possible."""
    from ..spec.dataunits import DataWarning, DataWarningCode

    if dt <= SLOW_SAMPLING_DT:
        return ()
    unit = getattr(spec, "time_unit", None)
    if unit:
        hint = f"the data map declares `{unit}` for `{spec.time}`: check that unit"
    else:
        col = spec.time
        hint = (f"if the time column is in milliseconds, declare it: `time: {{column: {col}, "
                f"unit: ms}}`")
    return (DataWarning(DataWarningCode.SLOW_SAMPLING,
                        f"sample period {dt:.6g} s (time column `{spec.time}`): flight-test "
                        f"records are sampled at 1 Hz or faster", path=path,
                        channel=spec.time, hint=hint),)


def missing_output_warnings(names, maps, y, *, path=None) -> tuple:
    """One :class:`DataWarning` per output with missing samples (NaN: an empty cell or a
    missing-value marker), naming the column, the count and the first samples (0-based data
    rows, as in data errors). They are not an error: a missing output sample is unobserved and
    the fit uses the others; the warning says so, so that a column that is mostly empty (a
    wrong column, a sensor that dropped out) is not taken for a fitted channel."""
    from ..spec.dataunits import DataWarning, DataWarningCode

    out = []
    n = y.shape[0]
    for j, nm in enumerate(names):
        miss = np.nonzero(np.isnan(y[:, j]))[0]
        if not len(miss):
            continue
        srcs = maps[nm].source_columns()
        col = srcs[0] if len(srcs) == 1 else None
        first = ", ".join(str(int(k)) for k in miss[:5]) + (", …" if len(miss) > 5 else "")
        plural = "s" if len(miss) > 1 else ""
        what = f"output '{nm}'" + (f" (column '{col}')" if col and col != nm else "")
        out.append(DataWarning(
            DataWarningCode.MISSING_SAMPLES,
            f"{what}: {len(miss)} of {n} samples missing (sample{plural} {first}), treated as "
            f"unobserved", path=path, channel=nm,
            hint="the fit uses the other samples; fill or check the column if the gaps are "
                 "not real sensor drop-outs"))
    return tuple(out)


def delay_input(values, t, delay: float) -> np.ndarray:
    """A recorded input as the model sees it through a pure transport delay ``τ = delay`` s:
    ``u_τ(t_k) = u(t_k − τ)``, linearly interpolated between the samples (fractional delays);
    before the record starts (``t_k − τ < t_0``) the first sample is held.

    ``delay`` ≥ 0 in seconds; ``t`` increasing (N,), ``values`` (N,).
    """
    v = np.asarray(values, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    if not delay > 0.0:
        return v.copy()
    return np.interp(t - float(delay), t, v, left=v[0], right=v[-1])


def most_extreme_sample(records) -> tuple[Record, str, int, float] | None:
    """The sample farthest from its channel's bulk, over every input and output of ``records``.

    Distance is the robust z-score ``|v - median| / (1.4826 MAD)`` of each channel
    (NaN ignored; a channel with MAD = 0 uses the mean absolute deviation, and a
    constant channel is skipped). Used to locate the culprit when the estimator
    cannot start on data that passed the per-value checks. Returns
    ``(record, channel, sample, value)`` or None.
    """
    best = None
    for rec in records:
        for names, block in ((rec.input_names, rec.u), (rec.output_names, rec.y)):
            for j, nm in enumerate(names):
                v = np.asarray(block[:, j], dtype=np.float64)
                ok = np.isfinite(v)
                if ok.sum() < 3:
                    continue
                with np.errstate(all="ignore"):
                    med = float(np.median(v[ok]))
                    dev = np.abs(v - med)
                    scale = 1.4826 * float(np.median(dev[ok]))
                    if not scale > 0:
                        scale = float(np.mean(dev[ok]))
                    if not scale > 0:
                        continue
                    z = np.where(ok, dev / scale, -np.inf)
                k = int(np.argmax(z))
                if best is None or z[k] > best[0]:
                    best = (float(z[k]), rec, nm, k, float(v[k]))
    return None if best is None else best[1:]


def resolution(values) -> float:
    """Default measurement-noise floor of a channel: quantisation step / √12.

    Rule (robust to print-rounding artefacts): take the absolute differences
    ``|y_{k+1} - y_k|`` of consecutive *finite* samples (NaN dropped), discard
    zeros and differences below ``1e-12 max|y|`` (round-off), sort them and
    take the 1st percentile (nearest rank, ``d[floor(0.01 n)]``; the minimum
    when fewer than 100 steps) as the step ``q``. A few spurious tiny steps
    (a value printed with fewer digits, e.g. one step of 1e-8 in a channel
    quantised at 1.7e-4) are thus ignored, while for a quantised channel the
    smallest quantum is found (it is normally far more frequent than 1 %).
    For a continuous, noisy channel of noise std σ the 1st percentile of the
    steps is ≈ 0.018 σ, so the floor stays far below the real noise. A
    uniform quantiser of step ``q`` has error variance ``q²/12``.
    Returns 0.0 for a constant (or empty) channel.
    """
    v = np.asarray(values, dtype=np.float64).ravel()
    v = v[np.isfinite(v)]
    if v.size < 2:
        return 0.0
    d = np.abs(np.diff(v))
    d = d[d > 1e-12 * np.max(np.abs(v))]
    if d.size == 0:
        return 0.0
    d.sort()
    return float(d[int(0.01 * d.size)] / math.sqrt(12.0))


def unique_names(records: Sequence[Record]) -> list[Record]:
    """The records with repeated names made unique: the second ``r`` becomes ``r_1``, the third ``r_2``."""
    seen: dict[str, int] = {}
    out = []
    for rec in records:
        name = rec.name
        if name in seen:
            seen[name] += 1
            name = f"{name}_{seen[name]}"
            rec = dataclasses.replace(rec, name=name)
        else:
            seen[name] = 0
        out.append(rec)
    return out


def as_paths(paths) -> list:
    """File paths as a list; one path (str or PathLike) is a list of one, not its characters
    (`run_fit(spec, "est.csv")` read "/" as a data file; session 44); None is empty."""
    if isinstance(paths, (str, os.PathLike)):
        return [paths]
    return list(paths or ())


def load_records(model, data: Sequence, validate: Sequence = ()) -> tuple[list[Record], list[Record]]:
    """(estimation, validation) records of the files ``data`` and ``validate``, their names
    unique across both lists (:func:`unique_names`): `fit d1/rec.csv --validate d2/rec.csv`
    wrote both records' signals to one ``signals_rec.csv`` (session 44)."""
    both = unique_names([load_record(model, p) for p in [*data, *validate]])
    return both[:len(data)], both[len(data):]


def write_csv(path, columns: Mapping[str, np.ndarray]) -> pathlib.Path:
    """Write equal-length columns to a CSV file atomically, at full precision.

    Values are written with ``%.17g`` (exact float64 round trip; NaN as
    ``nan``) through :func:`vsidgen.atomic.atomic_text_file`, so readers never
    see a partial file.
    """
    path = pathlib.Path(path)
    names = list(columns)
    if not names:
        raise VsidgenError("write_csv: no columns given")
    for nm in names:
        if not nm or any(ch in nm for ch in ',"\n\r'):
            raise VsidgenError(f"write_csv: invalid column name {nm!r}")
    arrs = [np.asarray(columns[nm], dtype=np.float64).ravel() for nm in names]
    n = arrs[0].shape[0]
    for nm, a in zip(names, arrs):
        if a.shape[0] != n:
            raise VsidgenError(f"write_csv: column '{nm}' has {a.shape[0]} values, expected {n}")
    block = np.column_stack(arrs) if n else np.empty((0, len(names)))
    with atomic_text_file(path) as fh:
        fh.write(",".join(names) + "\n")
        np.savetxt(fh, block, fmt="%.17g", delimiter=",")
    return path


__all__ = ["JITTER", "MAX_ABS_VALUE", "MAX_DT", "MIN_DT", "MIN_SAMPLES", "RESOLUTION", "fmt_number", "Record", "as_paths", "check_time", "delay_input", "hash_header", "load_record", "load_records", "most_extreme_sample", "refuse_other_delimiter", "resolution", "unique_names", "write_csv"]
