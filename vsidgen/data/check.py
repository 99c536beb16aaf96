"""A data record checked against a compiled spec (``vsidgen check SPEC --data DATA``).

The spec stage knows nothing of data files; this module, in the data stage, takes a
:class:`vsidgen.spec.symbolic.SymbolicModel` and a record and checks that the record can be fitted:
columns named by the data map are present, time is uniform, and the drift and outputs are finite
at every sample where the directly measured states are present.
"""

from __future__ import annotations

import csv
import math
import pathlib
from collections.abc import Mapping

import numpy as np
import sympy

from .records import (cell_hint, time_hint, cell_value, hash_header, load_record, refuse_other_delimiter,
                      refuse_units_row)
from ..errors import DataError, Location, SpecError, SpecWarning, printable
from ..spec.expr import did_you_mean
from .formats import DataFormat, detect_format
from ..limits import check_input_file
from ..metadata import ChannelMap
from ..suggest import column_hint
from ..spec import SymbolicModel

__all__ = ["check_first_sample", "check_record", "read_first_row"]


def _finite_value(expr: sympy.Expr, values: Mapping) -> float | None:
    try:
        v = sympy.S(expr).xreplace({k: sympy.Float(float(x)) for k, x in values.items()})
        v = sympy.N(v) if not v.is_Number else v
        if v.has(sympy.zoo, sympy.nan, sympy.oo, -sympy.oo, sympy.I):
            return None
        f = complex(v)
        if f.imag != 0 or not math.isfinite(f.real):
            return None
        return f.real
    except (TypeError, ValueError, ZeroDivisionError, OverflowError):
        return None


def read_first_row(csv_path) -> dict[str, float]:
    """Header and first data row of a CSV file as {column: value} (DataError on problems)."""
    csv_path = check_input_file(csv_path, what="data file")
    try:
        with csv_path.open(newline="", encoding="utf-8-sig") as fh:
            reader = csv.reader(fh)
            # blank lines are skipped, as the record's readers skip them
            rows = (r for r in reader if any(c.strip() for c in r))
            header = next(rows, None)
            line = reader.line_num
            row = next(rows, None)
    except FileNotFoundError:
        raise DataError("data file not found", path=csv_path) from None
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise DataError(f"cannot read data file: {exc}", path=csv_path) from None
    if not header or row is None:
        raise DataError("data file needs a header row and at least one data row", path=csv_path)
    header = hash_header([h.strip() for h in header], row, csv_path, line=line)
    refuse_other_delimiter(header, csv_path)
    if len(row) != len(header):
        raise DataError(f"first data row has {len(row)} fields but the header has {len(header)}",
                        path=csv_path, sample=0)
    refuse_units_row(row, header, csv_path)
    out = {}
    for h, cell in zip(header, row):
        if not cell.strip():
            out[h] = float("nan")      # a missing sample (allowed in outputs)
            continue
        try:
            out[h] = cell_value(cell)
        except ValueError:
            # a text column the data map does not use (a flight number, an event mark) is
            # read by nobody: `fit` ignores it, so `check` must too (session 44); the
            # columns the map uses are checked where their values are taken
            out[h] = _Text(cell)
    return out


class _Text(float):
    """A non-numeric cell of the first data row: NaN to arithmetic, refused where a channel
    reads it (:func:`_channel_value`)."""

    def __new__(cls, cell: str):
        obj = super().__new__(cls, float("nan"))
        obj.cell = cell
        return obj


def _channel_value(ch: ChannelMap, row: Mapping[str, float], csv_path, columns,
                   taken: Mapping[str, str] | None = None) -> float:
    for c in ch.columns:
        if c not in row:
            hint = column_hint(c, columns, taken)
            if hint and hint.startswith("did you mean"):
                hint = did_you_mean(c, [h for h in columns if h not in (taken or {}) or h == c])
            raise DataError(f"column `{c}` (for `{ch.name}`) is not in the file", path=csv_path,
                            column=c, hint=(hint + "; " if hint else "") +
                            "columns: " + ", ".join(columns))
    for c in ch.columns:
        if isinstance(row[c], _Text):
            # the cell, not the spec, is at fault (it was read as NaN and the drift at the
            # first sample then blamed the spec's equation)
            raise DataError(f"non-numeric value {row[c].cell.strip()[:40]!r}", path=csv_path,
                            column=c, sample=0, hint=cell_hint(row[c].cell))
    if ch.expr is None:
        base = row[ch.column]
    else:
        v = _finite_value(ch.expr, {sympy.Symbol(c, real=True): row[c] for c in ch.columns})
        base = float("nan") if v is None else v
    return float(ch.apply(base))


def check_first_sample(symbolic: SymbolicModel, csv_path, *, evaluate: bool = True) -> list[SpecWarning]:
    """Evaluate drift and outputs at the first sample of ``csv_path``.

    Inputs come from the data mapping, x0 from the outputs whose observation
    is exactly a state (zeros otherwise), parameters at their initial values.
    Non-finite inputs are returned as warnings; a non-finite drift or output
    raises SpecError naming the equation(s). ``evaluate=False``: the columns and
    inputs only (the caller evaluates the equations at other states).
    """
    row = read_first_row(csv_path)
    columns = list(row)
    warnings: list[SpecWarning] = []
    if symbolic.data.time not in row:
        raise DataError(f"time column `{symbolic.data.time}` is not in the file", path=csv_path,
                        column=symbolic.data.time, hint=time_hint(symbolic.data.time, columns))
    values: dict = dict(symbolic.constant_values())
    for p in symbolic.parameters:
        values[p.symbol] = p.initial
    taken = {symbolic.data.time: "the time"}
    for kind, chans in (("input", symbolic.data.inputs), ("output", symbolic.data.outputs)):
        for ch in chans:
            for c in ch.columns:
                taken.setdefault(c, f"{kind} `{ch.name}`")
    for v, ch in zip(symbolic.inputs, symbolic.data.inputs):
        val = _channel_value(ch, row, csv_path, columns, taken)
        if not math.isfinite(val) and ch.expr is not None and all(
                isinstance(row.get(c), float) and math.isfinite(row[c]) for c in ch.columns):
            # the columns are there and finite: the data map's expression is at fault, not
            # the data (red team, session 47: `log(de_rad - 1)` was "missing data")
            vals = ", ".join(f"{c} = {row[c]:.6g}" for c in ch.columns)
            raise SpecError(f"the data map's expression for input `{v.name}`, "
                            f"`{printable(ch.expr)}`, is not finite at the first sample of "
                            f"{pathlib.Path(csv_path).name} ({vals})", path=symbolic.source_path,
                            hint="the columns are present; the expression leaves its domain "
                                 "at these values (log or sqrt of a negative number, a division "
                                 "by zero): write it so that it is defined for the recorded "
                                 "values")
        if not math.isfinite(val):
            # a record's inputs must be present at every sample: the data are at fault, not
            # the spec's equations (which a NaN input would make non-finite below)
            raise DataError(f"input `{v.name}` is missing or not finite at the first sample",
                            path=csv_path, column=ch.columns[0] if ch.columns else None,
                            sample=0, hint="every sample needs a value for each input")
        values[v.symbol] = val
    if not evaluate:
        return warnings
    x0 = {s.symbol: 0.0 for s in symbolic.states}
    for o, ch, h in zip(symbolic.outputs, symbolic.data.outputs, symbolic.observations):
        if h in x0:
            val = _channel_value(ch, row, csv_path, columns, taken)
            if math.isfinite(val):
                x0[h] = val
    values.update(x0)
    bad = []
    for kind, names, exprs in (("drift", symbolic.states, symbolic.drift_expanded()),
                               ("observations", symbolic.outputs, symbolic.observations_expanded())):
        for v, e in zip(names, exprs):
            if _finite_value(e, values) is None:
                bad.append(f"{kind}:{v.name}")
    if bad:
        loc = symbolic.locations.get(bad[0], Location(symbolic.source_path))
        named = ", ".join(("drift of `" if b.startswith("drift") else "observation of `")
                          + b.split(":", 1)[1] + "`" for b in bad)
        raise SpecError(f"non-finite value at the first sample of {pathlib.Path(csv_path).name}: "
                        f"{named}", path=loc.path, line=loc.line, column=loc.column,
                        hint="x0 comes from outputs that are a state (else 0), parameters at "
                             "their initial values: check divisions, log and sqrt")
    return warnings


def check_record(symbolic: SymbolicModel, path, *, start=None) -> list:
    """Check a whole record against the spec (``vsidgen check --data``).

    ``start`` (optional): a callable ``start(record) -> (N, nx)`` giving the state means the fit
    starts from (the CLI passes the estimator's measured start, which also solves the states
    no output measures directly from the outputs, e.g. body-axis u, w from V and α); the
    equations are then evaluated there, so that the check and the fit agree on where a model
    is finite. Without it, x as in step 3 below.

    1. CSV files: the first sample as :func:`check_first_sample` (column names,
       a non-finite first drift).
    2. Every sample, through :func:`vsidgen.data.load_record`: time finite,
       strictly increasing and uniform (gaps), inputs present (no NaN), no
       infinite value, enough samples; warnings for value ranges implausible
       for a channel's unit.
    3. Drift and outputs at every sample where the states measured directly
       are present (x from outputs that are a state, 0 otherwise; parameters at
       their initial values), evaluated with numpy: the first sample where an
       equation is not finite raises SpecError naming it and the sample.

    Returns the warnings (SpecWarning and DataWarning records).
    """
    path = check_input_file(path, what="data file")
    warnings: list = []
    if detect_format(path) is DataFormat.CSV:
        warnings += check_first_sample(symbolic, path, evaluate=start is None)
    rec = load_record(symbolic, path)
    warnings += list(rec.warnings)
    n = rec.n
    values: dict = {c.symbol: np.full(n, float(c.value)) for c in symbolic.constants}
    for p in symbolic.parameters:
        values[p.symbol] = np.full(n, float(p.initial))
    for j, v in enumerate(symbolic.inputs):
        values[v.symbol] = rec.u[:, j]
    usable = np.ones(n, bool)
    for s in symbolic.states:
        values[s.symbol] = np.zeros(n)
    x_start = None if start is None else np.asarray(start(rec), float)
    if x_start is not None:
        usable &= np.isfinite(x_start).all(axis=1)
        for i, s in enumerate(symbolic.states):
            values[s.symbol] = np.where(usable, x_start[:, i], 0.0)
    else:
        for j, h in enumerate(symbolic.observations):
            if h in values and h in {s.symbol for s in symbolic.states}:
                col = rec.y[:, j]
                usable &= np.isfinite(col)
                values[h] = np.where(np.isfinite(col), col, 0.0)
    syms = list(values)
    bad: list[tuple[int, str]] = []
    for kind, names, exprs in (("drift", symbolic.states, symbolic.drift_expanded()),
                               ("observations", symbolic.outputs, symbolic.observations_expanded())):
        for v, e in zip(names, exprs):
            try:
                fn = sympy.lambdify(syms, e, "numpy")
                with np.errstate(all="ignore"):
                    val = np.broadcast_to(np.asarray(fn(*[values[s] for s in syms]), float), (n,))
            except (TypeError, ValueError, NameError, AttributeError):
                continue  # a function numpy cannot evaluate (lookup tables): first sample only
            nonfinite = ~np.isfinite(val) & usable
            if nonfinite.any():
                bad.append((int(np.flatnonzero(nonfinite)[0]), f"{kind}:{v.name}"))
    if bad:
        k, key = min(bad)
        loc = symbolic.locations.get(key, Location(symbolic.source_path))
        named = ", ".join(("drift of `" if b.startswith("drift") else "observation of `")
                          + b.split(":", 1)[1] + "`" for kk, b in sorted(bad) if kk == k)
        raise SpecError(f"non-finite value at sample {k} (t = {rec.t_raw[k]:g} s) of "
                        f"{path.name}: {named}", path=loc.path, line=loc.line, column=loc.column,
                        hint=("x is the fit's start (outputs that are a state; the others "
                              "solved from the outputs), " if x_start is not None else
                              "x comes from outputs that are a state (else 0), ")
                        + "parameters at their initial values: check divisions, log and sqrt")
    return warnings
