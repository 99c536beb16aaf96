"""The estimator's problem object: the decision vector, its objective and the reduced Newton system.

One :class:`Problem` holds everything fixed while the ELBO of a model on a set of records is
maximised: the parameter map θ(z) (:class:`~vsidgen.estimator.core.ThetaMap`), the noise map
(G, σ)(w) (:class:`~vsidgen.estimator.core.NoiseMap`), the transition, the records and the
compiled objective (:class:`~vsidgen.estimator.core.Objective`).

Decision vector (:class:`Layout`). Shared by all records: s = (z, w), the free parameters in
unconstrained coordinates z and the noise parameters w. Per record i (N_i samples): the
assumed density's means μ_i (N_i × n) and covariance parameters r_i = (d, strict-lower L, vec C)
(q = n + n(n−1)/2 + n² of them). Two flat orderings are used:

* the *border* (global) vector b = (r_1, …, r_R, s) of length R q + n_s, the variables the
  state means are eliminated onto;
* the *full* vector v = (vec μ_1, …, vec μ_R, b) (:meth:`Layout.pack`, :meth:`Layout.unpack`).

Objective. f(v) = −ELBO = Σ_i f_i(μ_i, r_i, s). Its Hessian is block tridiagonal in each μ_i
(blocks D_k on the diagonal, B_k above it) with a dense border W_i = ∂²f_i/∂μ_i∂b and H_bb
(:meth:`Problem.blocks`, :meth:`Problem.gather`).

Reduced Newton system (:meth:`Problem.reduced_system`). With A_i = H_μ_iμ_i + λ diag(d_μ_i)
(damped block-tridiagonal, Cholesky O(N_i n³)) the state means are eliminated record by record:

    S   = H_bb + λ diag(d_b) − Σ_i W_iᵀ A_i⁻¹ W_i        (Schur complement over b)
    rhs = −g_b + Σ_i W_iᵀ A_i⁻¹ g_μ_i

so that the damped Newton step (H + λD) Δ = −g is Δb = S⁻¹ rhs and
Δμ_i = −A_i⁻¹ (g_μ_i + W_i Δb) (:meth:`Problem.back_substitute`). With λ = 0, S is the Hessian
of the profile f(b) = min_μ f(μ, b) to second order, so ½ rhsᵀ S⁻¹ rhs is half the Newton
decrement over all variables.

Start (:meth:`Problem.initial`): θ at the spec's initial values, the noise at one of the noise
starts, μ of a state measured directly by an output y = c + k·x (:func:`direct_measurements`)
at (y − c)/k, the other states that the outputs depend on solved from them sample by sample
(:func:`invert_outputs`: u, w of a body-axis model from V and α), the rest 0.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import math
import threading
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from ..model.dynamics import input_hold as transition_input_hold
from ..model.dynamics import settings as transition_settings
from ..model.dynamics import transition
from ..errors import FitError
from .core import (NoiseMap, SwitchedObjective, ThetaMap, bucket_length, carried_inputs, coherent_factors,
                   cov_factors_of, get_objective, input_filter_scales, make_cfg, quasi_deterministic_stds, record_data)
from .results import FitOptions, FitResult, WarmStart

from .. import precision  # noqa: F401  (float64, set once)


class ModelFamily:
    """Models of one shape whose problems share compiled objectives, while the family is active.

    ``models`` have the same numbers of states, inputs, outputs and parameters; they differ
    in their drift and output functions (diagnose's candidates that add the same number of
    states and parameters to one model). While :meth:`active` (a context manager; the
    registration is process-wide, so threads started inside see it), every :class:`Problem`
    of one of these models (matched by its drift and output functions) uses, instead of the
    model's own compiled objective, the family's
    :class:`~vsidgen.estimator.core.SwitchedObjective` for the problem's structure (the
    static keys of its parameter and noise maps and its transition setting), built on first
    use and kept by the family: the first fit of a member traces and compiles every member's
    functions once (``jax.lax.switch`` over the members, the branch a run-time argument),
    the fits of the other members reuse the compiled code. Values equal those of the
    member's own objective up to rounding (a different compiled function).
    """

    def __init__(self, models):
        self.models = tuple(models)
        if not self.models or len({(m.nx, m.nu, m.ny, m.np) for m in self.models}) != 1:
            raise FitError("a model family needs models with the same numbers of states, "
                           "inputs, outputs and parameters")
        self._objectives: dict = {}
        self._lock = threading.Lock()

    def branch_of(self, model) -> int | None:
        """Index of ``model`` in the family (its drift and output functions), else None."""
        for k, m in enumerate(self.models):
            if m.drift is model.drift and m.output is model.output:
                return k
        return None

    def objective(self, problem: "Problem") -> SwitchedObjective:
        """The family's objective for ``problem``'s structure (built once per structure)."""
        key = (problem.tm.static_key(), problem.nm.static_key(), getattr(problem.F, "key", None),
               problem.integrator, problem.substeps, problem.input_hold)
        with self._lock:
            obj = self._objectives.get(key)
            if obj is None:
                Fs = [transition(m, integrator=problem.integrator, substeps=problem.substeps,
                                 inputs=problem.input_hold) for m in self.models]
                obj = SwitchedObjective(self.models, problem.tm, problem.nm, Fs)
                self._objectives[key] = obj
        return obj

    @property
    def n_compiled_structures(self) -> int:
        """Number of problem structures compiled so far (one objective each)."""
        return len(self._objectives)

    @contextlib.contextmanager
    def active(self):
        """Problems of the family's models built inside this block share its compilation."""
        with _FAMILY_LOCK:
            _ACTIVE_FAMILIES.append(self)
        try:
            yield self
        finally:
            with _FAMILY_LOCK:
                _ACTIVE_FAMILIES.remove(self)


_ACTIVE_FAMILIES: list[ModelFamily] = []
_FAMILY_LOCK = threading.Lock()


def _active_family(model):
    """(family, branch) of the innermost active family holding ``model``, else (None, None)."""
    with _FAMILY_LOCK:
        families = list(reversed(_ACTIVE_FAMILIES))
    for fam in families:
        k = fam.branch_of(model)
        if k is not None:
            return fam, k
    return None, None


@dataclasses.dataclass(frozen=True)
class DirectMeasurement:
    """Output ``output`` measures one state directly: y = offset + gain · x_i.

    ``gain`` ≠ 0 and ``offset`` are numbers during the fit (spec constants and fixed
    parameters allowed, estimated parameters not), so the state is known from the
    measurement up to its noise: x_i = (y − offset)/gain.
    """

    output: int
    gain: float = 1.0
    offset: float = 0.0

    def state_of(self, y):
        """The state a measured value stands for: (y − offset)/gain."""
        return (y - self.offset) / self.gain


def _affine_in(e, x, const_values) -> tuple[float, float] | None:
    """(gain, offset) when ``e`` is offset + gain·x with numeric gain ≠ 0 and offset, else None."""
    import sympy

    e = e.xreplace(const_values)
    if e.free_symbols != {x}:
        return None
    try:
        poly = sympy.Poly(e, x)
    except sympy.PolynomialError:
        return None
    if poly.degree() != 1:
        return None
    k, c = (float(v) for v in (poly.coeff_monomial(x), poly.coeff_monomial(1)))
    if not (math.isfinite(k) and math.isfinite(c) and k != 0.0):
        return None
    return k, c


def direct_measurements(model) -> dict[int, DirectMeasurement]:
    """{state index: DirectMeasurement} for outputs that measure one state directly.

    An output y_j = c + k·x_i with numbers k ≠ 0 and c (the state itself, the state in
    other units such as ``57.29578*alpha``, or a trim value plus a perturbation such as
    ``V0 + u`` with ``V0`` a spec constant or a fixed parameter) measures x_i directly: the
    measured values give the state's start μ_i = (y_j − c)/k and its data scale (spread of
    y_j's sample differences / |k|). The first such output of a state is taken.

    Uses ``model.symbolic.observations`` (definitions expanded, constants and fixed
    parameters substituted) when a symbolic model is attached, else tests h numerically:
    y_j must be the same affine function of x_i at random states and inputs, for two
    vectors of the estimated parameters.
    """
    out: dict[int, DirectMeasurement] = {}
    sym = model.symbolic
    if sym is not None:
        try:
            fixed = {p.name: float(p.initial) for p in model.parameters if p.fixed}
            consts = dict(sym.constant_values())
            consts.update({p.symbol: fixed[p.name] for p in sym.parameters if p.name in fixed})
            for j, e in enumerate(sym.observations_expanded()):
                for i, st in enumerate(sym.states):
                    kc = _affine_in(e, st.symbol, consts)
                    if kc is not None:
                        out.setdefault(i, DirectMeasurement(j, *kc))
            return out
        except Exception:  # fall back to the numerical test
            out = {}
    return _direct_measurements_numerical(model)


def _direct_measurements_numerical(model) -> dict[int, DirectMeasurement]:
    rng = np.random.default_rng(12345)
    p0 = np.asarray([float(q.initial) for q in model.parameters], float)
    out: dict[int, DirectMeasurement] = {}
    npts = 4
    X = rng.normal(size=(npts, model.nx)) * 0.7 + 0.3
    U = rng.normal(size=(npts, model.nu))
    free = np.array([not q.fixed for q in model.parameters], bool)
    P = [p0, p0 + free * rng.normal(size=p0.shape) * 0.1]
    with np.errstate(all="ignore"):
        H = np.array([[np.asarray(model.output(jnp.asarray(x), jnp.asarray(u), jnp.asarray(p)), float)
                       for x, u in zip(X, U)] for p in P])  # (2, npts, ny)
    for j in range(model.ny):
        for i in range(model.nx):
            x = X[:, i]
            h = H[0, :, j]
            if not np.all(np.isfinite(H[:, :, j])) or x[1] == x[0]:
                continue
            k = (h[1] - h[0]) / (x[1] - x[0])
            c = h[0] - k * x[0]
            pred = c + k * x
            tol = 1e-12 * (1 + np.abs(H[:, :, j]))
            if k != 0 and np.all(np.abs(H[:, :, j] - pred[None, :]) <= tol):
                out.setdefault(i, DirectMeasurement(j, float(k), float(c)))
    return out


def measured_states(model) -> dict[int, int]:
    """{state index: output index} for outputs that measure a state directly (:func:`direct_measurements`)."""
    return {i: m.output for i, m in direct_measurements(model).items()}


def initial_means(model, rec, pairs, how: str) -> np.ndarray:
    """Starting state means (N, nx) of a record: ``how`` = "measured" (a state measured directly,
    ``pairs``: :func:`direct_measurements`, starts at (y − offset)/gain, NaN samples interpolated;
    other states 0) or "zero"."""
    N = np.asarray(rec.y).shape[0]
    mu = np.zeros((N, model.nx))
    if how == "zero":
        return mu
    if how != "measured":
        raise FitError(f"init_states must be 'measured' or 'zero', got '{how}'")
    y = np.asarray(rec.y, float)
    k = np.arange(N)
    for i, dm in pairs.items():
        col = dm.state_of(y[:, dm.output])
        fin = np.isfinite(col)
        if fin.any():
            mu[:, i] = np.interp(k, k[fin], col[fin])
    return mu


#: Levenberg–Marquardt iterations and start offset of :func:`invert_outputs`
INVERT_ITERATIONS, INVERT_START = 40, 1e-6


@functools.lru_cache(maxsize=32)
def _inversion_functions(output, free: tuple):
    """Jitted (h, (h, ∂h/∂x_free)) over samples for :func:`invert_outputs`, one compilation per
    model output function and set of free states."""
    fi = np.asarray(free)

    def out(xf, x, uk, th):
        return output(x.at[fi].set(xf), uk, th)

    both = jax.vmap(lambda xf, x, uk, th: (out(xf, x, uk, th), jax.jacfwd(out)(xf, x, uk, th)),
                    in_axes=(0, 0, 0, None))
    return jax.jit(jax.vmap(out, in_axes=(0, 0, 0, None))), jax.jit(both)


#: share of a record's samples at which the outputs must determine a state for it to count as
#: measured through them (:func:`invert_outputs`)
SOLVED_SHARE = 0.5


def invert_outputs(model, rec, mu, measured, theta) -> tuple[np.ndarray, tuple[int, ...]]:
    """(state means, solved states): state means ``mu`` (N, nx) with the states that no
    output measures directly but that
    the outputs depend on (at the initial parameters ``theta``) solved from the record's
    outputs, sample by sample: ``min_x Σ_j ((y_kj − h_j(x, u_k; θ))/s_j)²`` over those
    states, the directly measured ones (``measured``: state indices) held at ``mu``, ``s_j``
    the channel's standard deviation. Damped Gauss–Newton (Levenberg–Marquardt, one damping
    per sample), started a hair off zero (``INVERT_START``: the derivative of √(u² + w²) or
    atan2(w, u) does not exist at the origin).

    A body-axis model (states u, w; outputs V = √(u² + w²), α = atan2(w, u)) then starts at
    u = V cos α, w = V sin α instead of u = w = 0, where its airspeed vanishes. States the
    outputs do not depend on at the start stay at 0. A sample whose fit is not finite, not
    better than the start, or does not determine those states (the weighted Jacobian there
    is rank deficient: V without α) is interpolated between the samples that do; with none,
    the start is kept.

    The solved states are those the outputs determine (full column rank) at no fewer than
    :data:`SOLVED_SHARE` of the samples: measured through the outputs, though by none
    directly (u and w through V and α).
    """
    free = [i for i in range(model.nx) if i not in set(measured)]
    y = np.asarray(rec.y, float)
    if not free or y.shape[0] == 0:
        return mu, ()
    u = jnp.asarray(np.asarray(rec.u, float))
    th = jnp.asarray(np.asarray(theta, float))
    fi = np.asarray(free)
    out_v, both = _inversion_functions(model.output, tuple(free))
    x0 = np.array(mu, float)
    x0[:, fi] = INVERT_START

    def full(xf):                      # the free states' values inserted into the start
        x = x0.copy()
        x[:, fi] = xf
        return jnp.asarray(x)

    def h_and_jacobian(xf):
        return (np.asarray(a, float) for a in both(jnp.asarray(xf), full(xf), u, th))

    h, J = h_and_jacobian(x0[:, fi])
    finite = np.isfinite(h).all(axis=1) & np.isfinite(J).all(axis=(1, 2))
    dep = np.any(np.abs(np.where(finite[:, None, None], J, 0.0)) > 0, axis=(0, 1))
    if not dep.any():
        return mu, ()
    nd = int(dep.sum())
    obs = np.isfinite(y)
    sd = np.array([np.std(y[obs[:, j], j]) if obs[:, j].sum() > 1 else 1.0
                   for j in range(y.shape[1])])
    w = np.where(obs, 1.0 / np.where(sd > 0, sd, 1.0) ** 2, 0.0)
    y0 = np.where(obs, y, 0.0)

    def cost(h):
        fin = np.isfinite(h).all(axis=1)
        return np.where(fin, np.sum(w * (y0 - np.where(np.isfinite(h), h, 0.0)) ** 2, axis=1),
                        np.inf)

    xf = x0[:, fi].copy()
    xf[:, ~dep] = 0.0
    c = np.where(finite, cost(h), np.inf)
    c_start = c.copy()
    lam = np.full(y.shape[0], 1e-3)
    for _ in range(INVERT_ITERATIONS):
        h, J = h_and_jacobian(xf)
        ok = np.isfinite(h).all(axis=1) & np.isfinite(J).all(axis=(1, 2))
        J = np.where(ok[:, None, None], J, 0.0)[:, :, dep]
        r = np.where(ok[:, None], y0 - h, 0.0)
        A = np.einsum("kja,kj,kjb->kab", J, w, J)
        g = np.einsum("kja,kj,kj->ka", J, w, r)
        D = np.einsum("kaa->ka", A) + 1e-12
        step = np.linalg.solve(A + (lam[:, None] * D)[:, :, None] * np.eye(nd),
                               g[:, :, None])[:, :, 0]
        trial = xf.copy()
        trial[:, dep] += step
        ct = cost(np.asarray(out_v(jnp.asarray(trial), full(trial), u, th), float))
        better = (ct < c) & np.isfinite(trial).all(axis=1)
        xf = np.where(better[:, None], trial, xf)
        c = np.where(better, ct, c)
        lam = np.where(better, np.maximum(lam / 10.0, 1e-12), np.minimum(lam * 10.0, 1e12))
    # only where the outputs determine those states (full column rank of the weighted
    # Jacobian at the solution): V alone does not fix u and w, and the damped steps from a
    # symmetric start would put them at 45°
    _, J = h_and_jacobian(xf)
    J = np.where(np.isfinite(J), J, 0.0)[:, :, dep] * np.sqrt(w)[:, :, None]
    determined = _determined_columns(J)               # (N, nd): per sample and state
    good = np.isfinite(c) & (c < c_start) & np.isfinite(xf).all(axis=1)
    out_mu = np.array(mu, float)
    k = np.arange(y.shape[0])
    solved = []
    for j, (a, col) in enumerate(zip(np.nonzero(dep)[0], fi[dep])):
        # per state: a state the outputs determine (u through V and α) even where others
        # are not (a gust W beside w: only w − W is seen) is solved there; samples that do
        # not determine it (a missing α) are interpolated between those that do, as a
        # measured state's missing samples (:func:`initial_means`); a state determined
        # nowhere keeps its start
        use = good & determined[:, j]
        if not use.any():
            continue
        out_mu[:, col] = np.interp(k, k[use], xf[use, a])
        if np.mean(determined[:, j]) >= SOLVED_SHARE:
            solved.append(int(col))
    if not (good[:, None] & determined).any():
        return mu, ()
    return out_mu, tuple(solved)


def _determined_columns(J: np.ndarray, rtol: float = 1e-8) -> np.ndarray:
    """Per sample (rows of ``J``, (N, m, n)) and column: whether the column's variable is
    determined by the linearised equations, i.e. has no component in the null space of
    ``J[k]`` (singular values below ``rtol`` times the largest count as zero). With full
    column rank every variable is; with V = √(u² + w²) alone neither u nor w is; with u, w and
    a gust W seen only through w − W, u is and w, W are not."""
    N, _, n = J.shape
    if N == 0 or n == 0:
        return np.zeros((N, n), bool)
    _, sv, Vt = np.linalg.svd(J, full_matrices=True)   # Vt: (N, n, n), rows by sv
    rank = np.sum(sv > rtol * np.maximum(sv[:, :1], 1e-300), axis=1)
    null = np.arange(n)[None, :, None] >= rank[:, None, None]   # rows spanning the null space
    return ~np.any(null & (np.abs(Vt) > 1e-6), axis=1)


def _check_records(model, records):
    """The records of a fit, checked; the model and each record must be vsidgen's objects
    (a spec path as the model, a file path or an array as a record raised AttributeError
    deep inside; session 44)."""
    if not all(hasattr(model, a) for a in ("ny", "nu", "nx", "parameters", "output_names")):
        raise FitError(f"the model must be a vsidgen Model, got {_shown(model)}\n  hint: "
                       "model = vsidgen.load_model('spec.yaml')")
    if not isinstance(records, Sequence) or isinstance(records, (str, bytes)):
        records = [records]
    if len(records) == 0:
        raise FitError("no records to fit")
    for rec in records:
        if not all(hasattr(rec, a) for a in ("t", "dt", "u", "y")):
            raise FitError(f"a record must be a vsidgen Record, got {_shown(rec)}\n  hint: "
                           "record = vsidgen.load_record(model, 'flight.csv'), or "
                           "vsidgen.Record.from_arrays(model, t, u, y)")
        y = np.asarray(rec.y, float)
        u = np.asarray(rec.u, float)
        name = getattr(rec, "name", "?")
        if y.ndim != 2 or y.shape[1] != model.ny:
            raise FitError(f"record '{name}': y has shape {y.shape}, expected (N, {model.ny})")
        if u.ndim != 2 or u.shape != (y.shape[0], model.nu):
            raise FitError(f"record '{name}': u has shape {u.shape}, expected ({y.shape[0]}, {model.nu})")
        if y.shape[0] < 3:
            raise FitError(f"record '{name}' has {y.shape[0]} samples; at least 3 are needed")
        if not np.all(np.isfinite(u)):
            raise FitError(f"record '{name}': inputs contain NaN or inf")
        for attr, want in (("output_names", model.output_names), ("input_names", model.input_names)):
            got = getattr(rec, attr, None)
            if got is not None and tuple(got) != tuple(want):
                raise FitError(f"record '{name}': {attr} {tuple(got)} differ from the model's {tuple(want)}")
        if not float(rec.dt) > 0:
            raise FitError(f"record '{name}': sample period dt must be positive")
    return list(records)


def _shown(value) -> str:
    """A value named for an error message: its type, and a short text of it."""
    text = repr(value)
    return f"{type(value).__name__} {text[:60]}{'…' if len(text) > 60 else ''}"


@dataclasses.dataclass(frozen=True)
class Layout:
    """Index layout of the decision vector (module docstring): R records of ``lengths`` samples,
    ``nx`` states, ``nq`` assumed-density parameters per record, and the shared vector
    s = (z: ``n_theta`` free parameters, w: ``n_proc`` process- then ``n_meas`` measurement-noise
    parameters)."""

    nx: int
    lengths: tuple[int, ...]
    nq: int
    n_theta: int
    n_proc: int
    n_meas: int

    @property
    def nrec(self) -> int:
        return len(self.lengths)

    @property
    def ng(self) -> int:
        """Length of the shared vector s."""
        return self.n_theta + self.n_proc + self.n_meas

    @property
    def nglob(self) -> int:
        """Length of the border vector b = (r_1, …, r_R, s)."""
        return self.nrec * self.nq + self.ng

    @property
    def n_mu(self) -> int:
        """Number of state means, Σ_i N_i n."""
        return sum(self.lengths) * self.nx

    @property
    def size(self) -> int:
        """Length of the full vector v."""
        return self.n_mu + self.nglob

    @property
    def shared_offset(self) -> int:
        """Position of s in b."""
        return self.nrec * self.nq

    @property
    def theta_index(self) -> np.ndarray:
        """Positions of the free parameters z in b."""
        return self.shared_offset + np.arange(self.n_theta)

    @property
    def noise_index(self) -> np.ndarray:
        """Positions of the noise parameters w in b (process first, then measurement)."""
        return self.shared_offset + self.n_theta + np.arange(self.n_proc + self.n_meas)

    def r_index(self, i: int) -> np.ndarray:
        """Positions of r_i in b."""
        return np.arange(i * self.nq, (i + 1) * self.nq)

    def border_index(self, i: int) -> np.ndarray:
        """Positions in b of record i's border (r_i, s): the rows of its W_i and H_bb blocks."""
        return np.concatenate([self.r_index(i), self.shared_offset + np.arange(self.ng)])

    def pack(self, s, recs):
        """Full vector v = (vec μ_1, …, vec μ_R, r_1, …, r_R, s) of the decision (s, [(μ_i, r_i)])."""
        return np.concatenate([np.asarray(m, float).ravel() for m, _ in recs]
                              + [np.asarray(r, float) for _, r in recs] + [np.asarray(s, float)])

    def unpack(self, v):
        """(s, [(μ_i, r_i)]) of a full vector v (numpy or a traced JAX array: slices of v)."""
        mus, o = [], 0
        for n in self.lengths:
            mus.append(v[o:o + n * self.nx].reshape(n, self.nx))
            o += n * self.nx
        rs = [v[o + i * self.nq:o + (i + 1) * self.nq] for i in range(self.nrec)]
        return v[o + self.nrec * self.nq:], list(zip(mus, rs))


#: relative Marquardt damping of a score system (:meth:`Problem.score_system`): keeps the
#: elimination of the state means and the Cholesky factor of the global system defined where a
#: curvature vanishes at the nesting point
SCORE_DAMPING = 1e-10
#: a profiled curvature eigenvalue below −tol·(largest |eigenvalue|) is negative curvature,
#: not rounding of a flat direction (about √ε of double precision)
NEGATIVE_CURVATURE_TOL = 1e-8


def split_density(r, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(d, L, C) of one record's assumed-density parameters r = (d, strict-lower L row by row, vec C)
    for n states: Σ_cond = L diag(eᵈ) Lᵀ (L unit lower triangular), C the cross factor."""
    r = np.asarray(r, float)
    nl = n * (n - 1) // 2
    L = np.eye(n)
    L[np.tril_indices(n, -1)] = r[n:n + nl]
    return r[:n].copy(), L, r[n + nl:].reshape(n, n).copy()


def join_density(d, L, C) -> np.ndarray:
    """r = (d, strict-lower L, vec C), the inverse of :func:`split_density`."""
    n = len(d)
    return np.concatenate([np.asarray(d, float), np.asarray(L, float)[np.tril_indices(n, -1)],
                           np.asarray(C, float).ravel()])


@dataclasses.dataclass(frozen=True)
class ReducedSystem:
    """The Newton system with the state means eliminated (module docstring): ``S`` (symmetric,
    nglob × nglob) and ``rhs`` over the border b, and per record the factors that give back
    Δμ_i (:meth:`Problem.back_substitute`)."""

    S: np.ndarray
    rhs: np.ndarray
    factors: tuple


@dataclasses.dataclass(frozen=True)
class Gradient:
    """∂(−ELBO) split by the decision vector's parts: ``shared`` (s), ``records_r`` (per r_i),
    ``records_mu`` (per μ_i, (N_i, n))."""

    shared: np.ndarray
    records_r: tuple[np.ndarray, ...]
    records_mu: tuple[np.ndarray, ...]


@dataclasses.dataclass(frozen=True)
class CoherentScale:
    """Per decision variable v, the factor c with c·v the same variable in coherent units
    (SI, rad; :func:`~vsidgen.estimator.core.coherent_factors`).

    With x = D x' (x in coherent units, x' in the declared ones, D = diag(``state``)): a
    state mean scales by its state's factor; Σ_cond = L diag(eᵈ) Lᵀ gives L = D L' D⁻¹ (L_ij
    by s_i/s_j) and Σ_marg = Sm Smᵀ, Sm = D Sm', gives the cross factor C = D C' (row i by
    s_i); a free unbounded parameter scales by its unit's factor, a bounded one's transformed
    coordinate not at all; an off-diagonal entry of a full process-noise factor G (G → D G)
    by its row state's factor. A logarithmic coordinate (a log-variance d, a noise log-std w
    of σ = floor + eʷ) is shifted, not scaled: its factor is 1 and ``shared_shift``/``r_shift``
    hold the shift to its coherent value (2 log s for a variance, log s for a std; 0
    elsewhere). ``shared`` covers s, ``r`` one record's r, ``output`` the outputs' factors.
    """

    state: np.ndarray
    output: np.ndarray
    shared: np.ndarray
    r: np.ndarray
    shared_shift: np.ndarray
    r_shift: np.ndarray

    @staticmethod
    def reference(v, c, shift) -> np.ndarray:
        """max(|v + shift|, 1/c) per coordinate: max(|v|, 1) of the coordinate in coherent
        units, expressed in the declared ones — the scale of a relative gradient or step that
        is the same for a model in degrees as in radians (and the old max(|v|, 1) where every
        unit is coherent)."""
        return np.maximum(np.abs(np.asarray(v, float) + shift), 1.0 / c)

    @classmethod
    def of(cls, P: "Problem") -> "CoherentScale":
        sx = coherent_factors(P.model.states)
        sy = coherent_factors(P.model.outputs)
        n = len(sx)
        il = np.tril_indices(n, -1)
        r = np.concatenate([np.ones(n), sx[il[0]] / sx[il[1]], np.repeat(sx, n)])
        r_shift = np.zeros(len(r))
        r_shift[:n] = 2.0 * np.log(sx)
        pf = coherent_factors(P.model.parameters)[P.tm.free_idx]
        nm = P.nm
        n_diag = len(nm.proc_est_idx)
        # s = (free θ, process-noise log-stds, off-diagonal G entries, measurement log-stds)
        shared = np.concatenate([np.where(P.tm.kind == 0, pf, 1.0), np.ones(n_diag),
                                 np.array([sx[a] for a, _ in nm.offdiag], float),
                                 np.ones(nm.n_meas)])
        shared_shift = np.concatenate([np.zeros(P.tm.n_free), np.log(sx[nm.proc_est_idx]),
                                       np.zeros(len(nm.offdiag)), np.log(sy[nm.meas_est_idx])])
        if len(shared) != P.layout.ng:
            raise FitError(f"internal: {len(shared)} unit factors for {P.layout.ng} shared variables")
        return cls(state=sx, output=sy, shared=shared, r=r, shared_shift=shared_shift, r_shift=r_shift)

    def border(self, nrec: int) -> np.ndarray:
        """Factors of the border b = (r_1, …, r_nrec, s)."""
        return np.concatenate([np.tile(self.r, nrec), self.shared])


class Problem:
    """Everything fixed during one optimisation: maps, objective, records, layout (module docstring).

    Built from the model, the records, the estimator options (integrator, sub-steps, input
    hold, deterministic std, padding) and the noise/θ metadata of this problem:
    ``theta_fixed`` (all parameters fixed at these values: smoothing), ``fixed_G``/``fixed_R``
    (noise fixed), ``relax`` (deterministic states' noise estimated: the first stage of the
    deterministic limit), ``hold`` (noisy states held deterministic).

    Compilation: ``objective`` (default None: this model's own, shared through
    :func:`~vsidgen.estimator.core.get_objective`, or the active :class:`ModelFamily`'s
    when the model is one of its members) a
    :class:`~vsidgen.estimator.core.SwitchedObjective` of this problem's layout, or a
    :class:`ModelFamily`, whose model ``branch`` (its index there) is this problem's, so
    problems of several models share one compilation (diagnose's score screen and its
    refits of candidates that add states).
    """

    def __init__(self, model, records, options: FitOptions = FitOptions(), *, theta_fixed=None, fixed_G=None,
                 fixed_R=None, relax: bool = False, hold=(), objective=None, branch: int | None = None):
        if (objective is None) != (branch is None):
            raise FitError("a shared objective needs the problem's branch, and a branch a shared objective")
        if objective is None:
            objective, branch = _active_family(model)     # ModelFamily.active()
        self.model = model
        self.relax = relax
        self._shared_obj = objective
        self.branch = branch
        #: start the assumed density at the start noise (Σ_cond = T diag(G Gᵀ), C = 0) instead of Σ = I
        self.noise_scaled_start = False
        if not isinstance(options, FitOptions):
            raise FitError(f"options must be a FitOptions, got {_shown(options)}\n  hint: "
                           "options=vsidgen.FitOptions(max_iter=300)")
        self.records = _check_records(model, records)
        self.integrator, self.substeps = transition_settings(
            model, integrator=options.integrator, substeps=options.substeps)
        self.input_hold = transition_input_hold(model, options.input_hold)
        self.F = transition(model, integrator=self.integrator, substeps=self.substeps, inputs=self.input_hold)
        self.tm = ThetaMap(model.parameters, fixed_all=theta_fixed is not None, values=theta_fixed)
        #: {state index: DirectMeasurement} of the model (:func:`direct_measurements`)
        self.direct = direct_measurements(model)
        det = quasi_deterministic_stds(model, self.records, options.deterministic_std,
                                       options.deterministic_input_scale)
        self.nm = NoiseMap(model, self.records, deterministic_std=det,
                           fixed_G=fixed_G, fixed_R=fixed_R, state_outputs=self.direct, relax=relax,
                           hold=hold)
        self.cfg = self._make_cfg()
        self.data = [record_data(r) for r in self.records]  # unpadded (reference path, tests)
        self.lengths = [int(np.asarray(r.y).shape[0]) for r in self.records]
        # the structured path pads each record to its bucket length (shared compiled code)
        self.padded = [bucket_length(n) if options.bucket else n for n in self.lengths]
        self.bdata = [record_data(r, length=L) if L > n else d
                      for r, n, L, d in zip(self.records, self.lengths, self.padded, self.data)]
        nx = model.nx
        self.layout = Layout(nx=nx, lengths=tuple(self.lengths), nq=nx + nx * (nx - 1) // 2 + nx * nx,
                             n_theta=self.tm.n_free, n_proc=self.nm.n_proc, n_meas=self.nm.n_meas)
        self.nrec = self.layout.nrec
        self.nglob = self.layout.nglob
        self.idx = [self.layout.border_index(i) for i in range(self.nrec)]
        #: mask over s of the free parameters held at their start (``FitOptions.held_parameters``)
        self.held = np.zeros(self.layout.ng, bool)
        free = self.free_names
        for name in tuple(getattr(options, "held_parameters", ()) or ()):
            if name not in free:
                raise FitError(f"held parameter '{name}' is not a free parameter of the model")
            self.held[free.index(name)] = True
        self.theta_idx = self.layout.theta_index
        self.prior = _input_state_prior(model, self.records, options.input_state_prior)

    @functools.cached_property
    def obj(self):
        """The compiled objective (shared between problems of the same structure), built on first use;
        its construction evaluates the model at sample points (curvature structure), eagerly even
        when the first use is inside a JAX trace (:meth:`flat_value` under ``jax.hessian``)."""
        if self._shared_obj is not None:
            obj = self._shared_obj
            if isinstance(obj, ModelFamily):
                obj = obj.objective(self)
            if (obj.tm.static_key(), obj.nm.static_key()) != (self.tm.static_key(), self.nm.static_key()):
                raise FitError("the shared objective's parameter or noise structure differs from the problem's")
        else:
            with jax.ensure_compile_time_eval():
                obj = get_objective(self.model, self.tm, self.nm, self.F, (self.integrator, self.substeps))
        if (obj.nq, obj.ng) != (self.layout.nq, self.layout.ng):
            raise FitError("objective layout differs from the problem's")
        return obj

    # -- the shared vector s by name
    @property
    def free_names(self) -> list[str]:
        """Names of the free parameters, in the order of z."""
        return [self.model.parameters[i].name for i in self.tm.free_idx]

    def theta(self, s) -> np.ndarray:
        """All parameters θ (model order) of a shared vector s (or of z = s[:n_theta])."""
        z = np.asarray(s, float)[:self.tm.n_free]
        return np.asarray(self.tm.theta(jnp.asarray(z)), float)

    def theta_jacobian(self, s) -> np.ndarray:
        """dθ_free/dz (diagonal of the parameter map) at s."""
        return np.asarray(self.tm.dtheta_dz(np.asarray(s, float)[:self.tm.n_free]), float)

    def parameter_start(self) -> np.ndarray:
        """z of the spec's initial values (the start of every fit)."""
        return np.asarray(self.tm.z0, float)

    def process_noise_index(self, state: str) -> int | None:
        """Position in b of the estimated diagonal process-noise parameter of ``state`` (None: not estimated)."""
        i = self.model.state_names.index(state)
        hits = np.nonzero(self.nm.proc_est_idx == i)[0]
        return int(self.layout.noise_index[hits[0]]) if hits.size else None

    def noise_vector(self, *, proc_std: dict, proc_G: dict, meas_std: dict, default_std: float) -> np.ndarray:
        """Noise parameters w holding the given stds (the inverse of the noise map, by name).

        ``proc_std``: {state: std} (G_ii; states absent get ``default_std``); ``proc_G``:
        {(row state, column state): value} off-diagonal entries of G (absent: 0); ``meas_std``:
        {output: σ}. With floors φ: w = log(std − φ) (clipped at 1e-300), off-diagonals as given.
        """
        nm, names = self.nm, self.model.state_names
        w = [math.log(max(float(proc_std.get(names[i], default_std)) - float(nm.proc_floor[i]), 1e-300))
             for i in nm.proc_est_idx]
        w += [float(proc_G.get((names[a], names[b]), 0.0)) for a, b in nm.offdiag]
        w += [math.log(max(float(meas_std[self.model.output_names[j]]) - float(nm.meas_floor[j]), 1e-300))
              for j in nm.meas_est_idx]
        if len(w) != nm.n:
            raise FitError("noise layout mismatch")
        return np.asarray(w, float)

    def _make_cfg(self):
        cfg = make_cfg(self.tm, self.nm)
        if self.branch is not None:
            cfg["branch"] = jnp.asarray(self.branch, jnp.int32)
        return cfg

    def set_deterministic_std(self, std) -> None:
        """Fix the process-noise std of the deterministic states (one value per such state)."""
        self.nm.set_deterministic_std(std)
        self.cfg = self._make_cfg()

    # -- start
    def initial(self, options: FitOptions, start: str = "data"):
        ws = options.warm_start
        if isinstance(ws, FitResult):
            ws = None if ws.decision is None else WarmStart.from_decision(ws.decision)
        if ws is not None:
            s = np.asarray(ws.shared, float)
            recs = [(np.asarray(m, float), np.asarray(r, float)) for m, r in ws.records]
            if s.shape == (self.layout.ng,) and len(recs) == self.nrec and all(
                    m.shape == (np.asarray(r.y).shape[0], self.model.nx) for (m, _), r in zip(recs, self.records)):
                return s, recs
            raise FitError("warm_start result does not match this problem's shape")
        s = np.concatenate([self.tm.z0, self.nm.inits[start]])
        pairs = self.direct
        r0 = np.zeros(self.layout.nq)  # Σ_cond = Σ_marg = I in coherent units (rad², not deg²)
        r0[:self.model.nx] = -2.0 * np.log(self.coherent.state)
        if (self.nm.fixed_G is not None and self.tm.n_free == 0) or self.noise_scaled_start:
            # smoothing with known noise (validation mode): start the assumed density at the
            # prior's conditional covariance, Σ_cond = diag(T G Gᵀ), C = 0. With Σ = I the
            # sigma points of a nonlinear model lie ±√(2n) state units away (radians for an
            # angle), and the smoother can stop in a far, non-physical stationary point.
            # The release start does the same at its start noise (Σ = I is not unit free).
            T = float(np.mean([float(r.dt) for r in self.records]))
            G = np.asarray(self.nm.fixed_G if self.nm.fixed_G is not None
                           else self.nm.G(jnp.asarray(self.nm.inits[start])), float)
            r0[:self.model.nx] = np.log(np.maximum(T * np.diag(G @ G.T), 1e-300))
        if options.init_states == "measured":
            recs = [(mu.copy(), r0.copy()) for mu in self.measured_start]
        else:
            recs = [(initial_means(self.model, r, pairs, options.init_states), r0.copy())
                    for r in self.records]
        return s, recs

    @functools.cached_property
    def coherent(self) -> "CoherentScale":
        """Factors from the decision vector's declared units to coherent ones (:class:`CoherentScale`)."""
        return CoherentScale.of(self)

    @functools.cached_property
    def elbo_shift(self) -> float:
        """ELBO in coherent units minus the ELBO in declared ones (a constant of the problem).

        Under x = D x′, y = E y′ (D, E the states' and outputs' factors) every density of the
        joint transforms with its Jacobian and the entropy of q with the opposite one, except
        what is not a density: the flat prior of the initial states. So ELBO′ = ELBO +
        Σ_j M_j log e_j − Σ_records Σ_{i flat} log d_i (M_j the observed samples of output j;
        a state with the initial-value prior of ``input_state_prior`` is not flat). The
        estimator's tests that compare a change of the ELBO with its magnitude (the relative
        gradient, the stall test) use the coherent value."""
        cs = self.coherent
        m = sum(np.sum(np.isfinite(np.asarray(r.y, float)), axis=0) for r in self.records)
        flat = np.ones(self.model.nx, bool)
        if self.prior is not None:
            flat[np.asarray(self.prior[0][0], int)] = False
        return float(-(np.asarray(m, float) @ np.log(cs.output)) + self.nrec * np.sum(np.log(cs.state[flat])))

    @functools.cached_property
    def measured_start(self) -> list[np.ndarray]:
        """Per record, the state means of the "measured" start at the initial parameters:
        :func:`initial_means`, then :func:`invert_outputs` (computed once: every noise start
        and the release start's drift scale use it)."""
        return [mu for mu, _ in self._inverted]

    @functools.cached_property
    def output_solved(self) -> frozenset[int]:
        """States that no output measures directly but the outputs determine at the start
        (in every record; :func:`invert_outputs`): u and w of a body-axis model,
        through V and α."""
        sets = [set(solved) for _, solved in self._inverted]
        return frozenset(set.intersection(*sets)) if sets else frozenset()

    @functools.cached_property
    def _inverted(self) -> list[tuple[np.ndarray, tuple[int, ...]]]:
        theta = self.theta(self.tm.z0)
        pairs = list(self.direct)
        return [invert_outputs(self.model, r, initial_means(self.model, r, self.direct, "measured"),
                               pairs, theta) for r in self.records]

    def floor_active(self, s, gs):
        """Mask over s of noise parameters whose lower bound (floor) is active, and of the held
        parameters (``FitOptions.held_parameters``).

        σ = floor + exp(w) reaches its floor only asymptotically (w → −∞), so the
        gradient in w never vanishes there; a parameter with floor > 0, σ within
        1 % of the floor and a gradient pushing it towards the floor (∂(−L)/∂w > 0)
        is treated as an active bound constraint in the convergence test
        (projected / KKT gradient; flagged by the ``noise_at_floor`` warning).
        """
        act = self.held.copy()      # held parameters: bounds active on both sides
        nt, nm = self.tm.n_free, self.nm
        w = np.asarray(s[nt:], float)
        gw = np.asarray(gs[nt:], float)
        for a, i in enumerate(nm.proc_est_idx):
            fl = nm.proc_floor[i]
            act[nt + a] = fl > 0 and math.exp(min(w[a], 700.0)) <= 0.01 * fl and gw[a] > 0
        for a, j in enumerate(nm.meas_est_idx):
            fl = nm.meas_floor[j]
            k = nm.n_proc + a
            act[nt + k] = fl > 0 and math.exp(min(w[k], 700.0)) <= 0.01 * fl and gw[k] > 0
        return act

    # -- objective
    @staticmethod
    def pad(m, L):
        """μ (N, n) padded to L rows by repeating its last row (the model is evaluated there, weight 0)."""
        m = np.asarray(m)
        return jnp.asarray(m if L == m.shape[0] else np.concatenate([m, np.repeat(m[-1:], L - m.shape[0], 0)]))

    def value(self, s, recs) -> float:
        """−ELBO at the decision (s, [(μ_i, r_i)])."""
        sj = jnp.asarray(s)
        out = float(sum(self.obj.value(self.pad(m, L), jnp.asarray(r), sj, d, self.cfg)
                        for (m, r), d, L in zip(recs, self.bdata, self.padded)))
        if self.prior is not None:
            out += sum(float(_prior_value(jnp.asarray(m)[0], jnp.asarray(r), *pr))
                       for (m, r), pr in zip(recs, self.prior))
        return out

    def flat_value(self, v, cfg=None, data=None):
        """−ELBO of a full vector v (:meth:`Layout.unpack`) on the unpadded records, traceable by JAX
        (``jax.grad``, ``jax.hessian``: the dense reference of the structured derivatives).
        ``cfg``/``data`` (default this problem's) may be passed as jit arguments."""
        cfg = self.cfg if cfg is None else cfg
        data = self.data if data is None else data
        s, recs = self.layout.unpack(v)
        out = sum(self.obj._value_impl(m, r, s, d, cfg) for (m, r), d in zip(recs, data))
        if self.prior is not None:
            out = out + sum(_prior_value(m[0], r, *pr) for (m, r), pr in zip(recs, self.prior))
        return out

    def blocks(self, s, recs):
        """Per-record value, gradient and Hessian blocks (f, gmu, gb, D, B, W, Hbb; see
        :meth:`vsidgen.estimator.core.Objective.blocks`) on the padded length (D, B, W, gmu have
        ``self.padded[i]`` rows; the padding's gradient, couplings and off-diagonal blocks are
        exactly 0 and its diagonal blocks the identity)."""
        sj = jnp.asarray(s)
        blks = [self.obj.blocks(self.pad(m, L), jnp.asarray(r), sj, d, self.cfg)
                for (m, r), d, L in zip(recs, self.bdata, self.padded)]
        if self.prior is not None:
            blks = [_with_prior(b, jnp.asarray(m)[0], jnp.asarray(r), pr)
                    for b, (m, r), pr in zip(blks, recs, self.prior)]
        return blks

    @staticmethod
    def total(blks) -> float:
        """−ELBO from the blocks."""
        return float(sum(float(b["f"]) for b in blks))

    def gather(self, blks):
        """Border gradient g_b and Hessian H_bb over b (sums over records)."""
        gg = np.zeros(self.nglob)
        Hg = np.zeros((self.nglob, self.nglob))
        for ix, b in zip(self.idx, blks):
            gg[ix] += np.asarray(b["gb"])
            Hg[np.ix_(ix, ix)] += np.asarray(b["Hbb"])
        return gg, Hg

    def gradient(self, blks, gg=None) -> Gradient:
        """The gradient split by parts (``gg``: g_b from :meth:`gather`, computed when not given)."""
        gg = self.gather(blks)[0] if gg is None else gg
        nq = self.layout.nq
        return Gradient(shared=gg[self.nrec * nq:],
                        records_r=tuple(gg[i * nq:(i + 1) * nq] for i in range(self.nrec)),
                        records_mu=tuple(np.asarray(b["gmu"])[:n] for b, n in zip(blks, self.lengths)))

    # -- reduced Newton system
    def reduced_system(self, blks, *, lam: float = 0.0, dmus=None, dglob=None) -> ReducedSystem | None:
        """The state means eliminated (module docstring): S = H_bb + λ diag(d_b) − Σ W_iᵀA_i⁻¹W_i and
        rhs = −g_b + Σ W_iᵀA_i⁻¹g_μ_i, A_i = H_μ_iμ_i + λ diag(d_μ_i) (block-tridiagonal Cholesky);
        ``dmus`` (per record, the padded (N_i, n) diagonal) and ``dglob`` (nglob) default to 0.
        None when some A_i is not positive definite."""
        if dmus is None:
            dmus = [np.zeros((np.asarray(b["D"]).shape[0], self.model.nx)) for b in blks]
        facs = [self.obj.factor(b, jnp.asarray(dm), lam) for b, dm in zip(blks, dmus)]
        if not all(bool(f["ok"]) for f in facs):
            return None
        S = np.zeros((self.nglob, self.nglob))
        rhs = np.zeros(self.nglob)
        for ix, f in zip(self.idx, facs):
            S[np.ix_(ix, ix)] += np.asarray(f["S"])
            rhs[ix] += np.asarray(f["rhs"])
        if dglob is not None:
            S += lam * np.diag(dglob)
        return ReducedSystem(S=0.5 * (S + S.T), rhs=rhs, factors=tuple(facs))

    def score_system(self, blks, *, lam: float = SCORE_DAMPING):
        """(S, rhs) of :meth:`reduced_system` with the tiny Marquardt damping
        λ·max(|diag|, 1e-300) on every diagonal (state means and the global system), the
        system of score (Lagrange-multiplier) statistics at a nesting point; (None, None)
        when the state-mean blocks are not positive definite."""
        red = self.damped_reduced_system(blks, lam=lam)
        if red is None:
            return None, None
        S = red.S
        S += lam * np.diag(np.maximum(np.abs(np.diag(S)), 1e-300))
        return S, red.rhs

    def damped_reduced_system(self, blks, *, lam: float = SCORE_DAMPING) -> ReducedSystem | None:
        """:meth:`reduced_system` with the state-mean blocks damped by λ·max(|diag|, 1e-300)
        (the global system undamped): defined where a block is singular, e.g. the free
        initial value of an unmeasured state that couples to nothing."""
        dmus = [np.maximum(np.abs(np.diagonal(np.asarray(b["D"]), axis1=1, axis2=2)), 1e-300)
                for b in blks]
        return self.reduced_system(blks, lam=lam, dmus=dmus)

    def back_substitute(self, red: ReducedSystem, db):
        """(Δs, [Δμ_i], [Δr_i]) of the border step Δb: Δμ_i = −A_i⁻¹(g_μ_i + W_i Δb_i), unpadded."""
        dmu = [np.asarray(self.obj.back(f, jnp.asarray(db[ix])))[:n]
               for ix, f, n in zip(self.idx, red.factors, self.lengths)]
        nq = self.layout.nq
        dr = [db[i * nq:(i + 1) * nq] for i in range(self.nrec)]
        return db[self.nrec * nq:], dmu, dr

    def newton_step(self, blks, lam, dmus, dglob, frozen=None, delta=None):
        """Solve (H + λ diag(D)) Δ = −∇. Returns (Δs, [Δμ], [Δr], S), or None when H + λD is not
        positive definite.

        ``frozen``: mask over s of variables whose step is prescribed (``delta``, default 0:
        active floor bounds held fixed): the other variables get the (damped) Newton step
        given these components (projected Newton step).
        """
        red = self.reduced_system(blks, lam=lam, dmus=dmus, dglob=dglob)
        if red is None:
            return None
        S, rhs = red.S, red.rhs
        if frozen is not None and np.any(frozen):
            k = self.nrec * self.layout.nq + np.nonzero(frozen)[0]
            dk = np.zeros(len(k)) if delta is None else np.asarray(delta, float)[np.nonzero(frozen)[0]]
            rhs = rhs - S[:, k] @ dk
            S[k, :] = 0.0
            S[:, k] = 0.0
            S[k, k] = 1.0
            rhs[k] = dk
        if self.nglob:
            try:
                Lc = np.linalg.cholesky(S)
            except np.linalg.LinAlgError:
                return None
            db = np.linalg.solve(Lc.T, np.linalg.solve(Lc, rhs))
        else:
            db = np.zeros(0)
        ds, dmu, dr = self.back_substitute(red, db)
        return ds, dmu, dr, S


def input_state_prior_scales(model, records, names="all") -> dict[int, tuple[float, list[float]]]:
    """The initial-value prior of the states that carry an input (``FitOptions.input_state_prior``):
    ``{state index: (std, [mean per record])}`` with x_0 ~ N(u_0, std²), u_0 the carried input's
    first finite sample of the record and std its spread about each record's mean, pooled over
    ``records`` (:func:`~vsidgen.estimator.core.input_filter_scales`). ``names``: "all" (every
    such state whose input varies), "none", or state names (each must carry a varying input)."""
    if isinstance(names, str):
        if names not in ("all", "none"):
            raise FitError(f"input_state_prior must be 'all', 'none' or state names, not {names!r}")
        names = None if names == "all" else ()
    if names is not None and not names:
        return {}
    carried = dict(carried_inputs(model))
    snames = list(model.state_names)
    if names is None:
        chosen = sorted(carried)
    else:
        chosen = []
        for nm in names:
            if nm not in snames:
                raise FitError(f"input_state_prior: '{nm}' is not a state of the model")
            if snames.index(nm) not in carried:
                raise FitError(f"input_state_prior: state '{nm}' does not carry an input (its drift is "
                               f"not driven by the difference between it and an input of its unit)")
            chosen.append(snames.index(nm))
    spread = input_filter_scales(model, records)
    out = {}
    for i in chosen:
        sd = float(spread[i])
        if not (math.isfinite(sd) and sd > 0):
            if names is None:
                continue       # "all": a constant input gives no scale; the state keeps the flat prior
            raise FitError(f"input_state_prior: the input carried by '{snames[i]}' does not vary in the "
                           f"records (no scale for the prior of its initial value)")
        means = []
        for r in records:
            c = np.asarray(r.u, float)[:, carried[i]]
            fin = np.nonzero(np.isfinite(c))[0]
            means.append(float(c[fin[0]]) if fin.size else 0.0)
        out[i] = (sd, means)
    return out


def _input_state_prior(model, records, names):
    """Per record ``(idx, mean, w, n)`` of :func:`input_state_prior_scales` (w = 1/std²) for the
    objective; None when no state gets the prior."""
    sc = input_state_prior_scales(model, records, names)
    if not sc:
        return None
    idx = sorted(sc)
    w = jnp.asarray([1.0 / sc[i][0] ** 2 for i in idx])
    return [(jnp.asarray(np.asarray(idx, int)), jnp.asarray([sc[i][1][ri] for i in idx]), w, int(model.nx))
            for ri in range(len(records))]


def initial_prior_term(var, std=None) -> float:
    """The initial-value term of one added state at its nesting point, relative to a model
    without the state: the entropy of q(x_0), ½ log(2πe var) (var: q's marginal variance of
    the state), plus, for a state with the initial-value prior N(m, std²), E_q log N(x_0; m,
    std²) with q's mean at m: − ½ log(2π std²) − ½ var/std². ``std`` None: the flat prior
    (the entropy alone)."""
    var = max(float(var), 1e-300)
    h = 0.5 * math.log(2 * math.pi * math.e * var)
    return h if std is None else h - 0.5 * math.log(2 * math.pi * std ** 2) - 0.5 * var / std ** 2


def _prior_value(mu0, r, idx, mean, w, n):
    """−E_q log N(x_0,idx; mean, 1/w) (independent per state): ½ Σ w((μ_0 − m)² + Σ_marg,ii)
    + ½ Σ log(2π/w); Σ_marg from the assumed density's r (:func:`cov_factors_of`)."""
    Sm = cov_factors_of(r, n)[2]
    var = jnp.sum(Sm[idx, :] ** 2, axis=1)
    return 0.5 * jnp.sum(w * ((mu0[idx] - mean) ** 2 + var)) + 0.5 * jnp.sum(jnp.log(2.0 * math.pi / w))


@functools.partial(jax.jit, static_argnums=(5,))
def _prior_r_derivatives(r, idx, mean, w, mu0, n):
    """(value, ∇_r, ∇²_r) of :func:`_prior_value` in r (it is separable: μ_0 enters only its mean term)."""
    def fr(rr):
        return _prior_value(mu0, rr, idx, mean, w, n)
    return fr(r), jax.grad(fr)(r), jax.hessian(fr)(r)


def _with_prior(blk, mu0, r, prior):
    """One record's blocks (of −ELBO) with the initial-value prior added: its value, the r part of
    the border gradient and Hessian, and μ_0's gradient and diagonal block (the prior is separable
    in μ_0 and r, so there is no μ–border coupling)."""
    idx, mean, w, n = prior
    f, gr, Hr = _prior_r_derivatives(r, idx, mean, w, mu0, n)
    nq = r.shape[0]
    out = dict(blk)
    out["f"] = blk["f"] + f
    out["gb"] = blk["gb"].at[:nq].add(gr)
    out["Hbb"] = blk["Hbb"].at[:nq, :nq].add(Hr)
    out["gmu"] = blk["gmu"].at[0, idx].add(w * (mu0[idx] - mean))
    out["D"] = blk["D"].at[0, idx, idx].add(w)
    return out


def parameter_start(model) -> tuple[np.ndarray, np.ndarray]:
    """The start of every fit of ``model``: the free parameters' unconstrained coordinates z₀ and the
    θ (all parameters, model order) they map to — the spec's initial values."""
    tm = ThetaMap(model.parameters)
    return np.asarray(tm.z0, float), np.asarray(tm.theta(tm.z0), float)
