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

The conditions are checked at random points, six more than free parameters (states, inputs
and free parameters drawn in [0.2, 1.2], fixed parameters and constants at their values; for
equations with non-smooth functions — ``sat``, ``interp``, ``sign``, ``abs`` — every other
point has its states and inputs scattered around the functions' break values instead):
``c`` is a common null vector of the stacked, column-normalised matrices
``[J_k diag(θ_k)]`` (scaling) and ``[J_k]`` (translation); the null space, in reduced row
echelon form, is split into the groups of parameters its rows join (independent symmetries
are reported apart). A polynomial or analytic identity that holds at random points holds
everywhere with probability one (Schwartz–Zippel); a symmetry that holds is found at every
point. Columns of parameters that reach no equation are left out (the spec check warns about
those already). Symmetries that also move states (a state rescaled with a parameter) are not
tested.

A product of parameters that all start at 0 is a saddle point of the fit: the gradient of
``a·b`` with respect to each factor vanishes there. More generally (:func:`frozen_at_start`),
parameters whose equations do not depend on them at their initial values, whatever the other
parameters are (``wn`` and ``zeta`` of ``wn**2*(u - x) - 2*zeta*wn*v`` both at 0), have a zero
gradient as long as they stay there: a fit leaves such a start only along negative curvature
(``estimator.fit._saddle_step``), and the warnings say so.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import sympy

from ..errors import SpecWarning
from .symbolic import SymbolicModel, tree_size

__all__ = ["Symmetry", "frozen_at_start", "parameter_symmetries", "symmetry_warnings"]

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
    ``coefficients`` are the ``c_j`` of ``parameters`` (largest magnitude 1); ``dimension``
    the number of independent such directions within the group."""

    kind: str
    parameters: tuple[str, ...]
    coefficients: tuple[float, ...]
    #: independent symmetries within the group (the coefficients are NaN when more than one)
    dimension: int = 1

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
        free = (f" ({self.dimension} of these {len(a)} parameters are undetermined)"
                if self.dimension > 1 else "")
        return (f"a combination of {names} invariant under a common rescaling{free}"
                if self.kind == "scaling" else f"a linear combination of {names}{free}")


def _random_point(rng, n):
    return rng.uniform(0.2, 1.2, n)


_NONSMOOTH = ("Abs", "sign", "Min", "Max", "Heaviside", "Piecewise", "Interp", "InterpSlope")


def _break_values(exprs) -> tuple[float, ...]:
    """The numbers at which the equations' non-smooth functions change form: the numeric
    arguments of ``Min``/``Max`` (``sat(x, lo, hi)``'s limits), an ``interp`` table's nodes,
    and 0 (``sign``, ``abs``). Analytic equations give ()."""
    out: set[float] = set()
    for e in exprs:
        for node in sympy.preorder_traversal(e):
            name = type(node).__name__
            if name not in _NONSMOOTH:
                continue
            out.add(0.0)
            for a in node.atoms(sympy.Number):
                if a.is_finite and a.is_real:
                    out.add(float(a))
    return tuple(sorted(out))


def _near_breaks(rng, n, breaks):
    """States and inputs scattered around the break values (each variable near a random one,
    on either side): an identity of a piecewise equation seen only on one side of its breaks
    (``MDE*sat(de, -0.1, 0.1)`` is the constant ``0.1*MDE`` for ``de`` in [0.2, 1.2], so ``M0``
    and ``MDE`` looked like one combination: red team, session 47) is broken there. A
    structural symmetry holds at every point, so it is found as before."""
    b = np.asarray(breaks, float)[rng.integers(0, len(breaks), n)]
    return b + rng.normal(size=n) * 0.5 * np.maximum(np.abs(b), 0.1)


class _Jacobian:
    """``∂(f, h)/∂θ`` of the expanded equations for the free parameters that reach them, as a
    numeric function of (states, inputs, those parameters); constants and fixed parameters at
    their values. ``fn`` is None when the equations exceed :data:`MAX_SIZE` nodes."""

    def __init__(self, model: SymbolicModel):
        free = [p for p in model.parameters if not p.fixed]
        exprs = list(model.drift_expanded()) + list(model.observations_expanded())
        #: (equation key of ``model.locations``, its symbols once expanded), drift then outputs
        self.uses = [(f"{section}:{v.name}", e.free_symbols) for (section, v), e in zip(
            [("drift", v) for v in model.states] + [("observations", v) for v in model.outputs],
            exprs)]
        self.fn, self.names, self.initial, self.n_eq = None, [], np.zeros(0), len(exprs)
        memo: dict = {}
        if not free or sum(tree_size(e, memo) for e in exprs) > MAX_SIZE:
            return
        values = {c.symbol: sympy.Float(c.value) for c in model.constants}
        values.update({p.symbol: sympy.Float(p.initial) for p in model.parameters if p.fixed})
        exprs = [e.xreplace(values) for e in exprs]
        used = [p for p in free if any(p.symbol in e.free_symbols for e in exprs)]
        if not used:
            return
        self.names = [p.name for p in used]
        self.initial = np.array([float(p.initial) for p in used])
        psyms = [p.symbol for p in used]
        jac = [sympy.diff(e, q) for e in exprs for q in psyms]
        self.n_var = len(model.states) + len(model.inputs)
        from .expr import Interp, InterpSlope

        def interp(x, xs, ys):
            return float(Interp(sympy.Float(float(x)), xs, ys))

        def slope(x, xs, ys):
            return float(InterpSlope(sympy.Float(float(x)), xs, ys))

        #: where non-smooth functions change form (``sat``'s limits, ``interp``'s nodes, 0
        #: of ``sign``/``abs``); empty for analytic equations
        self.breaks = _break_values(exprs)
        self.fn = sympy.lambdify(list(model.state_symbols) + list(model.input_symbols) + psyms,
                                 jac, modules=[{Interp.__name__: interp,
                                                InterpSlope.__name__: slope}, "numpy"])

    def at(self, xu, theta) -> np.ndarray | None:
        """The Jacobian (equations × parameters) at one point; None when not finite there."""
        try:
            with np.errstate(all="ignore"):
                J = np.asarray(self.fn(*xu, *theta), dtype=float)
        except (ValueError, ZeroDivisionError, OverflowError, TypeError):
            return None
        J = J.reshape(self.n_eq, len(self.names))
        return J if np.all(np.isfinite(J)) else None

    def samples(self, rng, count: int, theta=None):
        """Up to ``count`` finite (θ, J) at random states and inputs, with ``theta(rng)`` (default:
        every parameter random) — at most ten tries per sample."""
        out = []
        for _ in range(10 * count):
            if len(out) == count:
                break
            th = _random_point(rng, len(self.names)) if theta is None else theta(rng)
            xu = (_random_point(rng, self.n_var) if not self.breaks or len(out) % 2 == 0
                  else _near_breaks(rng, self.n_var, self.breaks))
            J = self.at(xu, th)
            if J is not None:
                out.append((th, J))
        return out


def parameter_symmetries(model: SymbolicModel, *, extra_points: int = EXTRA_POINTS,
                         seed: int = 0, jacobian: _Jacobian | None = None) -> tuple[Symmetry, ...]:
    """The scaling and translation symmetries of ``model``'s free parameters (module docstring).

    Returns () when fewer than two free parameters reach the equations, when the expanded
    equations exceed :data:`MAX_SIZE` nodes, or when too few points give finite Jacobians.
    """
    jac = jacobian or _Jacobian(model)
    if jac.fn is None or len(jac.names) < 2:
        return ()
    points = len(jac.names) + extra_points
    got = jac.samples(np.random.default_rng(seed), points)
    if len(got) < points:
        return ()
    out = []
    for kind, blocks in (("scaling", [J * th[None, :] for th, J in got]),
                         ("translation", [J for _, J in got])):
        out.extend(_null_groups(kind, np.vstack(blocks), jac.names))
    return tuple(out)


def frozen_at_start(model: SymbolicModel, *, points: int = 3, seed: int = 1,
                    jacobian: _Jacobian | None = None) -> tuple[str, ...]:
    """Free parameters whose gradient stays zero as long as they keep their initial values.

    The largest set ``S`` such that, with ``θ_S`` at its initial values and every other free
    parameter anywhere, no equation depends on ``θ_S`` (``∂(f, h)/∂θ_S = 0`` for all states and
    inputs): the gradient of the ELBO in ``θ_S`` is then zero until they move, which a damped
    Newton step never makes them do (only a step along negative curvature can). Found by
    starting from every parameter at its initial value and releasing (to random values) each
    parameter whose column is not zero, until none is released (``wn`` and ``zeta`` of
    ``wn**2*(u - x) - 2*zeta*wn*v`` both starting at 0; ``T`` in ``Z*(alpha + T*q)`` is released
    once ``Z`` is). Zero is tested at random points, relative to the Jacobian's scale."""
    jac = jacobian or _Jacobian(model)
    if jac.fn is None:
        return ()
    rng = np.random.default_rng(seed)
    frozen = np.ones(len(jac.names), bool)
    while frozen.any():
        def theta(r, frozen=frozen.copy()):
            th = _random_point(r, len(jac.names))
            th[frozen] = jac.initial[frozen]
            return th
        got = jac.samples(rng, points, theta)
        if not got:
            return ()
        live = np.zeros(len(jac.names), bool)
        for _, J in got:
            scale = max(float(np.max(np.abs(J))), 1e-300)
            live |= np.max(np.abs(J), axis=0) > 1e-12 * scale
        release = frozen & live
        if not release.any():
            break
        frozen &= ~release
    return tuple(n for n, f in zip(jac.names, frozen) if f)


def _rref(M: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    """Reduced row echelon form of ``M`` (Gauss–Jordan with partial pivoting); rows that
    vanish are dropped. A null space in this form has sparse rows, one pivot parameter each."""
    R = np.array(M, float)
    rows, cols = R.shape
    r = 0
    for c in range(cols):
        if r == rows:
            break
        p = r + int(np.argmax(np.abs(R[r:, c])))
        if abs(R[p, c]) <= tol:
            continue
        R[[r, p]] = R[[p, r]]
        R[r] /= R[r, c]
        for i in range(rows):
            if i != r:
                R[i] -= R[i, c] * R[r]
        r += 1
    R[np.abs(R) <= tol] = 0.0
    return R[:r]


def _null_groups(kind: str, A: np.ndarray, names: list[str]) -> list[Symmetry]:
    """The symmetries in the null space of ``A`` (columns: parameters), one per group of
    parameters that the null directions connect (several independent symmetries — ``a·q + b·q``
    and ``c·α + d·α`` — are reported apart, not as one mixed basis vector)."""
    norms = np.linalg.norm(A, axis=0)
    live = np.nonzero(norms > 0)[0]
    if live.size < 2:
        return []
    An = A[:, live] / norms[live]
    _, sv, vt = np.linalg.svd(An, full_matrices=True)
    sv = np.concatenate([sv, np.zeros(vt.shape[0] - sv.size)])
    null = vt[sv <= NULL_RTOL * max(float(sv[0]), 1e-300)]
    if not len(null):
        return []
    basis = _rref(null / norms[live][None, :])          # the parameters' own scale
    # groups: connected components of the parameters the sparse basis rows join
    parent = list(range(live.size))

    def find(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i
    for row in basis:
        nz = np.nonzero(row)[0]
        for j in nz[1:]:
            parent[find(j)] = find(nz[0])
    groups: dict = {}
    for row in basis:
        nz = np.nonzero(row)[0]
        if nz.size >= 2:
            groups.setdefault(find(nz[0]), []).append(row)
    out = []
    for rows in groups.values():
        support = sorted({int(j) for row in rows for j in np.nonzero(row)[0]})
        if len(rows) == 1:
            c = rows[0][support]
            c = c / np.max(np.abs(c))
        else:
            c = np.full(len(support), np.nan)          # several directions: no one vector
        out.append(Symmetry(kind, tuple(names[live[j]] for j in support),
                            tuple(float(x) for x in c), len(rows)))
    return out


def _locator(model: SymbolicModel, uses):
    """``where(name)``: the location (as SpecWarning keywords) of the first drift or observation
    equation that uses parameter ``name`` (``uses``: :attr:`_Jacobian.uses`; {} if none)."""
    symbol = {p.name: p.symbol for p in model.parameters}

    def where(name: str) -> dict:
        key = next((k for k, syms in uses if symbol[name] in syms), None)
        loc = None if key is None else model.locations.get(key)
        return {} if loc is None else {"path": loc.path, "line": loc.line, "column": loc.column}
    return where


def symmetry_warnings(model: SymbolicModel) -> list[SpecWarning]:
    """:func:`parameter_symmetries` and :func:`frozen_at_start` as spec warnings (codes
    ``parameter_symmetry``, ``parameter_frozen_at_start``), each at the first equation that
    uses the first parameter named, with what to do."""
    out = []
    init = {p.name: p.initial for p in model.parameters}
    jac = _Jacobian(model)
    frozen = set(frozen_at_start(model, jacobian=jac))
    told: set = set()
    where = _locator(model, jac.uses)
    for s in parameter_symmetries(model, jacobian=jac):
        what = s.combination()
        which = ("one of them" if s.dimension == 1 else
                 f"{s.dimension} of them ({', '.join(s.parameters[-s.dimension:])})")
        hint = (f"fix {which} at a value of your choice (e.g. `{s.parameters[-1]}: "
                f"{{initial: {1 if s.kind == 'scaling' else 0}, fixed: true}}`) or write the "
                "combination as one parameter")
        if s.kind == "scaling" and all(init[n] == 0 for n in s.parameters):
            hint += ("; they all start at 0, a saddle point of the fit (the gradient of a "
                     "product vanishes there): the fit leaves it only along negative curvature")
            told |= set(s.parameters)
        out.append(SpecWarning(
            f"parameters {', '.join(f'`{n}`' for n in s.parameters)} enter the equations only "
            f"through {what}: the data determine that, not each parameter", hint=hint,
            code="parameter_symmetry", **where(s.parameters[0])))
    stuck = [n for n in init if n in frozen and n not in told]
    if stuck:
        values = ", ".join(f"{n} = {init[n]:g}" for n in stuck)
        out.append(SpecWarning(
            f"parameter{'s' if len(stuck) > 1 else ''} {', '.join(f'`{n}`' for n in stuck)} "
            f"start{'' if len(stuck) > 1 else 's'} where no equation depends on "
            f"{'them' if len(stuck) > 1 else 'it'} ({values}), whatever the other parameters "
            "are: the fit's gradient in them is zero there, and the fit leaves this point only "
            "along negative curvature of the ELBO (a saddle), if there is some",
            hint=(f"give {'them' if len(stuck) > 1 else 'it'} an initial value of the right "
                  f"size and sign (e.g. `{stuck[0]}: {{initial: 1}}`), e.g. from a handbook or "
                  "an earlier fit"),
            code="parameter_frozen_at_start", **where(stuck[0])))
    return out
