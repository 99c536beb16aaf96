"""The typed, immutable, located spec: the YAML read once into declarations, equations,
add-terms, noise and data map.

:func:`read_spec` loads a spec with everything it ``extends`` (:func:`vsidgen.spec.load.load_spec`)
and checks its *structure*: the allowed keys of every mapping, that every value has the
right kind (a mapping, a list, a number, a true/false, a text), that names are valid and
not reserved. The result, :class:`Spec`, holds plain Python values, each kept with its
place in the file (:class:`Located`: path, line, column of the value and of its key, the
source lines shown under a message), so that :mod:`vsidgen.spec.symbolic`, which compiles it to
sympy and checks its *meaning* (names declared once, expressions, definition cycles, noise
and data maps against the declarations, units), reports every problem at the text that
causes it without reading YAML itself. Expressions stay text here: parsing them needs the
namespace of declared names, which is the compiler's job.
"""

from __future__ import annotations

import dataclasses
import keyword
import math
import pathlib
import re
from collections.abc import Callable
from typing import Any, Generic, TypeVar

from ..errors import SpecError
from .expr import FUNCTIONS, did_you_mean, non_ascii_note
from .load import RawSpec, YNode, keys_check, load_spec

T = TypeVar("T")

_NAME_RE = re.compile(r"[A-Za-z][A-Za-z0-9_]*")
#: longest name (model, state, input, output, parameter, constant, definition) accepted
MAX_NAME_LENGTH = 64
#: largest pure transport delay of an input (``inputs: {u: {delay: seconds}}``)
MAX_INPUT_DELAY_S = 10.0
#: most entries per section: the generated Jacobians are dense (states × states, states ×
#: parameters), so build time and module size grow with their product — 100 states took 4 s,
#: 1500 took 83 s and a 14 MB module (red team, session 47); an aircraft model has tens
MAX_ENTRIES = {"state": 100, "input": 100, "output": 200, "parameter": 2000}

#: names the generated module defines or imports (no spec name may equal one of them;
#: every other name the module uses itself starts with ``_``, which spec names cannot)
GENERATED_MODULE_NAMES = frozenset({
    "jnp", "drift", "output", "drift_jac_x", "drift_jac_u", "drift_jac_p", "output_jac_x",
    "output_jac_u", "output_jac_p", "STATES", "INPUTS", "OUTPUTS", "PARAMETERS", "SPEC_PATH",
    "SPEC_HASH", "GENERATOR_VERSION",
})

INTEGRATOR_METHODS = ("euler", "rk4")
INPUT_HOLDS = ("zoh", "foh")


def valid_name(name: str) -> bool:
    """True for an ASCII letter followed by letters, digits and ``_``, at most
    :data:`MAX_NAME_LENGTH` characters (the whole string: no trailing line break)."""
    return (isinstance(name, str) and len(name) <= MAX_NAME_LENGTH
            and _NAME_RE.fullmatch(name) is not None)


def show_name(name) -> str:
    """A name for a message: repr-escaped (no line breaks), cut at 40 characters."""
    shown = repr(str(name))[1:-1]
    return "`" + (shown[:40] + "..." if len(shown) > 40 else shown) + "`"


@dataclasses.dataclass(frozen=True)
class Located(Generic[T]):
    """A spec value with its place: ``line``/``column`` of the value, ``key_line``/
    ``key_column`` of its key (the value's own place when it has none), ``text`` and
    ``key_text`` the stripped source lines shown under an error message."""

    value: T
    path: pathlib.Path
    line: int
    column: int
    key_line: int
    key_column: int
    text: str = dataclasses.field(default="", repr=False)
    key_text: str = dataclasses.field(default="", repr=False)
    #: file (line, column) of a character offset into the value's text (expressions, units)
    locator: Callable[[int], tuple[int, int | None]] | None = dataclasses.field(
        default=None, repr=False, compare=False)

    @classmethod
    def of(cls, node: YNode, value) -> "Located":
        lines = node.src.splitlines()
        kl = node.key_line or node.line
        return cls(value, node.path, node.line, node.column, kl, node.key_column or node.column,
                   node.source_line(), lines[kl - 1].strip() if 1 <= kl <= len(lines) else "",
                   node.locate)

    @property
    def loc(self) -> dict:
        """``path``/``line``/``column`` keywords of :class:`SpecError` at the value."""
        return {"path": self.path, "line": self.line, "column": self.column}

    @property
    def key_loc(self) -> dict:
        """``path``/``line``/``column`` keywords of :class:`SpecError` at the key."""
        return {"path": self.path, "line": self.key_line, "column": self.key_column}

    def relocate(self, err: SpecError) -> SpecError:
        """``err``, raised while reading this value's text from line 1 column 1, moved to the
        file position of the same character."""
        offset = (err.column - 1) if err.column is not None else 0
        if self.locator is None:
            line, column = self.line, self.column + offset
        else:
            line, column = self.locator(offset)
        return SpecError(err.message, path=self.path, line=line, column=column, text=err.text,
                         hint=err.hint, span=err.span)


@dataclasses.dataclass(frozen=True)
class VariableDecl:
    """A state, input or output: ``name`` (located at its key), optional ``unit`` text,
    description, and for inputs the pure transport ``delay`` in seconds."""

    name: Located[str]
    unit: Located[str] | None = None
    description: str = ""
    delay: Located[float] | None = None


@dataclasses.dataclass(frozen=True)
class ConstantDecl:
    name: Located[str]
    value: float
    unit: Located[str] | None = None
    source: str = ""


@dataclasses.dataclass(frozen=True)
class ParameterDecl:
    """A parameter; ``initial_at`` is where the initial value is written (None: default 0),
    ``bounds`` the located ``[lower, upper]`` list (None: unbounded)."""

    name: Located[str]
    unit: Located[str] | None = None
    description: str = ""
    initial: float = 0.0
    initial_at: Located[float] | None = None
    bounds: Located[tuple[float | None, float | None]] | None = None
    fixed: bool = False


@dataclasses.dataclass(frozen=True)
class Equation:
    """``name: expression`` of ``definitions``, ``drift``, ``observations`` or ``add_terms``
    (``name`` located at the key, ``expression`` the text as written)."""

    name: Located[str]
    expression: Located[str]


@dataclasses.dataclass(frozen=True)
class AddTerm:
    """An ``add_terms`` entry: ``term.expression`` is added to ``section[term.name]``."""

    section: str
    term: Equation


@dataclasses.dataclass(frozen=True)
class ProcessNoiseDecl:
    """``noise.process``; ``states`` None: every state; ``std``/``floor`` (state, value) pairs."""

    at: Located[None]
    states: Located[tuple[Located[str], ...]] | None = None
    structure: Located[str] | None = None
    estimate: bool = True
    std: tuple[tuple[Located[str], Located[float]], ...] = ()
    floor: tuple[tuple[Located[str], Located[float]], ...] = ()
    degenerate: tuple[Located[str], ...] = ()


@dataclasses.dataclass(frozen=True)
class MeasurementNoiseDecl:
    """``noise.measurement.<output>``; ``floor`` a located number or ``"auto"``."""

    output: Located[str]
    estimate: bool = True
    std: Located[float] | None = None
    floor: Located[Any] | None = None


@dataclasses.dataclass(frozen=True)
class ChannelDecl:
    """One data-map entry (``at``: the entry itself): ``bare`` for ``name: column`` written
    as a plain text (it sets ``column``), else the mapping's ``column``/``expr`` (the
    compiler requires exactly one), ``scale``, ``offset`` and the column's ``unit``."""

    name: Located[str]
    at: Located[None]
    bare: bool = False
    column: Located[str] | None = None
    expr: Located[str] | None = None
    scale: float = 1.0
    offset: float = 0.0
    unit: Located[str] | None = None


@dataclasses.dataclass(frozen=True)
class DataDecl:
    """``data``; ``inputs_at``/``outputs_at`` the sub-mappings (None when absent)."""

    at: Located[None]
    time: str = "t_s"
    inputs: tuple[ChannelDecl, ...] = ()
    outputs: tuple[ChannelDecl, ...] = ()
    inputs_at: Located[None] | None = None
    outputs_at: Located[None] | None = None
    #: ``time: {column: t_ms, unit: ms}``: the time column's unit (seconds when absent)
    time_unit: Located[str] | None = None


@dataclasses.dataclass(frozen=True)
class Spec:
    """A spec read once (module docstring). Sections keep the file order (``extends``
    merged); ``add_terms`` are in application order (parents first)."""

    path: pathlib.Path
    name: Located[str]
    description: str
    integrator: str
    substeps: int
    input_hold: str
    states: tuple[VariableDecl, ...]
    inputs: tuple[VariableDecl, ...]
    outputs: tuple[VariableDecl, ...]
    constants: tuple[ConstantDecl, ...]
    parameters: tuple[ParameterDecl, ...]
    definitions: tuple[Equation, ...]
    drift: tuple[Equation, ...]
    observations: tuple[Equation, ...]
    add_terms: tuple[AddTerm, ...]
    process_noise: ProcessNoiseDecl | None
    measurement_noise: tuple[MeasurementNoiseDecl, ...]
    data: DataDecl | None
    #: the ``drift``/``observations`` section keys (None when the section is absent)
    sections_at: dict = dataclasses.field(default_factory=dict, compare=False)
    #: every file of the spec, the ``extends`` ancestors first
    files: tuple[pathlib.Path, ...] = ()
    #: the merged spec in canonical JSON (what :attr:`hash` covers)
    canonical: str = dataclasses.field(default="", repr=False, compare=False)
    hash: str = ""


# ---------------------------------------------------------------------------
# reading
# ---------------------------------------------------------------------------

def check_name(name: str, node: YNode, what: str) -> None:
    """A declared name: valid, not reserved by the generated module, not a function name."""
    at = Located.of(node, name)
    if not valid_name(name):
        note = non_ascii_note(name) if isinstance(name, str) and len(name) <= 200 else None
        raise SpecError(f"invalid {what} name {show_name(name)}", **at.key_loc, text=at.key_text,
                        hint=(f"{note}; " if note else "")
                        + "names start with an ASCII letter and contain only letters, digits "
                          f"and _ (at most {MAX_NAME_LENGTH} characters)")
    if name in GENERATED_MODULE_NAMES:
        raise SpecError(f"{what} name `{name}` is reserved by the generated module",
                        **at.key_loc, text=at.key_text,
                        hint="choose another name (reserved: "
                             + ", ".join(sorted(GENERATED_MODULE_NAMES)) + ")")
    if name in FUNCTIONS:
        raise SpecError(f"{what} name `{name}` is the name of a built-in function", **at.key_loc,
                        text=at.key_text, hint="choose another name")


def _unit(fields: dict, what: str) -> Located[str] | None:
    node = fields.get("unit")
    if node is None or (node.kind == "scalar" and node.value is None):
        return None
    text = node.text if node.kind == "scalar" else None
    if text is None:
        node.string(f"unit of {what}")
    if not text.isprintable():
        raise SpecError(f"unit of {what} contains a line break or another non-printable "
                        "character", **node.loc, text=node.source_line(),
                        hint="write the unit on one line, e.g. m/s^2")
    return Located.of(node, text)


def _desc(fields: dict, what: str) -> str:
    node = fields.get("description")
    if node is None or (node.kind == "scalar" and node.value is None):
        return ""
    return node.string(f"description of {what}")


def _integrator(top: dict) -> tuple[str, int, str]:
    method, substeps, input_hold = "euler", 1, "zoh"
    if "integrator" not in top:
        return method, substeps, input_hold
    integ = keys_check(top["integrator"], ("method", "substeps", "inputs"), "`integrator`")
    if "method" in integ:
        method = integ["method"].string("integrator method")
        if method not in INTEGRATOR_METHODS:
            raise SpecError(f"unknown integrator method `{method}`", **integ["method"].loc,
                            text=integ["method"].source_line(),
                            hint=did_you_mean(method, INTEGRATOR_METHODS) or "use euler or rk4")
    if "substeps" in integ:
        n = integ["substeps"]
        from ..limits import MAX_SUBSTEPS

        if n.kind != "scalar" or isinstance(n.value, bool) or not isinstance(n.value, int) \
                or not 1 <= n.value <= MAX_SUBSTEPS:
            raise SpecError(f"integrator substeps must be an integer from 1 to {MAX_SUBSTEPS}",
                            **n.loc, text=n.source_line(),
                            hint="sub-steps are unrolled into the compiled code; for accuracy "
                                 "use `method: rk4` with a few sub-steps")
        substeps = n.value
    if "inputs" in integ:
        input_hold = integ["inputs"].string("integrator inputs")
        if input_hold not in INPUT_HOLDS:
            raise SpecError(f"unknown input hold `{input_hold}`", **integ["inputs"].loc,
                            text=integ["inputs"].source_line(),
                            hint=did_you_mean(input_hold, INPUT_HOLDS)
                            or "use zoh (inputs held over each sample) or foh (inputs "
                               "interpolated linearly between samples)")
    return method, substeps, input_hold


def _at_most(section: dict, what: str) -> None:
    """Refuse more than :data:`MAX_ENTRIES` entries of a section, at the first one too many."""
    limit = MAX_ENTRIES[what]
    if len(section) > limit:
        name, node = list(section.items())[limit]
        raise SpecError(f"more than {limit} {what}s (this is number {limit + 1}: `{name}`)",
                        **node.loc, text=node.source_line(),
                        hint=f"vsidgen builds dense Jacobians of the equations, whose size grows "
                             f"with the number of {what}s; split the model, or write tables "
                             "(interp) instead of one entry per value")


def _variables(raw: RawSpec, key: str, what: str) -> tuple[VariableDecl, ...]:
    entries = []
    section = raw.section(key)
    _at_most(section, what)
    for name, node in section.items():
        check_name(name, node, what)
        if node.kind == "scalar" and node.value is None:
            fields = {}
        elif node.kind == "scalar" and not isinstance(node.value, str):
            # `alpha: 5` or `alpha: true` was accepted and the value dropped (red team, session 47)
            raise SpecError(f"{what} `{name}` must be a mapping like {{unit: rad, description: ...}}, "
                            f"not the value {node.value!r}", **node.loc, text=node.source_line(),
                            hint="write `{unit: \"...\", description: \"...\"}` (or nothing after "
                                 "the colon)")
        elif node.kind == "scalar" and isinstance(node.value, str):
            raise SpecError(f"{what} `{name}` must be a mapping like {{unit: m/s, description: ...}}",
                            **node.loc, text=node.source_line(),
                            hint="write `{unit: \"...\", description: \"...\"}`")
        else:
            fields = node.expect_map(f"{what} `{name}`") if node.kind != "scalar" else {}
        entries.append((name, node, fields))
    out = []
    for name, node, fields in entries:
        allowed = ("unit", "description", "delay") if key == "inputs" else ("unit", "description")
        if node.kind == "map":
            keys_check(node, allowed, f"{what} `{name}`")
        unit = _unit(fields, f"{what} `{name}`")
        delay = None
        if "delay" in fields:
            dn = fields["delay"]
            value = dn.number(f"delay of input `{name}`")
            if not (math.isfinite(value) and 0.0 <= value <= MAX_INPUT_DELAY_S):
                raise SpecError(f"delay of input `{name}` must be between 0 and "
                                f"{MAX_INPUT_DELAY_S:g} seconds, got {value:g}", **dn.loc,
                                text=dn.source_line(),
                                hint="a pure transport delay in seconds: the model sees the "
                                     f"recorded {name} shifted later by this time")
            delay = Located.of(dn, value)
        out.append(VariableDecl(Located.of(node, name), unit, _desc(fields, name), delay))
    return tuple(out)


def _constants(raw: RawSpec) -> tuple[ConstantDecl, ...]:
    out = []
    for name, node in raw.section("constants").items():
        check_name(name, node, "constant")
        if node.kind == "scalar":
            value = node.number(f"constant `{name}`")
            fields = {}
        else:
            fields = keys_check(node, ("value", "unit", "source", "description"), f"constant `{name}`")
            if "value" not in fields:
                raise SpecError(f"constant `{name}` has no `value`", **node.key_loc,
                                text=Located.of(node, name).key_text,
                                hint="write `{value: 9.80665, unit: m/s^2}`")
            value = fields["value"].number(f"value of constant `{name}`")
        unit = _unit(fields, f"constant `{name}`")
        source = ""
        if "source" in fields and fields["source"].value is not None:
            source = fields["source"].string(f"source of constant `{name}`")
        out.append(ConstantDecl(Located.of(node, name), value, unit, source))
    return tuple(out)


def _parameters(raw: RawSpec) -> tuple[ParameterDecl, ...]:
    out = []
    section = raw.section("parameters")
    _at_most(section, "parameter")
    for name, node in section.items():
        check_name(name, node, "parameter")
        fields: dict = {}
        initial = 0.0
        initial_at = None
        if node.kind == "scalar" and node.value is not None:
            initial = node.number(f"initial value of parameter `{name}`")
            initial_at = Located.of(node, initial)
        elif node.kind != "scalar":
            fields = keys_check(node, ("unit", "description", "initial", "bounds", "fixed"),
                                f"parameter `{name}`")
            if "initial" in fields:
                initial = fields["initial"].number(f"initial value of parameter `{name}`")
                initial_at = Located.of(fields["initial"], initial)
        bounds = None
        if "bounds" in fields:
            b = fields["bounds"]
            if b.kind != "seq" or len(b.value) != 2:
                raise SpecError(f"bounds of parameter `{name}` must be a list [lower, upper]", **b.loc,
                                text=b.source_line(), hint="use null for an open side: [0, null]")
            lower = b.value[0].number(f"lower bound of `{name}`", allow_none=True)
            upper = b.value[1].number(f"upper bound of `{name}`", allow_none=True)
            if lower is not None and upper is not None and lower >= upper:
                raise SpecError(f"bounds of parameter `{name}`: lower {lower:g} >= upper {upper:g}",
                                **b.loc, text=b.source_line(), hint="write [lower, upper] with lower < upper")
            if (lower is not None and initial < lower) or (upper is not None and initial > upper):
                where = initial_at or Located.of(b, None)
                raise SpecError(f"initial value {initial:g} of parameter `{name}` is outside its bounds "
                                f"[{'-inf' if lower is None else format(lower, 'g')}, "
                                f"{'inf' if upper is None else format(upper, 'g')}]",
                                **where.loc, text=where.text,
                                hint="set `initial` inside the bounds"
                                     + (" (the default initial value is 0)" if initial_at is None else ""))
            bounds = Located.of(b, (lower, upper))
        fixed = fields["fixed"].boolean(f"`fixed` of parameter `{name}`") if "fixed" in fields else False
        out.append(ParameterDecl(Located.of(node, name), _unit(fields, f"parameter `{name}`"),
                                 _desc(fields, name), initial, initial_at, bounds, fixed))
    return tuple(out)


def _equation(name: str, node: YNode) -> Equation:
    if node.kind != "scalar" or node.value is None or isinstance(node.value, bool):
        raise SpecError(f"expected an expression, got {node.describe()}", **node.loc,
                        text=node.source_line())
    return Equation(Located.of(node, name), Located.of(node, node.text))


def _located_numbers(node: YNode, what: str) -> tuple:
    return tuple((Located.of(v, k), Located.of(v, v.number(f"{what} of `{k}`")))
                 for k, v in node.expect_map(what).items())


def _process_noise(node: YNode) -> ProcessNoiseDecl:
    fields = keys_check(node, ("states", "structure", "estimate", "std", "floor", "degenerate"),
                        "`noise.process`")
    states = None
    if "states" in fields:
        s = fields["states"]
        if s.kind != "seq":
            raise SpecError("noise.process.states must be a list of state names", **s.loc,
                            text=s.source_line())
        states = Located.of(s, tuple(Located.of(item, item.string("a process-noise state"))
                                     for item in s.value))
    degenerate = ()
    if "degenerate" in fields:
        d = fields["degenerate"]
        if d.kind != "seq":
            raise SpecError("noise.process.degenerate must be a list of state names", **d.loc,
                            text=d.source_line(),
                            hint="e.g. degenerate: [q] (with structure: full)")
        degenerate = tuple(Located.of(item, item.string("a degenerate process-noise state"))
                           for item in d.value)
    structure = None
    if "structure" in fields:
        structure = Located.of(fields["structure"], fields["structure"].string("noise.process.structure"))
        if structure.value not in ("diagonal", "full"):
            raise SpecError(f"unknown process-noise structure `{structure.value}`",
                            **structure.loc, text=structure.text,
                            hint=did_you_mean(structure.value, ("diagonal", "full")) or "use diagonal or full")
    estimate = fields["estimate"].boolean("noise.process.estimate") if "estimate" in fields else True
    std = _located_numbers(fields["std"], "process noise std") if "std" in fields else ()
    floor = _located_numbers(fields["floor"], "process noise floor") if "floor" in fields else ()
    return ProcessNoiseDecl(Located.of(node, None), states, structure, estimate, std, floor,
                            degenerate)


def _measurement_noise(o: str, node: YNode) -> MeasurementNoiseDecl:
    fields = keys_check(node, ("estimate", "std", "floor"), f"measurement noise of `{o}`")
    estimate = fields["estimate"].boolean(f"noise.measurement.{o}.estimate") if "estimate" in fields else True
    std = None
    if "std" in fields:
        std = Located.of(fields["std"], fields["std"].number(f"measurement noise std of `{o}`"))
        if std.value <= 0:
            raise SpecError(f"measurement noise std of `{o}` must be > 0", **std.loc, text=std.text)
    if not estimate and std is None:
        raise SpecError(f"measurement noise of `{o}` is fixed (estimate: false) but has no `std`",
                        **node.key_loc, text=Located.of(node, o).key_text,
                        hint="add `std: <value in output units>`")
    floor = None
    if "floor" in fields:
        f = fields["floor"]
        if f.kind == "scalar" and f.value == "auto":
            floor = Located.of(f, "auto")
        else:
            floor = Located.of(f, f.number(f"measurement noise floor of `{o}` (a number or auto)"))
            if floor.value < 0:
                raise SpecError(f"measurement noise floor of `{o}` must be >= 0", **floor.loc,
                                text=floor.text)
    return MeasurementNoiseDecl(Located.of(node, o), estimate, std, floor)


def _channel(name: str, node: YNode) -> ChannelDecl:
    at = Located.of(node, None)
    if node.kind == "scalar":
        return ChannelDecl(Located.of(node, name), at, bare=True,
                           column=Located.of(node, node.string(f"data column of `{name}`")))
    fields = keys_check(node, ("column", "expr", "scale", "offset", "unit"), f"data mapping of `{name}`")
    scale = fields["scale"].number(f"scale of `{name}`") if "scale" in fields else 1.0
    if scale == 0.0:
        # every sample would be read as the offset: a constant channel (session 44)
        raise SpecError(f"scale of `{name}` is 0: every sample would read as the offset",
                        **fields["scale"].loc, text=fields["scale"].source_line(),
                        hint="write the factor that converts the column (e.g. -1 for a sign, "
                             "or 0.3048 for ft to m), or leave `scale` out")
    offset = fields["offset"].number(f"offset of `{name}`") if "offset" in fields else 0.0
    unit = None
    if "unit" in fields:
        unit = Located.of(fields["unit"], fields["unit"].string(f"unit of the data column of `{name}`"))
    column = expr = None
    if "column" in fields:
        column = Located.of(fields["column"], fields["column"].string(f"column of `{name}`"))
    if "expr" in fields:
        e = fields["expr"]
        if e.kind != "scalar" or e.value is None or isinstance(e.value, bool):
            raise SpecError(f"expected an expression, got {e.describe()}", **e.loc, text=e.source_line())
        expr = Located.of(e, e.text)
    return ChannelDecl(Located.of(node, name), at, False, column, expr, scale, offset, unit)


def _data(node: YNode) -> DataDecl:
    fields = keys_check(node, ("time", "inputs", "outputs"), "`data`")
    time, time_unit = "t_s", None
    if "time" in fields and fields["time"].kind == "map":
        tf = keys_check(fields["time"], ("column", "unit"), "`data.time`")
        if "column" not in tf:
            raise SpecError("`data.time` needs a `column`", **fields["time"].key_loc,
                            text=Located.of(fields["time"], None).key_text,
                            hint="e.g. time: {column: t_ms, unit: ms}")
        time = tf["column"].string("data.time.column")
        if "unit" in tf:
            time_unit = Located.of(tf["unit"], tf["unit"].string("unit of the time column"))
    elif "time" in fields:
        time = fields["time"].string("data.time")
    chans = {}
    for key in ("inputs", "outputs"):
        sub = fields[key].expect_map(f"`data.{key}`") if key in fields else {}
        chans[key] = tuple(_channel(nm, ch) for nm, ch in sub.items())
    return DataDecl(Located.of(node, None), time, chans["inputs"], chans["outputs"],
                    Located.of(fields["inputs"], None) if "inputs" in fields else None,
                    Located.of(fields["outputs"], None) if "outputs" in fields else None,
                    time_unit)


def parse(raw: RawSpec, *, generator_version: str) -> Spec:
    """The typed spec of a merged :class:`vsidgen.spec.load.RawSpec` (structure checked).

    Raises:
        SpecError: a key, kind or value that the spec language does not allow.
    """
    top = raw.top
    if "name" not in top:
        raise SpecError("the spec has no `name`", path=raw.path, line=1, column=1,
                        hint="add `name: mymodel` (the generated module is generated/<name>.py)")
    name = top["name"].string("`name`")
    if not valid_name(name):
        raise SpecError(f"invalid model name {show_name(name)}", **top["name"].loc,
                        text=top["name"].source_line(),
                        hint="use an ASCII letter, then letters, digits and _, at most "
                             f"{MAX_NAME_LENGTH} characters (it becomes a Python module name)")
    if keyword.iskeyword(name):
        # the generated module's name is an identifier in its text (`import` was an internal
        # error in `build`, after `check` had passed; session 46)
        raise SpecError(f"model name `{name}` is a Python keyword", **top["name"].loc,
                        text=top["name"].source_line(),
                        hint=f"choose another name, e.g. `{name}_model` (the name becomes a "
                             "Python module name)")
    description = ""
    if "description" in top and top["description"].value is not None:
        description = top["description"].string("`description`")
    method, substeps, input_hold = _integrator(top)
    states = _variables(raw, "states", "state")
    inputs = _variables(raw, "inputs", "input")
    outputs = _variables(raw, "outputs", "output")
    constants = _constants(raw)
    parameters = _parameters(raw)
    definitions = []
    for nm, node in raw.section("definitions").items():
        check_name(nm, node, "definition")
        definitions.append((nm, node))
    definitions = tuple(_equation(nm, node) for nm, node in definitions)
    add_terms = tuple(AddTerm(a.section, _equation(a.name, a.node)) for a in raw.add_terms)
    drift = tuple(_equation(nm, node) for nm, node in raw.section("drift").items())
    observations = tuple(_equation(nm, node) for nm, node in raw.section("observations").items())
    process, measurement = None, ()
    if "noise" in top:
        noise = keys_check(top["noise"], ("process", "measurement"), "`noise`")
        if "process" in noise:
            process = _process_noise(noise["process"])
        if "measurement" in noise:
            measurement = tuple(_measurement_noise(o, node) for o, node in
                                noise["measurement"].expect_map("`noise.measurement`").items())
    data = _data(top["data"]) if "data" in top else None
    sections_at = {k: Located.of(top[k], None) for k in ("drift", "observations") if k in top}
    return Spec(raw.path, Located.of(top["name"], name), description, method, substeps, input_hold,
                states, inputs, outputs, constants, parameters, definitions, drift, observations,
                add_terms, process, measurement, data, sections_at, raw.files, raw.canonical(),
                raw.hash(generator_version))


def read_spec(path, *, generator_version: str) -> Spec:
    """:func:`parse` of :func:`vsidgen.spec.load.load_spec` ``(path)``: a spec file read once."""
    return parse(load_spec(path), generator_version=generator_version)


__all__ = ["AddTerm", "ChannelDecl", "ConstantDecl", "DataDecl", "Equation", "GENERATED_MODULE_NAMES",
           "Located", "MAX_INPUT_DELAY_S", "MAX_NAME_LENGTH", "MeasurementNoiseDecl", "ParameterDecl",
           "ProcessNoiseDecl", "Spec", "VariableDecl", "check_name", "parse", "read_spec", "show_name",
           "valid_name"]
