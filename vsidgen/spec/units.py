"""Unit strings -> physical dimensions, and dimensional-consistency checks.

Unit strings ("m/s", "m/s^2", "1/(kg*m)", "kg/m^3", "rad", "1") are parsed by
the same safe parser as model expressions (``^`` means power) into
``sympy.physics.units`` dimensions. Angles (rad, deg) are dimensionless.

:func:`dimension_of` computes the dimension of an expression recursively:
sums must agree, arguments of transcendental functions must be
dimensionless, ``min/max/sat/abs`` keep the dimension of their arguments,
``sign``/Heaviside and numbers are dimensionless. Terms whose dimension is
unknown (a symbol without unit, a lookup table) make the containing
expression unknown; checks involving them are skipped.
"""

from __future__ import annotations

import dataclasses
import math
import re
from collections.abc import Callable, Mapping

import sympy
from sympy.physics.units import Dimension
from sympy.physics.units.definitions.dimension_definitions import (
    amount_of_substance, current, length, mass, temperature, time,
)

from ..errors import SpecError
from .expr import Interp, InterpSlope, parse_expression

ONE = Dimension(1)

#: unit name -> dimension
UNITS: dict[str, Dimension] = {
    "m": length, "km": length, "ft": length, "nmi": length,
    "s": time, "min": time, "h": time,
    "kg": mass, "lb": mass, "slug": mass,
    # the units of US flight-test practice: knots, pound-force, and g, the standard
    # acceleration of gravity (the unit of load factors, as in the data map; not gram)
    "kt": length / time, "lbf": mass * length / time**2, "g": length / time**2,
    "K": temperature,
    "A": current, "mol": amount_of_substance,
    "N": mass * length / time**2,
    "Pa": mass / (length * time**2),
    "J": mass * length**2 / time**2,
    "W": mass * length**2 / time**3,
    "Hz": 1 / time,
    "rad": ONE, "deg": ONE, "sr": ONE,
}

_UNIT_SYMBOLS = {name: sympy.Symbol(name, positive=True) for name in UNITS}

#: units that are not coherent SI (rad for angles): their size in the coherent unit. The
#: equations are evaluated with the numbers as they stand, so a quantity in one of these
#: is off by the factor wherever it meets coherent ones (a constant of 3 deg in cos() is
#: 3 rad; a span in ft beside a speed in m/s)
NON_COHERENT = {"km": ("m", 1000.0), "ft": ("m", 0.3048), "min": ("s", 60.0),
                "h": ("s", 3600.0), "deg": ("rad", math.pi / 180.0), "nmi": ("m", 1852.0),
                "lb": ("kg", 0.45359237), "slug": ("kg", 14.593902937206364),
                "kt": ("m/s", 1852.0 / 3600.0), "lbf": ("N", 4.4482216152605),
                "g": ("m/s^2", 9.80665)}


def is_conversion_factor(text) -> bool:
    """A ratio of a non-coherent unit and its coherent counterpart (``deg/rad``, ``rad/deg``,
    ``ft/m``): a constant in it exists to convert, e.g. an output in deg = R2D·α."""
    try:
        expr = parse_expression(str(text).replace("^", "**"), _UNIT_SYMBOLS, units=True)
    except SpecError:
        return False
    names = {n for n, s in _UNIT_SYMBOLS.items() if s in expr.free_symbols}
    return any(n in names and set(re.findall(r"[A-Za-z_]\w*", NON_COHERENT[n][0])) <= names
               for n in NON_COHERENT)


def coherent(text, *, path=None, line=None, column=None) -> tuple[float, str]:
    """``(factor, coherent unit text)`` of a unit: a value in ``text`` times ``factor`` is
    the value in the coherent unit (SI, rad for angles). ``(1.0, text)`` when it is
    coherent already (``deg/s`` → ``(π/180, "rad/s")``, ``ft`` → ``(0.3048, "m")``)."""
    if isinstance(text, (int, float)) and not isinstance(text, bool):
        return 1.0, repr(text)
    expr = parse_expression(str(text).replace("^", "**"), _UNIT_SYMBOLS, path=path, line=line,
                            column=column, units=True)
    present = {name for name in NON_COHERENT if _UNIT_SYMBOLS[name] in expr.free_symbols}
    if not present:
        return 1.0, str(text)
    factor = float(expr.xreplace({_UNIT_SYMBOLS[n]: NON_COHERENT[n][1] if n in NON_COHERENT
                                  else 1.0 for n in UNITS}))
    shown = re.sub(r"[A-Za-z_]\w*", lambda m: NON_COHERENT.get(m.group(0), (m.group(0),))[0],
                   str(text))
    return factor, shown


def scale_of(expr: sympy.Expr, scales: Mapping[sympy.Symbol, float | None],
             report: Callable[[sympy.Expr, float, sympy.Expr | None, float], None] | None = None
             ) -> float | None:
    """The factor from ``expr``'s value, computed with every number in its declared unit, to
    its value in coherent units (SI, rad): ``s`` in ``s·x = x_coherent``. ``scales`` gives
    each symbol's factor (:func:`coherent`; None: no unit). None when it is unknown (a
    symbol without a unit, a table) or when the numbers as they stand are wrong somewhere
    in ``expr``: terms of a sum with different factors (``M_q·q`` with q in deg/s beside
    ``M_α·α`` with α in rad), a function of an argument not in coherent units (sin of
    degrees). An equation is right in its declared units exactly where this factor is
    defined and equals its left-hand side's: a derivative in m/(s·deg) times a rate in
    deg/s is a term in m/s² (factor 1), as its equation needs. ``report(term, factor,
    other, other_factor)`` is told of each place where the numbers disagree (``other`` None:
    a function's argument, which needs factor 1)."""
    def agree(args) -> float | None:
        found, first = None, None
        for a in args:
            f = scale_of(a, scales, report)
            if f is None:
                return None
            if a.is_Number:
                continue        # a bare number takes the unit of its sum (V - 100)
            if found is None:
                found, first = f, a
            elif not math.isclose(f, found, rel_tol=1e-9):
                if report is not None:
                    report(a, f, first, found)
                return None
        return 1.0 if found is None else found

    if expr.is_Number or expr in (sympy.pi, sympy.E):
        return 1.0
    if expr.is_Symbol:
        return scales.get(expr)
    if isinstance(expr, (sympy.Add, sympy.Min, sympy.Max)):
        return agree(expr.args)
    if isinstance(expr, sympy.Abs):
        return scale_of(expr.args[0], scales, report)
    if isinstance(expr, sympy.Mul):
        out = 1.0
        for factor in expr.args:
            f = scale_of(factor, scales, report)
            if f is None:
                return None
            out *= f
        return out
    if isinstance(expr, sympy.Pow):
        base, exp = expr.args
        fb = scale_of(base, scales, report)
        if fb is None:
            return None
        if exp.is_Number:
            try:
                return float(fb ** float(exp))
            except (OverflowError, ZeroDivisionError, ValueError):
                return None
        fe = scale_of(exp, scales, report)
        if fe is None:
            return None
        for part, f in ((base, fb), (exp, fe)):
            if not math.isclose(f, 1.0):
                if report is not None:
                    report(part, f, None, 1.0)
                return None
        return 1.0
    if isinstance(expr, _TRANSCENDENTAL):
        f = scale_of(expr.args[0], scales, report)
        if f is not None and not math.isclose(f, 1.0):
            if report is not None:
                report(expr.args[0], f, None, 1.0)
            return None
        return None if f is None else 1.0
    if isinstance(expr, sympy.atan2):
        return None if agree(expr.args) is None else 1.0
    if isinstance(expr, (sympy.sign, sympy.Heaviside)):
        # the sign of a quantity does not depend on its unit; its argument must be a sum
        # that agrees
        return None if scale_of(expr.args[0], scales, report) is None else 1.0
    return None


def parse_unit(text, *, path=None, line=None, column=None) -> Dimension:
    """Parse a unit string into a dimension (``"1"`` and ``""``-free numbers are dimensionless)."""
    if isinstance(text, (int, float)) and not isinstance(text, bool):
        text = repr(text)
    if not isinstance(text, str):
        raise SpecError(f"a unit must be a text like \"m/s\", got {type(text).__name__}",
                        path=path, line=line, column=column)
    # `^` binds like `**` in units ("m/s^2" = m/(s**2)); Python's `^` would bind last.
    expr = parse_expression(text.replace("^", "**"), _UNIT_SYMBOLS, path=path, line=line,
                            column=column, units=True)
    subs = {sym: UNITS[name].name for name, sym in _UNIT_SYMBOLS.items()}
    try:
        dim_expr = expr.xreplace(subs)
    except Exception:  # pragma: no cover
        raise SpecError(f"invalid unit `{text}`", path=path, line=line, column=column) from None
    if dim_expr.is_Number:
        return ONE
    # drop numeric factors (e.g. "1/(kg*m)" has a 1)
    coeff, rest = dim_expr.as_coeff_Mul()
    return Dimension(rest)


def same(a: Dimension, b: Dimension) -> bool:
    """Whether two dimensions are equal."""
    return sympy.simplify(a.name - b.name) == 0 if a.name != b.name else True


def show(d: Dimension) -> str:
    """Readable dimension, e.g. ``length/time``; ``1`` for dimensionless."""
    return str(d.name)


@dataclasses.dataclass(frozen=True)
class DimensionIssue:
    """A dimensional inconsistency: the offending term and both dimensions."""

    term: sympy.Expr
    dimension: Dimension
    expected: Dimension
    other: sympy.Expr | None
    reason: str

    def message(self) -> str:
        if self.other is not None:
            return (f"term `{self.term}` has dimension {show(self.dimension)} but "
                    f"`{self.other}` has dimension {show(self.expected)} ({self.reason})")
        return (f"term `{self.term}` has dimension {show(self.dimension)}, expected "
                f"{show(self.expected)} ({self.reason})")


_TRANSCENDENTAL = (sympy.sin, sympy.cos, sympy.tan, sympy.asin, sympy.acos, sympy.atan,
                   sympy.exp, sympy.log, sympy.tanh)


def dimension_of(expr: sympy.Expr, dims: Mapping[sympy.Symbol, Dimension | None],
                 report: Callable[[DimensionIssue], None]) -> Dimension | None:
    """Dimension of ``expr`` (None if unknown); inconsistencies go to ``report``."""
    if expr.is_Number or expr in (sympy.pi, sympy.E):
        return ONE
    if expr.is_Symbol:
        return dims.get(expr)
    if isinstance(expr, sympy.Add):
        first_term, first_dim = None, None
        unknown = False
        for term in expr.args:
            d = dimension_of(term, dims, report)
            if d is None:
                unknown = True
                continue
            if term.is_Number:
                # a bare number in a sum takes the dimension of the sum (offsets like V - 100)
                continue
            if first_dim is None:
                first_term, first_dim = term, d
            elif not same(d, first_dim):
                report(DimensionIssue(term, d, first_dim, first_term, "terms of a sum must agree"))
        if unknown:
            return None
        return first_dim if first_dim is not None else ONE
    if isinstance(expr, sympy.Mul):
        out = ONE
        for factor in expr.args:
            d = dimension_of(factor, dims, report)
            if d is None:
                out = None
            elif out is not None:
                out = out * d
        return out
    if isinstance(expr, sympy.Pow):
        base, exp = expr.args
        db = dimension_of(base, dims, report)
        if exp.is_Number:
            # dimensions are positive symbols: (length²/time²)^(1/2) is length/time (sympy
            # keeps sqrt(length**2/time**2) unless forced, and then √(u² + w²) in m/s
            # 'differs' from a speed)
            if exp.is_Float:        # x**0.5 as x**(1/2): length**1.0 is not length to sympy
                exp = sympy.nsimplify(exp, rational=True)
            return None if db is None else Dimension(sympy.powdenest(
                sympy.expand_power_base(db.name ** exp, force=True), force=True))
        de = dimension_of(exp, dims, report)
        if de is not None and not same(de, ONE):
            report(DimensionIssue(exp, de, ONE, None, "an exponent must be dimensionless"))
        if db is not None and not same(db, ONE):
            report(DimensionIssue(base, db, ONE, None, "base of a symbolic power must be dimensionless"))
        return ONE
    if isinstance(expr, _TRANSCENDENTAL):
        d = dimension_of(expr.args[0], dims, report)
        if d is not None and not same(d, ONE):
            report(DimensionIssue(expr.args[0], d, ONE, None,
                                  f"the argument of {type(expr).__name__} must be dimensionless"))
        return ONE
    if isinstance(expr, sympy.atan2):
        a = dimension_of(expr.args[0], dims, report)
        b = dimension_of(expr.args[1], dims, report)
        if a is not None and b is not None and not same(a, b):
            report(DimensionIssue(expr.args[0], a, b, expr.args[1],
                                  "the arguments of atan2 must agree"))
        return ONE
    if isinstance(expr, (sympy.sign, sympy.Heaviside, InterpSlope)):
        for a in expr.args[:1]:
            dimension_of(a, dims, report)
        return ONE if not isinstance(expr, InterpSlope) else None
    if isinstance(expr, sympy.Abs):
        return dimension_of(expr.args[0], dims, report)
    if isinstance(expr, (sympy.Min, sympy.Max)):
        first_term, first_dim, unknown = None, None, False
        for a in expr.args:
            d = dimension_of(a, dims, report)
            if d is None:
                unknown = True
            elif a.is_Number:
                continue
            elif first_dim is None:
                first_term, first_dim = a, d
            elif not same(d, first_dim):
                report(DimensionIssue(a, d, first_dim, first_term,
                                      f"the arguments of {type(expr).__name__.lower()} must agree"))
        if unknown:
            return None
        return first_dim if first_dim is not None else ONE
    if isinstance(expr, Interp):
        dimension_of(expr.args[0], dims, report)
        return None
    return None
