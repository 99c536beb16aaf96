"""Maneuver generators and stochastic simulation of a model (synthetic records).

Simulation model (same discretisation as the estimator, see
:mod:`vsidgen.model.dynamics`):

.. math::

    x_{k+1} = F(x_k, u_k, θ, T) + \\sqrt{T}\\, G\\, w_k,\\qquad
    y_k = h(x_k, u_k, θ) + v_k,\\qquad w_k \\sim N(0, I),\\ v_k \\sim N(0, R),

with ``G = diag(process_std)`` (state-unit/√s), ``R = diag(measurement_std²)``
and ``T`` the sample period. Optional quantisation of an output with step
``q``: ``y ← round(y/q) q``.

Maneuvers (numpy, one value per time stamp, zero before ``start``):

* ``doublet``: ``+A`` on ``[s, s+w)``, ``−A`` on ``[s+w, s+2w)``.
* ``3211``: ``+A`` for 3 units, ``−A`` for 2, ``+A`` for 1, ``−A`` for 1.
* ``multisine``: ``n`` equally spaced frequencies ``f_j`` in
  ``[f_min, f_max]`` with Schroeder phases ``φ_j = −π j(j−1)/n`` (low peak
  factor), ``Σ_j cos(2π f_j (t−s) + φ_j)`` scaled so that its peak over the
  given ``t`` is ``A``.
* ``step``: ``A`` for ``t ≥ s``.

Command-line input syntax (:func:`parse_input_spec`)::

    NAME=MANEUVER[:OPT=VALUE,...][+MANEUVER[:OPT=VALUE,...]...]
    de=3211:amplitude=0.02,start=1,unit=0.5
    thrust=const:value=11600
    de=const:value=-0.05+doublet:amplitude=0.01,start=2,width=1   (terms add up)
"""

from __future__ import annotations

import dataclasses
import inspect
import math
import pathlib
import re
from collections.abc import Callable, Mapping

import jax
import jax.numpy as jnp
import numpy as np

from .records import write_csv
from ..model.dynamics import transition
from ..errors import VsidgenError
from ..model.runtime import finite_theta

from .. import precision  # noqa: F401  (float64, set once)


# --------------------------------------------------------------------------- maneuvers

def _t(t) -> np.ndarray:
    return np.asarray(t, dtype=np.float64)


def _positive(maneuver: str, option: str, value: float) -> None:
    """Refuse a duration that is not a positive finite number (a doublet of width −1 was
    accepted and gave a zero input: red team, session 47)."""
    if not (math.isfinite(value) and value > 0):
        raise VsidgenError(f"{maneuver}: {option} must be a positive number of seconds, got "
                           f"{value:g}\n  hint: e.g. `{maneuver}:amplitude=0.02,{option}=1`")


def doublet(t, *, amplitude: float, start: float = 1.0, width: float = 1.0) -> np.ndarray:
    """Doublet: ``+A`` on ``[start, start+width)``, ``−A`` on ``[start+width, start+2 width)``."""
    _positive("doublet", "width", width)
    t = _t(t)
    return amplitude * (((t >= start) & (t < start + width)).astype(float)
                        - ((t >= start + width) & (t < start + 2 * width)).astype(float))


def three_two_one_one(t, *, amplitude: float, start: float = 1.0, unit: float = 0.5) -> np.ndarray:
    """3-2-1-1: ``+A`` for 3 units, ``−A`` for 2, ``+A`` for 1, ``−A`` for 1 (then 0)."""
    _positive("3211", "unit", unit)
    t = _t(t)
    out = np.zeros_like(t)
    edges = np.cumsum([0, 3, 2, 1, 1]) * unit + start
    for sign, a, b in zip((1, -1, 1, -1), edges[:-1], edges[1:]):
        out[(t >= a) & (t < b)] = sign * amplitude
    return out


#: most components of a multisine (a sum of n cosines is evaluated on every sample: n =
#: 1e8 asked for 75 GiB; session 44)
MAX_COMPONENTS = 1000


def multisine(t, *, amplitude: float, f_min: float = 0.1, f_max: float = 2.0, n: int = 10,
              start: float = 0.0) -> np.ndarray:
    """Schroeder-phased multisine of ``n`` components in ``[f_min, f_max]`` Hz.

    ``u(t) = c Σ_{j=1..n} cos(2π f_j (t−start) + φ_j)``, ``φ_j = −π j(j−1)/n``,
    ``f_j`` equally spaced (``f_min`` when ``n = 1``), zero before ``start``;
    ``c`` makes ``max |u| = amplitude`` over the given ``t``.
    """
    n = int(n)
    if n < 1 or n > MAX_COMPONENTS or f_min <= 0 or f_max < f_min:
        raise VsidgenError(f"multisine: need 1 <= n <= {MAX_COMPONENTS} and 0 < f_min <= f_max (got n={n}, "
                           f"f_min={f_min}, f_max={f_max})")
    t = _t(t)
    f = np.linspace(f_min, f_max, n) if n > 1 else np.array([float(f_min)])
    j = np.arange(1, n + 1)
    phi = -np.pi * j * (j - 1) / n
    tau = (t - start)[..., None]
    s = np.cos(2 * np.pi * f * tau + phi).sum(axis=-1)
    s = np.where(t >= start, s, 0.0)
    peak = np.max(np.abs(s)) if s.size else 0.0
    return amplitude * s / peak if peak > 0 else s


def step(t, *, amplitude: float, start: float = 1.0) -> np.ndarray:
    """Step: ``A`` for ``t ≥ start``, 0 before."""
    t = _t(t)
    return amplitude * (t >= start).astype(float)


def const(t, *, value: float) -> np.ndarray:
    """Constant input (trim value) ``value``."""
    return np.full_like(_t(t), float(value))


MANEUVERS: dict[str, Callable] = {
    "doublet": doublet,
    "3211": three_two_one_one,
    "multisine": multisine,
    "step": step,
}
_ALL = {**MANEUVERS, "const": const}


def _options(fn) -> tuple[list[str], dict[str, object]]:
    sig = inspect.signature(fn)
    required, defaults = [], {}
    for p in sig.parameters.values():
        if p.kind is inspect.Parameter.KEYWORD_ONLY:
            if p.default is inspect.Parameter.empty:
                required.append(p.name)
            else:
                defaults[p.name] = p.default
    return required, defaults


def _maneuver_help() -> str:
    parts = []
    for name, fn in _ALL.items():
        req, dfl = _options(fn)
        opts = req + [f"{k}={v}" for k, v in dfl.items()]
        parts.append(f"{name}:{','.join(opts)}")
    return ("syntax NAME=MANEUVER:OPT=VALUE,... (terms joined by '+' add up), e.g. "
            "de=3211:amplitude=0.02,start=1,unit=0.5 or thrust=const:value=11600; "
            "maneuvers and options: " + "; ".join(parts))


@dataclasses.dataclass(frozen=True)
class InputSpec:
    """A parsed ``--input`` option: ``name`` = sum of maneuver ``terms``.

    ``terms`` is a tuple of ``(maneuver, options)``; call :meth:`evaluate`.
    """

    name: str
    terms: tuple[tuple[str, tuple[tuple[str, float], ...]], ...]

    def evaluate(self, t) -> np.ndarray:
        """Input time history at the time stamps ``t``."""
        t = _t(t)
        out = np.zeros_like(t)
        for man, opts in self.terms:
            out = out + _ALL[man](t, **dict(opts))
        return out

    __call__ = evaluate


def parse_input_spec(text: str) -> InputSpec:
    """Parse ``NAME=MANEUVER:OPT=VALUE,...[+MANEUVER:...]`` (see the module docstring).

    Raises:
        VsidgenError: with a hint listing the maneuvers and their options.
    """
    hint = _maneuver_help()

    def fail(msg):
        raise VsidgenError(f"input spec {text!r}: {msg}\n  hint: {hint}")

    if "=" not in text:
        fail("expected NAME=MANEUVER...")
    name, rest = text.split("=", 1)
    name = name.strip()
    if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", name):
        fail(f"invalid input name {name!r}")
    terms = []
    for term in re.split(r"\+(?=\s*[A-Za-z0-9_]+\s*(?::|$))", rest):
        term = term.strip()
        if not term:
            fail("empty maneuver term")
        man, _, opt_text = term.partition(":")
        man = man.strip()
        if man not in _ALL:
            fail(f"unknown maneuver {man!r}")
        required, defaults = _options(_ALL[man])
        opts: dict[str, float] = {}
        for item in filter(None, (s.strip() for s in opt_text.split(","))):
            key, eq, val = item.partition("=")
            key = key.strip()
            if not eq:
                fail(f"option {item!r} of {man} needs KEY=VALUE")
            if key not in required and key not in defaults:
                fail(f"unknown option {key!r} of {man} (valid: {', '.join(required + list(defaults))})")
            if key in opts:
                fail(f"option {key} of {man} given twice")
            try:
                v = float(val)
            except ValueError:
                fail(f"option {key} of {man}: {val.strip()!r} is not a number")
            if not math.isfinite(v):
                fail(f"option {key} of {man} must be finite")
            if key == "n":
                if v != int(v) or v < 1 or v > MAX_COMPONENTS:
                    fail(f"option n of multisine must be an integer from 1 to {MAX_COMPONENTS}")
                v = int(v)
            opts[key] = v
        missing = [k for k in required if k not in opts]
        if missing:
            fail(f"maneuver {man} needs option(s) {', '.join(missing)}")
        terms.append((man, tuple(opts.items())))
    return InputSpec(name=name, terms=tuple(terms))


# --------------------------------------------------------------------------- simulation

@dataclasses.dataclass(frozen=True, eq=False)
class SimulationResult:
    """Simulated time histories: ``t`` (N,), ``x`` (N, nx), ``y`` (N, ny), ``u`` (N, nu)."""

    t: np.ndarray
    x: np.ndarray
    y: np.ndarray
    u: np.ndarray
    #: what the user should know about the record (e.g. an output quantised to one level)
    warnings: tuple[str, ...] = ()


#: the largest magnitude whose square float64 holds: a record beyond it cannot be fitted (its
#: squared residuals overflow), so a simulation reaching it is refused like a divergence
LARGEST_VALUE = math.sqrt(np.finfo(np.float64).max)


def _named_vector(model, values, names, what) -> np.ndarray:
    if isinstance(values, Mapping):
        unknown = [k for k in values if k not in names]
        missing = [k for k in names if k not in values]
        if unknown or missing:
            raise VsidgenError(f"{what}: unknown {unknown} / missing {missing}\n"
                               f"  hint: expected names {', '.join(names)}")
        return np.array([float(values[k]) for k in names])
    arr = np.asarray(values, dtype=np.float64).ravel()
    if arr.shape != (len(names),):
        raise VsidgenError(f"{what}: expected {len(names)} values ({', '.join(names)}), got {arr.size}")
    return arr


def _std_vector(std, names, what) -> np.ndarray:
    out = np.zeros(len(names))
    if std is None:
        return out
    if not isinstance(std, Mapping):
        return _named_vector(None, std, names, what)
    for k, v in std.items():
        if k not in names:
            raise VsidgenError(f"{what}: unknown name {k!r}\n  hint: expected one of {', '.join(names)}")
        if not (float(v) >= 0 and math.isfinite(float(v))):
            raise VsidgenError(f"{what}: std of {k!r} must be finite and >= 0, got {v}")
        out[names.index(k)] = float(v)
    return out


def _input_matrix(model, u, t) -> np.ndarray:
    n = t.shape[0]
    names = model.input_names
    if isinstance(u, Mapping):
        unknown = [k for k in u if k not in names]
        missing = [k for k in names if k not in u]
        if unknown or missing:
            raise VsidgenError(f"inputs: unknown {unknown} / missing {missing}\n"
                               f"  hint: model {model.name} has inputs {', '.join(names)}")
        cols = []
        for k in names:
            v = u[k]
            v = v(t) if callable(v) else v
            cols.append(np.broadcast_to(np.asarray(v, dtype=np.float64), (n,)))
        U = np.stack(cols, axis=1) if cols else np.zeros((n, 0))
    else:
        U = np.asarray(u, dtype=np.float64)
        if U.ndim == 1 and model.nu == 1:
            U = U[:, None]
        if U.shape != (n, model.nu):
            raise VsidgenError(f"u has shape {U.shape}, expected ({n}, {model.nu})")
    if not np.isfinite(U).all():
        raise VsidgenError("inputs must be finite")
    return np.array(U)


def simulate(model, *, theta, t, u, x0, process_std=None, measurement_std=None,
             integrator: str | None = "euler", substeps: int | None = 1,
             input_hold: str | None = None, seed: int = 0,
             quantize=None) -> SimulationResult:
    """Simulate ``model`` (see the module docstring for the equations).

    Args:
        theta: dict name->value (missing: ``Parameter.initial``) or (np,) array.
        t: (N,) uniformly spaced time stamps (T = t[1] - t[0]).
        u: (N, nu) array or dict input -> scalar | (N,) array | callable(t).
        x0: (nx,) array or dict state -> value.
        process_std: dict state -> std of G (state-unit/√s); default no process noise.
        measurement_std: dict output -> std; default no measurement noise.
        integrator, substeps: mean transition, see :func:`vsidgen.model.dynamics.transition`
            (``None`` = the model's choice).
        input_hold: "zoh" | "foh", inputs held or interpolated linearly between the
            samples of ``t`` (``None`` = the model's choice).
        seed: seed of the noise generator (numpy ``default_rng``).
        quantize: dict output -> quantisation step (applied after the noise).

    Raises:
        VsidgenError: bad arguments or a diverging simulation.
    """
    t = np.asarray(t, dtype=np.float64).ravel()
    if t.shape[0] < 2:
        raise VsidgenError("simulate: need at least 2 time stamps")
    T = float(t[1] - t[0])
    steps = np.diff(t)
    if not (T > 0) or np.abs(steps - T).max() > 1e-9 * max(1.0, abs(t[-1])) + 1e-6 * T:
        raise VsidgenError("simulate: t must be increasing and uniformly spaced")
    n = t.shape[0]
    for k, q in (quantize or {}).items():
        if k not in model.output_names:
            raise VsidgenError(f"quantize: unknown output {k!r}")
        if not (math.isfinite(float(q)) and float(q) > 0):
            raise VsidgenError(f"quantize: the step of {k!r} must be finite and > 0, got {q}\n"
                               "  hint: leave the output out of --quantize for no quantisation")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise VsidgenError(f"simulate: seed must be an integer >= 0, got {seed!r}")
    if substeps is not None or integrator is not None or input_hold is not None:
        from ..model.dynamics import check_settings
        check_settings(integrator or model.integrator, model.substeps if substeps is None
                       else substeps, input_hold or model.input_hold)
    p = finite_theta(model, theta, who="simulate")
    U = _input_matrix(model, u, t)
    x0v = _named_vector(model, x0, model.state_names, "x0")
    g = _std_vector(process_std, model.state_names, "process_std")
    r = _std_vector(measurement_std, model.output_names, "measurement_std")
    rng = np.random.default_rng(seed)
    W = rng.standard_normal((n - 1, model.nx)) * (math.sqrt(T) * g)
    V = rng.standard_normal((n, model.ny)) * r

    F = transition(model, integrator=integrator, substeps=substeps, inputs=input_hold)

    @jax.jit
    def run(x0, U, p, W):
        def body(x, inp):
            vk, wk = inp
            xn = F(x, vk, p, T) + wk
            return xn, xn

        _, xs = jax.lax.scan(body, x0, (F.step_inputs(U), W))
        X = jnp.concatenate([x0[None, :], xs], axis=0)
        Y = jax.vmap(lambda x, u: model.output(x, u, p))(X, U)
        return X, Y

    X, Y = run(jnp.asarray(x0v), jnp.asarray(U), jnp.asarray(p), jnp.asarray(W))
    X = np.asarray(X)
    Y = np.asarray(Y) + V
    for arr, names, what in ((U, model.input_names, "input"), (X, model.state_names, "state"),
                             (Y, model.output_names, "output")):
        big = ~(np.abs(arr) <= LARGEST_VALUE)          # also NaN and inf
        if big.any():
            k, j = (int(i[0]) for i in np.nonzero(big))
            how = "is not finite" if not np.isfinite(arr[k, j]) else f"reaches {arr[k, j]:.3g}"
            raise VsidgenError(
                ("" if what == "input" else "simulation diverged: ")
                + f"{what} `{names[j]}` {how} at sample {k} "
                f"(t = {t[k]:.6g} s)\n"
                f"  hint: values beyond {LARGEST_VALUE:.3g} cannot be fitted (their squares "
                "overflow); check theta, x0, the input amplitudes and the noise stds, or use a "
                "smaller sample period / more substeps")
    notes = []
    for k, q in (quantize or {}).items():
        j = model.output_names.index(k)
        before = np.ptp(Y[:, j])
        big = float(np.max(np.abs(Y[:, j]))) if Y.shape[0] else 0.0
        if big / q > 2.0 ** 52:
            # y/q would overflow, or the step is below the values' own float resolution (a
            # step of 1e-320 wrote -inf into the record: red team, session 47)
            raise VsidgenError(f"quantize: the step of {k!r} ({q:g}) is below the resolution of "
                               f"its values (up to {big:.3g} in magnitude: a double holds "
                               "about 16 digits)\n  hint: give a step of at least "
                               f"{big / 2.0 ** 52:.3g}, or leave {k!r} out of --quantize")
        Y[:, j] = np.round(Y[:, j] / q) * q
        if before > 0 and np.ptp(Y[:, j]) == 0:
            notes.append(f"output `{k}` quantised to a single level (step {q:g} against a range "
                         f"of {before:.3g}): the channel carries no information")
    from .records import MIN_SAMPLES
    if len(t) < MIN_SAMPLES:
        notes.append(f"{len(t)} samples: a fit needs at least {MIN_SAMPLES} (give a longer "
                     "duration or a shorter sample period)")
    return SimulationResult(t=t, x=X, y=Y, u=U, warnings=tuple(notes))


def _inverse_columns(cmap, values: np.ndarray) -> dict[str, np.ndarray]:
    """Column values that make ``cmap`` read back ``values``.

    ``column`` map: ``((value − offset)/scale − b)/a`` with ``(a, b)`` the
    unit conversion of the data map (identity without ``unit:``). ``expr`` map: if the
    expression can be solved for its first column with the other columns set
    to 0 (e.g. ``(da_right − da_left)/2`` → ``da_right = 2 da``), those
    columns are written; otherwise only a column named after the channel is
    written (and the record cannot be read back through this map).
    """
    a, b = getattr(cmap, "unit_conversion", (1.0, 0.0))
    raw = ((values - cmap.offset) / cmap.scale - b) / a
    if cmap.expr is None:
        return {cmap.source_columns()[0]: raw}
    import sympy

    cols = cmap.source_columns()
    by_name = {str(s): s for s in cmap.expr.free_symbols}
    out = {cmap.name: raw}
    if not cols or cols[0] not in by_name:
        return out
    target = sympy.Dummy("v")
    first = by_name[cols[0]]
    zero = {by_name[c]: 0 for c in cols[1:] if c in by_name}
    try:
        sols = sympy.solve(sympy.Eq(cmap.expr.subs(zero), target), first)
    except Exception:  # noqa: BLE001 - sympy raises many types; fall back
        return out
    if len(sols) != 1:
        return out
    inv = sympy.lambdify([target], sols[0], "numpy")
    col0 = np.broadcast_to(np.asarray(inv(raw), dtype=np.float64), raw.shape)
    check = sympy.lambdify([first], cmap.expr.subs(zero), "numpy")(col0)
    if not np.allclose(check, raw, rtol=1e-12, atol=1e-300):
        return out
    out[cols[0]] = np.array(col0)
    for c in cols[1:]:
        out[c] = np.zeros_like(raw)
    return out


def simulate_to_csv(model, out_path, **simulate_kwargs) -> SimulationResult:
    """Simulate and write a CSV record readable by :func:`vsidgen.data.load_record`.

    Columns: ``model.data.time`` (= ``t``), then for every input and output the
    column(s) of its data map with the inverse mapping ``(value − offset)/scale``.
    For an ``expr`` map a column named after the channel is written, plus the
    expression's columns when the expression can be inverted (see
    :func:`_inverse_columns`). Written atomically (:func:`vsidgen.data.write_csv`).
    """
    res = simulate(model, **simulate_kwargs)
    maps_in = {c.name: c for c in model.data.inputs}
    maps_out = {c.name: c for c in model.data.outputs}
    from ..metadata import ChannelMap

    columns: dict[str, np.ndarray] = {
        model.data.time: res.t / float(getattr(model.data, "time_scale", 1.0))}
    for names, maps, values in ((model.input_names, maps_in, res.u),
                                (model.output_names, maps_out, res.y)):
        for j, nm in enumerate(names):
            cmap = maps.get(nm) or ChannelMap(nm, nm)
            for col, val in _inverse_columns(cmap, values[:, j]).items():
                if col in columns and not np.array_equal(columns[col], val, equal_nan=True):
                    raise VsidgenError(f"simulate_to_csv: column '{col}' is needed with two "
                                       "different values by the data map")
                columns[col] = val
    write_csv(pathlib.Path(out_path), columns)
    return res


__all__ = ["InputSpec", "MANEUVERS", "SimulationResult", "const", "doublet", "multisine",
           "parse_input_spec", "simulate", "simulate_to_csv", "step",
           "three_two_one_one"]
