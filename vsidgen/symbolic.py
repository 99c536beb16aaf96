"""SymbolicModel: a validated spec as sympy expressions.

:func:`compile_spec` loads a spec (:mod:`vsidgen.spec`), parses every
expression with the safe parser (:mod:`vsidgen.expr`), validates the model
(declarations, equations, definition cycles, bounds, noise, data mapping) and
checks dimensional consistency (:mod:`vsidgen.units`). The model is

    dx/dt = f(x, u, θ)     (``drift``, one expression per state)
    y     = h(x, u, θ)     (``observations``, one per output)

where f and h may use the ordered ``definitions`` (intermediate quantities);
:meth:`SymbolicModel.drift_expanded` substitutes them.
"""

from __future__ import annotations

import dataclasses
import pathlib
import re
from collections.abc import Mapping
from typing import Any

import sympy

from .errors import Location, SpecError, SpecWarning
from .expr import FUNCTIONS, did_you_mean
from .metadata import (ChannelMap, Constant, DataSpec, MeasurementNoiseSpec, Parameter,
                       ProcessNoiseSpec, Variable)
from .spec import RawSpec, YNode, keys_check, load_spec
from . import __version__
from . import units as _units

#: the generated modules record it; a new vsidgen version rebuilds them
GENERATOR_VERSION = __version__

_NAME_RE = re.compile(r"[A-Za-z][A-Za-z0-9_]*")
#: most nodes of one drift/observation equation with its definitions substituted (the
#: shipped specs need at most 77; building a 12000-node one took 11 s on a loaded 2-core machine)
MAX_EXPANDED_SIZE = 10_000
#: longest name (model, state, input, output, parameter, constant, definition) accepted
MAX_NAME_LENGTH = 64

#: names the generated module defines or imports (no spec name may equal one of them;
#: every other name the module uses itself starts with ``_``, which spec names cannot)
GENERATED_MODULE_NAMES = frozenset({
    "jnp", "drift", "output", "drift_jac_x", "drift_jac_u", "drift_jac_p", "output_jac_x",
    "output_jac_u", "output_jac_p", "STATES", "INPUTS", "OUTPUTS", "PARAMETERS", "SPEC_PATH",
    "SPEC_HASH", "GENERATOR_VERSION",
})


def valid_name(name: str) -> bool:
    """True for an ASCII letter followed by letters, digits and ``_``, at most
    :data:`MAX_NAME_LENGTH` characters (the whole string: no trailing line break)."""
    return (isinstance(name, str) and len(name) <= MAX_NAME_LENGTH
            and _NAME_RE.fullmatch(name) is not None)

__all__ = ["GENERATOR_VERSION", "SymbolicModel", "Variable", "Constant", "Parameter",
           "ProcessNoiseSpec", "MeasurementNoiseSpec", "ChannelMap", "DataSpec",
           "compile_spec"]


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


# ---------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------

def _sym(name: str) -> sympy.Symbol:
    return sympy.Symbol(name, real=True)


def _check_name(name: str, node: YNode, what: str) -> None:
    if not valid_name(name):
        raise SpecError(f"invalid {what} name {_show_name(name)}", **node.key_loc,
                        text=_key_text(node),
                        hint="names start with an ASCII letter and contain only letters, digits "
                             f"and _ (at most {MAX_NAME_LENGTH} characters)")
    if name in GENERATED_MODULE_NAMES:
        raise SpecError(f"{what} name `{name}` is reserved by the generated module",
                        **node.key_loc, text=_key_text(node),
                        hint="choose another name (reserved: "
                             + ", ".join(sorted(GENERATED_MODULE_NAMES)) + ")")
    if name in FUNCTIONS:
        raise SpecError(f"{what} name `{name}` is the name of a built-in function", **node.key_loc,
                        text=_key_text(node), hint="choose another name")


def _show_name(name) -> str:
    """A name for a message: repr-escaped (no line breaks), cut at 40 characters."""
    shown = repr(str(name))[1:-1]
    return "`" + (shown[:40] + "..." if len(shown) > 40 else shown) + "`"


def _key_text(node: YNode) -> str:
    lines = node.src.splitlines()
    ln = node.key_line or node.line
    return lines[ln - 1].strip() if 1 <= ln <= len(lines) else ""


def _warn(warnings: list, message: str, node: YNode | None, *, code: str, hint: str = "",
          key: bool = True) -> None:
    if node is None:
        warnings.append(SpecWarning(message, code=code, hint=hint))
        return
    loc = node.key_loc if key else node.loc
    warnings.append(SpecWarning(message, path=loc["path"], line=loc["line"], column=loc["column"],
                                text=_key_text(node) if key else node.source_line(),
                                hint=hint, code=code))


def _variables(raw: RawSpec, key: str, what: str) -> list[tuple[str, YNode, dict]]:
    out = []
    for name, node in raw.section(key).items():
        _check_name(name, node, what)
        if node.kind == "scalar" and node.value is None:
            fields = {}
        elif node.kind == "scalar" and isinstance(node.value, str) and key != "constants":
            raise SpecError(f"{what} `{name}` must be a mapping like {{unit: m/s, description: ...}}",
                            **node.loc, text=node.source_line(),
                            hint="write `{unit: \"...\", description: \"...\"}`")
        else:
            fields = node.expect_map(f"{what} `{name}`") if node.kind != "scalar" else {}
        out.append((name, node, fields))
    return out


def _unit_of(fields: dict, what: str):
    node = fields.get("unit")
    if node is None or (node.kind == "scalar" and node.value is None):
        return None, None
    text = node.text if node.kind == "scalar" else None
    if text is None:
        node.string(f"unit of {what}")
    if not text.isprintable():
        raise SpecError(f"unit of {what} contains a line break or another non-printable "
                        "character", **node.loc, text=node.source_line(),
                        hint="write the unit on one line, e.g. m/s^2")
    try:
        dim = _units.parse_unit(text, path=node.path, line=1, column=1)
    except SpecError as err:
        raise node.relocate(err) from None
    return text, dim


def _desc(fields: dict, what: str) -> str:
    node = fields.get("description")
    if node is None or (node.kind == "scalar" and node.value is None):
        return ""
    return node.string(f"description of {what}")


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


# ---------------------------------------------------------------------------
# compile
# ---------------------------------------------------------------------------

def compile_spec(path) -> SymbolicModel:
    """Load, validate and compile a spec file into a :class:`SymbolicModel`.

    Raises:
        SpecError: any problem in the spec (with file, line, column and hint).
    """
    try:
        return _compile(path)
    except RecursionError:
        raise SpecError("spec is nested too deeply", path=path) from None


def _compile(path) -> SymbolicModel:
    raw = load_spec(path)
    top = raw.top
    warnings: list[SpecWarning] = []
    root_loc = {"path": raw.path, "line": 1, "column": 1}

    # name / description / integrator ------------------------------------------------
    if "name" not in top:
        raise SpecError("the spec has no `name`", **root_loc,
                        hint="add `name: mymodel` (the generated module is generated/<name>.py)")
    name = top["name"].string("`name`")
    if not valid_name(name):
        raise SpecError(f"invalid model name {_show_name(name)}", **top["name"].loc,
                        text=top["name"].source_line(),
                        hint="use an ASCII letter, then letters, digits and _, at most "
                             f"{MAX_NAME_LENGTH} characters (it becomes a Python module name)")
    description = ""
    if "description" in top and top["description"].value is not None:
        description = top["description"].string("`description`")
    method, substeps = "euler", 1
    if "integrator" in top:
        integ = keys_check(top["integrator"], ("method", "substeps"), "`integrator`")
        if "method" in integ:
            method = integ["method"].string("integrator method")
            if method not in ("euler", "rk4"):
                raise SpecError(f"unknown integrator method `{method}`", **integ["method"].loc,
                                text=integ["method"].source_line(),
                                hint=did_you_mean(method, ("euler", "rk4")) or "use euler or rk4")
        if "substeps" in integ:
            n = integ["substeps"]
            if n.kind != "scalar" or isinstance(n.value, bool) or not isinstance(n.value, int) \
                    or n.value < 1:
                raise SpecError("integrator substeps must be an integer >= 1", **n.loc,
                                text=n.source_line())
            substeps = n.value

    # declarations -----------------------------------------------------------------
    declared: dict[str, tuple[str, YNode]] = {}

    def declare(nm: str, what: str, node: YNode):
        if nm in declared:
            other_what, other = declared[nm]
            raise SpecError(f"name `{nm}` is declared twice: as {other_what} "
                            f"({other.path.name if hasattr(other.path, 'name') else other.path}"
                            f":{other.key_line}) and as {what}", **node.key_loc,
                            text=_key_text(node), hint="every name must be unique across states, "
                                                       "inputs, constants, parameters and definitions")
        declared[nm] = (what, node)

    dims: dict[sympy.Symbol, Any] = {}
    states, inputs, outputs = [], [], []
    output_dims: dict[str, Any] = {}
    for key, what, bucket in (("states", "state", states), ("inputs", "input", inputs),
                              ("outputs", "output", outputs)):
        for nm, node, fields in _variables(raw, key, what):
            keys_check(node, ("unit", "description"), f"{what} `{nm}`") if node.kind == "map" else None
            unit, dim = _unit_of(fields, f"{what} `{nm}`")
            if key != "outputs":
                declare(nm, f"a {what}", node)
                dims[_sym(nm)] = dim
                bucket.append(Variable(nm, unit, _desc(fields, nm), _sym(nm)))
            else:
                output_dims[nm] = dim
                bucket.append(Variable(nm, unit, _desc(fields, nm), _sym(nm)))
    if not states:
        raise SpecError("the spec declares no states", **root_loc,
                        hint="add a `states:` section, e.g. `states: {V: {unit: m/s}}`")

    constants = []
    const_nodes: dict[str, YNode] = {}
    for nm, node in raw.section("constants").items():
        _check_name(nm, node, "constant")
        declare(nm, "a constant", node)
        if node.kind == "scalar":
            value = node.number(f"constant `{nm}`")
            fields = {}
        else:
            fields = keys_check(node, ("value", "unit", "source", "description"), f"constant `{nm}`")
            if "value" not in fields:
                raise SpecError(f"constant `{nm}` has no `value`", **node.key_loc,
                                text=_key_text(node), hint="write `{value: 9.80665, unit: m/s^2}`")
            value = fields["value"].number(f"value of constant `{nm}`")
        unit, dim = _unit_of(fields, f"constant `{nm}`")
        dims[_sym(nm)] = dim
        source = ""
        if "source" in fields and fields["source"].value is not None:
            source = fields["source"].string(f"source of constant `{nm}`")
        constants.append(Constant(nm, value, unit, source, _sym(nm)))
        const_nodes[nm] = node

    parameters = []
    param_nodes: dict[str, YNode] = {}
    for nm, node in raw.section("parameters").items():
        _check_name(nm, node, "parameter")
        declare(nm, "a parameter", node)
        fields: dict = {}
        initial = 0.0
        init_node = None
        if node.kind == "scalar" and node.value is not None:
            initial = node.number(f"initial value of parameter `{nm}`")
            init_node = node
        elif node.kind != "scalar":
            fields = keys_check(node, ("unit", "description", "initial", "bounds", "fixed"),
                                f"parameter `{nm}`")
            if "initial" in fields:
                init_node = fields["initial"]
                initial = init_node.number(f"initial value of parameter `{nm}`")
        lower = upper = None
        if "bounds" in fields:
            b = fields["bounds"]
            if b.kind != "seq" or len(b.value) != 2:
                raise SpecError(f"bounds of parameter `{nm}` must be a list [lower, upper]", **b.loc,
                                text=b.source_line(), hint="use null for an open side: [0, null]")
            lower = b.value[0].number(f"lower bound of `{nm}`", allow_none=True)
            upper = b.value[1].number(f"upper bound of `{nm}`", allow_none=True)
            if lower is not None and upper is not None and lower >= upper:
                raise SpecError(f"bounds of parameter `{nm}`: lower {lower:g} >= upper {upper:g}",
                                **b.loc, text=b.source_line(), hint="write [lower, upper] with lower < upper")
            if (lower is not None and initial < lower) or (upper is not None and initial > upper):
                where = init_node or b
                raise SpecError(f"initial value {initial:g} of parameter `{nm}` is outside its bounds "
                                f"[{'-inf' if lower is None else format(lower, 'g')}, "
                                f"{'inf' if upper is None else format(upper, 'g')}]",
                                **where.loc, text=where.source_line(),
                                hint="set `initial` inside the bounds"
                                     + (" (the default initial value is 0)" if init_node is None else ""))
        fixed = fields["fixed"].boolean(f"`fixed` of parameter `{nm}`") if "fixed" in fields else False
        unit, dim = _unit_of(fields, f"parameter `{nm}`")
        dims[_sym(nm)] = dim
        parameters.append(Parameter(nm, unit, _desc(fields, nm), initial, lower, upper, fixed, _sym(nm)))
        param_nodes[nm] = node

    def_nodes = raw.section("definitions")
    for nm, node in def_nodes.items():
        _check_name(nm, node, "definition")
        declare(nm, "a definition", node)

    namespace = {nm: _sym(nm) for nm in declared}
    def_syms = {nm: _sym(nm) for nm in def_nodes}

    # add_terms --------------------------------------------------------------------
    added: dict[tuple[str, str], list[sympy.Expr]] = {}
    sections = {"definitions": def_nodes, "drift": raw.section("drift"),
                "observations": raw.section("observations")}
    for term in raw.add_terms:
        target = sections[term.section]
        if term.name not in target:
            word = {"definitions": "definition", "drift": "drift equation for",
                    "observations": "observation equation for"}[term.section]
            raise SpecError(f"add_terms: there is no {word} `{term.name}` to add to",
                            **term.node.key_loc, text=_key_text(term.node),
                            hint=did_you_mean(term.name, target) or
                            f"add_terms only extends existing {term.section} entries")
        added.setdefault((term.section, term.name), []).append(term.node.expression(namespace))

    locations: dict[str, Location] = {}

    def equation(section: str, nm: str, node: YNode) -> sympy.Expr:
        expr = node.expression(namespace)
        for extra in added.get((section, nm), []):
            expr = expr + extra
        locations[f"{section}:{nm}"] = Location(node.path, node.line, node.column)
        return expr

    # definitions ------------------------------------------------------------------
    def_exprs = {nm: equation("definitions", nm, node) for nm, node in def_nodes.items()}
    deps = {nm: [d for d in def_nodes if def_syms[d] in e.free_symbols] for nm, e in def_exprs.items()}
    order = list(def_nodes)
    cycle = _find_cycle(deps, order)
    if cycle:
        first = def_nodes[cycle[0]]
        raise SpecError("definition cycle: " + " -> ".join(cycle), **first.key_loc,
                        text=_key_text(first),
                        hint="definitions may refer to each other, but not in a circle")
    topo = _topo(deps, order)
    definitions = tuple((nm, def_exprs[nm]) for nm in topo)

    # drift / observations ---------------------------------------------------------
    def equations(section: str, variables: list[Variable], what: str) -> list[sympy.Expr]:
        nodes = sections[section]
        names = [v.name for v in variables]
        for nm, node in nodes.items():
            if nm not in names:
                raise SpecError(f"{section} equation for undeclared {what} `{nm}`", **node.key_loc,
                                text=_key_text(node),
                                hint=did_you_mean(nm, names) or f"declare `{nm}` under `{what}s`")
        out = []
        for v in variables:
            if v.name not in nodes:
                where = top.get(section)
                loc = where.key_loc if where is not None else root_loc
                raise SpecError(f"missing {section} equation for {what} `{v.name}`", **loc,
                                text=_key_text(where) if where is not None else None,
                                hint=f"add `{v.name}: <expression>` under `{section}` "
                                     f"(exactly one equation per {what})")
            out.append(equation(section, v.name, nodes[v.name]))
        return out

    drift = equations("drift", states, "state")
    observations = equations("observations", outputs, "output")

    # size of the definition-expanded equations (bounded before anything expands) -----
    _check_expanded_size(definitions, def_nodes, drift, states, observations, outputs, sections)

    # unused symbols (through the definition graph, nothing expanded) -------------
    reach: set[str] = set()
    stack = [nm for nm in def_nodes if any(def_syms[nm] in e.free_symbols for e in drift + observations)]
    while stack:
        n = stack.pop()
        if n not in reach:
            reach.add(n)
            stack.extend(deps[n])
    used: set = set()
    for e in drift + observations:
        used |= e.free_symbols
    for n in reach:
        used |= def_exprs[n].free_symbols
    for what, items, nodes in (("parameter", [p.name for p in parameters], param_nodes),
                               ("constant", [c.name for c in constants], const_nodes)):
        for nm in items:
            if _sym(nm) not in used:
                _warn(warnings, f"unused {what} `{nm}`", nodes[nm], code=f"unused_{what}",
                      hint="remove it or use it in an equation")
    for v in inputs:
        if v.symbol not in used:
            _warn(warnings, f"unused input `{v.name}`", raw.section("inputs")[v.name],
                  code="unused_input", hint="remove it or use it in an equation")
    for nm, node in def_nodes.items():
        if nm not in reach:
            _warn(warnings, f"unused definition `{nm}`", node, code="unused_definition",
                  hint="no drift or observation equation depends on it")

    # noise ------------------------------------------------------------------------
    state_names = [s.name for s in states]
    output_names = [o.name for o in outputs]
    process = ProcessNoiseSpec(states=tuple(state_names))
    measurement = {o: MeasurementNoiseSpec(o) for o in output_names}
    if "noise" in top:
        noise = keys_check(top["noise"], ("process", "measurement"), "`noise`")
        if "process" in noise:
            process = _process_noise(noise["process"], state_names)
        if "measurement" in noise:
            for o, node in noise["measurement"].expect_map("`noise.measurement`").items():
                if o not in output_names:
                    raise SpecError(f"measurement noise for undeclared output `{o}`", **node.key_loc,
                                    text=_key_text(node), hint=did_you_mean(o, output_names) or
                                    "keys of noise.measurement are output names")
                measurement[o] = _measurement_noise(o, node)

    # data -------------------------------------------------------------------------
    var_units = {("input", v.name): v.unit for v in inputs}
    var_units.update({("output", v.name): v.unit for v in outputs})
    data = _data_spec(top.get("data"), [v.name for v in inputs], output_names, root_loc, var_units)

    # units ------------------------------------------------------------------------
    _check_dimensions(warnings, dims, definitions, def_nodes, drift, sections, states,
                      observations, outputs, output_dims)

    return SymbolicModel(
        name=name, description=description, source_path=raw.path,
        source_hash=raw.hash(GENERATOR_VERSION),
        states=tuple(states), inputs=tuple(inputs), outputs=tuple(outputs),
        constants=tuple(constants), parameters=tuple(parameters), definitions=definitions,
        drift=tuple(drift), observations=tuple(observations), process_noise=process,
        measurement_noise=tuple(measurement[o] for o in output_names), data=data,
        integrator=method, substeps=substeps, warnings=tuple(warnings), locations=locations,
        files=raw.files, canonical=raw.canonical())


def expanded_sizes(definitions) -> dict[sympy.Symbol, int]:
    """Tree size (nodes) of each definition with the definitions it uses substituted.

    Counted on the expression DAG with memoisation, so the cost is linear in the size
    of the written expressions even when the expanded trees are exponentially large.
    """
    sizes: dict[sympy.Basic, int] = {}
    for nm, e in definitions:
        sizes[_sym(nm)] = _tree_size(e, sizes)
    return {k: v for k, v in sizes.items() if isinstance(k, sympy.Symbol)}


def _tree_size(expr, memo: dict) -> int:
    stack = [(expr, False)]
    while stack:
        node, done = stack.pop()
        if node in memo:
            continue
        if done or not node.args:
            memo[node] = 1 + sum(memo[a] for a in node.args)
            continue
        stack.append((node, True))
        stack.extend((a, False) for a in node.args if a not in memo)
    return memo[expr]


def _check_expanded_size(definitions, def_nodes, drift, states, observations, outputs,
                         sections) -> None:
    """Refuse equations whose definition-expanded form exceeds :data:`MAX_EXPANDED_SIZE`.

    Code generation differentiates the expanded drift and outputs; chained definitions
    (``d2 = d1*d1 + d1`` and so on) double the expanded size at every level, so without
    this bound twelve levels take minutes. The error points at the first definition
    (or equation) that crosses the bound.
    """
    memo: dict[sympy.Basic, int] = {}
    for nm, e in definitions:
        size = _tree_size(e, memo)
        memo[_sym(nm)] = size
        if size > MAX_EXPANDED_SIZE:
            node = def_nodes[nm]
            raise SpecError(f"definition `{nm}` expands to {size} expression nodes when the "
                            f"definitions it uses are substituted (at most {MAX_EXPANDED_SIZE})",
                            **node.key_loc, text=_key_text(node),
                            hint="the generated Jacobians differentiate the expanded equations; "
                                 "chained definitions that each use the previous one several "
                                 "times grow exponentially")
    for section, variables, exprs in (("drift", states, drift),
                                      ("observations", outputs, observations)):
        for v, e in zip(variables, exprs):
            size = _tree_size(e, memo)
            if size > MAX_EXPANDED_SIZE:
                node = sections[section][v.name]
                raise SpecError(f"{section} equation of `{v.name}` expands to {size} expression "
                                f"nodes when definitions are substituted (at most "
                                f"{MAX_EXPANDED_SIZE})", **node.loc, text=node.source_line(),
                                hint="the generated Jacobians differentiate the expanded "
                                     "equations; use fewer chained definitions")


def _number_map(node: YNode, allowed: list[str], what: str, *, positive: bool = False) -> dict:
    out = {}
    for k, v in node.expect_map(what).items():
        if k not in allowed:
            raise SpecError(f"{what}: `{k}` is not a state with process noise", **v.key_loc,
                            text=_key_text(v), hint=did_you_mean(k, allowed) or
                            "list the state under noise.process.states")
        x = v.number(f"{what} of `{k}`")
        if x < 0 or (positive and x == 0):
            raise SpecError(f"{what} of `{k}` must be {'> 0' if positive else '>= 0'}", **v.loc,
                            text=v.source_line())
        out[k] = x
    return out


def _process_noise(node: YNode, state_names: list[str]) -> ProcessNoiseSpec:
    fields = keys_check(node, ("states", "structure", "estimate", "std", "floor"), "`noise.process`")
    names = list(state_names)
    if "states" in fields:
        s = fields["states"]
        if s.kind != "seq":
            raise SpecError("noise.process.states must be a list of state names", **s.loc,
                            text=s.source_line())
        names = []
        for item in s.value:
            nm = item.string("a process-noise state")
            if nm not in state_names:
                raise SpecError(f"noise.process.states: `{nm}` is not a state", **item.loc,
                                text=item.source_line(), hint=did_you_mean(nm, state_names))
            if nm in names:
                raise SpecError(f"noise.process.states: `{nm}` is listed twice", **item.loc,
                                text=item.source_line())
            names.append(nm)
    structure = "diagonal"
    if "structure" in fields:
        structure = fields["structure"].string("noise.process.structure")
        if structure not in ("diagonal", "full"):
            raise SpecError(f"unknown process-noise structure `{structure}`",
                            **fields["structure"].loc, text=fields["structure"].source_line(),
                            hint=did_you_mean(structure, ("diagonal", "full")) or "use diagonal or full")
    estimate = fields["estimate"].boolean("noise.process.estimate") if "estimate" in fields else True
    std = _number_map(fields["std"], names, "process noise std") if "std" in fields else {}
    floor = _number_map(fields["floor"], names, "process noise floor") if "floor" in fields else {}
    return ProcessNoiseSpec(tuple(names), structure, estimate, std, floor)


def _measurement_noise(o: str, node: YNode) -> MeasurementNoiseSpec:
    fields = keys_check(node, ("estimate", "std", "floor"), f"measurement noise of `{o}`")
    estimate = fields["estimate"].boolean(f"noise.measurement.{o}.estimate") if "estimate" in fields else True
    std = None
    if "std" in fields:
        std = fields["std"].number(f"measurement noise std of `{o}`")
        if std <= 0:
            raise SpecError(f"measurement noise std of `{o}` must be > 0", **fields["std"].loc,
                            text=fields["std"].source_line())
    if not estimate and std is None:
        raise SpecError(f"measurement noise of `{o}` is fixed (estimate: false) but has no `std`",
                        **node.key_loc, text=_key_text(node), hint="add `std: <value in output units>`")
    floor: Any = "auto"
    if "floor" in fields:
        f = fields["floor"]
        if f.kind == "scalar" and f.value == "auto":
            floor = "auto"
        else:
            floor = f.number(f"measurement noise floor of `{o}` (a number or auto)")
            if floor < 0:
                raise SpecError(f"measurement noise floor of `{o}` must be >= 0", **f.loc,
                                text=f.source_line())
    return MeasurementNoiseSpec(o, estimate, std, floor)


def _unit_conversion(name: str, what: str, node: YNode, spec_unit: str | None):
    """(declared data unit, (a, b)) of a data map's ``unit:`` entry, checked against the spec."""
    from . import dataunits

    data_unit = node.string(f"unit of the data column of `{name}`")
    try:
        dataunits.check_unit(data_unit)
    except dataunits.UnitConversionError as exc:
        raise SpecError(f"data map of {what} `{name}`: {exc}", **node.loc, text=node.source_line(),
                        hint="units are read by pint: e.g. rad, deg, deg/s, m/s, ft, ft/s, kt, "
                             "m/s^2, g (gravity), N, lbf, Pa, K, 1") from None
    if spec_unit is None:
        raise SpecError(f"data map of {what} `{name}` declares unit `{data_unit}` but the spec "
                        f"declares no unit for `{name}`", **node.loc, text=node.source_line(),
                        hint=f"add `unit:` to {what} `{name}` (the unit the model works in)")
    try:
        conv = dataunits.conversion(data_unit, spec_unit)
    except dataunits.UnitConversionError as exc:
        raise SpecError(f"data map of {what} `{name}`: unit {exc}", **node.loc,
                        text=node.source_line(),
                        hint=f"{what} `{name}` is declared in `{spec_unit}`: the column must have "
                             "the same dimension (angles are dimensionless)") from None
    return data_unit, conv


def _channel(name: str, node: YNode, what: str = "input", spec_unit: str | None = None) -> ChannelMap:
    if node.kind == "scalar":
        col = node.string(f"data column of `{name}`")
        return ChannelMap(name, column=col, columns=(col,))
    fields = keys_check(node, ("column", "expr", "scale", "offset", "unit"),
                        f"data mapping of `{name}`")
    scale = fields["scale"].number(f"scale of `{name}`") if "scale" in fields else 1.0
    offset = fields["offset"].number(f"offset of `{name}`") if "offset" in fields else 0.0
    unit, conv = None, (1.0, 0.0)
    if "unit" in fields:
        unit, conv = _unit_conversion(name, what, fields["unit"], spec_unit)
    if ("column" in fields) == ("expr" in fields):
        raise SpecError(f"data mapping of `{name}` needs exactly one of `column` or `expr`",
                        **node.key_loc, text=_key_text(node),
                        hint="e.g. {column: de_rad} or {expr: \"(a_rad - b_rad)/2\"}")
    if "column" in fields:
        col = fields["column"].string(f"column of `{name}`")
        return ChannelMap(name, column=col, scale=scale, offset=offset, columns=(col,),
                          unit=unit, unit_conversion=conv)
    expr, cols = fields["expr"].expression({}, free_names=True)
    return ChannelMap(name, column=None, scale=scale, offset=offset, expr=expr, columns=cols,
                      unit=unit, unit_conversion=conv)


def _data_spec(node: YNode | None, input_names, output_names, root_loc,
               units: Mapping[tuple[str, str], str | None] | None = None) -> DataSpec:
    if node is None:
        if input_names or output_names:
            raise SpecError("the spec has no `data` mapping", **root_loc,
                            hint="add `data: {time: t_s, inputs: {...}, outputs: {...}}` mapping "
                                 "every input and output to CSV columns")
        return DataSpec()
    fields = keys_check(node, ("time", "inputs", "outputs"), "`data`")
    time = fields["time"].string("data.time") if "time" in fields else "t_s"
    result = {}
    for key, names in (("inputs", input_names), ("outputs", output_names)):
        sub = fields[key].expect_map(f"`data.{key}`") if key in fields else {}
        what = key[:-1]
        for nm, ch in sub.items():
            if nm not in names:
                raise SpecError(f"data mapping for unknown {what} `{nm}`", **ch.key_loc,
                                text=_key_text(ch),
                                hint=did_you_mean(nm, names) or f"declare `{nm}` under `{key}`")
        chans = []
        for nm in names:
            if nm not in sub:
                where = fields.get(key, node)
                raise SpecError(f"{what} `{nm}` is not mapped to a data column", **where.key_loc,
                                text=_key_text(where),
                                hint=f"add `{nm}: <column name>` under `data.{key}`")
            chans.append(_channel(nm, sub[nm], what, (units or {}).get((what, nm))))
        result[key] = tuple(chans)
    return DataSpec(time, result["inputs"], result["outputs"])


def _check_dimensions(warnings, dims, definitions, def_nodes, drift, sections, states,
                      observations, outputs, output_dims) -> None:
    dims = dict(dims)
    seen: set[str] = set()

    def reporter(where: str, node: YNode):
        def report(issue: _units.DimensionIssue):
            msg = f"inconsistent units in {where}: {issue.message()}"
            if msg in seen:
                return
            seen.add(msg)
            _warn(warnings, msg, node, code="units", key=False,
                  hint="check the units of the symbols in this term")
        return report

    for nm, expr in definitions:
        node = def_nodes[nm]
        dims[_sym(nm)] = _units.dimension_of(expr, dims, reporter(f"definition `{nm}`", node))
    for v, expr in zip(states, drift):
        node = sections["drift"][v.name]
        d = _units.dimension_of(expr, dims, reporter(f"drift of `{v.name}`", node))
        want = dims.get(v.symbol)
        if d is not None and want is not None:
            want = _units.Dimension(want.name / _units.time.name)
            if not _units.same(d, want):
                _warn(warnings, f"inconsistent units in drift of `{v.name}`: the expression has "
                      f"dimension {_units.show(d)} but d{v.name}/dt must have dimension "
                      f"{_units.show(want)} (unit({v.name})/s)", node, code="units", key=False)
    for o, expr in zip(outputs, observations):
        node = sections["observations"][o.name]
        d = _units.dimension_of(expr, dims, reporter(f"observation of `{o.name}`", node))
        want = output_dims.get(o.name)
        if d is not None and want is not None and not _units.same(d, want):
            _warn(warnings, f"inconsistent units in observation of `{o.name}`: the expression has "
                  f"dimension {_units.show(d)} but output `{o.name}` has dimension "
                  f"{_units.show(want)}", node, code="units", key=False)
