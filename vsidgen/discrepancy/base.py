"""Catalogue plumbing: the :class:`Effect` base class, :class:`Candidate` records,
the model summary :class:`ModelInfo` that effects instantiate themselves for, the
effect registry and plugin loading.

An *effect* is a documented template of physics that aircraft models commonly
leave out (a missing derivative, a sensor bias, an actuator lag, ...). For a
given model it proposes concrete :class:`Candidate` augmentations: new
parameters (starting at the value that reproduces the base model, so that the
augmented model *nests* the base one), new states, new definitions and
``add_terms`` for drift/observation equations. A candidate becomes a spec that
``extends`` the base spec (:meth:`Candidate.spec_dict`); it is compiled by the
normal spec compiler and refitted by the search (:mod:`.search`).

Adding an effect (no change to the search code)::

    from vsidgen.discrepancy import Effect, Candidate, register_effect

    @register_effect
    class GearDrag(Effect):
        id = "gear_drag"
        title = "landing-gear drag"
        explanation = "The {target} equation lacks a drag increment of the extended gear ..."
        def applies_to(self, info):
            return [...]               # list[Candidate]
        def score(self, candidate, evidence):
            return ...                 # float, larger = more plausible

Effects are also found through the entry-point group ``vsidgen.effects``
(``[project.entry-points."vsidgen.effects"] gear = "mypkg.effects:GearDrag"``)
and in Python files given to ``vsidgen diagnose --effects-module path.py``
(every :class:`Effect` subclass defined there with an ``id`` is registered).
"""

from __future__ import annotations

import dataclasses
import functools
import importlib.util
import pathlib
import re
import sys
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import sympy
import yaml

from ..errors import VsidgenError
from ..metadata import VariableNames
from ..spec import compile_spec

ENTRY_POINT_GROUP = "vsidgen.effects"

#: parameter/state names the catalogue creates start with this prefix
PREFIX = "D_"

#: what a variable is to the aircraft (its *role*), recognised by name: the names users write
ROLE_NAMES: Mapping[str, tuple[str, ...]] = {
    "alpha": ("alpha", "alfa", "aoa", "alp", "alpha_b"),
    "beta": ("beta", "bet", "aos", "sideslip", "beta_b"),
    "p": ("p", "pb", "p_b", "roll_rate", "rollrate"),
    "q": ("q", "qb", "q_b", "pitch_rate", "pitchrate"),
    "r": ("r", "rb", "r_b", "yaw_rate", "yawrate"),
    "V": ("v", "vt", "vtas", "tas", "va", "airspeed", "v_tas", "vel", "vtrue", "speed"),
    "ax": ("ax", "a_x", "nx", "n_x"),
    "ay": ("ay", "a_y", "ny", "n_y"),
    "az": ("az", "a_z", "an", "nz", "n_z"),
}
#: ... and by description, where the name says nothing ("a: angle of attack")
ROLE_DESCRIPTIONS: tuple[tuple[str, re.Pattern], ...] = tuple(
    (role, re.compile(rx, re.IGNORECASE)) for role, rx in (
        ("alpha", r"\bangle[\s-]+of[\s-]+attack\b|\bincidence\b|\baoa\b"),
        ("beta", r"\bside[\s-]?slip\b"),
        ("p", r"\broll(ing)?[\s-]+rate\b"),
        ("q", r"\bpitch(ing)?[\s-]+rate\b"),
        ("r", r"\byaw(ing)?[\s-]+rate\b"),
        ("V", r"\b(true\s+)?air[\s-]?speed\b|\bflight\s+speed\b"),
        ("ax", r"\b(longitudinal|axial|forward)\s+(specific\s+force|acceleration|load)"),
        ("ay", r"\b(lateral|side(ward)?)\s+(specific\s+force|acceleration|load)"),
        ("az", r"\b(normal|vertical)\s+(specific\s+force|acceleration|load)"),
    ))
#: a description naming a rate, derivative, command or trim of the quantity is not the
#: quantity itself ("angle of attack rate", "pitch rate command")
_NOT_THE_VARIABLE = re.compile(r"\b(rates?|derivatives?|commands?|commanded|demands?|demanded"
                               r"|trim|accelerations?)\b|\bd/dt\b", re.IGNORECASE)
#: a velocity described as one component (``v: lateral velocity``) is not the airspeed
_VELOCITY_COMPONENT = re.compile(r"\b(lateral|side(ward)?|vertical|normal|body[\s-]*[xyz]|"
                                 r"[xyz][\s-]*(axis|component))\b", re.IGNORECASE)
_ROLE_BY_NAME = {n: role for role, names in ROLE_NAMES.items() for n in names}
_UNIT_SUFFIX = re.compile(r"_(rad|deg|degs|dps|rps|mps|meas|measured|m|b|body|s)$")


def variable_role(name: str, description: str = "") -> str | None:
    """The role of a variable (``"alpha"``, ``"beta"``, ``"p"``, ``"q"``, ``"r"``, ``"V"``,
    ``"ax"``, ``"ay"``, ``"az"``) from its name (case-insensitive, a unit suffix such as
    ``_rad``/``_deg``/``_meas`` dropped) or, failing that, its description ("angle of
    attack", "pitch rate", "true airspeed", "normal acceleration"); None when neither says.

    A description that names a rate, derivative, command or trim of the quantity ("angle of
    attack rate", "pitch rate command") gives no role: only the angle or the rate itself.
    """
    low = name.lower()
    for cand in (low, _UNIT_SUFFIX.sub("", low)):
        if cand in _ROLE_BY_NAME:
            role = _ROLE_BY_NAME[cand]
            if role == "V" and description and _VELOCITY_COMPONENT.search(description):
                return None          # `v: lateral velocity` is a body-axis component
            return role
    if description:
        for role, rx in ROLE_DESCRIPTIONS:
            m = rx.search(description)
            if m is None:
                continue
            rest = description[:m.start()] + " " + description[m.end():]
            return None if _NOT_THE_VARIABLE.search(rest) else role
    return None


def roles_of(variables: Iterable[Any]) -> dict[str, str]:
    """``{name: role}`` of the variables (names, or objects with ``name`` and optional
    ``description``) whose role :func:`variable_role` recognises; each role goes to one
    variable only, a name match before a description match, then the first in order."""
    variables = [VarInfo(v) if isinstance(v, str) else v for v in variables]
    # `v` beside `u` or `w` is the body y-velocity, not the airspeed
    body_axes = {v.name.lower() for v in variables} & {"u", "w"}
    by_name: dict[str, str] = {}
    by_desc: dict[str, str] = {}
    for v in variables:
        if body_axes and v.name.lower() == "v":
            continue
        desc = getattr(v, "description", "") or ""
        named = variable_role(v.name)
        if named is not None:
            if variable_role(v.name, desc) == named:    # the description does not veto it
                by_name.setdefault(named, v.name)
            continue
        role = variable_role(v.name, desc)
        if role is not None:
            by_desc.setdefault(role, v.name)
    out = {name: role for role, name in by_name.items()}
    for role, name in by_desc.items():
        if role not in by_name:
            out[name] = role
    return out


class DiscrepancyError(VsidgenError):
    """A problem with the discrepancy search (bad effect plugin, bad options...)."""


# ---------------------------------------------------------------------------
# model summary
# ---------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class VarInfo:
    """A state, input or output of the model at hand."""

    name: str
    unit: str | None = None
    description: str = ""


@dataclasses.dataclass(frozen=True)
class ModelInfo(VariableNames):
    """What an effect needs to know about the model it augments.

    ``drift``/``observations`` hold spec text for each equation as written
    (definition names allowed); ``drift_expanded``/``observations_expanded`` hold
    sympy expressions with the definitions substituted (used for derivatives and
    "does this equation already depend on x?" questions). ``dt`` is the sample
    period of the estimation data when known (used for lag lower bounds).
    """

    spec_path: pathlib.Path
    name: str
    states: tuple[VarInfo, ...]
    inputs: tuple[VarInfo, ...]
    outputs: tuple[VarInfo, ...]
    parameters: tuple[str, ...]
    constants: tuple[str, ...]
    definitions: tuple[str, ...]
    drift: Mapping[str, str]
    observations: Mapping[str, str]
    drift_expanded: Mapping[str, Any]
    observations_expanded: Mapping[str, Any]
    process_states: tuple[str, ...]
    dt: float | None = None
    #: the model's integrator method and sub-steps per sample (the spec's ``integrator``)
    integrator: str = "euler"
    substeps: int = 1
    #: break points of flow angles/inputs seen in the data: {name: (("hinge", b), ("hingelo", b))}
    breaks: Mapping[str, tuple[tuple[str, float], ...]] = dataclasses.field(default_factory=dict)
    #: the spec's constant values by name
    constant_values: Mapping[str, float] = dataclasses.field(default_factory=dict)
    #: trim airspeed, gravity and sensor positions from the records and the aircraft's
    #: constants file (:func:`.flightconst.flight_conditions`); None when not looked up
    flight: Any = None
    #: each definition with the definitions it uses substituted (sympy, real symbols)
    definitions_expanded: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    #: the parameters each definition's own expression names (not through other definitions)
    definition_parameters: Mapping[str, tuple[str, ...]] = dataclasses.field(default_factory=dict)
    #: the equations that use each definition, directly or through others
    #: (``"drift:alpha"``, ``"observations:az"``)
    definition_users: Mapping[str, tuple[str, ...]] = dataclasses.field(default_factory=dict)
    #: declared unit of each parameter (None: none declared)
    parameter_units: Mapping[str, str | None] = dataclasses.field(default_factory=dict)
    #: unit of each spec constant (``constants:``), None where the spec gives none
    constant_units: Mapping[str, str | None] = dataclasses.field(default_factory=dict)
    #: states an earlier diagnose round added as a filter (a lag, a delay, a missing mode,
    #: a gust: :attr:`NewState.physical` False): their equations are not extended by the
    #: catalogue (:meth:`equation_states`); they stay variables of the other equations
    filter_states: frozenset[str] = frozenset()

    def equation_states(self) -> tuple[str, ...]:
        """The states whose equations the catalogue may extend: all but
        :attr:`filter_states` (a round-2 "break in the rudder" inside the equation of the
        yaw-rate mode round 1 added is not aerodynamics)."""
        return tuple(s for s in self.state_names if s not in self.filter_states)

    @property
    def names(self) -> frozenset[str]:
        return frozenset(self.state_names + self.input_names + self.output_names
                         + self.parameters + self.constants + self.definitions)

    def unit(self, name: str) -> str | None:
        for v in self.states + self.inputs + self.outputs:
            if v.name == name:
                return v.unit
        _, output = self.defined_flow_angles.get(name, (None, None))
        return self.unit(output) if output else None    # the output that measures it

    def radians_per(self, name: str) -> float:
        """Radians (or rad/s, rad/s²) per unit of the state, input or output ``name``: 1 for
        ``rad``, ``rad/s`` or no unit, π/180 for ``deg``, ``deg/s``; 1 for other units. The
        physical candidates (vane and accelerometer positions in metres, gravity along the
        flight path) convert angles and rates with it, so that a model written in degrees
        gets its positions in metres and its speed equation in m/s."""
        from ..spec.dataunits import angle_kind

        kind = angle_kind(self.unit(name))
        return 1.0 if kind is None else kind[1]

    def symbol(self, name: str) -> sympy.Symbol:
        return sympy.Symbol(name, real=True)

    def depends(self, state: str, name: str) -> bool:
        """Whether the (expanded) drift of ``state`` already contains ``name``."""
        e = self.drift_expanded[state]
        return name in {s.name for s in e.free_symbols}

    def measured_state(self, output: str) -> str | None:
        """The state an output measures directly (observation ``y = x``), else None."""
        e = self.observations_expanded.get(output)
        if isinstance(e, sympy.Symbol) and e.name in self.state_names:
            return e.name
        return None

    @functools.cached_property
    def state_roles(self) -> dict[str, str]:
        """``{state: role}`` (:func:`roles_of`): which state is α, β, p, q, r, V."""
        return roles_of(self.states)

    @functools.cached_property
    def output_roles(self) -> dict[str, str]:
        """``{output: role}`` (:func:`roles_of`): which output is α, β, ax, ay, az..."""
        return roles_of(self.outputs)

    def state_with_role(self, role: str) -> str | None:
        """The state whose role is ``role`` (e.g. ``"q"``), else None."""
        return next((s for s, r in self.state_roles.items() if r == role), None)

    def flow_angle(self, kind: str) -> str | None:
        """The state that is the angle of attack (kind 'alpha') or sideslip ('beta'),
        recognised by name or description (:func:`variable_role`)."""
        return self.state_with_role(kind)

    @functools.cached_property
    def defined_flow_angles(self) -> dict[str, tuple[str, str | None]]:
        """``{definition: (role, output)}``: definitions that are the angle of attack or the
        sideslip angle of a model whose states are body velocities (``a: atan2(w, u)``).

        A definition is a flow angle when an output observes exactly it and that output's
        role is ``alpha``/``beta`` (``alpha: a`` with ``alpha`` the vane): the model's own
        equations say so, whatever the definition is called; else when its name has the role
        (``alpha: atan2(w, u)``; ``output`` None). A model whose flow angle is a state has
        none (the state is the flow angle)."""
        out: dict[str, tuple[str, str | None]] = {}
        for kind in ("alpha", "beta"):
            if self.flow_angle(kind) is not None:
                continue
            found = None
            for o, role in self.output_roles.items():
                if role != kind:
                    continue
                text = str(self.observations.get(o, "")).strip()
                e = self.observations_expanded.get(o)
                for d in self.definitions:
                    if d in out:
                        continue
                    if text == d or (e is not None and self.definitions_expanded.get(d) == e
                                     and not isinstance(e, sympy.Symbol)):
                        found = (d, o)
                        break
                if found:
                    break
            if found is None:
                d = next((d for d in self.definitions if d not in out
                          and variable_role(d) == kind), None)
                found = (d, None) if d is not None else None
            if found is not None:
                out[found[0]] = (kind, found[1])
        return out

    def flow_variable(self, kind: str) -> str | None:
        """The angle of attack (``kind`` 'alpha') or sideslip ('beta') as the model writes it:
        the state (:meth:`flow_angle`) or, in a body-velocity model, the definition
        (:attr:`defined_flow_angles`); None when the model has neither. Terms that are
        functions of the angle (squares, breaks, products of the aerodynamic coefficients)
        use it; candidates that need the angle as a state (unsteady aerodynamics, wind) do
        not."""
        s = self.flow_angle(kind)
        if s is not None:
            return s
        return next((d for d, (r, _) in self.defined_flow_angles.items() if r == kind), None)

    def rate_states(self) -> tuple[str, ...]:
        """The body angular-rate states (roles p, q, r), in state order."""
        roles = self.state_roles
        return tuple(v.name for v in self.states if roles.get(v.name) in ("p", "q", "r"))

    def drift_text_of(self, state: str) -> str:
        return self.drift[state]

    def gain_text(self, state: str, name: str) -> str | None:
        """Spec text of ∂f_state/∂name (expanded), or None when it cannot be written."""
        d = sympy.diff(self.drift_expanded[state], self.symbol(name))
        d = sympy.simplify(d) if d.count_ops() < 60 else d
        if d == 0:
            return None
        return spec_text(d)

    def output_gain_text(self, output: str, name: str) -> str | None:
        """Spec text of ∂h_output/∂name (expanded), or None when it is zero."""
        e = self.observations_expanded[output]
        if name not in {s.name for s in e.free_symbols}:
            return None
        d = sympy.diff(e, self.symbol(name))
        d = sympy.simplify(d) if d.count_ops() < 60 else d
        return None if d == 0 else spec_text(d)

    def fresh(self, base: str, taken: Iterable[str] = ()) -> str:
        """A new identifier derived from ``base`` not used by the model (or ``taken``)."""
        base = re.sub(r"[^A-Za-z0-9_]", "_", base)
        if not re.match(r"[A-Za-z_]", base):
            base = "D_" + base
        used = set(self.names) | set(taken)
        name, i = base, 2
        while name in used:
            name, i = f"{base}_{i}", i + 1
        return name


class _SpecPrinter(sympy.printing.str.StrPrinter):
    """Prints sympy expressions in the spec expression language (whitelist only)."""

    _FUN = {"Abs": "abs", "Min": "min", "Max": "max", "sin": "sin", "cos": "cos",
            "tan": "tan", "asin": "asin", "acos": "acos", "atan": "atan", "atan2": "atan2",
            "exp": "exp", "log": "log", "tanh": "tanh", "sign": "sign"}

    def _print_Function(self, expr):
        name = type(expr).__name__
        if name not in self._FUN:
            raise _Unprintable(name)
        return f"{self._FUN[name]}({', '.join(self._print(a) for a in expr.args)})"

    _print_Abs = _print_Function
    _print_Min = _print_Function
    _print_Max = _print_Function

    def _print_Exp1(self, expr):
        return "exp(1)"

    def _print_Pi(self, expr):
        return "pi"

    def _print_Float(self, expr):
        return repr(float(expr))

    def _print_Rational(self, expr):
        return f"({expr.p}/{expr.q})"

    def _print_Half(self, expr):
        return "(1/2)"

    def _print_Infinity(self, expr):
        raise _Unprintable("oo")

    _print_NegativeInfinity = _print_Infinity
    _print_ComplexInfinity = _print_Infinity
    _print_NaN = _print_Infinity

    def _print_Piecewise(self, expr):
        raise _Unprintable("Piecewise")

    def _print_Derivative(self, expr):
        raise _Unprintable("Derivative")

    def _print_Heaviside(self, expr):
        raise _Unprintable("Heaviside")

    def _print_Pow(self, expr, rational=False):
        b, e = expr.args
        if e == sympy.Rational(1, 2):
            return f"sqrt({self._print(b)})"
        return f"({self._print(b)})**({self._print(e)})"


class _Unprintable(Exception):
    pass


def spec_text(expr) -> str | None:
    """Spec-language text of a sympy expression, or None if it uses anything else."""
    try:
        return _SpecPrinter().doprint(expr)
    except _Unprintable:
        return None
    except Exception:  # pragma: no cover - defensive
        return None


def model_info(spec_path, *, dt: float | None = None) -> ModelInfo:
    """Summarise the spec at ``spec_path`` (``extends`` resolved) for the catalogue.

    Compiles it with :func:`vsidgen.spec.symbolic.compile_spec`; raises
    :class:`~vsidgen.errors.SpecError` for a bad spec.
    """
    spec_path = pathlib.Path(spec_path)
    return _info_from_symbolic(compile_spec(spec_path), spec_path, dt)


def info_from_model(model, *, dt: float | None = None) -> ModelInfo:
    """:class:`ModelInfo` of a runtime :class:`vsidgen.model.Model` loaded from a spec."""
    sym = model.symbolic
    if sym is None:
        raise DiscrepancyError("diagnose needs a model loaded from a spec (no symbolic model)")
    return _info_from_symbolic(sym, pathlib.Path(sym.source_path), dt)


def _vars(vs) -> tuple[VarInfo, ...]:
    return tuple(VarInfo(v.name, getattr(v, "unit", None), getattr(v, "description", "") or "")
                 for v in vs)


def _info_from_symbolic(sym, spec_path, dt) -> ModelInfo:
    states = _vars(sym.states)
    drift_exp = sym.drift_expanded()
    obs_exp = sym.observations_expanded()
    drift_txt = {}
    for v, e in zip(states, sym.drift):
        drift_txt[v.name] = spec_text(e) or spec_text(drift_exp[len(drift_txt)])
    outputs = _vars(sym.outputs)
    obs_txt = {}
    for i, (v, e) in enumerate(zip(outputs, sym.observations)):
        obs_txt[v.name] = spec_text(e) or spec_text(obs_exp[i])
    pnames = {p.name for p in sym.parameters}
    pn = sym.process_noise
    pstates = tuple(pn.states) if pn is not None and pn.states else tuple(v.name for v in states)
    return ModelInfo(
        spec_path=pathlib.Path(spec_path), name=sym.name, states=states,
        inputs=_vars(sym.inputs), outputs=outputs,
        parameters=tuple(p.name for p in sym.parameters),
        constants=tuple(c.name for c in sym.constants),
        constant_values={c.name: float(c.value) for c in sym.constants},
        definitions=tuple(n for n, _ in sym.definitions),
        drift=drift_txt, observations=obs_txt,
        drift_expanded={v.name: _realify(e) for v, e in zip(states, drift_exp)},
        observations_expanded={v.name: _realify(e) for v, e in zip(outputs, obs_exp)},
        process_states=pstates, dt=dt,
        integrator=str(getattr(sym, "integrator", "euler") or "euler"),
        substeps=int(getattr(sym, "substeps", 1) or 1),
        definitions_expanded={n: _realify(e) for n, e in _expanded_definitions(sym).items()},
        definition_parameters={n: tuple(sorted(s.name for s in e.free_symbols if s.name in pnames))
                               for n, e in sym.definitions},
        definition_users=_definition_users(sym),
        parameter_units={p.name: getattr(p, "unit", None) for p in sym.parameters},
        constant_units={c.name: getattr(c, "unit", None) for c in sym.constants})


def _expanded_definitions(sym) -> dict[str, Any]:
    return {sy.name: e for sy, e in sym.expansion().items()}


def _definition_users(sym) -> dict[str, tuple[str, ...]]:
    """{definition: equations using it} — ``"drift:<state>"`` and ``"observations:<output>"``,
    through other definitions too (found by the symbols of the unexpanded equations and the
    definitions' own dependencies, no expansion)."""
    names = [n for n, _ in sym.definitions]
    direct = {n: {s.name for s in e.free_symbols} & set(names) for n, e in sym.definitions}
    reach: dict[str, set[str]] = {}
    for n in names:                       # definitions are in dependency order
        reach[n] = set(direct[n]).union(*(reach[d] for d in direct[n] if d in reach))
    users: dict[str, list[str]] = {n: [] for n in names}
    eqs = ([(f"drift:{v.name}", e) for v, e in zip(sym.states, sym.drift)]
           + [(f"observations:{v.name}", e) for v, e in zip(sym.outputs, sym.observations)])
    for where, e in eqs:
        used = {s.name for s in e.free_symbols} & set(names)
        used = used.union(*(reach[d] for d in used))
        for d in sorted(used):
            users[d].append(where)
    return {n: tuple(u) for n, u in users.items()}


def _realify(e):
    """Replace every symbol by a real symbol of the same name (for name comparisons)."""
    return e.xreplace({s: sympy.Symbol(s.name, real=True) for s in e.free_symbols})


# ---------------------------------------------------------------------------
# candidates
# ---------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class NewParameter:
    """A parameter a candidate adds. ``initial`` is the value that reproduces the base model."""

    name: str
    unit: str | None = None
    description: str = ""
    initial: float = 0.0
    lower: float | None = None
    upper: float | None = None
    fixed: bool = False

    def spec(self) -> dict:
        d: dict[str, Any] = {"unit": self.unit if self.unit is not None else "1",
                             "description": self.description, "initial": float(self.initial)}
        if self.lower is not None or self.upper is not None:
            d["bounds"] = [self.lower, self.upper]
        if self.fixed:
            d["fixed"] = True
        return d


@dataclasses.dataclass(frozen=True)
class NewState:
    """A state a candidate adds (actuator/lag/delay/mode/wind state) with its drift text."""

    name: str
    drift: str
    unit: str | None = None
    description: str = ""
    process_noise: bool = False   # receives process noise (a wind/gust state does)
    #: a state of the aircraft with a force or moment equation of its own (the speed of the
    #: phugoid), whose equation later rounds may extend like the spec's; False for a filter
    #: (an actuator lag, a Padé delay, a missing mode, a gust), whose equation is the
    #: candidate's own form (:attr:`ModelInfo.filter_states`)
    physical: bool = False


@dataclasses.dataclass(frozen=True)
class Candidate:
    """One concrete augmentation of the model at hand proposed by an effect.

    Attributes:
        effect: catalogue identifier of the effect (``Effect.id``).
        key: unique identifier of this candidate, e.g. ``missing_derivative:q:de``.
        target: the state equation (``"drift:q"``) or output channel
            (``"output:alpha"``) it changes.
        explanation: plain-words text for an engineer.
        parameters, states, definitions: what is added.
        add_terms: ``{"drift": {state: text}, "observations": {output: text},
            "definitions": {name: text}}`` terms added to existing equations.
        evidence_keys: which locate statistics the score came from (for the report).
        info: free-form details (regressor, break point, ...).
        screenable: the candidate reproduces the current model *exactly* at its
            initial parameter values, with an informative gradient there, so the score
            pre-screen (:mod:`.score`) applies. False for lags/delays (their smallest
            time constant is a sample shift, not the current model) and for gust states
            (their intensity starts on the boundary, zero): those are ranked by their
            locate score.
    """

    effect: str
    key: str
    target: str
    explanation: str
    parameters: tuple[NewParameter, ...] = ()
    states: tuple[NewState, ...] = ()
    definitions: Mapping[str, str] = dataclasses.field(default_factory=dict)
    add_terms: Mapping[str, Mapping[str, str]] = dataclasses.field(default_factory=dict)
    info: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    screenable: bool = True

    @property
    def n_free(self) -> int:
        """Number of new free parameters (the degrees of freedom of the LR test)."""
        return sum(1 for p in self.parameters if not p.fixed)

    @property
    def target_kind(self) -> str:
        return self.target.split(":", 1)[0]

    @property
    def target_name(self) -> str:
        return self.target.split(":", 1)[1]

    def added_terms(self) -> dict[str, Any]:
        """The spec fragments this candidate adds, for findings.json."""
        out: dict[str, Any] = {}
        for sect in ("drift", "observations", "definitions"):
            if self.add_terms.get(sect):
                out[sect] = dict(self.add_terms[sect])
        if self.definitions:
            out["new_definitions"] = dict(self.definitions)
        if self.states:
            out["new_states"] = {s.name: s.drift for s in self.states}
        delay = self.info.get("delay") if self.info else None
        if delay:  # a profiled transport delay (.delay): the spec's input declaration
            out["inputs"] = {self.info["input"]: {"delay": delay.get("spec_value",
                                                                     delay["estimate"])}}
            hc = delay.get("hold_comparison") or {}
            if hc and delay.get("input_hold") != hc.get("current_hold"):
                # the delay profile chose the other setting (search.delay_trial): the other
                # input hold, and RK4 where the current model steps by Euler
                method = delay.get("integrator_method")
                before = (hc.get("current") or {}).get("method", method)
                out["integrator"] = ({"method": method} if method != before else {}) | {
                    "inputs": delay.get("input_hold")}
        return out

    def spec_dict(self, base_spec, *, name: str, candidate_path=None,
                  info: ModelInfo | None = None) -> dict:
        """The YAML mapping of the augmented spec extending ``base_spec``.

        ``candidate_path`` is where the YAML will be written (``extends`` is made
        relative to it). ``info`` (the base model's) is needed when new states
        receive process noise (the process-noise state list is extended).
        """
        base_spec = pathlib.Path(base_spec).resolve()
        if candidate_path is not None:
            import os
            ext = os.path.relpath(base_spec, pathlib.Path(candidate_path).resolve().parent)
        else:
            ext = str(base_spec)
        d: dict[str, Any] = {"name": name,
                             "description": f"{self.key}: {self.explanation}"[:400],
                             "extends": ext}
        if self.states:
            d["states"] = {s.name: {"unit": s.unit if s.unit is not None else "1",
                                    "description": s.description} for s in self.states}
        if self.parameters:
            d["parameters"] = {p.name: p.spec() for p in self.parameters}
        if self.definitions:
            d["definitions"] = dict(self.definitions)
        if self.states:
            d["drift"] = {s.name: s.drift for s in self.states}
        adds = {k: dict(v) for k, v in self.add_terms.items() if v}
        if adds:
            d["add_terms"] = adds
        noisy = [s.name for s in self.states if s.process_noise]
        if self.states:
            # always explicit: a spec without a noise section gives every state process
            # noise, the added ones too (on the real HFB-320 record a lag state with free,
            # correlated process noise became a coloured-noise channel: 2ΔELBO 151.7 with
            # its time constant at the lower bound, no lag)
            base_states = list(info.process_states) if info is not None else []
            d["noise"] = {"process": {"states": base_states + noisy}}
        return d

    def spec_yaml(self, base_spec, *, name: str, candidate_path=None,
                  info: ModelInfo | None = None) -> str:
        head = (f"# vsidgen diagnose candidate {self.key}\n"
                f"# effect: {self.effect}; target: {self.target}\n")
        return head + yaml.safe_dump(self.spec_dict(base_spec, name=name,
                                                    candidate_path=candidate_path, info=info),
                                     sort_keys=False, width=100)


def hold_lag(model, dt: float) -> float:
    """Delay (s) the model's own transition already applies to a continuously varying input.

    A zero-order hold uses ``u_k`` over ``[t_k, t_k + T)``, i.e. ``u(t − (t − t_k))``: to
    first order in T the input delayed by the mean ``T/2``. With a first-order hold Euler
    sub-step j uses the input at its start, ``T/(2m)`` behind on average; RK4 evaluates
    the interpolated input at its stage times (no lag). The physical transport delay is the
    spec's delay plus this lag.
    """
    return setting_hold_lag(getattr(model, "input_hold", "zoh") or "zoh",
                            getattr(model, "integrator", "euler") or "euler",
                            int(getattr(model, "substeps", 1) or 1), dt)


def setting_hold_lag(inputs: str, method: str, substeps: int, dt: float) -> float:
    """:func:`hold_lag` of an integrator setting: input hold ``inputs`` ("zoh"/"foh"),
    ``method`` ("euler"/"rk4") with ``substeps`` per sample of ``dt`` s."""
    if inputs == "zoh":
        return 0.5 * dt
    if method == "rk4":
        return 0.0
    return 0.5 * dt / int(substeps)


# ---------------------------------------------------------------------------
# effects and registry
# ---------------------------------------------------------------------------

class Effect:
    """Base class of a catalogue entry.

    Subclasses set ``id`` (identifier used in findings.json), ``title``,
    ``explanation`` (a ``str.format`` template; fields are those of the
    candidate's ``info`` plus ``target``) and implement :meth:`applies_to` and
    :meth:`score`.
    """

    id: str = ""
    title: str = ""
    explanation: str = ""
    #: short physics description for the documentation
    doc: str = ""

    def applies_to(self, info: ModelInfo) -> list[Candidate]:
        """Concrete candidates for the model described by ``info``."""
        raise NotImplementedError

    def score(self, candidate: Candidate, evidence) -> float:
        """Plausibility of ``candidate`` given the locate evidence (:class:`.locate.Evidence`).

        Conventionally ``-log10`` of the p-value of the locate statistic that
        supports the candidate (0 = no support). Only the best-scoring candidates
        are refitted.
        """
        return 0.0

    def explain(self, **fields) -> str:
        try:
            return self.explanation.format(**fields)
        except (KeyError, IndexError, ValueError):
            return self.explanation

    def check_estimates(self, candidate: Candidate, estimates: dict) -> str:
        """A sentence comparing the refitted estimates with what physics gives for them, for
        the finding's explanation ("" when the effect has no such reference). ``estimates``:
        {parameter: (value, standard error or None)}."""
        return ""

    def __repr__(self) -> str:
        return f"<Effect {self.id}>"


_REGISTRY: dict[str, Effect] = {}


#: effects that add a linear term in one variable, and those that add a nonlinear term
LINEAR_TERM_EFFECTS = ("coefficient_derivative", "missing_derivative")
NONLINEAR_TERM_EFFECTS = ("coefficient_nonlinear", "nonlinear_aero")


def term_variables(c: Candidate) -> tuple[str, ...]:
    """The variables of a linear or nonlinear term candidate (``info["var"]`` of a linear
    term; the regressor's of a nonlinear one: ``sq:alpha`` → (alpha,), ``hinge:de:0.04`` →
    (de,), ``prod:alpha*de`` → (alpha, de)); () for other effects."""
    info = c.info or {}
    if c.effect in LINEAR_TERM_EFFECTS:
        return (info["var"],) if info.get("var") else ()
    if c.effect not in NONLINEAR_TERM_EFFECTS:
        return ()
    kind, _, rest = str(info.get("regressor", "")).partition(":")
    if not rest:
        return ()
    return tuple(rest.split("*")) if kind == "prod" else (rest.split(":", 1)[0],)


#: effect classes that are forms of one physical effect on the same target: a time delay of an
#: input as a first-order Padé state or as the input shifted by τ (the same τ, the same
#: physics; at the bandwidths of a flight record the two predict alike)
SAME_EFFECT_FORMS = (frozenset({"control_delay", "transport_delay"}),)


def same_physics(a: Candidate, b: Candidate) -> bool:
    """Whether two candidates are forms of one physical explanation: the same effect class on
    the same target, two forms of one effect on the same target (:data:`SAME_EFFECT_FORMS`:
    an input delay as a Padé state or as a shifted input), or a linear and a nonlinear term
    of a common variable in the same target (a missing derivative and a break of the same
    coefficient in the same input) — a choice of form, not between explanations. One effect
    class on two targets is two explanations: a β vane ahead of the CG and a lateral
    accelerometer ahead of it are different sensors (session 47: their tie was called "form
    uncertain" when the accelerometer led, AMBIGUOUS when the vane did)."""
    if a.effect == b.effect:
        return a.target == b.target
    kinds = {a.effect, b.effect}
    if a.target == b.target and any(kinds <= forms for forms in SAME_EFFECT_FORMS):
        return True
    if a.target != b.target or not (kinds & set(LINEAR_TERM_EFFECTS)
                                    and kinds & set(NONLINEAR_TERM_EFFECTS)):
        return False
    return bool(set(term_variables(a)) & set(term_variables(b)))


def register_effect(effect, *, replace: bool = False):
    """Register an :class:`Effect` subclass or instance (usable as a class decorator)."""
    inst = effect() if isinstance(effect, type) else effect
    if not isinstance(inst, Effect):
        raise DiscrepancyError(f"{effect!r} is not a vsidgen.discrepancy.Effect")
    if not inst.id or not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", inst.id):
        raise DiscrepancyError(f"effect {effect!r} needs an identifier `id` (letters, digits, _)")
    if inst.id in _REGISTRY and not replace and type(_REGISTRY[inst.id]) is not type(inst):
        raise DiscrepancyError(f"an effect with id '{inst.id}' is already registered")
    _REGISTRY[inst.id] = inst
    return effect


def unregister_effect(effect_id: str) -> None:
    _REGISTRY.pop(effect_id, None)


_ENTRY_POINTS_LOADED = False


def load_entry_points() -> list[str]:
    """Register the effects of the ``vsidgen.effects`` entry-point group; returns their ids."""
    global _ENTRY_POINTS_LOADED
    from importlib.metadata import entry_points

    ids = []
    try:
        eps = entry_points(group=ENTRY_POINT_GROUP)
    except TypeError:  # pragma: no cover - python < 3.10
        eps = entry_points().get(ENTRY_POINT_GROUP, [])
    for ep in eps:
        try:
            obj = ep.load()
        except Exception as err:  # noqa: BLE001 - a broken plugin must not crash diagnose
            raise DiscrepancyError(f"cannot load effect plugin '{ep.name}' ({ep.value}): {err}") \
                from None
        register_effect(obj, replace=True)
        ids.append(obj.id)
    _ENTRY_POINTS_LOADED = True
    return ids


def load_effects_module(path) -> list[str]:
    """Import the Python file ``path`` and register every Effect subclass it defines."""
    path = pathlib.Path(path)
    if not path.is_file():
        raise DiscrepancyError(f"effects module not found: {path}")
    modname = f"vsidgen_effects_{re.sub(r'[^A-Za-z0-9_]', '_', path.stem)}"
    spec = importlib.util.spec_from_file_location(modname, path)
    if spec is None or spec.loader is None:
        raise DiscrepancyError(f"cannot import effects module {path}")
    module = importlib.util.module_from_spec(spec)
    sys.modules[modname] = module
    try:
        spec.loader.exec_module(module)
    except Exception as err:  # noqa: BLE001
        raise DiscrepancyError(f"error while importing effects module {path}: "
                               f"{type(err).__name__}: {err}") from None
    ids = []
    for obj in vars(module).values():
        if (isinstance(obj, type) and issubclass(obj, Effect) and obj is not Effect
                and obj.__module__ == modname and obj.id):
            register_effect(obj, replace=True)
            ids.append(obj.id)
    if not ids:
        raise DiscrepancyError(f"effects module {path} defines no Effect subclass with an `id`")
    return ids


def registered_effects(*, entry_points: bool = True) -> tuple[Effect, ...]:
    """All registered effects (built-in catalogue first, then plugins).

    The built-ins register themselves when :mod:`.catalogue` is imported, which the package
    ``vsidgen.discrepancy`` does before any of its modules can be used.
    """
    if entry_points and not _ENTRY_POINTS_LOADED:
        load_entry_points()
    return tuple(_REGISTRY.values())


def get_effect(effect_id: str) -> Effect:
    registered_effects()
    try:
        return _REGISTRY[effect_id]
    except KeyError:
        raise DiscrepancyError(f"unknown effect '{effect_id}'; known: "
                               f"{', '.join(sorted(_REGISTRY))}") from None


def propose(info: ModelInfo, effects: Sequence[Effect] | None = None) -> list[Candidate]:
    """Every candidate of every effect for the model ``info`` (duplicates by key removed)."""
    effects = registered_effects() if effects is None else effects
    out: dict[str, Candidate] = {}
    for eff in effects:
        try:
            cands = eff.applies_to(info)
        except VsidgenError:
            raise
        except Exception as err:  # noqa: BLE001 - plugin bugs become clear errors
            raise DiscrepancyError(f"effect '{eff.id}' failed for model {info.name}: "
                                   f"{type(err).__name__}: {err}") from None
        for c in cands:
            out.setdefault(c.key, c)
    return list(out.values())
