"""Units of data columns: conversion to the spec's units (pint) and range plausibility.

A data map may declare the unit of a column, ``{column: da_deg, unit: deg}``;
the loader then converts the column to the unit the spec declares for that
input or output:

    value_spec = scale * (a * column + b) + offset,   a = du/ds, b = conversion of 0

where ``a`` and ``b`` come from :mod:`pint` (``b`` ≠ 0 only for affine units
such as degC). The spec's ``scale``/``offset`` are applied after the
conversion, in the spec's unit. Units are parsed by pint with two aviation
conventions: ``g`` is the standard acceleration of gravity (9.80665 m/s², the
unit of load factors; write ``gram`` for grams) and ``^`` is a power. Angles
(``rad``, ``deg``) are dimensionless, as in SI and :mod:`vsidgen.spec.units`, so
``deg`` converts to ``rad`` and to ``1``; ``ft`` does not convert to ``rad``
(a dimension error located at the ``unit:`` entry of the spec).

:func:`plausibility_warnings` flags value ranges that do not fit the spec's
unit: an angle channel in rad whose magnitude exceeds 2π (one revolution), or
an angular rate beyond 2π rad/s — the signature of a column recorded in
degrees but read as radians.
"""

from __future__ import annotations

import collections
import dataclasses
import enum
import functools
import math
import pathlib
import re

import numpy as np


class UnitConversionError(ValueError):
    """A unit that pint cannot parse, or two units of different dimensions."""


class DataWarningCode(enum.Enum):
    """Kinds of data warnings."""

    IMPLAUSIBLE_RANGE = "implausible_range"
    MISSING_SAMPLES = "missing_samples"
    CONSTANT_OUTSIDE_RECORD = "constant_outside_record"
    SLOW_SAMPLING = "slow_sampling"


@dataclasses.dataclass(frozen=True)
class DataWarning:
    """A warning about the values of a record's channel (not an error: the fit still runs)."""

    code: DataWarningCode
    message: str
    path: pathlib.Path | None = None
    channel: str | None = None
    hint: str = ""

    def __str__(self) -> str:
        where = f"{self.path}: " if self.path is not None else ""
        out = f"{where}warning: {self.message}"
        return out + (f"\n  hint: {self.hint}" if self.hint else "")

    def to_json(self) -> dict:
        return {"code": self.code.value, "message": self.message, "channel": self.channel,
                "path": None if self.path is None else str(self.path), "hint": self.hint}


_G_TOKEN = re.compile(r"(?<![\w.])g(?![\w])")


@functools.lru_cache(maxsize=1)
def _registry():
    import pint

    return pint.UnitRegistry()


def _normalise(text: str) -> str:
    s = str(text).strip().replace("^", "**")
    if s in ("", "1", "-"):
        return "dimensionless"
    return _G_TOKEN.sub("standard_gravity", s)


#: longest unit text handed to pint (``kg*m^2/s^2`` is 10 characters)
MAX_UNIT_CHARS = 80
#: a power in a unit: one digit (``m^3``, ``s^-2``, ``s^0.5``), never a power of a power
_POWER = re.compile(r"\*\*\s*(\(\s*)?[-+]?\d(\.\d{1,3})?(?![\d.])(\s*\))?")


def _screen(text: str, normalised: str) -> None:
    """Refuse unit texts pint would evaluate at any cost before parsing them: pint computes
    ``9**9**9`` literally (a unit in a data map or a column header hung `check` and `fit`;
    session 44). A unit is short and its powers are small numbers."""
    if len(normalised) > MAX_UNIT_CHARS:
        raise UnitConversionError(f"unknown unit `{text[:40]}…`: longer than {MAX_UNIT_CHARS} "
                                  "characters")
    rest = normalised
    for m in _POWER.finditer(normalised):
        if normalised[m.end():].lstrip().startswith("**"):
            break
        rest = rest.replace(m.group(0), " ", 1)
    if "**" in rest:
        raise UnitConversionError(f"unknown unit `{text}` (a power must be a number from -9 to 9, "
                                  "as in `m/s^2`)")


@functools.lru_cache(maxsize=256)
def _quantity_unit(text: str):
    ureg = _registry()
    _screen(text, _normalise(text))
    try:
        return ureg.Unit(_normalise(text))
    except Exception as exc:  # pint raises UndefinedUnitError, DefinitionSyntaxError, ...
        why = "" if type(exc).__name__ == "UndefinedUnitError" else " (not a unit expression)"
        raise UnitConversionError(f"unknown unit `{text}`{why}") from None


def check_unit(text: str) -> None:
    """Raise UnitConversionError when pint cannot parse ``text``."""
    _quantity_unit(text)


def dimensionality(text: str) -> str:
    """Readable dimension of a unit, e.g. ``[length] / [time]``; ``dimensionless``."""
    return str(_quantity_unit(text).dimensionality) or "dimensionless"


@functools.lru_cache(maxsize=256)
def conversion(data_unit: str, spec_unit: str) -> tuple[float, float]:
    """``(a, b)`` with ``value[spec_unit] = a * value[data_unit] + b``.

    Raises:
        UnitConversionError: a unit pint does not know, or different dimensions.
    """
    ureg = _registry()
    src, dst = _quantity_unit(data_unit), _quantity_unit(spec_unit)
    if src.dimensionality != dst.dimensionality:
        raise UnitConversionError(
            f"`{data_unit}` ({dimensionality(data_unit)}) cannot be converted to "
            f"`{spec_unit}` ({dimensionality(spec_unit)})")
    try:
        b = float(ureg.Quantity(0.0, src).to(dst).magnitude)
        a = float(ureg.Quantity(1.0, src).to(dst).magnitude) - b
    except (OverflowError, ZeroDivisionError, ValueError, ArithmeticError):
        a = b = math.inf
    if not (math.isfinite(a) and math.isfinite(b) and 1e-100 < abs(a) < 1e100):
        # e.g. `deg*deg*...` (400 factors) / deg: (π/180)^399 underflows to 0, and every
        # sample would have been read as 0 without a word
        raise UnitConversionError(
            f"converting `{data_unit}` to `{spec_unit}` multiplies by {a:g}: not a usable factor")
    return a, b


def angle_kind(spec_unit: str | None) -> tuple[str, float] | None:
    """``("angle"|"rate", radians per spec unit)`` for angle and angular-rate units, else None."""
    if not spec_unit:
        return None
    try:
        u = _quantity_unit(spec_unit)
    except UnitConversionError:
        return None
    names = set(u._units.keys())
    if not names & {"radian", "degree", "arcminute", "arcsecond", "turn", "revolution"}:
        return None
    ureg = _registry()
    if u.dimensionality == ureg.radian.dimensionality:
        return "angle", float(ureg.Quantity(1.0, u).to("radian").magnitude)
    if u.dimensionality == (ureg.radian / ureg.second).dimensionality:
        return "rate", float(ureg.Quantity(1.0, u).to("radian/second").magnitude)
    return None


#: unit suffixes of column names (``alpha_deg``, ``q_degps``, ``az_g``, ``V_kts``) and the
#: unit each one names; only unambiguous tokens (no ``rps``: rad/s or revolutions per second)
COLUMN_SUFFIX_UNITS: dict[str, str] = {
    "deg": "deg", "degrees": "deg", "rad": "rad", "radians": "rad",
    "degps": "deg/s", "dps": "deg/s", "deg_s": "deg/s", "degpersec": "deg/s",
    "radps": "rad/s", "rad_s": "rad/s",
    "degps2": "deg/s^2", "dps2": "deg/s^2", "deg_s2": "deg/s^2",
    "radps2": "rad/s^2", "rad_s2": "rad/s^2",
    "ft": "ft", "m": "m", "fps": "ft/s", "ftps": "ft/s", "ft_s": "ft/s", "mps": "m/s",
    "m_s": "m/s", "kt": "knot", "kts": "knot", "knots": "knot", "kn": "knot",
    "mps2": "m/s^2", "m_s2": "m/s^2", "fps2": "ft/s^2", "ftps2": "ft/s^2", "ft_s2": "ft/s^2",
    "g": "g", "n": "N", "kn_force": "kN", "lbf": "lbf", "pa": "Pa", "psf": "lbf/ft^2",
    "s": "s", "sec": "s", "kg": "kg", "kgpm3": "kg/m^3", "kg_m3": "kg/m^3",
    "kgm2": "kg*m^2", "kg_m2": "kg*m^2",
}
_BRACKETED = re.compile(r"[\[(]\s*([^\])]+?)\s*[\])]\s*$")


def _split_unit(column: str) -> tuple[str, str | None]:
    """(the name without the unit it states, that unit) of a column, or (name, None)."""
    name = column.strip()
    m = _BRACKETED.search(name)
    if m:
        try:
            check_unit(m.group(1))
        except UnitConversionError:
            return name, None
        return name[:m.start()].strip(), m.group(1)
    parts = name.split("_")
    low = [x.lower() for x in parts]
    if len(parts) >= 3 and "_".join(low[-2:]) in COLUMN_SUFFIX_UNITS:
        return "_".join(parts[:-2]), COLUMN_SUFFIX_UNITS["_".join(low[-2:])]
    if len(parts) >= 2 and low[-1] in COLUMN_SUFFIX_UNITS:
        return "_".join(parts[:-1]), COLUMN_SUFFIX_UNITS[low[-1]]
    return name, None


def column_suffix_unit(column: str) -> str | None:
    """The unit a column's name states (``alpha_deg`` → ``deg``, ``q (deg/s)`` → ``deg/s``,
    ``az_g`` → ``g``), or None. A bracketed unit must parse (pint); a ``_suffix`` must be one
    of :data:`COLUMN_SUFFIX_UNITS` (two tokens, ``deg_s``, before one)."""
    return _split_unit(column)[1]


def suffix_mismatch(column: str, spec_unit: str | None) -> str | None:
    """The unit ``column``'s name states when it has the spec unit's dimension but another
    scale (``alpha_deg`` for an angle in ``rad``), else None: the values would be read in the
    spec's unit."""
    named = column_suffix_unit(column)
    if named is None or not spec_unit:
        return None
    try:
        a, b = conversion(named, spec_unit)
    except UnitConversionError:
        return None
    return None if (math.isclose(a, 1.0, rel_tol=1e-9) and b == 0.0) else named


def suffix_other_dimension(column: str, spec_unit: str | None) -> str | None:
    """The unit ``column``'s name states when it has another dimension than the spec unit
    (``v_mps`` mapped to an angle in ``rad``: most likely the wrong column), else None."""
    named = column_suffix_unit(column)
    if named is None or not spec_unit:
        return None
    try:
        conversion(named, spec_unit)
    except UnitConversionError:
        try:
            dimensionality(spec_unit)
        except UnitConversionError:
            return None            # the spec unit itself is unknown to pint: nothing to say
        return named
    return None


def plausibility_warnings(model, u: np.ndarray, y: np.ndarray, *, path=None) -> tuple[DataWarning, ...]:
    """Warnings for channels whose value range is implausible for the spec's unit.

    An angle beyond one revolution (``max |x| > 2π rad``) and an angular rate
    beyond one revolution per second (``2π rad/s``) are flagged: both are what
    a column in degrees (deg/s) read as radians looks like.
    """
    out = []
    maps = {("input", c.name): c for c in model.data.inputs}
    maps.update({("output", c.name): c for c in model.data.outputs})
    for kind, variables, values in (("input", model.inputs, u), ("output", model.outputs, y)):
        for j, v in enumerate(variables):
            ak = angle_kind(v.unit)
            if ak is None:
                continue
            col = values[:, j]
            finite = col[np.isfinite(col)]
            if finite.size == 0:
                continue
            peak = float(np.max(np.abs(finite))) * ak[1]
            if peak <= 2.0 * math.pi:
                continue
            cmap = maps.get((kind, v.name))
            source = getattr(cmap, "column", None) or v.name
            declared = getattr(cmap, "unit", None)
            what = "angle" if ak[0] == "angle" else "angular rate"
            limit = "2π rad (360°)" if ak[0] == "angle" else "2π rad/s (360°/s)"
            other = None if declared else suffix_other_dimension(source, v.unit)
            if declared:
                hint = (f"the data map declares `{declared}` for `{source}`: check that unit "
                        "and the column")
            elif other:
                hint = (f"the column's name states `{other}` ({dimensionality(other)}), not an "
                        f"{what}: is `{source}` the right column for `{v.name}`?")
            else:
                deg = "deg" if ak[0] == "angle" else "deg/s"
                hint = (f"if the column is in degrees, declare it in the data map: "
                        f"`{v.name}: {{column: {yaml_name(source)}, unit: {deg}}}`")
            out.append(DataWarning(
                DataWarningCode.IMPLAUSIBLE_RANGE,
                f"{kind} `{v.name}` (column `{source}`) reaches {peak:.3g} rad"
                f"{'/s' if ak[0] == 'rate' else ''}, beyond {limit}: implausible for an "
                f"{what} in `{v.unit}`", path=path, channel=v.name, hint=hint))
    return tuple(out)


def yaml_name(column: str) -> str:
    """A column name as it must be written in a spec's flow mapping: plain when it is a
    simple name, else double-quoted (`DA [deg]` pasted plain was a YAML syntax error)."""
    if re.fullmatch(r"[A-Za-z_][\w.]*", column):
        return column
    return '"' + column.replace("\\", "\\\\").replace('"', '\\"') + '"'


def column_stem(column: str) -> str:
    """A column's name without the unit its name states (``v_mps`` → ``v``, ``mass_kg`` →
    ``mass``, ``V (kts)`` → ``V``; :func:`column_suffix_unit`), else the name itself."""
    return _split_unit(column)[0]


def constant_columns(constants, header, *, taken=()) -> dict[str, list[str]]:
    """Columns of ``header`` that record the quantity a constant names: the column's name
    without its unit (:func:`column_stem`) equals the constant's name, case aside (``V`` and
    ``v_mps``, ``mass`` and ``MASS_KG``). Columns in ``taken`` (the time, the mapped channels)
    and columns that appear more than once are left out. {constant name: [columns]}."""
    counts = collections.Counter(header)     # (header.count per column was quadratic)
    taken = set(taken)
    once = {h for h, n in counts.items() if n == 1 and h not in taken}
    out: dict[str, list[str]] = {}
    for c in constants:
        cols = [h for h in header if h in once and column_stem(h).lower() == c.name.lower()]
        if cols:
            out[c.name] = cols
    return out


def written_half_digit(value: float) -> float:
    """Half a unit of the last digit of ``value`` as Python writes it shortest (``repr``):
    0.05 for 32920.6, 5e-4 for 0.001, 0.05 for 90.0: the precision a number written with
    those digits claims."""
    import decimal

    if not math.isfinite(value):
        return 0.0
    exponent = decimal.Decimal(repr(float(value))).as_tuple().exponent
    return 0.5 * 10.0 ** int(exponent) if isinstance(exponent, int) else 0.0


def constant_range_warnings(constants, columns, matches, *, path=None) -> tuple[DataWarning, ...]:
    """One warning per constant whose value lies outside the recorded range of a column that
    records the same quantity (``matches``: :func:`constant_columns`; ``columns``: {column:
    values}).

    A constant that stands for a flight condition (airspeed, mass, density) should lie within
    what the record measured for it: a constant outside ``[min, max]`` of that column is a
    trim value from another flight, or a unit slip. The column is converted to the constant's
    unit where its name states a unit (``v_kts`` for a constant in ``m/s``); a column whose
    unit has another dimension records something else and is skipped. Scale-free: no
    tolerance beyond the recorded range itself."""
    out = []
    by_name = {c.name: c for c in constants}
    for name, cols in matches.items():
        c = by_name[name]
        for col in cols:
            v = np.asarray(columns.get(col, ()), dtype=np.float64)
            v = v[np.isfinite(v)]
            if v.size == 0:
                continue
            named = column_suffix_unit(col)
            shown = c.unit or ""
            if named and c.unit:
                try:
                    a, b = conversion(named, c.unit)
                except UnitConversionError:
                    continue
                v = a * v + b
            elif named and not c.unit:
                shown = named
            lo, hi, mean = float(v.min()), float(v.max()), float(v.mean())
            # the constant as written (32920.6) agrees with a column that records 32920.6156
            # to the digits it was written with: half a unit of its last digit (session 44)
            half = written_half_digit(c.value)
            if lo - half <= c.value <= hi + half:
                continue
            unit = f" {shown}" if shown else ""
            conv = f" (converted from {named})" if named and c.unit and named != c.unit else ""
            out.append(DataWarning(
                DataWarningCode.CONSTANT_OUTSIDE_RECORD,
                f"constant `{name}` = {c.value:.6g}{unit} lies outside the range column `{col}` "
                f"records ({lo:.6g} … {hi:.6g}{unit}{conv}, mean {mean:.6g})",
                path=path, channel=name,
                hint=(f"if `{name}` is the recorded quantity, set it to this record's value "
                      f"(mean {mean:.6g}{unit}) or map the column as an input "
                      f"(`data: {{inputs: {{{name}: {col}}}}}` with `{name}` under inputs); "
                      f"check its unit")))
            break
    return tuple(out)


__all__ = ["COLUMN_SUFFIX_UNITS", "DataWarning", "DataWarningCode", "UnitConversionError",
           "check_unit", "column_stem", "column_suffix_unit", "constant_columns",
           "constant_range_warnings", "conversion", "dimensionality",
           "plausibility_warnings", "suffix_mismatch", "suffix_other_dimension"]
