"""SymbolicModel: a validated spec as sympy expressions.

:func:`compile_spec` reads a spec once into the typed, located
:class:`vsidgen.spec.typed.Spec` (structure checked there) and compiles it: every
expression parsed with the safe parser (:mod:`vsidgen.spec.expr`) in the namespace of the
declared names, the model validated (names declared once, equations, definition
cycles, noise and data map against the declarations) and dimensional consistency
checked (:mod:`vsidgen.spec.units`). The model is

    dx/dt = f(x, u, θ)     (``drift``, one expression per state)
    y     = h(x, u, θ)     (``observations``, one per output)

where f and h may use the ordered ``definitions`` (intermediate quantities);
:meth:`SymbolicModel.drift_expanded` substitutes them.
"""

from __future__ import annotations

import dataclasses
import os
import pathlib
import math
import re
from collections.abc import Mapping
from typing import Any

import sympy

from ..errors import Location, SpecError, SpecWarning
from .expr import did_you_mean, parse_expression, parse_expression_free
from ..metadata import (ChannelMap, Constant, DataSpec, MeasurementNoiseSpec, Parameter,
                       ProcessNoiseSpec, Variable)
from .typed import (GENERATED_MODULE_NAMES, ChannelDecl, Equation, Located, Spec, read_spec,
                        valid_name)
from .. import __version__
from . import units as _units

#: the generated modules record it; a new vsidgen version rebuilds them
GENERATOR_VERSION = __version__

#: most nodes of one drift/observation equation with its definitions substituted (the
#: shipped specs need at most 77; building a 12000-node one took 11 s on a loaded 2-core machine)
MAX_EXPANDED_SIZE = 10_000

#: deepest nesting of one drift/observation equation with its definitions substituted (the
#: shipped and users' specs reach 10; sympy's differentiation and printing recurse once or
#: more per level, and a chain of 110-140 nested definitions ended in a RecursionError)
MAX_EXPANDED_DEPTH = 40
#: most arguments of one min/max once definitions are substituted (sympy flattens nested
#: ones): their Jacobians are piecewise, and sympy's differentiation and printing of a
#: max of n arguments grow combinatorially (max of 8 parameters: `check` 49 s, `build` of
#: 50: over 5 minutes; red team, session 48)
MAX_MINMAX_ARGS = 4

__all__ = ["GENERATOR_VERSION", "SymbolicModel", "Variable", "Constant", "Parameter",
           "ProcessNoiseSpec", "MeasurementNoiseSpec", "ChannelMap", "DataSpec",
           "compile_spec", "compile_typed", "valid_name", "GENERATED_MODULE_NAMES"]


@dataclasses.dataclass(frozen=True)
class SymbolicModel:
    """A compiled spec (see docs/architecture.md, "SymbolicModel")."""

    name: str
    description: str
    source_path: pathlib.Path
    source_hash: str
    states: tuple[Variable, ...]
    inputs: tuple[Variable, ...]
    outputs: tuple[Variable, ...]
    constants: tuple[Constant, ...]
    parameters: tuple[Parameter, ...]
    definitions: tuple[tuple[str, sympy.Expr], ...]
    drift: tuple[sympy.Expr, ...]
    observations: tuple[sympy.Expr, ...]
    process_noise: ProcessNoiseSpec
    measurement_noise: tuple[MeasurementNoiseSpec, ...]
    data: DataSpec
    integrator: str
    substeps: int
    warnings: tuple[SpecWarning, ...] = ()
    #: input hold between samples of the transition: "zoh" | "foh" (:mod:`vsidgen.model.dynamics`)
    input_hold: str = "zoh"
    #: "drift:V" / "observations:V" / "definitions:qbar" -> where the equation is written
    locations: Mapping[str, Location] = dataclasses.field(default_factory=dict, compare=False)
    #: every file of the spec, the `extends` ancestors first
    files: tuple[pathlib.Path, ...] = ()
    #: the merged spec in canonical JSON (what source_hash covers)
    canonical: str = dataclasses.field(default="", repr=False, compare=False)

    @property
    def definition_symbols(self) -> dict[sympy.Symbol, sympy.Expr]:
        return {sympy.Symbol(n, real=True): e for n, e in self.definitions}

    def expansion(self) -> dict[sympy.Symbol, sympy.Expr]:
        """definition symbol -> expression in states/inputs/parameters/constants only."""
        out: dict[sympy.Symbol, sympy.Expr] = {}
        for name, expr in self.definitions:
            out[sympy.Symbol(name, real=True)] = expr.xreplace(out)
        return out

    def drift_expanded(self) -> tuple[sympy.Expr, ...]:
        sub = self.expansion()
        return tuple(e.xreplace(sub) for e in self.drift)

    def observations_expanded(self) -> tuple[sympy.Expr, ...]:
        sub = self.expansion()
        return tuple(e.xreplace(sub) for e in self.observations)

    @property
    def state_symbols(self):
        return tuple(v.symbol for v in self.states)

    @property
    def input_symbols(self):
        return tuple(v.symbol for v in self.inputs)

    @property
    def parameter_symbols(self):
        return tuple(p.symbol for p in self.parameters)

    def constant_values(self) -> dict[sympy.Symbol, float]:
        return {c.symbol: c.value for c in self.constants}

    def trim_parameters(self) -> tuple[str, ...]:
        """Free parameters that are trim constants: every additive term of the expanded drift
        and observations that names one names no state and no input, and it enters those
        terms linearly (``Z0`` in ``α̇ = Z0 + Z_α α + …``, ``az0`` in ``a_z = V(…) + az0``, a
        sensor bias). They are properties of the flight condition of a record, not of the
        aircraft (the textbook's multi-manoeuvre estimation fits biases per time segment), so
        validation on another record re-estimates them (``estimator.validate_own_noise``)."""
        xu = {v.symbol for v in self.states} | {v.symbol for v in self.inputs}
        free = [p for p in self.parameters if not p.fixed]
        seen: dict[sympy.Symbol, bool] = {p.symbol: False for p in free}
        bad: set = set()
        for e in self.drift_expanded() + self.observations_expanded():
            constant, varying = split_constant_terms(e, xu)
            for term in varying:
                for ps in term.free_symbols & set(seen):
                    seen[ps] = True
                    bad.add(ps)
            for term in constant:
                for ps in term.free_symbols & set(seen):
                    seen[ps] = True
                    try:
                        linear = sympy.degree(term, ps) == 1
                    except (sympy.PolynomialError, ValueError, TypeError):
                        linear = False
                    if not linear:
                        bad.add(ps)
        return tuple(p.name for p in free if seen[p.symbol] and p.symbol not in bad)


def split_constant_terms(expr, variables) -> tuple[list, list]:
    """(the additive terms of ``expr``, expanded, that contain none of the symbols
    ``variables``; those that do): the constant part of an equation in its states and inputs."""
    constant, varying = [], []
    for term in sympy.Add.make_args(sympy.expand(expr)):
        (varying if term.free_symbols & set(variables) else constant).append(term)
    return constant, varying


# ---------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------

def _sym(name: str) -> sympy.Symbol:
    return sympy.Symbol(name, real=True)


def _warn(warnings: list, message: str, at: Located | None, *, code: str, hint: str = "",
          key: bool = True) -> None:
    if at is None:
        warnings.append(SpecWarning(message, code=code, hint=hint))
        return
    loc = at.key_loc if key else at.loc
    warnings.append(SpecWarning(message, path=loc["path"], line=loc["line"], column=loc["column"],
                                text=at.key_text if key else at.text, hint=hint, code=code))


def _expression(text: Located[str], namespace, *, free_names: bool = False):
    """Parse an expression text; errors point at the exact file position."""
    try:
        if free_names:
            return parse_expression_free(text.value, namespace, path=text.path, line=1, column=1)
        return parse_expression(text.value, namespace, path=text.path, line=1, column=1)
    except SpecError as err:
        raise text.relocate(err) from None


def _unit_dim(unit: Located[str] | None):
    if unit is None:
        return None
    try:
        return _units.parse_unit(unit.value, path=unit.path, line=1, column=1)
    except SpecError as err:
        raise unit.relocate(err) from None


def _coherent(unit: Located[str] | None) -> tuple[float, str | None]:
    """(factor to the coherent unit, coherent unit text) of a declared unit (1, None: none)."""
    if unit is None:
        return 1.0, None
    try:
        return _units.coherent(unit.value, path=unit.path, line=1, column=1)
    except SpecError as err:
        raise unit.relocate(err) from None


def _warn_coherence(warnings: list, spec: Spec, right: set[tuple[str, str]]) -> None:
    """Warnings for units that are not coherent SI (rad for angles): every number is used as
    it stands, which is right only where each equation it enters is written in those units
    (3 deg inside cos() is 3 rad; a span in ft beside a speed in m/s is not metres). A
    conversion factor between a unit and its coherent counterpart (`deg/rad`, `ft/m`) is
    written to convert, and is not warned about; nor is a constant, variable or parameter in
    ``right`` (:func:`_right_as_written`: every equation it enters is consistent in declared
    units; a reference speed in kt times a kt-to-m/s factor is)."""
    for c in spec.constants:
        factor, unit = _coherent(c.unit)
        if factor != 1.0 and not _units.is_conversion_factor(c.unit.value) \
                and ("constant", c.name.value) not in right:
            _warn(warnings, f"constant `{c.name.value}` is {c.value:g} {c.unit.value}, and the "
                            f"equations use the number {c.value:g} as it stands: where it meets "
                            f"quantities in coherent units (SI, rad) it counts as {c.value:g} "
                            f"{unit}", c.name, code="noncoherent_unit",
                  hint=f"write `{{value: {c.value * factor:.6g}, unit: {unit}}}`")
    for decls, what in ((spec.states, "state"), (spec.inputs, "input"),
                        (spec.outputs, "output"), (spec.parameters, "parameter")):
        for d in decls:
            factor, unit = _coherent(d.unit)
            if factor == 1.0 or (what, d.name.value) in right:
                continue
            if what == "parameter":
                msg = (f"parameter `{d.name.value}` is declared in `{d.unit.value}`, but the "
                       "equations use the numbers as they stand: where they meet quantities in "
                       f"coherent units (SI, rad) the estimate is in `{unit}`, and its initial "
                       "value and bounds are read in that unit too")
                hint = f"declare `unit: {unit}` (1 {d.unit.value} = {factor:.6g} {unit})"
            else:
                msg = (f"{what} `{d.name.value}` is declared in `{d.unit.value}`: the equations "
                       f"use its numbers in `{d.unit.value}`, so every equation it enters must be "
                       "written in that unit (no sin/cos of it, rates and kinematics in the same "
                       "unit)")
                hint = (f"declare `unit: {unit}`; a data column in `{d.unit.value}` is converted "
                        f"by the data map: `{{column: NAME, unit: {d.unit.value}}}`")
            _warn(warnings, msg, d.name, code="noncoherent_unit", hint=hint)


def _factor_words(f: float) -> str:
    """A unit factor to coherent units in words: `deg` numbers, coherent numbers, or ×f."""
    for k, words in ((1.0, "coherent units (SI, rad)"),
                     (math.pi / 180.0, "degree-based units (deg, deg/s, …)"),
                     (180.0 / math.pi, "per-degree units"),
                     ((math.pi / 180.0) ** 2, "units of degrees squared")):
        if math.isclose(f, k, rel_tol=1e-9):
            return words
    return f"units {f:.6g} × the coherent ones"


def _disagreement(found) -> str:
    """Words for one place where :func:`units.scale_of` found the numbers disagreeing."""
    term, f, other, fo = found
    return f"`{term}` is in {_factor_words(f)}" + (
        f" but `{other}` beside it in {_factor_words(fo)}" if other is not None
        else " where a function needs coherent units (rad)")


def _pair(found) -> frozenset[str] | None:
    """The two terms of a :func:`units.scale_of` disagreement, as texts (None: one term)."""
    term, _, other, _ = found
    return None if other is None else frozenset((str(term), str(other)))


def _right_as_written(decl: "_Declared", definitions, drift, observations,
                      issues: list | None = None) -> set[tuple[str, str]]:
    """(kind, name) of the declarations in a non-coherent unit whose numbers are right as they stand: every
    equation that uses them, directly or through definitions, is consistent in the declared
    units — :func:`units.scale_of` gives the equation a factor to coherent units and it
    equals its left-hand side's (a drift's is its state's, per second). A model written in
    degrees throughout (q in deg/s, a bias in deg/s², a side-force derivative in m/(s·deg)
    times a rate in deg/s) is; sin() of a state in deg, or an α in rad beside a derivative
    per deg, is not, and neither is an equation with a symbol without a unit (unknown).
    The check follows the algebra, not which names appear (sessions 43–44). ``issues``
    receives ``(where, name, section, message)`` for each equation or definition whose
    numbers disagree, naming the terms (`θ − α` with θ in rad and α in deg had only the
    generic warnings; session 44)."""
    def factor(unit) -> float | None:
        return None if unit is None else _units.coherent(unit)[0]

    scales: dict[sympy.Symbol, float | None] = {}
    for v in decl.states + decl.inputs:
        scales[v.symbol] = factor(v.unit)
    for c in decl.constants:
        scales[c.symbol] = factor(c.unit)
    for q in decl.parameters:
        scales[q.symbol] = factor(q.unit)
    reach: dict[sympy.Symbol, frozenset] = {}
    for nm, expr in definitions:
        found_def: list = []
        scales[_sym(nm)] = _units.scale_of(expr, scales, lambda *a: found_def.append(a))
        reach[_sym(nm)] = frozenset().union(*(reach.get(x, {x}) for x in expr.free_symbols))
        if issues is not None and found_def:
            # terms of a definition that disagree make every equation using it unknown, so
            # those were silent: the definition itself is named (a new user's `side: Yb*beta
            # + Y0` with beta in deg had no unit_scale warning; written out, it had; session 46)
            issues.append((f"definition of `{nm}`", nm, "definitions", _disagreement(found_def[0]),
                           _pair(found_def[0])))
    used: set[sympy.Symbol] = set()
    wrong: set[sympy.Symbol] = set()
    right_outputs: set[str] = set()
    for lhs, exprs in ((decl.states, drift), (decl.outputs, observations)):
        is_drift = lhs is decl.states
        for v, expr in zip(lhs, exprs):
            names = frozenset().union(*(reach.get(x, {x}) for x in expr.free_symbols))
            if is_drift:                # the state's own unit is the left-hand side's
                names |= {v.symbol}
            used |= names
            found: list = []
            got = _units.scale_of(expr, scales, lambda *a: found.append(a))
            want = factor(v.unit)
            ok = got is not None and want is not None and math.isclose(got, want, rel_tol=1e-9)
            if not ok:
                wrong |= names
            elif not is_drift:          # an output is right when its own observation is
                right_outputs.add(v.name)
            if issues is None or (ok or (not found and (got is None or want is None))):
                continue
            where = f"{'drift' if is_drift else 'observation'} of `{v.name}`"
            pair = _pair(found[0]) if found else None
            if found:
                what = _disagreement(found[0])
            else:
                what = (f"the expression is in {_factor_words(got)} but `{v.name}` is "
                        f"declared in {_factor_words(want)}")
            issues.append((where, v.name, "drift" if is_drift else "observations", what, pair))
    kinds = {v.symbol: "state" for v in decl.states}
    kinds.update({v.symbol: "input" for v in decl.inputs})
    kinds.update({q.symbol: "parameter" for q in decl.parameters})
    kinds.update({c.symbol: "constant" for c in decl.constants})
    return ({(kinds[s], s.name) for s in used - wrong if s in kinds}
            | {("output", n) for n in right_outputs})


def _find_cycle(deps: dict[str, list[str]], order: list[str]) -> list[str] | None:
    color: dict[str, int] = {}
    stack: list[str] = []

    def visit(n):
        color[n] = 1
        stack.append(n)
        for d in deps[n]:
            if color.get(d) == 1:
                return stack[stack.index(d):] + [d]
            if color.get(d) is None:
                found = visit(d)
                if found:
                    return found
        stack.pop()
        color[n] = 2
        return None

    for n in order:
        if color.get(n) is None:
            found = visit(n)
            if found:
                return found
    return None


def _topo(deps: dict[str, list[str]], order: list[str]) -> list[str]:
    done: list[str] = []
    seen: set[str] = set()

    def visit(n):
        if n in seen:
            return
        seen.add(n)
        for d in deps[n]:
            visit(d)
        done.append(n)

    for n in order:
        visit(n)
    return done


class _Names:
    """Every declared name (states, inputs, constants, parameters, definitions), once."""

    def __init__(self):
        self.declared: dict[str, tuple[str, Located]] = {}

    def declare(self, at: Located[str], what: str) -> None:
        nm = at.value
        if nm in self.declared:
            other_what, other = self.declared[nm]
            raise SpecError(f"name `{nm}` is declared twice: as {other_what} "
                            f"({other.path.name if hasattr(other.path, 'name') else other.path}"
                            f":{other.key_line}) and as {what}", **at.key_loc,
                            text=at.key_text, hint="every name must be unique across states, "
                                                   "inputs, constants, parameters and definitions")
        self.declared[nm] = (what, at)

    def namespace(self) -> dict[str, sympy.Symbol]:
        return {nm: _sym(nm) for nm in self.declared}


# ---------------------------------------------------------------------------
# compile
# ---------------------------------------------------------------------------

def compile_spec(path) -> SymbolicModel:
    """Read, validate and compile a spec file into a :class:`SymbolicModel`.

    Raises:
        SpecError: any problem in the spec (with file, line, column and hint).
    """
    if not isinstance(path, (str, os.PathLike)):
        raise SpecError(f"compile_spec reads a spec file; got {type(path).__name__}",
                        hint="compile_spec('specs/my_aircraft.yaml')")
    if isinstance(path, str) and "\n" in path and ":" in path and not os.path.lexists(path):
        raise SpecError("compile_spec reads a spec file; got a text of several lines (the "
                        "spec itself?)", hint="write the text to a .yaml file and give its path")
    try:
        return compile_typed(read_spec(path, generator_version=GENERATOR_VERSION))
    except RecursionError:
        raise SpecError("spec is nested too deeply", path=path) from None


@dataclasses.dataclass
class _Declared:
    """The declarations of a spec, in order, with each name's physical dimension."""

    states: list[Variable]
    inputs: list[Variable]
    outputs: list[Variable]
    output_dims: dict[str, Any]
    constants: list[Constant]
    parameters: list[Parameter]
    definitions: dict[str, Equation]
    dims: dict[sympy.Symbol, Any]
    namespace: dict[str, sympy.Symbol]


def _declarations(spec: Spec, root_loc: dict) -> _Declared:
    """Declare every name once (states, inputs, constants, parameters, definitions) and
    record the variables, constants and parameters with their units."""
    names = _Names()
    dims: dict[sympy.Symbol, Any] = {}
    states, inputs, outputs = [], [], []
    output_dims: dict[str, Any] = {}
    for decls, what, bucket in ((spec.states, "state", states), (spec.inputs, "input", inputs),
                                (spec.outputs, "output", outputs)):
        for d in decls:
            nm = d.name.value
            unit = d.unit.value if d.unit is not None else None
            dim = _unit_dim(d.unit)
            if what != "output":
                names.declare(d.name, f"a {what}")
                dims[_sym(nm)] = dim
                delay = d.delay.value if d.delay is not None else 0.0
                bucket.append(Variable(nm, unit, d.description, _sym(nm), delay=float(delay)))
            else:
                output_dims[nm] = dim
                bucket.append(Variable(nm, unit, d.description, _sym(nm)))
    if not states:
        raise SpecError("the spec declares no states", **root_loc,
                        hint="add a `states:` section, e.g. `states: {V: {unit: m/s}}`")

    constants = []
    for c in spec.constants:
        names.declare(c.name, "a constant")
        dims[_sym(c.name.value)] = _unit_dim(c.unit)
        constants.append(Constant(c.name.value, c.value, c.unit.value if c.unit else None,
                                  c.source, _sym(c.name.value)))

    parameters = []
    for q in spec.parameters:
        names.declare(q.name, "a parameter")
        dims[_sym(q.name.value)] = _unit_dim(q.unit)
        lower, upper = q.bounds.value if q.bounds is not None else (None, None)
        parameters.append(Parameter(q.name.value, q.unit.value if q.unit else None, q.description,
                                    q.initial, lower, upper, q.fixed, _sym(q.name.value)))

    def_at = {e.name.value: e for e in spec.definitions}
    for e in spec.definitions:
        names.declare(e.name, "a definition")
    return _Declared(states, inputs, outputs, output_dims, constants, parameters, def_at, dims,
                     names.namespace())


#: the prefix of a stability/control derivative named after its variable: `Ldr` (L + dr),
#: `Cl_p`, `CYb`, `Mq`
_DERIVATIVE_PREFIX = re.compile(r"[A-Z][A-Za-z]?_?")


def _undeclared_hint(name: str, spec: Spec, decl: _Declared) -> str | None:
    """The hint for an unknown ``name`` in an equation when it is evidently a variable that
    was not declared (None: keep the expression parser's hint).

    A name mapped under ``data.inputs`` or ``data.outputs``, or one that declared parameters
    are named after (``dr`` with ``Ldr``, ``Ndr``: the did-you-mean would offer ``Ldr``),
    is a variable to declare; an output's name is a measurement, not a variable.
    """
    if not re.fullmatch(r"[A-Za-z]\w*", name):
        return None
    if any(o.name == name for o in decl.outputs):
        return (f"`{name}` is an output (a measurement); equations use states, inputs, "
                "constants, parameters and definitions: write the quantity it measures")
    data = spec.data
    if data is not None:
        for key, chans in (("inputs", data.inputs), ("outputs", data.outputs)):
            for ch in chans:
                if ch.name.value != name:
                    continue
                source = (f"column `{ch.column.value}`" if ch.column is not None
                          else f"`{ch.expr.value}`" if ch.expr is not None else "a column")
                if key == "inputs":
                    return (f"declare `{name}` under `inputs:` (e.g. `{name}: {{unit: ...}}`): "
                            f"`data.inputs` maps it to {source}, but it is not declared")
                return (f"`data.outputs` maps `{name}` to {source}, but it is not declared; "
                        f"declare it under `states:` or `inputs:` as fits (an output, "
                        f"declared under `outputs:`, is not used in equations)")
    if name == "e":   # the parser's hint is about Euler's number
        return None
    named_after = sorted(q.name for q in decl.parameters
                         if len(q.name) > len(name) and q.name.endswith(name)
                         and _DERIVATIVE_PREFIX.fullmatch(q.name[:-len(name)]))
    if named_after:
        listed = ", ".join(f"`{q}`" for q in named_after[:4])
        return (f"`{name}` looks like an undeclared variable (the parameter"
                f"{'s' if len(named_after) > 1 else ''} {listed} "
                f"{'are' if len(named_after) > 1 else 'is'} named after it): declare it under "
                f"`inputs:` (and map its column under `data.inputs`) or `states:` as fits")
    return None


class _Equations:
    """The equations of the three sections, each parsed once with its ``add_terms`` added;
    records where each equation is written (``locations``)."""

    def __init__(self, spec: Spec, decl: _Declared, root_loc: dict):
        self.spec, self.namespace, self.root_loc = spec, decl.namespace, root_loc
        self.decl = decl
        self.sections: dict[str, dict[str, Equation]] = {
            "definitions": decl.definitions, "drift": {e.name.value: e for e in spec.drift},
            "observations": {e.name.value: e for e in spec.observations}}
        self.locations: dict[str, Location] = {}
        self.added: dict[tuple[str, str], list[sympy.Expr]] = {}
        #: (section, name) -> [(added expression, where it is written)]
        self.added_at: dict[tuple[str, str], list[tuple[sympy.Expr, Located]]] = {}
        for a in spec.add_terms:
            target = self.sections[a.section]
            if a.term.name.value not in target:
                word = {"definitions": "definition", "drift": "drift equation for",
                        "observations": "observation equation for"}[a.section]
                raise SpecError(f"add_terms: there is no {word} `{a.term.name.value}` to add to",
                                **a.term.name.key_loc, text=a.term.name.key_text,
                                hint=did_you_mean(a.term.name.value, target) or
                                f"add_terms only extends existing {a.section} entries")
            expr = self._parse(a.term.expression)
            self.added.setdefault((a.section, a.term.name.value), []).append(expr)
            self.added_at.setdefault((a.section, a.term.name.value), []).append(
                (expr, a.term.expression))

    def _parse(self, text: Located[str]) -> sympy.Expr:
        """An equation's expression; an unknown name that is an undeclared variable gets a
        hint to declare it (not a did-you-mean towards a parameter named after it)."""
        try:
            return _expression(text, self.namespace)
        except SpecError as err:
            m = re.fullmatch(r"unknown symbol `(.+)`", err.message)
            hint = _undeclared_hint(m.group(1), self.spec, self.decl) if m else None
            if hint is None:
                raise
            raise SpecError(err.message, path=err.path, line=err.line, column=err.column,
                            text=err.text, hint=hint, span=err.span) from None

    def equation(self, section: str, e: Equation) -> sympy.Expr:
        """One equation's expression plus its added terms."""
        expr = self._parse(e.expression)
        for extra in self.added.get((section, e.name.value), []):
            expr = expr + extra
        at = e.expression
        self.locations[f"{section}:{e.name.value}"] = Location(at.path, at.line, at.column)
        return expr

    def equations(self, section: str, variables: list[Variable], what: str) -> list[sympy.Expr]:
        """Exactly one equation per declared variable, in declaration order."""
        entries = self.sections[section]
        declared = [v.name for v in variables]
        for nm, e in entries.items():
            if nm not in declared:
                raise SpecError(f"{section} equation for undeclared {what} `{nm}`", **e.name.key_loc,
                                text=e.name.key_text,
                                hint=did_you_mean(nm, declared) or f"declare `{nm}` under `{what}s`")
        out = []
        for v in variables:
            if v.name not in entries:
                where = self.spec.sections_at.get(section)
                raise SpecError(f"missing {section} equation for {what} `{v.name}`",
                                **(where.key_loc if where is not None else self.root_loc),
                                text=where.key_text if where is not None else None,
                                hint=f"add `{v.name}: <expression>` under `{section}` "
                                     f"(exactly one equation per {what})")
            out.append(self.equation(section, entries[v.name]))
        return out

    def definitions(self) -> tuple[tuple[tuple[str, sympy.Expr], ...], dict[str, list[str]]]:
        """The definitions in dependency order and each one's direct dependencies.

        Raises:
            SpecError: a definition cycle, named by its first definition.
        """
        def_at = self.sections["definitions"]
        def_syms = {nm: _sym(nm) for nm in def_at}
        exprs = {nm: self.equation("definitions", e) for nm, e in def_at.items()}
        deps = {nm: [d for d in def_at if def_syms[d] in e.free_symbols] for nm, e in exprs.items()}
        order = list(def_at)
        cycle = _find_cycle(deps, order)
        if cycle:
            first = def_at[cycle[0]].name
            raise SpecError("definition cycle: " + " -> ".join(cycle), **first.key_loc,
                            text=first.key_text,
                            hint="definitions may refer to each other, but not in a circle")
        return tuple((nm, exprs[nm]) for nm in _topo(deps, order)), deps


def _warn_unused(warnings: list, spec: Spec, definitions, deps, equations) -> None:
    """Warn about parameters, constants, inputs and definitions no drift or observation
    equation reaches (through the definition graph, nothing expanded)."""
    def_exprs = dict(definitions)
    def_syms = {nm: _sym(nm) for nm in def_exprs}
    reach: set[str] = set()
    stack = [nm for nm in def_exprs if any(def_syms[nm] in e.free_symbols for e in equations)]
    while stack:
        n = stack.pop()
        if n not in reach:
            reach.add(n)
            stack.extend(deps[n])
    used: set = set()
    for e in equations:
        used |= e.free_symbols
    for n in reach:
        used |= def_exprs[n].free_symbols
    for what, decls in (("parameter", spec.parameters), ("constant", spec.constants)):
        for d in decls:
            if _sym(d.name.value) not in used:
                _warn(warnings, f"unused {what} `{d.name.value}`", d.name, code=f"unused_{what}",
                      hint="remove it or use it in an equation")
    for d in spec.inputs:
        if _sym(d.name.value) not in used:
            _warn(warnings, f"unused input `{d.name.value}`", d.name,
                  code="unused_input", hint="remove it or use it in an equation")
    for e in spec.definitions:
        if e.name.value not in reach:
            _warn(warnings, f"unused definition `{e.name.value}`", e.name,
                  code="unused_definition", hint="no drift or observation equation depends on it")


def _noise(spec: Spec, state_names: list[str], output_names: list[str]):
    """The process-noise declaration and one measurement-noise entry per output."""
    process = ProcessNoiseSpec(states=tuple(state_names))
    if spec.process_noise is not None:
        process = _process_noise(spec.process_noise, state_names)
    measurement = {o: MeasurementNoiseSpec(o) for o in output_names}
    for m in spec.measurement_noise:
        o = m.output.value
        if o not in output_names:
            raise SpecError(f"measurement noise for undeclared output `{o}`", **m.output.key_loc,
                            text=m.output.key_text, hint=did_you_mean(o, output_names) or
                            "keys of noise.measurement are output names")
        measurement[o] = MeasurementNoiseSpec(o, m.estimate, m.std.value if m.std else None,
                                              m.floor.value if m.floor is not None else "auto")
    return process, tuple(measurement[o] for o in output_names)


def compile_typed(spec: Spec) -> SymbolicModel:
    """Compile a typed spec (:func:`vsidgen.spec.typed.read_spec`) to a :class:`SymbolicModel`.

    Phases: declarations (every name once, with its dimension) → equations (parsed in the
    declared namespace, ``add_terms`` added) → definition order (no cycles) → bounded
    expansion size → unused names (warnings) → noise and data map → dimensional check.

    Raises:
        SpecError: a name declared twice, an expression that does not parse or names an
            undeclared symbol, a definition cycle, an equation missing or for an undeclared
            variable, an oversized expansion, a noise or data entry that does not match
            the declarations, a unit that does not parse or convert.
    """
    warnings: list[SpecWarning] = []
    root_loc = {"path": spec.path, "line": 1, "column": 1}
    decl = _declarations(spec, root_loc)
    eqs = _Equations(spec, decl, root_loc)
    definitions, deps = eqs.definitions()
    drift = eqs.equations("drift", decl.states, "state")
    observations = eqs.equations("observations", decl.outputs, "output")
    _check_expanded_size(definitions, decl.definitions, drift, decl.states, observations,
                         decl.outputs, eqs.sections)
    _check_minmax(definitions, decl.definitions, drift, decl.states, observations,
                  decl.outputs, eqs.sections)
    _check_constant_singularities(decl, definitions, drift, observations, eqs.sections)
    _warn_unused(warnings, spec, definitions, deps, drift + observations)
    unit_issues: list = []
    _warn_coherence(warnings, spec, _right_as_written(decl, definitions, drift, observations,
                                                      unit_issues))
    scale_at = len(warnings)
    output_names = [o.name for o in decl.outputs]
    process, measurement = _noise(spec, [v.name for v in decl.states], output_names)
    var_units = {("input", v.name): v.unit for v in decl.inputs}
    var_units.update({("output", v.name): v.unit for v in decl.outputs})
    data = _data_spec(spec, [v.name for v in decl.inputs], output_names, root_loc, var_units,
                      warnings)
    scale_warnings: list = []
    wrong_dims = _check_dimensions(warnings, decl.dims, definitions, decl.definitions, drift,
                                   eqs.sections, decl.states, observations, decl.outputs,
                                   decl.output_dims, eqs.added_at)
    for where, name, section, what, pair in unit_issues:
        if pair is not None and (section, name, pair) in wrong_dims:
            # the same two terms disagree in dimension: that warning is the defect to fix, and
            # the two read as contradicting each other (session 47: `ay_m: V0*side/g0 + ay0`
            # was told both that `V0*side/g0` is "in coherent units" beside `ay0` in g, and
            # that it is dimensionless beside an acceleration)
            continue
        at = eqs.sections[section][name].expression
        _warn(scale_warnings, f"units in the {where}: {what}; the numbers are used as they "
              "stand", at, code="unit_scale", key=False,
              hint="write every term in one unit system (convert with pi/180, or declare the "
                   "variable in rad and convert its data column in the data map)")
    warnings[scale_at:scale_at] = scale_warnings

    return SymbolicModel(
        name=spec.name.value, description=spec.description, source_path=spec.path,
        source_hash=spec.hash,
        states=tuple(decl.states), inputs=tuple(decl.inputs), outputs=tuple(decl.outputs),
        constants=tuple(decl.constants), parameters=tuple(decl.parameters),
        definitions=definitions, drift=tuple(drift), observations=tuple(observations),
        process_noise=process, measurement_noise=measurement, data=data,
        integrator=spec.integrator, substeps=spec.substeps, input_hold=spec.input_hold,
        warnings=tuple(warnings), locations=eqs.locations, files=spec.files,
        canonical=spec.canonical)


def expanded_sizes(definitions) -> dict[sympy.Symbol, int]:
    """Tree size (nodes) of each definition with the definitions it uses substituted.

    Counted on the expression DAG with memoisation, so the cost is linear in the size
    of the written expressions even when the expanded trees are exponentially large.
    """
    sizes: dict[sympy.Basic, int] = {}
    for nm, e in definitions:
        sizes[_sym(nm)] = tree_size(e, sizes)
    return {k: v for k, v in sizes.items() if isinstance(k, sympy.Symbol)}


def _dag_fold(expr, memo: dict, combine) -> int:
    """``combine(children's values)`` folded over ``expr``'s DAG without recursion (``memo``
    maps sub-expressions to their values and may be shared between calls)."""
    stack = [(expr, False)]
    while stack:
        node, done = stack.pop()
        if node in memo:
            continue
        if done or not node.args:
            memo[node] = combine([memo[a] for a in node.args])
            continue
        stack.append((node, True))
        stack.extend((a, False) for a in node.args if a not in memo)
    return memo[expr]


def tree_size(expr, memo: dict) -> int:
    """Nodes of ``expr``'s tree, counted on its DAG (``memo`` may be shared between calls),
    so that the cost stays linear in the DAG."""
    return _dag_fold(expr, memo, lambda kids: 1 + sum(kids))


def tree_depth(expr, memo: dict) -> int:
    """Levels of ``expr``'s tree (a leaf: 1), counted on its DAG without recursion."""
    return _dag_fold(expr, memo, lambda kids: 1 + max(kids, default=0))


def _check_constant_singularities(decl, definitions, drift, observations, sections) -> None:
    """Refuse an expression that the constants' values alone make infinite or undefined
    (``1/K`` with ``K: {value: 0}``): it cannot be evaluated at any state, and it used to
    end in an internal error when the generated code was first run."""
    consts = {c.symbol: sympy.Float(c.value) for c in decl.constants}
    if not consts:
        return
    items = [("definition", nm, e, decl.definitions[nm].name, True) for nm, e in definitions]
    items += [("drift equation of", v.name, e, sections["drift"][v.name].expression, False)
              for v, e in zip(decl.states, drift)]
    items += [("observation of", v.name, e, sections["observations"][v.name].expression, False)
              for v, e in zip(decl.outputs, observations)]
    bad_values = (sympy.zoo, sympy.oo, -sympy.oo, sympy.nan)
    for what, name, e, at, key in items:
        used = [c for c in decl.constants if c.symbol in e.free_symbols]
        if not used:
            continue
        try:
            val = e.xreplace(consts)
        except (ZeroDivisionError, ValueError, TypeError):
            val = sympy.zoo
        if any(val.has(b) for b in bad_values):
            loc = at.key_loc if key else at.loc
            raise SpecError(f"{what} `{name}` is infinite or undefined for every state with the "
                            "constants' values (" + ", ".join(f"{c.name} = {c.value:g}"
                                                               for c in used) + ")",
                            **loc, text=at.key_text if key else at.text,
                            hint="a division by a constant that is 0, or log/sqrt of a constant "
                                 "outside its domain: check the constants' values")


def _check_expanded_size(definitions, def_at, drift, states, observations, outputs,
                         sections) -> None:
    """Refuse equations whose definition-expanded form exceeds :data:`MAX_EXPANDED_SIZE`.

    Code generation differentiates the expanded drift and outputs; chained definitions
    (``d2 = d1*d1 + d1`` and so on) double the expanded size at every level, so without
    this bound twelve levels take minutes. The error points at the first definition
    (or equation) that crosses the bound.
    """
    memo: dict[sympy.Basic, int] = {}
    deep: dict[sympy.Basic, int] = {}
    for nm, e in definitions:
        size = tree_size(e, memo)
        memo[_sym(nm)] = size
        depth = tree_depth(e, deep)
        deep[_sym(nm)] = depth
        if depth > MAX_EXPANDED_DEPTH:
            at = def_at[nm].name
            raise SpecError(f"definition `{nm}` is nested {depth} levels deep when the "
                            f"definitions it uses are substituted (at most {MAX_EXPANDED_DEPTH})",
                            **at.key_loc, text=at.key_text,
                            hint="a long chain of definitions each wrapping the previous one "
                                 "(d2 = sin(d1), d3 = sin(d2), ...): write the model with fewer "
                                 "levels; the generated Jacobians differentiate the expanded form")
        if size > MAX_EXPANDED_SIZE:
            at = def_at[nm].name
            raise SpecError(f"definition `{nm}` expands to {size} expression nodes when the "
                            f"definitions it uses are substituted (at most {MAX_EXPANDED_SIZE})",
                            **at.key_loc, text=at.key_text,
                            hint="the generated Jacobians differentiate the expanded equations; "
                                 "chained definitions that each use the previous one several "
                                 "times grow exponentially")
    for section, variables, exprs in (("drift", states, drift),
                                      ("observations", outputs, observations)):
        for v, e in zip(variables, exprs):
            size = tree_size(e, memo)
            depth = tree_depth(e, deep)
            if depth > MAX_EXPANDED_DEPTH:
                at = sections[section][v.name].expression
                raise SpecError(f"{section} equation of `{v.name}` is nested {depth} levels deep "
                                f"when definitions are substituted (at most {MAX_EXPANDED_DEPTH})",
                                **at.loc, text=at.text,
                                hint="use fewer chained definitions; the generated Jacobians "
                                     "differentiate the expanded form")
            if size > MAX_EXPANDED_SIZE:
                at = sections[section][v.name].expression
                raise SpecError(f"{section} equation of `{v.name}` expands to {size} expression "
                                f"nodes when definitions are substituted (at most "
                                f"{MAX_EXPANDED_SIZE})", **at.loc, text=at.text,
                                hint="the generated Jacobians differentiate the expanded "
                                     "equations; use fewer chained definitions")


def _widest_minmax(e) -> int:
    """Most arguments of a ``Min``/``Max`` node in ``e`` (0: none)."""
    return max((len(a.args) for a in sympy.preorder_traversal(e)
                if isinstance(a, (sympy.Min, sympy.Max))), default=0)


def _check_minmax(definitions, def_at, drift, states, observations, outputs,
                  sections) -> None:
    """Refuse a min/max of more than :data:`MAX_MINMAX_ARGS` arguments in an equation with
    its definitions substituted (nested min/max of one kind flatten into one)."""
    if not any(e.has(sympy.Min, sympy.Max) for _, e in definitions) and not any(
            e.has(sympy.Min, sympy.Max) for e in (*drift, *observations)):
        return
    sub: dict = {}
    hint = ("its piecewise derivatives grow combinatorially with the number of arguments; "
            "split it over definitions of fewer arguments each combined without min/max, or "
            "model the envelope differently (sat, smoothsat)")
    for nm, e in definitions:
        ex = e.xreplace(sub)
        sub[_sym(nm)] = ex
        n = _widest_minmax(ex)
        if n > MAX_MINMAX_ARGS:
            at = def_at[nm].name
            raise SpecError(f"definition `{nm}` takes the min/max of {n} arguments when the "
                            f"definitions it uses are substituted (at most {MAX_MINMAX_ARGS})",
                            **at.key_loc, text=at.key_text, hint=hint)
    for section, variables, exprs in (("drift", states, drift),
                                      ("observations", outputs, observations)):
        for v, e in zip(variables, exprs):
            n = _widest_minmax(e.xreplace(sub))
            if n > MAX_MINMAX_ARGS:
                at = sections[section][v.name].expression
                raise SpecError(f"{section} equation of `{v.name}` takes the min/max of {n} "
                                f"arguments when definitions are substituted (at most "
                                f"{MAX_MINMAX_ARGS})", **at.loc, text=at.text, hint=hint)


def _number_map(entries, allowed: list[str], what: str) -> dict:
    out = {}
    for k, v in entries:
        if k.value not in allowed:
            raise SpecError(f"{what}: `{k.value}` is not a state with process noise", **k.key_loc,
                            text=k.key_text, hint=did_you_mean(k.value, allowed) or
                            "list the state under noise.process.states")
        if v.value < 0:
            raise SpecError(f"{what} of `{k.value}` must be >= 0", **v.loc, text=v.text)
        out[k.value] = v.value
    return out


def _process_noise(decl, state_names: list[str]) -> ProcessNoiseSpec:
    names = list(state_names)
    if decl.states is not None:
        names = []
        for item in decl.states.value:
            nm = item.value
            if nm not in state_names:
                raise SpecError(f"noise.process.states: `{nm}` is not a state", **item.loc,
                                text=item.text, hint=did_you_mean(nm, state_names))
            if nm in names:
                raise SpecError(f"noise.process.states: `{nm}` is listed twice", **item.loc,
                                text=item.text)
            names.append(nm)
    structure = decl.structure.value if decl.structure is not None else "diagonal"
    std = _number_map(decl.std, names, "process noise std")
    floor = _number_map(decl.floor, names, "process noise floor")
    return ProcessNoiseSpec(tuple(names), structure, decl.estimate, std, floor,
                            _degenerate(decl, names, state_names, structure))


def _degenerate(decl, names: list[str], state_names: list[str], structure: str) -> tuple[str, ...]:
    """``noise.process.degenerate``: states with process noise, after the first one in state
    order, under ``structure: full`` with estimated noise."""
    out: list[str] = []
    noisy = [s for s in state_names if s in names]
    for item in decl.degenerate:
        nm = item.value
        if structure != "full" or not decl.estimate:
            raise SpecError("noise.process.degenerate needs `structure: full` and estimated process "
                            "noise", **item.loc, text=item.text,
                            hint="a degenerate state's noise is a combination of other states' "
                                 "noise sources: only a full factor can express that")
        if nm not in names:
            raise SpecError(f"noise.process.degenerate: `{nm}` is not a state with process noise",
                            **item.loc, text=item.text, hint=did_you_mean(nm, names) or
                            "list the state under noise.process.states")
        if nm in out:
            raise SpecError(f"noise.process.degenerate: `{nm}` is listed twice", **item.loc,
                            text=item.text)
        if nm == noisy[0]:
            raise SpecError(f"noise.process.degenerate: `{nm}` is the first state with process noise "
                            "(state order), so no earlier noise source can drive it", **item.loc,
                            text=item.text,
                            hint="a state without any process noise is left out of "
                                 "noise.process.states instead")
        out.append(nm)
    return tuple(s for s in noisy if s in out)


def _unit_conversion(name: str, what: str, unit: Located[str], spec_unit: str | None):
    """(declared data unit, (a, b)) of a data map's ``unit:`` entry, checked against the spec."""
    from . import dataunits

    data_unit = unit.value
    try:
        dataunits.check_unit(data_unit)
    except dataunits.UnitConversionError as exc:
        raise SpecError(f"data map of {what} `{name}`: {exc}", **unit.loc, text=unit.text,
                        hint="units are read by pint: e.g. rad, deg, deg/s, m/s, ft, ft/s, kt, "
                             "m/s^2, g (gravity), N, lbf, Pa, K, 1") from None
    if spec_unit is None:
        raise SpecError(f"data map of {what} `{name}` declares unit `{data_unit}` but the spec "
                        f"declares no unit for `{name}`", **unit.loc, text=unit.text,
                        hint=f"add `unit:` to {what} `{name}` (the unit the model works in)")
    try:
        conv = dataunits.conversion(data_unit, spec_unit)
    except dataunits.UnitConversionError as exc:
        raise SpecError(f"data map of {what} `{name}`: unit {exc}", **unit.loc, text=unit.text,
                        hint=f"{what} `{name}` is declared in `{spec_unit}`: the column must have "
                             "the same dimension (angles are dimensionless)") from None
    return data_unit, conv


def _time_scale(unit: Located[str]) -> tuple[str, float]:
    """(unit, seconds per unit) of ``data.time``'s ``unit:`` entry."""
    from . import dataunits

    try:
        a, _ = dataunits.conversion(unit.value, "s")
    except dataunits.UnitConversionError as exc:
        raise SpecError(f"unit of the time column: {exc}", **unit.loc, text=unit.text,
                        hint="a unit of time: s, ms, us, min") from None
    return unit.value, a


def _channel(ch: ChannelDecl, what: str = "input", spec_unit: str | None = None) -> ChannelMap:
    name = ch.name.value
    if ch.bare:
        return ChannelMap(name, column=ch.column.value, columns=(ch.column.value,))
    unit, conv = None, (1.0, 0.0)
    if ch.unit is not None:
        unit, conv = _unit_conversion(name, what, ch.unit, spec_unit)
    if (ch.column is None) == (ch.expr is None):
        raise SpecError(f"data mapping of `{name}` needs exactly one of `column` or `expr`",
                        **ch.at.key_loc, text=ch.at.key_text,
                        hint="e.g. {column: de_rad} or {expr: \"(a_rad - b_rad)/2\"}")
    if ch.column is not None:
        col = ch.column.value
        return ChannelMap(name, column=col, scale=ch.scale, offset=ch.offset, columns=(col,),
                          unit=unit, unit_conversion=conv)
    expr, cols = _expression(ch.expr, {}, free_names=True)
    return ChannelMap(name, column=None, scale=ch.scale, offset=ch.offset, expr=expr, columns=cols,
                      unit=unit, unit_conversion=conv)


#: warnings about how the data map reads the records (a column named in another unit, or
#: of another dimension): printed by ``fit`` and ``diagnose`` too, not only by ``check``
DATA_MAP_WARNING_CODES = ("column_unit_suffix", "column_other_dimension")


def data_map_warnings(symbolic) -> list:
    """The spec's warnings about its data map (:data:`DATA_MAP_WARNING_CODES`)."""
    return [w for w in getattr(symbolic, "warnings", ()) if w.code in DATA_MAP_WARNING_CODES]


def _warn_column_suffix(warnings: list, ch: ChannelDecl, what: str, spec_unit) -> None:
    """Warn when a column's name states a unit of the spec unit's dimension but another scale
    (``alpha: alpha_deg`` for an angle in rad) and the entry converts nothing (no ``unit``,
    ``scale`` 1, ``offset`` 0): the values would be read as if in the spec's unit."""
    from . import dataunits

    if ch.column is None:
        return
    if ch.unit is not None:
        # `alpha: {column: alpha_rad, unit: deg}`: the declared unit contradicts the name
        named = dataunits.suffix_mismatch(ch.column.value, ch.unit.value)
        if named is not None:
            _warn(warnings, f"column `{ch.column.value}` of {what} `{ch.name.value}` is named in "
                  f"`{named}`, but the data map declares it in `{ch.unit.value}`: its values are "
                  f"converted from `{ch.unit.value}`", ch.unit, key=False, code="column_unit_suffix",
                  hint=f"declare `unit: {named}` if the name is right (or rename the column if it "
                       "misleads)")
        return
    name, col = ch.name.value, ch.column.value
    # a scale of magnitude other than 1 may carry a unit of its own: `nz: {column: az_mps2,
    # scale: -0.10197162}` (−1/g) reads a load factor from an acceleration, as documented;
    # a bare sign flip (scale −1) converts nothing and is still checked
    other = (dataunits.suffix_other_dimension(col, spec_unit)
             if abs(abs(ch.scale) - 1.0) <= 1e-12 else None)
    if other is not None:
        _warn(warnings, f"column `{col}` of {what} `{name}` is named in `{other}` "
              f"({dataunits.dimensionality(other)}), but `{name}` is in `{spec_unit}` "
              f"({dataunits.dimensionality(spec_unit)}): a wrong column?", ch.column, key=False,
              code="column_other_dimension",
              hint=f"map `{name}` to the column that records it (or rename the column if its "
                   f"name misleads)")
        return
    if ch.scale != 1.0 or ch.offset != 0.0:
        return
    named = dataunits.suffix_mismatch(col, spec_unit)
    if named is None:
        return
    shown = dataunits.yaml_name(col)
    _warn(warnings, f"column `{col}` of {what} `{name}` is named in `{named}`, but `{name}` is "
          f"in `{spec_unit}` and the data map converts nothing: its values are read as "
          f"`{spec_unit}`", ch.column, key=False, code="column_unit_suffix",
          hint=f"declare the column's unit, converted on reading: `{name}: {{column: {shown}, "
               f"unit: {named}}}` (or `unit: {spec_unit}` if the name misleads)")


def _warn_expr_suffix(warnings: list, ch: ChannelDecl, cm: ChannelMap, what: str, spec_unit) -> None:
    """:func:`_warn_column_suffix` for an ``expr`` entry: every column it reads is named in one
    unit of the spec unit's dimension but another scale (``da: {expr: "(da_r_rad - da_l_rad)/2"}``
    for an aileron in deg), the expression is linear in them with no coefficient (nor sum of
    coefficients' magnitudes) equal to that conversion's factor within 2 % (``alpha_rad*57.2958``
    converts), and the entry declares no unit, scale or offset: its values are read unconverted."""
    from . import dataunits

    if (ch.expr is None or ch.unit is not None or ch.scale != 1.0 or ch.offset != 0.0
            or cm.expr is None or not spec_unit):
        return
    cols = cm.source_columns()
    named = {dataunits.suffix_mismatch(c, spec_unit) for c in cols}
    if len(named) != 1 or None in named:
        return
    named = named.pop()
    try:
        a, _ = dataunits.conversion(named, spec_unit)
    except ValueError:
        return
    syms = sorted(cm.expr.free_symbols, key=str)
    zero = {sym: 0 for sym in syms}
    coefs = []
    for sym in syms:
        c = sympy.diff(cm.expr, sym)
        if c.free_symbols or not c.is_number:
            return                                   # not linear in its columns
        coefs.append(abs(float(c)))
    if not coefs or cm.expr.xreplace(zero) != 0:
        return
    if any(abs(c / abs(a) - 1.0) < 0.02 for c in coefs + [sum(coefs)]):
        return                                       # the expression converts
    _warn(warnings, f"expression of {what} `{ch.name.value}` reads columns named in `{named}`, but "
          f"`{ch.name.value}` is in `{spec_unit}` and the data map converts nothing: its values "
          f"are read as `{spec_unit}`", ch.expr, key=False, code="column_unit_suffix",
          hint=f"declare the columns' unit, converted on reading: add `unit: {named}` to the "
               f"entry of `{ch.name.value}` (or `unit: {spec_unit}` if the names mislead)")


def _data_spec(spec: Spec, input_names, output_names, root_loc,
               units: Mapping[tuple[str, str], str | None] | None = None,
               warnings: list | None = None) -> DataSpec:
    data = spec.data
    if data is None:
        if input_names or output_names:
            raise SpecError("the spec has no `data` mapping", **root_loc,
                            hint="add `data: {time: t_s, inputs: {...}, outputs: {...}}` mapping "
                                 "every input and output to CSV columns")
        return DataSpec()
    result = {}
    for key, names, chans, sub_at in (("inputs", input_names, data.inputs, data.inputs_at),
                                      ("outputs", output_names, data.outputs, data.outputs_at)):
        what = key[:-1]
        given = {c.name.value: c for c in chans}
        for nm, ch in given.items():
            if nm not in names:
                raise SpecError(f"data mapping for unknown {what} `{nm}`", **ch.name.key_loc,
                                text=ch.name.key_text,
                                hint=did_you_mean(nm, names) or f"declare `{nm}` under `{key}`")
        out = []
        for nm in names:
            if nm not in given:
                where = sub_at if sub_at is not None else data.at
                raise SpecError(f"{what} `{nm}` is not mapped to a data column", **where.key_loc,
                                text=where.key_text,
                                hint=f"add `{nm}: <column name>` under `data.{key}`")
            out.append(_channel(given[nm], what, (units or {}).get((what, nm))))
            if warnings is not None:
                _warn_column_suffix(warnings, given[nm], what, (units or {}).get((what, nm)))
                _warn_expr_suffix(warnings, given[nm], out[-1], what, (units or {}).get((what, nm)))
        result[key] = tuple(out)
    time_unit, time_scale = None, 1.0
    if data.time_unit is not None:
        time_unit, time_scale = _time_scale(data.time_unit)
    return DataSpec(data.time, result["inputs"], result["outputs"], time_scale=time_scale,
                    time_unit=time_unit)


def _dimension_hint(issue: "_units.DimensionIssue") -> str:
    """The hint of a dimension warning; a load factor (an acceleration divided by g) beside an
    acceleration gets its own, since declaring a quantity in `g` makes it an acceleration."""
    accel = _units.parse_unit("m/s^2")
    pair = (issue.dimension, issue.expected)
    if issue.other is not None and any(
            _units.same(a, _units.ONE) and _units.same(b, accel) for a, b in (pair, pair[::-1])):
        return ("an acceleration divided by g (g0, 9.81) is a load factor, dimension 1, while a "
                "quantity declared in `g` is an acceleration: write every term in m/s^2 (no "
                "division by g; a data column in g is converted by the data map, `{column: NAME, "
                "unit: g}`), or every term as a load factor (declared without a unit)")
    return "check the units of the symbols in this term"


def _check_dimensions(warnings, dims, definitions, def_at, drift, sections, states,
                      observations, outputs, output_dims, added_at=None) -> set:
    """Warn where the terms of an equation disagree in dimension, or an equation's dimension is
    not its left-hand side's; returns ``{(section, name, {term, other})}`` of the pairs of terms
    that disagree."""
    dims = dict(dims)
    seen: set[str] = set()
    added_at = added_at or {}
    pairs: set = set()

    def reporter(where: str, at: Located, key: tuple[str, str]):
        def report(issue: _units.DimensionIssue):
            if issue.other is not None:
                pairs.add((*key, frozenset((str(issue.term), str(issue.other)))))
            msg = f"inconsistent units in {where}: {issue.message()}"
            if msg in seen:
                return
            seen.add(msg)
            here = at
            for added, loc in added_at.get(key, ()):
                # a term of an `add_terms` entry is shown where it is written (the warning
                # quoted the parent's equation, which does not hold it; session 46)
                terms = sympy.Add.make_args(added)
                if issue.term in terms or (issue.other is not None and issue.other in terms):
                    here, msg = loc, msg + " (a term added by `add_terms`)"
                    break
            _warn(warnings, msg, here, code="units", key=False, hint=_dimension_hint(issue))
        return report

    for nm, expr in definitions:
        at = def_at[nm].expression
        dims[_sym(nm)] = _units.dimension_of(expr, dims, reporter(f"definition `{nm}`", at,
                                                                  ("definitions", nm)))
    for v, expr in zip(states, drift):
        at = sections["drift"][v.name].expression
        d = _units.dimension_of(expr, dims, reporter(f"drift of `{v.name}`", at,
                                                     ("drift", v.name)))
        want = dims.get(v.symbol)
        if d is not None and want is not None:
            want = _units.Dimension(want.name / _units.time.name)
            if not _units.same(d, want):
                _warn(warnings, f"inconsistent units in drift of `{v.name}`: the expression has "
                      f"dimension {_units.show(d)} but d{v.name}/dt must have dimension "
                      f"{_units.show(want)} (unit({v.name})/s)", at, code="units", key=False)
    for o, expr in zip(outputs, observations):
        at = sections["observations"][o.name].expression
        d = _units.dimension_of(expr, dims, reporter(f"observation of `{o.name}`", at,
                                                     ("observations", o.name)))
        want = output_dims.get(o.name)
        if d is not None and want is not None and not _units.same(d, want):
            _warn(warnings, f"inconsistent units in observation of `{o.name}`: the expression has "
                  f"dimension {_units.show(d)} but output `{o.name}` has dimension "
                  f"{_units.show(want)}", at, code="units", key=False)
    return pairs
