"""The built-in catalogue of physical effects that aircraft models commonly leave out.

Every entry is an :class:`~vsidgen.discrepancy.base.Effect`; its candidates add
spec terms whose new parameters start at the value that reproduces the base
model (0 for gains, the smallest admissible value for time constants), so the
augmented spec nests the base one. Notation: :math:`f_s` the drift of state
:math:`s`, :math:`h_o` the observation of output :math:`o`, :math:`T` the sample
period.

=====================  ===========================================================
id                     what is added
=====================  ===========================================================
missing_derivative     :math:`f_s \\mathrel{+}= D\\,v` for a state/input ``v`` absent from :math:`f_s`
trim_term              :math:`f_s \\mathrel{+}= D` where :math:`f_s` has no free constant
nonlinear_aero         :math:`D\\,v^2`, :math:`D\\,a v` (a flow angle), :math:`D\\max(v-b,0)`,
                       :math:`D\\max(b-v,0)` (stall break / control saturation at ``b``),
                       :math:`D\\,β^3` (sideslip: odd, as a symmetric aircraft's moments are)
unsteady_aero          :math:`D\\,\\dot a` through a downwash-lag state
                       :math:`\\dot a_l = (a - a_l)/τ_l`, :math:`\\dot a ≈ (a-a_l)/τ_l`
control_delay          first-order Padé delay of input ``u``: :math:`\\dot z = 2(u-z)/τ`,
                       :math:`u(t-τ) ≈ 2z-u`; :math:`f_s \\mathrel{+}= ∂f_s/∂u\\,(2z-2u)`
                       (discretised exactly over a held step: the model itself as τ → 0)
actuator_lag           :math:`\\dot z = (u-z)/τ`; :math:`f_s \\mathrel{+}= ∂f_s/∂u\\,(z-u)`
                       (engine/thrust lag when ``u`` is a thrust or throttle input)
sensor_bias            :math:`h_o \\mathrel{+}= b`
sensor_scale           :math:`h_o \\mathrel{+}= k\\,h_o`
sensor_position        vane x m ahead of the CG: :math:`α_m = α - x q/V`, :math:`β_m = β + x r/V`
                       (``V`` the model's airspeed; in s, ``c ω``, when it has none);
                       accelerometer x m ahead: :math:`a_z - x\\,\\dot q` (``ω̇ × r`` per axis)
time_skew              :math:`h_o(t-τ) ≈ h_o - τ\\,\\dot h_o`, :math:`\\dot h_o = ∑_i ∂h_o/∂x_i f_i`
missing_dynamics       a first-order mode :math:`\\dot m = -m/τ + K v`, :math:`f_s \\mathrel{+}= m`
unmodelled_wind        a Gauss–Markov gust angle :math:`\\dot w = -w/τ_w + σ_w \\dot W` added to
                       the aerodynamic angle: :math:`f_s \\mathrel{+}= ∂f_s/∂a\\,w`, vane :math:`+w`
=====================  ===========================================================
"""

from __future__ import annotations

import functools
import math

from .base import (Candidate, Effect, ModelInfo, NewParameter, NewState, register_effect,
                   roles_of, spec_text)
from ..spec.symbolic import split_constant_terms
from .locate import SPEED_REGRESSOR


def kinematic_state(info: ModelInfo, state: str) -> bool:
    """A state whose equation names no parameter (``θ̇ = q``, ``φ̇ = p + …``, a position):
    kinematics, not aerodynamics — its rate is fixed by other states, and no aerodynamic
    force or moment depends on it (attitude enters the dynamics through gravity only)."""
    e = info.drift_expanded.get(state)
    if e is None:
        return False
    return not ({s.name for s in e.free_symbols} & set(info.parameters))


def kinematic_rates(info: ModelInfo, state: str) -> frozenset[str] | None:
    """The rates an attitude or position equation is made of, or None when ``state`` is not
    one.

    A state is pure kinematics when its equation names no parameter
    (:func:`kinematic_state`) and vanishes when every state and input with the dimension
    of its rate is zero: ``φ̇ = p + tanθ (q sinφ + r cosφ)`` (p, q, r in rad/s),
    ``θ̇ = q``, ``ḣ = V sin γ`` (V in m/s). Such an equation is exact geometry: what it
    can leave out is a coupling with another rate of the same dimension, with a
    dimensionless coefficient (``φ̇ = p + tanθ₀·r`` when a bank equation omits the Euler
    term) — never a control derivative, a velocity or an attitude term, or a dynamic mode,
    which act on the rates' own equations. A sideslip equation written without side force
    (``β̇ = p sinα₀ − r cosα₀ + (g/V) φ``) keeps ``(g/V) φ`` at zero rates, so it is not
    pure kinematics and keeps every candidate. Units that are missing or do not parse give
    None (no restriction)."""
    if not kinematic_state(info, state):
        return None
    from ..errors import SpecError
    from ..spec.units import parse_unit, same
    if not info.unit(state):
        return None
    try:
        rate = parse_unit(_drift_unit(info, state))
        dims = {v: info.unit(v) for v in info.state_names + info.input_names}
        rates = frozenset(v for v, u in dims.items()
                          if u and same(parse_unit(u), rate))
    except SpecError:
        return None
    e = info.drift_expanded.get(state)
    if not rates or e is None:
        return None
    import sympy
    at_rest = e.xreplace({s: sympy.S.Zero for s in e.free_symbols if s.name in rates})
    return rates if at_rest == 0 else None    # xreplace evaluates: no simplify on user text


def aero_variable(info: ModelInfo, v: str) -> bool:
    """Whether an aerodynamic coefficient (or an aerodynamic term of a state equation) can
    depend on ``v``: the air-relative motion and the controls — flow angles, control
    deflections, Mach and other dimensionless inputs, angular rates, airspeed, and forces
    (thrust: a propeller's slipstream over the wing and tail). Not an attitude or position
    state (:func:`kinematic_state`), and not a measured quantity of another dimension —
    density, dynamic pressure, mass, inertia, altitude, temperature — which scale forces
    through the model's own equations but are not variables of a coefficient (a new user's
    Twin Otter model with measured density and two thrust inputs got `C_L` derivatives in θ
    and ρ, squares and breaks in ρ and nonlinear terms in θ̇ = q: 30 of its 159 candidates
    before break points). A variable without a declared or parsable unit is kept."""
    if v in info.state_names and kinematic_state(info, v):
        return False
    unit = info.unit(v)
    if not unit:
        return True
    from ..errors import SpecError
    from ..spec.units import parse_unit, same
    try:
        dim = parse_unit(unit)
    except SpecError:   # an unparsable unit: keep the variable
        return True
    return any(same(dim, d) for d in _aero_dimensions())


@functools.lru_cache(maxsize=1)
def _aero_dimensions() -> tuple:
    """Dimensions of :func:`aero_variable`: dimensionless (angles, Mach, throttle), 1/s
    (rates), m/s (airspeed), N (thrust)."""
    from ..spec.units import ONE, parse_unit
    return (ONE,) + tuple(parse_unit(u) for u in ("1/s", "m/s", "N"))


def _drift_unit(info: ModelInfo, state: str) -> str:
    u = info.unit(state)
    return f"({u})/s" if u and u != "1" else "1/s"


def _ratio(num: str, den: str | None) -> str:
    if not den or den == "1":
        return num
    return f"{num}/({den})"


def _paren(text: str) -> str:
    return f"({text})"


def _times(k: float, text: str) -> str:
    """``text`` multiplied by the unit factor ``k`` (as is when ``k`` is 1)."""
    return text if k == 1.0 else f"{k!r}*{_paren(text)}"


def _input_dynamics_evidence(c, ev) -> float:
    """Evidence for dynamics (a lag, a delay) between an input and the aircraft: the
    equation errors of the states the input drives correlate with its rate or a lagged copy."""
    u = c.info["input"]
    return max((max(ev.state_score(s, f"udot:{u}"), ev.state_score(s, f"lag:{u}"))
                for s in c.info["states"]), default=0.0)


#: the actuator lag's smallest time constant, in steps: its exact discretisation (any τ > 0,
#: :meth:`ActuatorLag.lower_bound`) and its continuous form under RK4 (stable for h/τ ≤ 2.785,
#: :meth:`ContinuousActuatorLag.lower_bound`)
#: (at 0.01 of a step the model there still saw 1 % of z − u and fitted 0.22 nats below the
#: current model on hfbb_none_0_s5, so a refit that found no lag ended "below its nesting
#: point"; the gap falls with the square of the fraction)
LAG_MIN_FRACTION, RK4_LAG_MIN_STEPS = 0.001, 0.4


def _lag_bounds(info: ModelInfo, factor: float = 1.0) -> float:
    dt = info.dt or 0.01
    return factor * dt


@register_effect
class MissingDerivative(Effect):
    id = "missing_derivative"
    title = "missing stability or control derivative"
    explanation = ("The {state} equation lacks a linear dependence on {var}: the equation error "
                   "between the smoothed derivative of {state} and the model drift follows {var}. "
                   "Physically this is a stability or control derivative the model left out "
                   "(d {state}/dt += {param}·{var}).")
    doc = ("A linear term in a state or input absent from a state equation (in an attitude or "
           "position equation only a rate of the same dimension: a kinematic coupling).")

    def applies_to(self, info):
        out = []
        for s in info.equation_states():
            rates = kinematic_rates(info, s)    # an attitude/position: couplings only
            for v in info.state_names + info.input_names:
                if info.depends(s, v) or (rates is not None and v not in rates):
                    continue
                p = info.fresh(f"D_{s}_{v}")
                kind = "x" if v in info.state_names else "u"
                out.append(Candidate(
                    effect=self.id, key=f"{self.id}:{s}:{v}", target=f"drift:{s}",
                    explanation=self.explain(state=s, var=v, param=p),
                    parameters=(NewParameter(p, _ratio(_drift_unit(info, s), info.unit(v)),
                                             f"derivative of d({s})/dt with respect to {v}"),),
                    add_terms={"drift": {s: f"{p}*{v}"}},
                    info={"regressor": f"{kind}:{v}", "state": s, "var": v}))
        return out

    def score(self, c, ev):
        return ev.state_score(c.info["state"], c.info["regressor"])


def has_constant_term(info: ModelInfo, state: str) -> bool:
    """Whether the drift of ``state`` already has a free constant: an additive term of its
    expanded equation that names a parameter and no state or input (``Z0 + Zα α + …``)."""
    e = info.drift_expanded.get(state)
    if e is None:
        return True
    xu = set(info.state_names) | set(info.input_names)
    constant, _ = split_constant_terms(e, {s for s in e.free_symbols if s.name in xu})
    return any({s.name for s in term.free_symbols} & set(info.parameters) for term in constant)


@register_effect
class TrimTerm(Effect):
    """A constant (trim) term missing from a state equation.

    A model written in the recorded (absolute) variables, ``α̇ = Z_α α + q + Z_δ δ``, balances
    its forces and moments only at ``α = δ = 0``; in flight the aircraft is trimmed elsewhere,
    so the equation needs the constant ``Z_0`` that the linearisation about the trim point
    leaves (the trim lift, weight and thrust components, the pitching moment at zero α).
    Without it the process noise carries the constant and the other derivatives bend to absorb
    it (on ATTAS ``attas_elv1`` without ``M_0`` the pitch damping came out positive and the free
    simulation diverged). Offered for every non-kinematic state whose drift has no free
    constant (:func:`has_constant_term`)."""

    id = "trim_term"
    title = "missing trim (constant) term"
    explanation = ("The {state} equation lacks a constant (trim) term ({param}): its equation "
                   "error has a mean the model's terms cannot supply. Physically it is the trim "
                   "force or moment — d({state})/dt where the variables the equation is written in "
                   "are zero — which a model linearised about zero instead of its trim point "
                   "leaves out (d({state})/dt += {param}).")
    explanation_all = ("The {states} equations lack their constant (trim) terms ({params}): the "
                       "model is written in the recorded variables without the trim point, so "
                       "no equation balances its forces or moments where the aircraft was "
                       "trimmed. All constants are added together (one omission; "
                       "d({first})/dt += {first_param}, …).")
    doc = "A constant (trim) term in a state equation that has none."

    def applies_to(self, info):
        out = []
        states = [s for s in info.equation_states()
                  if not kinematic_state(info, s) and not has_constant_term(info, s)]
        for s in states:
            p = info.fresh(f"D_TRIM_{s}")
            out.append(Candidate(
                effect=self.id, key=f"{self.id}:{s}", target=f"drift:{s}",
                explanation=self.explain(state=s, param=p),
                parameters=(NewParameter(p, _drift_unit(info, s),
                                         f"trim (constant) term of d({s})/dt"),),
                add_terms={"drift": {s: p}}, info={"regressor": "1", "states": (s,)}))
        if len(states) >= 2:
            # one omission: a model linearised about zero instead of the trim point lacks the
            # constant of every force and moment equation (a user's Tu-144 short period in
            # absolute α, δe: both constants together 2ΔELBO 1029, each alone 817 and 205)
            ps = [info.fresh(f"D_TRIM_{s}") for s in states]
            out.append(Candidate(
                effect=self.id, key=f"{self.id}:all", target="drift:" + "+".join(states),
                explanation=self.explanation_all.format(
                    states=", ".join(states[:-1]) + " and " + states[-1],
                    params=", ".join(ps), first=states[0], first_param=ps[0]),
                parameters=tuple(NewParameter(p, _drift_unit(info, s),
                                              f"trim (constant) term of d({s})/dt")
                                 for s, p in zip(states, ps)),
                add_terms={"drift": dict(zip(states, ps))},
                info={"regressor": "1", "states": tuple(states)}))
        return out

    def score(self, c, ev):
        return max(ev.state_score(s, "1") for s in c.info["states"])


def _coefficient_definitions(info: ModelInfo):
    """(definition, its users, the states whose equations use it, its unit) of every
    definition with parameters of its own that reaches a state equation (a coefficient
    model: ``coefficient_derivative``, ``coefficient_nonlinear``)."""
    for d, own in info.definition_parameters.items():
        users = info.definition_users.get(d, ())
        drift_users = [u.split(":", 1)[1] for u in users if u.startswith("drift:")]
        if own and drift_users:
            yield d, users, drift_users, _coefficient_unit(info, d)


def _users_score(c, ev) -> float:
    """Locate score of a coefficient candidate: its regressor's best share over the state
    equations that use the coefficient."""
    return max((ev.state_score(s, c.info["regressor"]) for s in c.info["states"]), default=0.0)


#: what a cubic sideslip term means: a symmetric aircraft's lateral force and moments are odd
#: in β (β and −β mirror each other), so their first nonlinearity is cubic, not square
_CUBE_WHAT = ("a cubic term {p}·{v}³ (odd in sideslip, as the lateral force and moments of a "
              "symmetric aircraft are: the stability grows or fades with |{v}|)")


def _break_term(kind: str, v: str, slope: str, bp: str) -> tuple[str, str]:
    """(term, side) of a change of slope of ``v`` at the break point ``bp``: ``hinge`` above
    it, ``hingelo`` below it."""
    if kind == "hinge":
        return f"{slope}*max({v} - {bp}, 0)", "above"
    return f"{slope}*max({bp} - {v}, 0)", "below"


@register_effect
class MissingCoefficientDerivative(Effect):
    """A derivative missing from an aerodynamic coefficient (a definition), not from one equation.

    Specs written with coefficient models (``CL: CL0 + CLV*V/V0 + CLAL*alpha``) use each
    coefficient in several equations and outputs: lift enters the α equation and both
    accelerometers. A lift-due-to-elevator derivative left out of ``CL`` changes all of them
    together, so the physical candidate adds ``D_CL_de·de`` to the definition — every user
    gets it through the model's own geometry (qbar, S/m, the axis projections) — where
    ``missing_derivative`` adds a free term to one state equation only (which explains the α
    equation's small share but not the accelerometer, whose residual is then named a sensor
    effect). Proposed for every definition that names parameters of its own (a coefficient
    model) and reaches a state equation, and every state and input it does not yet depend on.
    """

    id = "coefficient_derivative"
    title = "missing derivative of an aerodynamic coefficient"
    explanation = ("The coefficient {coef} lacks a linear dependence on {var}: every equation "
                   "and output that uses {coef} ({users}) is off by the same term. Physically "
                   "this is a stability or control derivative left out of the coefficient model "
                   "({coef} += {param}·{var}).")
    doc = "A linear term in a state or input absent from a coefficient definition (all its users)."

    def applies_to(self, info):
        out = []
        for d, users, drift_users, unit in _coefficient_definitions(info):
            e = info.definitions_expanded.get(d)
            have = {x.name for x in e.free_symbols} if e is not None else set()
            for v in info.state_names + info.input_names:
                if v in have or not aero_variable(info, v):
                    continue
                p = info.fresh(f"D_{d}_{v}")
                kind = "x" if v in info.state_names else "u"
                out.append(Candidate(
                    effect=self.id, key=f"{self.id}:{d}:{v}", target=f"definition:{d}",
                    explanation=self.explain(coef=d, var=v, param=p,
                                             users=", ".join(u.replace(":", " ") for u in users)),
                    parameters=(NewParameter(p, _ratio(unit, info.unit(v)) if unit else None,
                                             f"derivative of {d} with respect to {v}"),),
                    add_terms={"definitions": {d: f"{p}*{v}"}},
                    info={"regressor": f"{kind}:{v}", "definition": d, "var": v,
                          "states": drift_users, "users": list(users)}))
        return out

    def score(self, c, ev):
        return _users_score(c, ev)


def _own_parameters(info: ModelInfo, output: str) -> set[str]:
    """Parameters an output equation names itself, not through a definition it uses."""
    e = info.observations_expanded.get(output)
    if e is None:
        return set()
    have = {x.name for x in e.free_symbols} & set(info.parameters)
    via = set()
    for d, users in info.definition_users.items():
        if f"observations:{output}" in users:
            via |= set(info.definition_parameters.get(d, ()))
    return have - via


@register_effect
class OutputDerivative(Effect):
    """A derivative missing from an output that models a force or moment itself.

    A new user often writes the lateral accelerometer as its own equation, ``a_y = V·(Y_β β +
    Y_δr δr)``, with parameters of its own and not through a coefficient definition the state
    equations share; a side-force derivative left out there (``Y_r r``) has no candidate in
    ``missing_derivative`` (state equations) or ``coefficient_derivative`` (definitions), and
    an accelerometer-arm candidate took it (an ATTAS lateral model: arm −8.4 m for an
    accelerometer 1.01 m behind the CG). Proposed for every output equation that names a
    parameter of its own and is not a direct measurement of a state, and every state and
    input it does not yet depend on.
    """

    id = "output_derivative"
    title = "missing derivative of a modelled output"
    explanation = ("The modelled output {output} lacks a linear dependence on {var}: its "
                   "residual follows {var}. The output equation models a force or moment with "
                   "parameters of its own; physically this is a derivative left out of that "
                   "force model ({output} += {param}·{var}), not a sensor effect.")
    doc = ("A linear term in a state or input absent from an output equation that has "
           "parameters of its own (a force or moment modelled in the output).")

    def applies_to(self, info):
        out = []
        for o in info.output_names:
            if info.measured_state(o) is not None or not _own_parameters(info, o):
                continue
            have = {x.name for x in info.observations_expanded[o].free_symbols}
            for v in info.state_names + info.input_names:
                if v in have:
                    continue
                p = info.fresh(f"D_{o}_{v}")
                out.append(Candidate(
                    effect=self.id, key=f"{self.id}:{o}:{v}", target=f"output:{o}",
                    explanation=self.explain(output=o, var=v, param=p),
                    parameters=(NewParameter(p, _ratio(info.unit(o) or "1", info.unit(v)),
                                             f"derivative of output {o} with respect to {v}"),),
                    add_terms={"observations": {o: f"{p}*{v}"}},
                    info={"output": o, "var": v,
                          "regressor": f"rate:{v}" if v in info.rate_states() else ""}))
        return out

    def score(self, c, ev):
        reg = c.info.get("regressor")
        return ev.output_score(c.info["output"], reg) if reg else 0.0


@register_effect
class CoefficientNonlinearity(Effect):
    """A nonlinearity missing from an aerodynamic coefficient (a definition): a square or a
    change of slope (a break) in a flow angle or a control.

    The coefficient-level counterpart of ``nonlinear_aero``, as ``coefficient_derivative`` is
    of ``missing_derivative``: lift that loses slope above a stall break changes the α
    equation and both accelerometers together through ``CL``, so the physical candidate adds
    ``D·max(α − α_b, 0)`` (or ``D·α²``) to the definition and every user gets it through the
    model's own geometry. Proposed for every definition that names parameters of its own and
    reaches a state equation; the variables are the flow angles and the inputs. A break
    point is a parameter of its own (unit of the variable), started at a value located in the
    record (:func:`.locate.break_points`) and estimated by the refit: at the nesting value of
    the slope it does not enter the model (the score screen holds it), so the test of the
    break is the slope's, and the refit's likelihood ratio counts both (two degrees of
    freedom).
    """

    id = "coefficient_nonlinear"
    title = "nonlinearity of an aerodynamic coefficient"
    explanation = ("The coefficient {coef} depends nonlinearly on {var}: {what}. Every equation "
                   "and output that uses {coef} ({users}) is off by the same term (typical of "
                   "flow separation near stall, or of a control losing effectiveness).")
    doc = ("A square or a break in a flow angle or a control (or the cube of sideslip) added to a "
           "coefficient definition (all its users).")

    def applies_to(self, info):
        out = []
        flow = [v for v in (info.flow_variable("alpha"), info.flow_variable("beta")) if v]
        beta = info.flow_variable("beta")
        for d, users, drift_users, unit in _coefficient_definitions(info):
            user_text = ", ".join(u.replace(":", " ") for u in users)
            for v in flow + [u for u in info.input_names if aero_variable(info, u)]:
                uv = info.unit(v)
                p = info.fresh(f"D_{d}_{v}{v}")
                out.append(self._cand(d, f"sq:{v}", p, f"{p}*{v}**2",
                                      _ratio(unit, f"({uv})^2" if uv else None) if unit else None,
                                      var=v, what=f"a quadratic term {p}·{v}²", users=users,
                                      user_text=user_text, drift_users=drift_users))
                if v == beta:
                    p = info.fresh(f"D_{d}_{v}3")
                    out.append(self._cand(d, f"cube:{v}", p, f"{p}*{v}**3",
                                          _ratio(unit, f"({uv})^3" if uv else None) if unit else None,
                                          var=v, what=_CUBE_WHAT.format(p=p, v=v), users=users,
                                          user_text=user_text, drift_users=drift_users))
                for kind, b in info.breaks.get(v, ()):
                    p = info.fresh(f"D_{d}_{v}_brk")
                    bp = info.fresh(f"D_{d}_{v}_bp", taken=[p])
                    term, side = _break_term(kind, v, p, bp)
                    cause = "a break, e.g. flow separation" if v in flow else "saturation"
                    # the break point is estimated from the located grid value b: at D = 0 it
                    # does not enter (the score test holds it), the refit moves it
                    out.append(self._cand(d, f"{kind}:{v}:{b:.6g}", p, term,
                                          _ratio(unit, uv) if unit else None, var=v,
                                          what=f"a change of slope {side} a break point {bp} "
                                               f"of {v} (started at {b:.4g}; {cause})",
                                          users=users, user_text=user_text,
                                          drift_users=drift_users,
                                          extra=(NewParameter(bp, uv, f"break point of {v} in {d}",
                                                              initial=float(b)),)))
        return out

    def _cand(self, d, reg, p, term, unit, *, var, what, users, user_text, drift_users, extra=()):
        return Candidate(
            effect=self.id, key=f"{self.id}:{d}:{reg}", target=f"definition:{d}",
            explanation=self.explain(coef=d, var=var, what=what, users=user_text),
            parameters=(NewParameter(p, unit, f"nonlinear term {reg} of {d}"),) + tuple(extra),
            add_terms={"definitions": {d: term}},
            info={"regressor": reg, "definition": d, "var": var, "states": drift_users,
                  "users": list(users)})

    def score(self, c, ev):
        return _users_score(c, ev)


def _coefficient_unit(info: ModelInfo, d: str) -> str | None:
    """Unit of definition ``d`` from its constant term: a parameter of its own that appears as
    a term by itself (``CL0`` in ``CL0 + CLAL*alpha``); None when there is none."""
    e = info.definitions_expanded.get(d)
    if e is None:
        return None
    import sympy

    own = info.definition_parameters.get(d, ())
    terms = sympy.Add.make_args(sympy.expand(e))
    for term in terms:
        if isinstance(term, sympy.Symbol) and term.name in own:
            return info.parameter_units.get(term.name)
    # no constant term (Cn = Cnb·β + Cnp·p̂ + …): dimensionless when a derivative times its
    # variable is (Cnb [1/rad] · β [rad] → 1)
    for term in terms:
        if not isinstance(term, sympy.Mul) or len(term.args) != 2:
            continue
        a, b = term.args
        if not (isinstance(a, sympy.Symbol) and isinstance(b, sympy.Symbol)):
            continue
        par, var = (a, b) if a.name in own else (b, a)
        pu, vu = info.parameter_units.get(par.name), info.unit(var.name)
        if par.name in own and pu and vu and _unit_cancels(pu, vu):
            return "1"
    return None


def _unit_cancels(per: str, unit: str) -> bool:
    """Whether ``per`` (a derivative's unit, e.g. ``1/rad``) times ``unit`` (its variable's,
    ``rad``) is dimensionless."""
    from ..errors import SpecError
    from ..spec.units import parse_unit, same

    try:
        return same(parse_unit(f"({per})*({unit})"), parse_unit("1"))
    except SpecError:
        return False


@register_effect
class NonlinearAero(Effect):
    id = "nonlinear_aero"
    title = "nonlinear aerodynamic dependence"
    explanation = ("The {state} equation depends nonlinearly on {var}: {what}. The equation error "
                   "grows with {var} in a way no linear term reproduces (typical of flow "
                   "separation near stall, sideslip-dependent moments or control saturation).")
    doc = ("Squares, products, breaks or saturation in angle of attack, sideslip or a control; "
           "the cube of sideslip.")

    def applies_to(self, info):
        out = []
        flow = [v for v in (info.flow_variable("alpha"), info.flow_variable("beta")) if v]
        nonlin = flow + [u for u in info.input_names if aero_variable(info, u)]
        beta = info.flow_variable("beta")
        # a defined angle (a = atan2(w, u)) is a function of its velocities already: no
        # products with them
        made_of = {a: ({x.name for x in info.definitions_expanded[a].free_symbols}
                       if a in info.defined_flow_angles else set()) for a in flow}
        for s in info.equation_states():
            if kinematic_state(info, s):    # no aerodynamics in θ̇ = q
                continue
            du = _drift_unit(info, s)
            for v in nonlin:
                p = info.fresh(f"D_{s}_{v}{v}")
                out.append(self._cand(info, s, f"sq:{v}", p, f"{p}*{v}**2",
                                      _ratio(du, f"({info.unit(v)})^2" if info.unit(v) else None),
                                      var=v, what=f"a quadratic term {p}·{v}²"))
                if v == beta:
                    p = info.fresh(f"D_{s}_{v}3")
                    out.append(self._cand(info, s, f"cube:{v}", p, f"{p}*{v}**3",
                                          _ratio(du, f"({info.unit(v)})^3" if info.unit(v) else None),
                                          var=v, what=_CUBE_WHAT.format(p=p, v=v)))
                for kind, b in info.breaks.get(v, ()):
                    p = info.fresh(f"D_{s}_{v}_brk")
                    bp = info.fresh(f"D_{s}_{v}_bp", taken=[p])
                    term, side = _break_term(kind, v, p, bp)
                    # the break point is estimated from the located value b (see
                    # CoefficientNonlinearity: held by the score test, moved by the refit)
                    out.append(self._cand(info, s, f"{kind}:{v}:{b:.6g}", p, term,
                                          _ratio(du, info.unit(v)), var=v,
                                          what=f"a change of slope {side} a break point {bp} "
                                               f"of {v} (started at {b:.4g}; "
                                               f"{'a break, e.g. flow separation' if v in flow else 'saturation'})",
                                          extra=(NewParameter(bp, info.unit(v),
                                                              f"break point of {v} in d({s})/dt",
                                                              initial=float(b)),)))
            for a in flow:
                for o in info.state_names + info.input_names:
                    if o == a or o in made_of[a] or not aero_variable(info, o):
                        continue
                    p = info.fresh(f"D_{s}_{a}{o}")
                    out.append(self._cand(info, s, f"prod:{a}*{o}", p, f"{p}*{a}*{o}",
                                          _ratio(du, f"({info.unit(a)})*({info.unit(o)})"
                                                 if info.unit(a) and info.unit(o) else None),
                                          var=f"{a}·{o}",
                                          what=f"the effect of {o} changes with {a} "
                                               f"(product term {p}·{a}·{o})"))
        return out

    def _cand(self, info, s, reg, p, term, unit, *, var, what, extra=()):
        return Candidate(
            effect=self.id, key=f"{self.id}:{s}:{reg}", target=f"drift:{s}",
            explanation=self.explain(state=s, var=var, what=what),
            parameters=(NewParameter(p, unit, f"nonlinear term {reg} in d({s})/dt"),) + tuple(extra),
            add_terms={"drift": {s: term}}, info={"regressor": reg, "state": s})

    def score(self, c, ev):
        return ev.state_score(c.info["state"], c.info["regressor"])


@register_effect
class UnsteadyAero(Effect):
    id = "unsteady_aero"
    title = "unsteady aerodynamics (flow-angle rate / downwash lag)"
    explanation = ("The {state} equation responds to the rate of change of {angle}, not only to "
                   "{angle} itself: downwash from the wing reaches the tail with a lag, giving a "
                   "{angle}-dot derivative ({param}; approximated by a lag state with time "
                   "constant {tau:.3g} s).")
    doc = "alpha-dot / beta-dot derivatives through a downwash-lag state."

    def applies_to(self, info):
        from .locate import downwash_tau
        out = []
        for kind in ("alpha", "beta"):
            a = info.flow_angle(kind)
            if a is None:
                continue
            tau = downwash_tau(info.dt)
            lag = info.fresh(f"D_{a}_lag")
            for s in info.equation_states():
                if s == a or kinematic_state(info, s):   # no downwash in θ̇ = q
                    continue
                p = info.fresh(f"D_{s}_{a}dot", taken=[lag])
                tp = info.fresh(f"D_TAU_{a}_lag", taken=[lag, p])
                out.append(Candidate(
                    effect=self.id, key=f"{self.id}:{s}:{a}", target=f"drift:{s}",
                    explanation=self.explain(state=s, angle=a, param=p, tau=tau),
                    parameters=(NewParameter(p, _ratio(_drift_unit(info, s), info.unit(a) and
                                                       f"({info.unit(a)})/s"),
                                             f"{a}-dot derivative of d({s})/dt"),
                                NewParameter(tp, "s", f"time constant of the {a} lag filter",
                                             initial=tau, fixed=True)),
                    states=(NewState(lag, f"({a} - {lag})/{tp}", info.unit(a),
                                     f"{a} through a first-order lag (downwash lag)"),),
                    add_terms={"drift": {s: f"{p}*({a} - {lag})/{tp}"}},
                    info={"regressor": f"xdot:{a}", "state": s}))
        return out

    def score(self, c, ev):
        return ev.state_score(c.info["state"], c.info["regressor"])


def _input_gains(info: ModelInfo, u: str) -> dict[str, str]:
    gains = {}
    for s in info.state_names:
        if info.depends(s, u):
            g = info.gain_text(s, u)
            if g is not None:
                gains[s] = g
    return gains


def _driving_inputs(info: ModelInfo):
    """(input, {state: gain text}) for every input that enters some state equation."""
    for u in info.input_names:
        gains = _input_gains(info, u)
        if gains:
            yield u, gains


def _is_engine(u: str) -> bool:
    return any(k in u.lower() for k in ("thrust", "throttle", "thr", "engine", "power", "rpm", "pla"))


class _InputDynamics(Effect):
    """Shared form of the delay and lag effects: a new state ``z`` driven by input ``u`` that
    replaces ``u`` in every state equation and every output it enters
    (``f_s += ∂f_s/∂u · (coupling − u)``, ``h_o += ∂h_o/∂u · (coupling − u)``: an output such
    as a measured pitch acceleration sees the same filtered input as the dynamics).
    Subclasses give the names, the time-constant range and the state equation."""

    state_prefix = param_prefix = ""
    min_steps, upper = 1.0, 1.0
    #: the input filter its state realises (:func:`.score.filter_input`): its score statistic
    #: is profiled over the time constant (:func:`.score.screen_input_filters`)
    filter = "lag"

    def pieces(self, info, u, z, tau) -> dict:
        """``coupling`` (replaces u), ``drift`` of z, ``param_doc``, ``state_doc``, ``explain``."""
        raise NotImplementedError

    def lower_bound(self, info) -> float:
        """Smallest time constant (s) the model's transition realises: ``min_steps`` samples."""
        return _lag_bounds(info, self.min_steps)

    def applies_to(self, info):
        out = []
        for u, gains in _driving_inputs(info):
            z = info.fresh(f"D_{u}_{self.state_prefix}")
            tau = info.fresh(f"D_{self.param_prefix}_{u}", taken=[z])
            lo = self.lower_bound(info)
            pc = self.pieces(info, u, z, tau)
            adds = {s: f"{_paren(g)}*({pc['coupling']} - {u})" for s, g in gains.items()}
            out_gains = {o: info.output_gain_text(o, u) for o in info.output_names}
            obs = {o: f"{_paren(g)}*({pc['coupling']} - {u})" for o, g in out_gains.items()
                   if g is not None}
            out.append(Candidate(
                effect=self.id, key=f"{self.id}:{u}", target=f"input:{u}",
                explanation=self.explain(input=u, param=tau, **pc["explain"]),
                parameters=(NewParameter(tau, "s", pc["param_doc"], initial=lo,
                                         lower=lo, upper=self.upper),),
                states=(NewState(z, pc["drift"], info.unit(u), pc["state_doc"]),),
                add_terms={"drift": adds, **({"observations": obs} if obs else {})},
                info={"input": u, "states": tuple(gains), "filter": self.filter,
                      "label_upper": {tau: self.upper}},
                screenable=False))
        return out

    def score(self, c, ev):
        return _input_dynamics_evidence(c, ev)


@register_effect
class ControlDelay(_InputDynamics):
    id = "control_delay"
    title = "control time delay"
    explanation = ("The aircraft responds to {input} later than the recorded {input} signal: a pure "
                   "time delay (transport delay in the control system, filters or data "
                   "acquisition). Modelled as a first-order Padé delay of {param} seconds.")
    doc = "A time delay on one input (first-order Padé state)."
    state_prefix, param_prefix, min_steps, upper = "pade", "DELAY", 2.0, 1.0
    filter = "pade"

    def pieces(self, info, u, z, tau):
        """First-order Padé delay: the delayed input is ``2z − u`` with ``(τ/2) ż = u − z``, a
        lag of τ/2 in the lag's exact discretisation over a held step (:class:`ActuatorLag`):
        drift ``(u − z)(1 − e^{−2h/τ})/h``, the model seeing ``2·mean − u`` with the lag's mean
        over the step, ``u + (z − u)(τ/h)(1 − e^{−2h/τ})``. Stable for every τ > 0 and the
        current model as τ → 0, so the refit starts at its nesting point; the continuous form
        ``ż = 2(u − z)/τ`` under RK4 needs τ ≥ 2 steps, a 0.2-s delay at 10 Hz, which on the
        real HFB-320 record fitted 257 nats below the model without it (the refit was then
        reported as an optimizer failure although it had found that delay's optimum)."""
        docs = {"param_doc": f"time delay of {u}", "state_doc": f"Padé state of the delayed {u}",
                "explain": {}}
        if not info.dt:
            return {"coupling": f"(2*{z} - {u})", "drift": f"2*({u} - {z})/{tau}", **docs}
        h = f"{_lag_step(info):.12g}"
        decay = f"(1 - exp(-2*{h}/{tau}))"
        return {"coupling": f"({u} + ({z} - {u})*{tau}/{h}*{decay})",
                "drift": f"({u} - {z})*{decay}/{h}", **docs}

    def lower_bound(self, info) -> float:
        """Smallest delay (s): ``LAG_MIN_FRACTION`` of a step, as the lag's (the
        discretisation is stable for every τ > 0; :meth:`ActuatorLag.lower_bound`)."""
        if not info.dt:
            return super().lower_bound(info)
        return LAG_MIN_FRACTION * _lag_step(info)


class ContinuousControlDelay(ControlDelay):
    """The first-order Padé delay in its continuous form ``ż = 2(u − z)/τ``, the model seeing
    ``2z − u``: exact under an accurate integration (RK4 with a first-order hold).
    :func:`.search.lag_hold` refits an accepted Padé delay in this form, as it does a lag; not
    in the catalogue (it does not nest the current model: RK4 integrates it stably only for
    ``2h/τ ≤ 2.785``)."""

    def pieces(self, info, u, z, tau):
        return {"coupling": f"(2*{z} - {u})", "drift": f"2*({u} - {z})/{tau}",
                "param_doc": f"time delay of {u}", "state_doc": f"Padé state of the delayed {u}",
                "explain": {}}

    def lower_bound(self, info) -> float:
        """Twice the continuous lag's bound (the Padé state is a lag of τ/2): under RK4
        ``2 · RK4_LAG_MIN_STEPS`` of a step, under Euler two steps."""
        return 2.0 * ContinuousActuatorLag.lower_bound(self, info)


@register_effect
class TransportDelay(Effect):
    id = "transport_delay"
    title = "input transport delay"
    explanation = ("The aircraft responds to {input} later than the recorded {input} signal: a "
                   "pure transport delay (control system, filters, data acquisition) of "
                   "{delay} s, found by profiling the fit over delays of whole and fractional "
                   "samples up to about a second. Modelled by shifting the recorded {input} "
                   "itself (linear interpolation between samples; in the spec: input {input} "
                   "with `delay: {spec_delay}`); no state is added.")
    doc = ("A pure time delay of one input in seconds, u(t − τ), realised by shifting the input "
           "(fractional samples by interpolation); τ is profiled over a grid, not refitted "
           "from zero (:mod:`vsidgen.discrepancy.delay`).")

    def applies_to(self, info):
        out = []
        for u, gains in _driving_inputs(info):
            out.append(Candidate(
                effect=self.id, key=f"{self.id}:{u}", target=f"input:{u}",
                explanation=self.explain(input=u, delay="τ", spec_delay="τ"),
                info={"input": u, "states": tuple(gains), "profile": "delay",
                      "filter": "delay"},
                screenable=False))
        return out

    def score(self, c, ev):
        return _input_dynamics_evidence(c, ev)


@register_effect
class ActuatorLag(_InputDynamics):
    id = "actuator_lag"
    title = "actuator or engine lag"
    explanation = ("The recorded {input} is not what acts on the aircraft: the {what} responds "
                   "with a first-order lag (time constant {param}); the model uses the commanded "
                   "value directly.")
    doc = "A first-order actuator (or engine, for thrust inputs) state between input and aircraft."
    state_prefix, param_prefix, min_steps, upper = "act", "TAU", 1.0, 5.0

    def pieces(self, info, u, z, tau):
        """The lag's exact discretisation over a step ``h = dt/substeps`` with the input held,
        ``z_{k+1} = u + (z_k − u) e^{−h/τ}`` (drift ``(u − z)(1 − e^{−h/τ})/h``), the model
        seeing the lag's mean over the step, ``u + (z − u)(τ/h)(1 − e^{−h/τ})``. It is stable
        for every τ > 0 under Euler and RK4 (the drift's rate is at most ``1/h``) and tends to
        the model without the lag as τ → 0 (the mean becomes the input itself), so a refit
        from the lower bound starts at the current model whatever the integrator. Under an
        Euler step it is exact; under RK4 it is the lag to first order in frequency (the
        continuous form, :class:`ContinuousActuatorLag`, is refitted after acceptance,
        :func:`.search.lag_hold`). The plain Euler step of ``τ ż = u − z`` acts through
        ``z_k``, a whole step behind its own input (on test_delay_screen's independent 0.12 s
        lag at 20 Hz it fitted worse, 2ΔELBO 58.5 against 66.4); the continuous form under
        RK4 is unstable below 0.36 of a step, so a refit from its bound started 0.4 of a
        step away from the current model."""
        docs = _lag_docs(u)
        drift, increment = _held_lag(info, u, z, tau)
        return {"coupling": z if not info.dt else f"({u} + {increment})", "drift": drift,
                **docs}

    def lower_bound(self, info) -> float:
        """Smallest time constant (s): ``LAG_MIN_FRACTION`` of a step ``h = dt/substeps``. The
        exact discretisation is stable for every τ > 0, so the bound only keeps the lag's
        distance from the current model small: at τ the model sees the input moved by about
        τ/h of a step (``(τ/h)(1 − e^{−h/τ})`` of the previous step's value), whose cost in
        ELBO grows with that shift squared."""
        return LAG_MIN_FRACTION * _lag_step(info)


def _lag_docs(u: str) -> dict:
    """The lag parameter's and state's descriptions for input ``u``."""
    what = "engine (thrust response)" if _is_engine(u) else "actuator / control surface"
    return {"param_doc": f"lag time constant of {u}", "state_doc": f"lagged {u} ({what})",
            "explain": {"what": what}}


def _held_lag(info, x: str, z: str, tau: str) -> tuple[str, str]:
    """Drift of a lag state ``z`` of ``x`` with time constant ``tau`` and the increment
    ``mean − x`` of what is seen: the exact discretisation over a held step ``h``
    (:meth:`ActuatorLag.pieces`), drift ``(x − z)(1 − e^{−h/τ})/h``, the step's mean
    ``x + (z − x)(τ/h)(1 − e^{−h/τ})``; the continuous form without a sample period."""
    if not info.dt:
        return f"({x} - {z})/{tau}", f"({z} - {x})"
    h = f"{_lag_step(info):.12g}"
    decay = f"(1 - exp(-{h}/{tau}))"
    return f"({x} - {z})*{decay}/{h}", f"({z} - {x})*{tau}/{h}*{decay}"


def _lag_step(info) -> float:
    """The integration step ``h = dt/substeps`` of the model described by ``info`` (s)."""
    return float(info.dt or 0.01) / max(int(info.substeps or 1), 1)


class ContinuousActuatorLag(ActuatorLag):
    """The actuator lag in its continuous form ``τ ż = u − z``, acting through ``z``: exact
    under an accurate integration (RK4 with a first-order hold, where the input moves between
    samples as in flight). :func:`.search.lag_hold` refits an accepted lag in this form; it is
    not in the catalogue (it does not nest the current model: RK4 integrates it stably only
    down to ``RK4_LAG_MIN_STEPS`` of a step)."""

    def pieces(self, info, u, z, tau):
        return {"coupling": z, "drift": f"({u} - {z})/{tau}", **_lag_docs(u)}

    def lower_bound(self, info) -> float:
        """RK4 is stable for ``h/τ ≤ 2.785``: ``RK4_LAG_MIN_STEPS`` of a step; an Euler step
        of this form is only stable down to half a step and a whole step behind its input:
        one step."""
        return (RK4_LAG_MIN_STEPS if (info.integrator or "euler") != "euler" else 1.0) * _lag_step(info)


@register_effect
class SensorBias(Effect):
    id = "sensor_bias"
    title = "sensor bias"
    explanation = ("The {output} sensor reads with a constant offset ({param}): the residual "
                   "of {output} has a mean that measurement noise cannot explain.")
    doc = "A constant offset on one output channel."

    def applies_to(self, info):
        out = []
        for o in info.output_names:
            p = info.fresh(f"D_BIAS_{o}")
            out.append(Candidate(
                effect=self.id, key=f"{self.id}:{o}", target=f"output:{o}",
                explanation=self.explain(output=o, param=p),
                parameters=(NewParameter(p, info.unit(o), f"bias of the {o} sensor"),),
                add_terms={"observations": {o: p}}, info={"output": o}))
        return out

    def score(self, c, ev):
        return ev.output_score(c.info["output"], "bias")


@register_effect
class SensorScale(Effect):
    id = "sensor_scale"
    title = "sensor scale-factor error"
    explanation = ("The {output} sensor has a scale-factor (gain) error ({param}): its residual "
                   "is proportional to {output} itself (calibration error, wrong unit factor, "
                   "upwash on a flow vane).")
    doc = "A multiplicative error on one output channel."

    def applies_to(self, info):
        out = []
        for o in info.output_names:
            h = info.observations.get(o)
            if not h:
                continue
            p = info.fresh(f"D_SCALE_{o}")
            out.append(Candidate(
                effect=self.id, key=f"{self.id}:{o}", target=f"output:{o}",
                explanation=self.explain(output=o, param=p),
                parameters=(NewParameter(p, "1", f"scale-factor error of the {o} sensor"),),
                add_terms={"observations": {o: f"{p}*{_paren(h)}"}}, info={"output": o}))
        return out

    def score(self, c, ev):
        return ev.output_score(c.info["output"], "scale")


_ACCEL = ("ax", "ay", "az", "an", "a_x", "a_y", "a_z", "nx", "ny", "nz")
_SPEED_CONSTANTS = ("v0", "vt0", "vtas0", "vo", "u0", "uo", "u_0", "u", "vtrim", "v_0", "vref",
                    "v", "vt")


def airspeed_name(info: ModelInfo) -> str | None:
    """The model's own true airspeed: a state named like V/VT/TAS with a speed unit, else an
    input of that kind (a measured airspeed the model is driven with), else a constant named
    like V0/VT0/U0/U/Vtrim (the trim speed of a linear model), else None."""
    roles = {**roles_of(info.inputs), **info.state_roles}
    for v in info.states + info.inputs:
        if roles.get(v.name) == "V" and (v.unit or "").replace(
                " ", "") in ("m/s", "ft/s", "kt", "km/h"):
            return v.name
    by_lower = {c.lower(): c for c in info.constants}
    for name in _SPEED_CONSTANTS:
        if name in by_lower:
            return by_lower[name]
    return None



def speed_in_mps(info: ModelInfo, name: str) -> str:
    """Spec text of the model's airspeed ``name`` (a state, input or constant) in m/s: the name
    itself where its unit is m/s (or none), else the name times its unit's factor
    (``(0.514444444444*V)`` for V in kt, ``(0.3048*V)`` in ft/s), so that a lever arm over V
    comes out in metres whatever unit the user wrote the speed in."""
    from ..spec.units import coherent

    unit = info.unit(name) or (getattr(info, "constant_units", None) or {}).get(name)
    try:
        factor, shown = coherent(unit or "")
    except Exception:          # no unit the parser reads: the number as it stands
        return name
    if factor == 1.0 or shown.replace(" ", "") != "m/s":
        return name
    return f"({factor!r}*{name})"


_AXES = ("x", "y", "z")


def _arm_terms(arm: str, axis: str, rates: dict[str, str | None],
               rdots: dict[str, str | None]) -> list[str]:
    """Spec-text terms of the specific-force change along body ``axis`` per metre of lever
    arm along ``arm``: the ``axis`` component of ``ω̇ × e + ω × (ω × e)`` (``e`` the unit
    vector of ``arm``; ω = (p, q, r), rates the model lacks are zero, ω̇ from their drifts).

    ``ω̇ × e``: x-arm (0, ṙ, −q̇), y-arm (−ṙ, 0, ṗ), z-arm (q̇, −ṗ, 0);
    ``ω × (ω × e) = ω (ω·e) − e |ω|²``: x-arm (−(q²+r²), pq, pr), y-arm (pq, −(p²+r²), qr),
    z-arm (pr, qr, −(p²+q²)).
    """
    i, j = _AXES.index(arm), _AXES.index(axis)
    w = [rates.get(k) for k in "pqr"]
    wd = [rdots.get(k) for k in "pqr"]
    out = []
    # ω̇ × e, component j: ε_{j k i} ω̇_k  (e = unit vector i)
    for k in range(3):
        eps = _levi(j, k, i)
        if eps and wd[k]:
            out.append(("" if eps > 0 else "-") + _paren(wd[k]))
    # ω (ω·e) − e |ω|²: ω_j ω_i − δ_ij Σ ω_k²
    if i != j:
        if w[i] and w[j]:
            out.append(f"{w[j]}*{w[i]}")
    else:
        for k in range(3):
            if k != i and w[k]:
                out.append(f"-{w[k]}**2")
    return out


def _levi(a: int, b: int, c: int) -> int:
    return (a - b) * (b - c) * (c - a) // 2


#: (measured axis, rate) -> arm of the accelerometer candidates named by that rate:
#: az − x q̇, ax + z q̇, ay + x ṙ, ay − z ṗ, az + y ṗ (x ahead, y right, z below the CG)
_ARM_OF_RATE = {("z", "q"): "x", ("x", "q"): "z", ("y", "r"): "x", ("y", "p"): "z",
                ("z", "p"): "y"}
_WHERE = {"x": "ahead of the CG (body x)", "y": "right of the CG (body y)",
          "z": "below the CG (body z)"}


@register_effect
class SensorPosition(Effect):
    id = "sensor_position"
    title = "sensor position offset"
    explanation = ("The {output} sensor is not at the centre of gravity: {what}. The residual of "
                   "{output} follows {signal}.{reference}")
    doc = "Flow-angle vanes and accelerometers away from the centre of gravity."

    #: vane lever arms: (angle, rate) -> (sign of the term, what the distance is). Local air
    #: velocity at r from the CG is v + ω × r: a vane x ahead sees w − q x (α − x q/V) and
    #: v + r x (β + x r/V); a vane h above the CG (z = −h) sees v + p h (β + h p/V).
    _VANE = {("alpha", "q"): ("-", "ahead of the CG (body x)", "x", 1.0),
             ("beta", "r"): ("", "ahead of the CG (body x)", "x", 1.0),
             ("beta", "p"): ("", "above the CG (−body z)", "z", -1.0)}

    @staticmethod
    def _reference(info, sensor, axis, sign):
        """Text comparing with the aircraft constants' position of ``sensor``, and the value."""
        fl = info.flight
        pos = None if fl is None else fl.sensors.get(sensor)
        if pos is None:
            return "", None
        v = sign * pos[_AXES.index(axis)]
        src = fl.constants_file.name if fl.constants_file is not None else "aircraft constants"
        return (f" The aircraft constants ({src}) put the {sensor} at {v:.4g} m on this axis "
                f"(x, y, z from the CG = {pos[0]:g}, {pos[1]:g}, {pos[2]:g} m)."), v

    def _vane(self, info, o, r, p, kind, speed, speed_source):
        sign, where, axis, axsign = self._VANE[(kind, info.state_roles[r])]
        # x·r/V is in radians with r in rad/s: in the vane's unit (degrees too)
        k = info.radians_per(r) / info.radians_per(o)
        if speed is not None:
            speed_mps = speed_in_mps(info, speed)     # V in kt or ft/s: the arm still in metres
            ref, refv = self._reference(info, "noseboom", axis, axsign)
            what = (f"a flow vane {p} m {where} sees the induced angle "
                    f"{sign or '+'}{p}·{r}/V of the rotation {r} (local air velocity v + ω × r; "
                    f"V = {speed}, {speed_source})")
            return Candidate(
                effect=self.id, key=f"{self.id}:{o}:{r}", target=f"output:{o}",
                explanation=self.explain(output=o, what=what, signal=f"the rate {r}",
                                         reference=ref),
                parameters=(NewParameter(p, "m", f"{o} vane distance {where}"),),
                add_terms={"observations": {o: f"{sign}{p}*{_times(k, r)}/{speed_mps}"}},
                info={"output": o, "regressor": f"rate:{r}", "airspeed": speed,
                      "airspeed_source": speed_source, "reference_m": refv})
        what = (f"a flow vane ahead of/above the CG sees an induced angle proportional to the "
                f"{r} rate ({p} = {'−' if sign == '-' else ''}distance {where} / airspeed, in s; "
                f"neither the model nor the records nor the aircraft constants give an airspeed "
                f"to express it in metres)")
        return Candidate(
            effect=self.id, key=f"{self.id}:{o}:{r}", target=f"output:{o}",
            explanation=self.explain(output=o, what=what, signal=f"the rate {r}", reference=""),
            parameters=(NewParameter(p, "s", f"{o} vane position / airspeed ({r})"),),
            add_terms={"observations": {o: f"{p}*{r}"}},
            info={"output": o, "regressor": f"rate:{r}", "airspeed": None})

    def _accel(self, info, o, axis, arm, key_suffix, regressor):
        rates = {k: None for k in "pqr"}
        rdots = {k: None for k in "pqr"}
        roles = info.state_roles
        for s in info.rate_states():
            k = info.radians_per(s)  # rates in rad/s, their drifts in rad/s² (degrees too)
            rates[roles[s]] = s if k == 1.0 else _paren(_times(k, s))
            rdots[roles[s]] = _times(k, info.drift[s]) if info.drift.get(s) else None
        terms = _arm_terms(arm, axis, rates, rdots)
        if not terms:
            return None
        p = info.fresh(f"D_ARM_{o}_{arm}" if key_suffix.startswith("arm_") else
                       f"D_ARM_{o}_{key_suffix}")
        unit = (info.unit(o) or "").replace(" ", "")
        g, _ = _gravity(info)
        body = " + ".join(terms).replace("+ -", "- ")
        term = f"{p}*({body})" + (f"/{g!r}" if unit == "g" else "")
        ref, refv = self._reference(info, "accelerometer", arm, 1.0)
        what = (f"an accelerometer {p} m {_WHERE[arm]} measures, besides the CG's specific "
                f"force, the tangential and centripetal accelerations of the rotation, "
                f"{p}·({body}){'/g' if unit == 'g' else ''} (the {axis} component of "
                f"ω̇ × r + ω × (ω × r))")
        return Candidate(
            effect=self.id, key=f"{self.id}:{o}:{key_suffix}", target=f"output:{o}",
            explanation=self.explain(output=o, what=what,
                                     signal=(f"the angular acceleration d({regressor})/dt"
                                             if regressor else "the squared rates"),
                                     reference=ref),
            parameters=(NewParameter(p, "m", f"{o} accelerometer distance {_WHERE[arm]}"),),
            add_terms={"observations": {o: term}},
            info={"output": o, "regressor": f"accel:{regressor}" if regressor else None,
                  "arm": arm, "reference_m": refv})

    def _generic_accel(self, info, o, rates):
        """An acceleration channel of unknown axis (``an``, ``nz``): a lever arm times each
        angular acceleration, sign and axis left to the estimate."""
        out = []
        g_unit = (info.unit(o) or "").strip() == "g"
        g, _ = _gravity(info)
        for r in rates:
            rdot = info.drift.get(r)
            if not rdot:
                continue
            p = info.fresh(f"D_ARM_{o}_{r}")
            term = f"{p}*{_paren(_times(info.radians_per(r), rdot))}" + (
                f"/{g!r}" if g_unit else "")
            what = (f"an accelerometer at a lever arm {p} m from the CG measures the tangential "
                    f"acceleration {p}·d({r})/dt{'/g' if g_unit else ''} (ω̇ × r)")
            out.append(Candidate(
                effect=self.id, key=f"{self.id}:{o}:{r}", target=f"output:{o}",
                explanation=self.explain(output=o, what=what,
                                         signal=f"the angular acceleration d({r})/dt", reference=""),
                parameters=(NewParameter(p, "m", f"{o} accelerometer lever arm from the CG"),),
                add_terms={"observations": {o: term}},
                info={"output": o, "regressor": f"accel:{r}"}))
        return out

    def applies_to(self, info):
        out = []
        rates = info.rate_states()
        speed = airspeed_name(info)
        speed_source = f"the model's {speed}" if speed else ""
        if speed is None and info.flight is not None and info.flight.airspeed is not None:
            speed = repr(round(float(info.flight.airspeed.value), 4))
            speed_source = info.flight.airspeed.source
        out_roles = info.output_roles
        for o in info.output_names:
            ms = info.measured_state(o)
            kind = None
            orole = out_roles.get(o)
            if ms is not None and info.flow_angle("alpha") == ms or orole == "alpha":
                kind = "alpha"
            elif ms is not None and info.flow_angle("beta") == ms or orole == "beta":
                kind = "beta"
            elif orole in ("ax", "ay", "az") or o.lower() in _ACCEL or (
                    info.unit(o) or "").replace(" ", "") in ("m/s^2", "m/s**2", "g"):
                kind = "accel"
            if kind is None:
                continue
            if kind in ("alpha", "beta"):
                for r in rates:
                    rl = info.state_roles.get(r)
                    if (kind == "alpha" and rl != "q") or (kind == "beta" and rl not in ("p", "r")):
                        continue
                    p = info.fresh(f"D_POS_{o}_{r}")
                    out.append(self._vane(info, o, r, p, kind, speed, speed_source))
                continue
            if o.lower() in _ACCEL:
                # ax/a_y...; an, nx, nz (load factors, sign conventions vary): generic
                axis = o.lower()[-1] if o.lower().startswith("a") and o.lower()[-1] in _AXES \
                    else None
            else:
                # named otherwise, recognised by its description ("normal acceleration")
                axis = orole[-1] if orole in ("ax", "ay", "az") else None
            if axis is None:
                out.extend(self._generic_accel(info, o, rates))
                continue
            for r in rates:
                arm = _ARM_OF_RATE.get((axis, info.state_roles.get(r)))
                if arm is None or not info.drift.get(r):
                    continue
                c = self._accel(info, o, axis, arm, r, r)
                if c is not None:
                    out.append(c)
            # the arm along the measured axis itself: only the centripetal −ℓ(ω_k² + ω_l²)
            c = self._accel(info, o, axis, axis, f"arm_{axis}", None)
            if c is not None:
                out.append(c)
        return out

    def score(self, c, ev):
        reg = c.info.get("regressor")
        return ev.output_score(c.info["output"], reg) if reg else 0.0


@register_effect
class TimeSkew(Effect):
    id = "time_skew"
    title = "time skew between channels"
    explanation = ("The {output} channel is shifted in time against the other channels by "
                   "{param} seconds (sensor or data-acquisition latency, unsynchronised "
                   "recorders): its residual follows the rate of {output}. A positive "
                   "{param} means the channel is late; an early channel is non-causal and is "
                   "not accepted under this label (a vane ahead of the CG reads early).")
    doc = "A time shift of one output channel, first order: h(t−τ) ≈ h − τ dh/dt."

    def applies_to(self, info):
        import sympy
        out = []
        for o in info.output_names:
            h = info.observations_expanded.get(o)
            if h is None:
                continue
            pieces = []
            for s in info.state_names:
                d = sympy.diff(h, info.symbol(s))
                if d == 0:
                    continue
                dt_ = spec_text(d)
                if dt_ is None:
                    pieces = None
                    break
                pieces.append(f"{_paren(dt_)}*{_paren(info.drift[s])}" if dt_ != "1"
                              else _paren(info.drift[s]))
            if not pieces:
                continue
            p = info.fresh(f"D_SKEW_{o}")
            out.append(Candidate(
                effect=self.id, key=f"{self.id}:{o}", target=f"output:{o}",
                explanation=self.explain(output=o, param=p),
                parameters=(NewParameter(p, "s", f"time skew of the {o} channel (positive: late)",
                                         lower=-1.0, upper=1.0),),
                add_terms={"observations": {o: f"-{p}*({' + '.join(pieces)})"}},
                info={"output": o, "causal_sign": {p: 1}}))
        return out

    def score(self, c, ev):
        s = ev.output_score(c.info["output"], "rate")
        o = ev.outputs.get(c.info["output"])
        if s > 0 and o is not None and abs(o.lag_s) >= 0.5 * ev.dt:
            s += 3.0    # the cross-correlation peak is shifted: a skew, not a rate-proportional term
        return s


@register_effect
class SensorLag(Effect):
    id = "sensor_lag"
    title = "sensor lag (first-order sensor dynamics)"
    explanation = ("The {output} sensor does not follow the motion at once: it reads through "
                   "first-order dynamics of time constant {param} (vane inertia, pneumatic "
                   "tubing, an anti-aliasing or data-system filter), so its residual follows "
                   "the rate of {output} and fast changes are attenuated. To first order in "
                   "frequency a lag of τ and a time skew of τ are the same; the lag also "
                   "attenuates.")
    doc = ("First-order dynamics of one sensor: a state z with ``τ ż = h − z`` read instead of "
           "the output ``h``, in the held-step exact discretisation the actuator lag uses "
           "(nests the current model as τ → 0). Refitted beside a time skew or a position "
           "of the same channel (:func:`.search.choose_refits`), the two forms it competes "
           "with to first order.")

    def applies_to(self, info):
        import sympy
        out = []
        for o in info.output_names:
            h = info.observations_expanded.get(o)
            text = info.observations.get(o)
            if h is None or not text or not any(
                    sympy.diff(h, info.symbol(s)) != 0 for s in info.state_names):
                continue
            z = info.fresh(f"D_{o}_read")
            tau = info.fresh(f"D_TAU_SENSOR_{o}", taken=[z])
            step = _lag_step(info)
            lo = LAG_MIN_FRACTION * step
            drift, read = _held_lag(info, _paren(str(text)), z, tau)
            start = max(lo, float(info.dt or step))     # one sample: in the lag's basin
            out.append(Candidate(
                effect=self.id, key=f"{self.id}:{o}", target=f"output:{o}",
                explanation=self.explain(output=o, param=tau),
                parameters=(NewParameter(tau, "s", f"time constant of the {o} sensor",
                                         initial=start, lower=lo, upper=2.0),),
                states=(NewState(z, drift, info.unit(o), f"{o} as its lagged sensor reads it"),),
                add_terms={"observations": {o: read}},
                info={"output": o, "start_from_screen_s": start, "label_upper": {tau: 2.0}},
                screenable=False))
        return out

    def score(self, c, ev):
        return ev.output_score(c.info["output"], "rate")


@register_effect
class MissingDynamics(Effect):
    id = "missing_dynamics"
    title = "missing state dynamics"
    explanation = ("The {state} equation is driven by a dynamic mode the model omits (a slow "
                   "one: the speed/attitude (phugoid) motion absent from a short-period model, "
                   "an engine state; a fast one: an actuator, a sensor filter): its equation "
                   "error follows {var} filtered through a first-order lag. Added as a new "
                   "state {mode} with dynamics d({mode})/dt = -{mode}/{tau} + {gain}·{var}.")
    doc = ("A first-order mode driven by a state or input, feeding one state equation (not an "
           "attitude or position equation, which is exact geometry).")

    def applies_to(self, info):
        from .locate import LOWPASS_TAU
        out = []
        for s in info.equation_states():
            if kinematic_rates(info, s) is not None:
                continue    # no mode acts on an attitude or position rate (exact geometry)
            for v in info.state_names + info.input_names:
                m = info.fresh(f"D_MODE_{s}")
                tau = info.fresh(f"D_TAU_MODE_{s}", taken=[m])
                k = info.fresh(f"D_K_MODE_{s}_{v}", taken=[m, tau])
                lo = _lag_bounds(info, 4.0)
                out.append(Candidate(
                    effect=self.id, key=f"{self.id}:{s}:{v}", target=f"drift:{s}",
                    explanation=self.explain(state=s, var=v, mode=m, tau=tau, gain=k),
                    parameters=(NewParameter(k, None, f"gain of {v} into the missing mode"),
                                NewParameter(tau, "s", "time constant of the missing mode",
                                             initial=LOWPASS_TAU, lower=lo, upper=100.0)),
                    states=(NewState(m, f"-{m}/{tau} + {k}*{v}", _drift_unit(info, s),
                                     f"missing mode feeding d({s})/dt"),),
                    add_terms={"drift": {s: m}},
                    info={"state": s, "regressor": f"lp:{v}", "mode_driver": v,
                          "mode_tau": LOWPASS_TAU, "mode_gain": k, "dt": info.dt,
                          "driver_role": info.state_roles.get(v),
                          "driver_is_input": v in info.input_names}))
        return out

    def check_estimates(self, c, estimates):
        """What the fitted time constant says the mode is: at its lower bound (a few
        integration steps) a fast filter of the driver, not a slow mode — an actuator or
        sensor lag, which the lag candidates model with their own parameters; at its upper
        bound a drift slower than the model can place (a slowly varying bias); between them,
        a mode of that time constant, fast or slow against the sample period."""
        tau_p = c.parameters[1]
        tau, _ = estimates.get(tau_p.name, (None, None))
        if tau is None or not math.isfinite(tau) or tau <= 0:
            return ""
        lo, hi = tau_p.lower, tau_p.upper
        dt = c.info.get("dt")
        var = c.info.get("mode_driver")
        if lo is not None and tau <= 1.05 * lo:
            steps = f" ({tau / dt:.3g} sample periods)" if dt else ""
            text = (f" Physics check: its time constant {tau_p.name} = {tau:.3g} s is at its "
                    f"lower bound{steps}: not a slow mode but a fast filtering of {var}")
            if c.info.get("driver_is_input"):
                return text + (" — an actuator or a sensor lag of the input, which the "
                               "actuator-lag and control-delay candidates model with physical "
                               "parameters; here the gain and time constant are nearly "
                               "interchangeable (wide standard errors).")
            return text + (" — an unsteady-aerodynamic or sensor lag; the gain and time "
                           "constant are nearly interchangeable there (wide standard errors).")
        if hi is not None and tau >= 0.95 * hi:
            text = (f" Physics check: its time constant {tau_p.name} = {tau:.3g} s is at its "
                    f"upper bound: slower than the model can place, so the mode is the running "
                    f"integral of {var} over the record")
            angle = {"p": "bank", "q": "pitch attitude", "r": "heading"}.get(
                c.info.get("driver_role") or "")
            if angle:
                return text + (f" — the {angle} change: the {c.info.get('state')} equation "
                               f"depends on the {angle} (through gravity or the speed "
                               "(phugoid) motion the model leaves out), not a resolved "
                               "dynamic mode.")
            return text + (f": a slowly varying bias of the {c.info.get('state')} equation, "
                           "or a trim that changes during the record, not a resolved dynamic "
                           "mode.")
        if dt and tau < 10.0 * dt:
            return (f" Physics check: {tau_p.name} = {tau:.3g} s ({tau / dt:.3g} sample periods): "
                    f"a fast mode — an actuator, a sensor filter or an unsteady-aerodynamic lag "
                    "rather than the speed or an engine state.")
        return ""

    def score(self, c, ev):
        # the missing-mode signature: low-passed regressor, weighed down against a plain
        # linear term in the same variable (that is missing_derivative's job)
        s, reg = c.info["state"], c.info["regressor"]
        v = reg.split(":", 1)[1]
        lin = max(ev.state_score(s, f"x:{v}"), ev.state_score(s, f"u:{v}"))
        return max(0.0, ev.state_score(s, reg) - 0.5 * lin)


def _speed_value(info: ModelInfo) -> tuple[str | None, str]:
    """(spec text of the trim airspeed V₀ in m/s, where it came from): the model's own
    airspeed state/constant, else the flight conditions' number (record mean or the aircraft
    constants file), else (None, reason)."""
    own = airspeed_name(info)
    if own is not None:
        return speed_in_mps(info, own), f"the model's {own}"
    fl = info.flight
    if fl is not None and fl.airspeed is not None:
        return repr(round(float(fl.airspeed.value), 4)), fl.airspeed.source
    return None, "no airspeed in the model, the records or the aircraft constants"


def _number(text: str | None, info: ModelInfo) -> float | None:
    """The value of ``text``: a number, or the name of one of the model's constants."""
    if text is None:
        return None
    try:
        return float(text)
    except ValueError:
        v = (getattr(info, "constant_values", None) or {}).get(text)
        unit = ((getattr(info, "constant_units", None) or {}).get(text) or "").replace(" ", "")
        return None if v is None or unit != "m/s" else float(v)


def _gravity(info: ModelInfo) -> tuple[float, str]:
    fl = info.flight
    if fl is not None and fl.gravity is not None:
        return float(fl.gravity.value), fl.gravity.source
    for k, v in info.constant_values.items():
        if k.lower() in ("g", "g0"):
            return float(v), f"spec constant {k}"
    return 9.80665, "standard gravity"


@register_effect
class SpeedDynamics(Effect):
    id = "speed_dynamics"
    title = "speed (phugoid) dynamics missing"
    explanation = ("The short-period model holds the airspeed constant, but the aircraft "
                   "trades height for speed along its flight path (the phugoid): the speed "
                   "perturbation {dV} (m/s) changes lift ({zv}, into the {alpha} equation{az}) "
                   "and pitching moment ({mv}, into the {q} equation). Added as the standard "
                   "longitudinal speed equation d({dV})/dt = {xv}·{dV} + {xa}·{alpha} − g·γ "
                   "(drag/thrust change with speed and with {alpha}, gravity along the flight "
                   "path γ) {closure}; g = {g:.5g} m/s² ({g_source}); trim airspeed {v0} "
                   "({v_source}).")
    #: the two kinematic closures of the path angle γ = θ − α_inertial (see ``doc``)
    CLOSURES = {
        "air": ("with the path-angle perturbation d({ang})/dt = {q} − d({alpha})/dt from the "
                "model's {alpha} equation: the part of the measured {alpha} that its process "
                "noise carries (gusts: an air-relative vane) does not move the flight path"),
        "attitude": ("with γ = {ang} − {alpha} from the pitch-attitude perturbation "
                     "d({ang})/dt = {q}: the measured {alpha} is the inertial angle of attack "
                     "(process noise acts on the motion itself, e.g. α from inertial data)"),
    }
    doc = ("The speed degree of freedom a short-period (α, q) model leaves out: ΔV̇ = X_V ΔV + "
           "X_α α − g Δγ, α̇ += Z_V ΔV, q̇ += M_V ΔV (a vertical accelerometer += V₀ Z_V ΔV), "
           "with g and V₀ from the spec, the records or the aircraft constants. Two closures of "
           "the path angle γ = θ − α_inertial, two candidates: ``speed_dynamics:α:q`` "
           "integrates Δγ̇ = q − α̇ with α̇ the model's α equation without its process noise "
           "(right when α is air-relative, a vane in turbulence: a gust changes the measured α "
           "but not the path; the real Twin Otter record), ``speed_dynamics:α:q:attitude`` "
           "carries the attitude, Δθ̇ = q, and Δγ = Δθ − α (right when α is the inertial "
           "angle and the α equation's process noise moves the aircraft; the independent "
           "simulator's records, where the air-relative closure's Δγ drifts from θ − α and its "
           "refit stalls). The evidence decides between them.")

    def applies_to(self, info):
        a = info.flow_angle("alpha")
        q = info.state_with_role("q")
        if a is None or q is None:
            return []
        own = airspeed_name(info)
        if own is not None and (own in info.state_names or own in info.input_names):
            # the model has a speed state already, or is driven by the measured airspeed
            # (its speed variations are in the model through that input)
            return []
        if info.state_with_role("V") or any(s.lower() == "u" for s in info.state_names):
            return []
        return [self._candidate(info, a, q, closure) for closure in self.CLOSURES]

    def _candidate(self, info, a, q, closure):
        dv = info.fresh("D_dV")
        ang = info.fresh("D_dgamma" if closure == "air" else "D_dtheta", taken=[dv])
        xv, xa, zv, mv = (info.fresh(n, taken=[dv, ang]) for n in
                          ("D_XV", "D_Xalpha", "D_ZV", "D_MV"))
        g, g_source = _gravity(info)
        v0, v_source = _speed_value(info)
        au = info.unit(a) or "rad"
        qu = info.unit(q) or "rad/s"
        params = (
            NewParameter(xv, "1/s", "X_V: speed damping (drag and thrust change with speed)"),
            NewParameter(xa, f"(m/s^2)/({au})", f"X_alpha: speed derivative of {a} "
                                                 "(lift tilt / induced drag)"),
            NewParameter(zv, f"({au})/m", f"Z_V: change of d({a})/dt with speed (lift), per m/s"),
            NewParameter(mv, f"({qu})/m", f"M_V: change of d({q})/dt with speed, per m/s"))
        # angles in α's unit and q's in its own (degrees too): gravity along the path and the
        # vertical accelerometer need radians, the attitude integrates q in α's unit
        ka, kq = info.radians_per(a), info.radians_per(q)
        obs = {}
        for o in info.output_names:
            if info.output_roles.get(o) == "az" and v0 is not None:
                unit = (info.unit(o) or "").replace(" ", "")
                if unit in ("m/s^2", "m/s**2"):
                    obs[o] = f"{v0}*{_times(ka, zv)}*{dv}"
                elif unit == "g":
                    obs[o] = f"{v0}*{_times(ka, zv)}*{dv}/{g!r}"
        adds = {"drift": {a: f"{zv}*{dv}", q: f"{mv}*{dv}"}}
        if obs:
            adds["observations"] = obs
        if closure == "air":
            gamma = ang
            angle_state = NewState(ang, f"{_times(kq / ka, q)} - ({info.drift[a]}) - {zv}*{dv}", au,
                                   "flight-path-angle perturbation (θ − α without the "
                                   "air-mass part of α)", physical=True)
        else:
            gamma = f"({ang} - {a})"
            angle_state = NewState(ang, _times(kq / ka, q), au, "pitch-attitude perturbation (its start "
                                                    "absorbs the trim of the speed equation)",
                                   physical=True)
        states = (NewState(dv, f"{xv}*{dv} + {xa}*{a} - {g * ka!r}*{gamma}", "m/s",
                           "airspeed perturbation from trim (phugoid)", physical=True),
                  angle_state)
        return Candidate(
            effect=self.id, key=f"{self.id}:{a}:{q}" + ("" if closure == "air" else ":attitude"),
            target=f"drift:{a}",
            explanation=self.explain(dV=dv, alpha=a, q=q, xv=xv, xa=xa, zv=zv, mv=mv,
                                     closure=self.CLOSURES[closure].format(ang=ang, alpha=a, q=q),
                                     g=g, g_source=g_source,
                                     v0=(f"{v0} m/s" if v0 and v0[0].isdigit() else v0 or "—"),
                                     v_source=v_source,
                                     az=(f" and the vertical accelerometer {', '.join(obs)}"
                                         if obs else "")),
            parameters=params, states=states, add_terms=adds,
            info={"states": (a, q), "regressor": SPEED_REGRESSOR, "gravity": g,
                  "gravity_source": g_source, "airspeed": v0, "airspeed_source": v_source,
                  "airspeed_value": _number(v0, info), "closure": closure,
                  "angle_radians": ka, "q_in_alpha_units": kq / ka})

    def score(self, c, ev):
        """The equation errors of α and q follow the kinematic speed perturbation
        (:func:`.locate.speed_proxy`)."""
        return max(ev.state_score(s, SPEED_REGRESSOR) for s in c.info["states"])

    def check_estimates(self, c, estimates):
        """Z_V against −2g/V₀² (lift ∝ V² at the trim lift L = mg, constant α): a phugoid's
        speed coupling. Far from it (beyond 3 s.e. and outside a factor 2), the candidate
        absorbs a slow mismatch that is not (only) the phugoid, and the sentence says so."""
        from ..spec.dataunits import angle_kind

        zv_name = c.parameters[2].name
        v0 = c.info.get("airspeed_value")
        zv, se = estimates.get(zv_name, (None, None))
        unit = (c.parameters[2].unit or "").replace(" ", "")
        if (v0 is None or zv is None or not math.isfinite(zv) or v0 <= 0
                or not unit.endswith(")/m") or angle_kind(unit[1:-3]) is None):
            return ""
        # in rad/m whatever α's unit (a model in degrees: Z_V in deg/m)
        k = float(c.info.get("angle_radians", 1.0))
        zv = zv * k
        se = None if se is None else se * k
        ref = -2.0 * float(c.info["gravity"]) / v0 ** 2
        ratio = zv / ref
        if se is not None and math.isfinite(se) and se > 0:
            dist = f"{abs(zv - ref) / se:.2g} s.e. apart"
            near = abs(zv - ref) <= 3.0 * se or 0.5 <= ratio <= 2.0
        else:
            dist = "no standard error"
            near = 0.5 <= ratio <= 2.0
        text = (f" Physics check: {zv_name} = {zv:.4g} rad/m against −2g/V₀² = {ref:.4g} rad/m "
                f"(lift ∝ V² in trim at V₀ = {v0:.5g} m/s): ratio {ratio:.2g}, {dist}")
        if near:
            return text + ": the speed coupling of a phugoid."
        return (text + ": not the phugoid's speed coupling — the candidate may be absorbing "
                "another slow mismatch; read it with its estimates.")


@register_effect
class UnmodelledWind(Effect):
    id = "unmodelled_wind"
    title = "unmodelled wind / turbulence with a correlation time"
    explanation = ("The air mass moves: a gust component of {angle} with correlation time "
                   "{tau} (Dryden-like first-order Gauss–Markov state {w}) changes the "
                   "aerodynamic {angle} seen by the wings and the vane, while the inertial "
                   "motion does not. The equation errors are slow and coloured rather than "
                   "white turbulence increments. This is a model of the atmosphere (the "
                   "turbulence is coloured), not of the aircraft: a noise-model finding, not "
                   "missing physics.")
    doc = ("A Gauss–Markov gust state added to the aerodynamic flow angle: coloured "
           "turbulence, a disturbance model (``info['disturbance']``): refitted in every "
           "round until it is accepted, so that a physical candidate is accepted only where it "
           "beats the turbulence, and reported as a noise-model finding, not as physics.")

    def applies_to(self, info):
        out = []
        for kind in ("alpha", "beta"):
            a = info.flow_angle(kind)
            if a is None or any(s.startswith(f"D_WIND_{a}") for s in info.state_names):
                continue      # one gust state per flow angle (an accepted one is in the model)
            gains = {s: g for s, g in ((s, info.gain_text(s, a)) for s in info.state_names
                                       if info.depends(s, a)) if g is not None}
            if not gains:
                continue
            w = info.fresh(f"D_WIND_{a}")
            tau = info.fresh(f"D_TAU_WIND_{a}", taken=[w])
            lo = _lag_bounds(info, 4.0)
            obs = {o: w for o in info.output_names if info.measured_state(o) == a}
            adds = {"drift": {s: f"{_paren(g)}*{w}" for s, g in gains.items()}}
            if obs:
                adds["observations"] = obs
            out.append(Candidate(
                effect=self.id, key=f"{self.id}:{a}", target=f"drift:{a}",
                explanation=self.explain(angle=a, tau=tau, w=w),
                parameters=(NewParameter(tau, "s", f"correlation time of the {a} gust",
                                         initial=1.0, lower=lo, upper=50.0),),
                states=(NewState(w, f"-{w}/{tau}", info.unit(a), f"gust component of {a}",
                                 process_noise=True),),
                add_terms=adds, info={"angle": a, "states": tuple(gains), "disturbance": True},
                screenable=False))
        return out

    def score(self, c, ev):
        return max((ev.colored_score(s) for s in c.info["states"]), default=0.0)


BUILTIN_EFFECTS = ("missing_derivative", "trim_term", "coefficient_derivative", "output_derivative",
                   "nonlinear_aero",
                   "coefficient_nonlinear", "unsteady_aero", "control_delay", "actuator_lag", "sensor_bias", "sensor_scale", "sensor_position", "time_skew",
                   "sensor_lag", "missing_dynamics", "speed_dynamics", "unmodelled_wind")

