"""Structural symmetries of the free parameters: combinations the equations cannot determine.

A one-parameter group of parameter changes that leaves every drift and observation equation
unchanged, for every state and input, leaves the likelihood unchanged for every record: along
it the parameters are not determined by any data (the Hessian of the fit is singular there,
and standard errors are undefined). Two groups are tested, both exactly characterised by the
parameter Jacobian ``J(x, u, θ) = ∂(f, h)/∂θ`` of the expanded equations:

* **scaling** ``θ_j → θ_j e^{c_j t}``: the equations are invariant iff
  ``J(x, u, θ) (c ∘ θ) = 0`` for all ``(x, u, θ)``; e.g. ``c = (1, −1)`` for two
  parameters that appear only as their product ``a·b`` (``MAL*K*alpha``);
* **translation** ``θ → θ + t c``: invariant iff ``J(x, u, θ) c = 0`` for all ``(x, u, θ)``;
  e.g. ``c = (1, −1)`` for two parameters that appear only as their sum (two constant terms of
  one equation, ``M0 + MB``).

The conditions are checked at random points (six more than free parameters) (states, inputs and free parameters drawn in
[0.2, 1.2], fixed parameters and constants at their values): ``c`` is a common null vector
of the stacked, column-normalised matrices ``[J_k diag(θ_k)]`` (scaling) and ``[J_k]``
(translation). A polynomial or analytic identity that holds at random points holds
everywhere with probability one (Schwartz–Zippel); a symmetry that holds is found at every
point. Columns of parameters that reach no equation are left out (the spec check warns about
those already). Symmetries that also move states (a state rescaled with a parameter) are not
tested.

A product of parameters that all start at 0 is a saddle point of the fit: the gradient of
``a·b`` with respect to each factor vanishes there, so a fit from null initial values cannot
move them; the warning says so.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import sympy

from ..errors import SpecWarning
from .symbolic import SymbolicModel, tree_size

__all__ = ["Symmetry", "parameter_symmetries", "symmetry_warnings"]

#: largest total size (expression-tree nodes) of the expanded equations that is analysed;
#: larger specs are skipped (the test would cost more than the check it serves)
MAX_SIZE = 20_000
#: random points at which the Jacobian is evaluated, beyond the number of free parameters (an
#: equation linear in k parameters needs k points before its rows can have rank k)
EXTRA_POINTS = 6
#: a singular value below this fraction of the largest is a null direction
NULL_RTOL = 1e-9


@dataclasses.dataclass(frozen=True)
class Symmetry:
    """Free parameters the equations determine only in combination.

    ``kind`` is ``"scaling"`` (``θ_j → θ_j e^{c_j t}``) or ``"translation"`` (``θ → θ + t c``);
    ``coefficients`` are the ``c_j`` of ``parameters`` (largest magnitude 1)."""

    kind: str
    parameters: tuple[str, ...]
    coefficients: tuple[float, ...]

    def combination(self) -> str:
        """What the equations see, in words (``the product a·b``, ``the sum a + b``)."""
        a = self.parameters
        if len(a) == 2:
            same = self.coefficients[0] * self.coefficients[1] > 0
            ratio = abs(self.coefficients[0] / self.coefficients[1])
            if math.isclose(ratio, 1.0, rel_tol=1e-6):
                if self.kind == "scaling":
                    return f"the ratio {a[0]}/{a[1]}" if same else f"the product {a[0]}·{a[1]}"
                return f"the difference {a[0]} − {a[1]}" if same else f"the sum {a[0]} + {a[1]}"
        names = ", ".join(a)
        return (f"a combination of {names} invariant under a common rescaling"
                if self.kind == "scaling" else f"a linear combination of {names}")


def _random_point(rng, n):
    return rng.uniform(0.2, 1.2, n)


def parameter_symmetries(model: SymbolicModel, *, extra_points: int = EXTRA_POINTS,
                         seed: int = 0) -> tuple[Symmetry, ...]:
    """The scaling and translation symmetries of ``model``'s free parameters (module docstring).

    Returns () when fewer than two free parameters reach the equations, when the expanded
    equations exceed :data:`MAX_SIZE` nodes, or when no point gives finite Jacobians.
    """
    free = [p for p in model.parameters if not p.fixed]
    if len(free) < 2:
        return ()
    exprs = list(model.drift_expanded()) + list(model.observations_expanded())
    memo: dict = {}
    if sum(tree_size(e, memo) for e in exprs) > MAX_SIZE:
        return ()
    values = {c.symbol: sympy.Float(c.value) for c in model.constants}
    values.update({p.symbol: sympy.Float(p.initial) for p in model.parameters if p.fixed})
    exprs = [e.xreplace(values) for e in exprs]
    psyms = [p.symbol for p in free]
    used = [j for j, s in enumerate(psyms) if any(s in e.free_symbols for e in exprs)]
    if len(used) < 2:
        return ()
    psyms = [psyms[j] for j in used]
    names = [free[j].name for j in used]
    jac = [sympy.diff(e, s) for e in exprs for s in psyms]
    args = list(model.state_symbols) + list(model.input_symbols) + psyms
    from .expr import Interp, InterpSlope

    def interp(x, xs, ys):
        return float(Interp(sympy.Float(float(x)), xs, ys))

    def slope(x, xs, ys):
        return float(InterpSlope(sympy.Float(float(x)), xs, ys))

    fn = sympy.lambdify(args, jac, modules=[{Interp.__name__: interp,
                                              InterpSlope.__name__: slope}, "numpy"])
    points = len(psyms) + extra_points
    rng = np.random.default_rng(seed)
    scal, trans = [], []
    tries = 0
    while len(scal) < points and tries < 10 * points:
        tries += 1
        x = _random_point(rng, len(args))
        try:
            with np.errstate(all="ignore"):
                J = np.asarray(fn(*x), dtype=float).reshape(len(exprs), len(psyms))
        except (ValueError, ZeroDivisionError, OverflowError, TypeError):
            continue
        if not np.all(np.isfinite(J)):
            continue
        theta = x[-len(psyms):]
        trans.append(J)
        scal.append(J * theta[None, :])
    if len(scal) < points:
        return ()
    out = []
    for kind, blocks in (("scaling", scal), ("translation", trans)):
        out.extend(_null_groups(kind, np.vstack(blocks), names))
    return tuple(out)


def _null_groups(kind: str, A: np.ndarray, names: list[str]) -> list[Symmetry]:
    norms = np.linalg.norm(A, axis=0)
    live = np.nonzero(norms > 0)[0]
    if live.size < 2:
        return []
    An = A[:, live] / norms[live]
    _, sv, vt = np.linalg.svd(An, full_matrices=True)
    sv = np.concatenate([sv, np.zeros(vt.shape[0] - sv.size)])
    null = vt[sv <= NULL_RTOL * max(float(sv[0]), 1e-300)]
    out = []
    for v in null:
        c = v / norms[live]                  # back to the parameters' own scale
        c = c / np.max(np.abs(c))
        keep = np.nonzero(np.abs(c) > 1e-6)[0]
        if keep.size < 2:
            continue
        out.append(Symmetry(kind, tuple(names[live[j]] for j in keep),
                            tuple(float(c[j]) for j in keep)))
    return out


def _where(model: SymbolicModel, name: str):
    """The location of the first equation that uses parameter ``name`` (expanded)."""
    sym = next(p.symbol for p in model.parameters if p.name == name)
    for section, variables, exprs in (("drift", model.states, model.drift_expanded()),
                                      ("observations", model.outputs,
                                       model.observations_expanded())):
        for v, e in zip(variables, exprs):
            if sym in e.free_symbols:
                return model.locations.get(f"{section}:{v.name}")
    return None


def symmetry_warnings(model: SymbolicModel) -> list[SpecWarning]:
    """:func:`parameter_symmetries` as spec warnings (code ``parameter_symmetry``), each at the
    first equation that uses the group's first parameter, with what to do."""
    out = []
    init = {p.name: p.initial for p in model.parameters}
    for s in parameter_symmetries(model):
        what = s.combination()
        hint = (f"fix one of them at a value of your choice (e.g. `{s.parameters[-1]}: "
                f"{{initial: {1 if s.kind == 'scaling' else 0}, fixed: true}}`) or write the "
                "combination as one parameter")
        if s.kind == "scaling" and all(init[n] == 0 for n in s.parameters):
            hint += ("; they all start at 0, where the gradient of a product vanishes: a fit "
                     "from these initial values cannot move them")
        loc = _where(model, s.parameters[0])
        kw = {} if loc is None else {"path": loc.path, "line": loc.line, "column": loc.column}
        out.append(SpecWarning(
            f"parameters {', '.join(f'`{n}`' for n in s.parameters)} enter the equations only "
            f"through {what}: the data determine that, not each parameter", hint=hint,
            code="parameter_symmetry", **kw))
    return out
