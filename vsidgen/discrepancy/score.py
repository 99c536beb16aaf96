"""Score (Lagrange-multiplier) pre-screen of every candidate without a refit.


At the current optimum the candidate model is evaluated at its nesting point (new
parameters at the values that reproduce the current model, current parameters,
noise and assumed density at their estimates; added states embedded as in stage 0
of the staged refit, see :func:`.refit.stage0_start`). With the estimator's exact
gradient ``g`` and Hessian ``H`` of the negative ELBO over the *whole* decision
vector (θ, noise, assumed-density parameters and state means of every record,
block-tridiagonal in time, eliminated as in the estimator's Newton step) the
Newton decrement

    ``gain = ½ gᵀ H⁻¹ g``

is the ELBO increase a quadratic model predicts for re-optimising everything. The
same decrement with the new parameters held at their nesting values (``gain₀``)
is what re-optimising the rest alone would give. At an exact optimum of the current
model ``gain₀ = 0`` and

    ``S = 2 (gain − gain₀) = g_nᵀ (H/H_rest)⁻¹ g_n``

is the score statistic of the new parameters, profiled over every other variable
through the Schur complement: it approximates the likelihood-ratio statistic
``2ΔELBO`` of the refit, asymptotically ``χ²_k`` under the current model. Taking
the difference keeps the approximation when the start is not exactly stationary
(added states embedded by simulation).

For a batch that adds no state the statistic is Rao's (:func:`_rao_system`): the
assumed-density parameters of every record are eliminated too, so the system is that of the
likelihood of the parameters with the latent path profiled out, and the noise parameters are
held at their estimates — under the null the expected information between a mean parameter
and a noise parameter is zero, so this is exact for Rao's statistic; the gradient stays
exact. Observed, ``∂²/∂φ ∂log σ`` is about twice the gradient of φ, so it grows with the
effect: a strongly supported candidate had a negative or nearly zero profiled curvature (no
statistic, or an inflated one). On a linear model the statistic equals the exact
Kalman-filter Rao statistic (a sensor bias: 17.193 against 17.197; grid delays within
0.6 %: tests/test_score_states.py, tests/test_delay_screen.py).

A direction along which the ELBO is flat at the nesting point (a time constant
whose gain is still zero, e.g. the lag of an α̇ term with zero gain) carries no
information at the null (Davies' problem): such parameters are held at their
nesting values and not counted in the degrees of freedom. New noise parameters
(a wind state's intensity at its vanishing start) are held likewise; a candidate
with nothing testable left gets ``None`` and is ranked after every tested one, by its
locate score (:class:`.search.Ranked`).


Candidates that add states. The added states are embedded at the nesting point as in
stage 0 of the refit (:func:`.refit.stage0_start`: means simulated with their own
transition along the current smoother). Three things make the statistic well-posed there
(:func:`condition_added_states`, :func:`nesting_reach`):

* a proper prior on each added state's first value, centred on its nesting value with the
  precision of one step of its own process noise, ``1/(T G_ii²)`` — with the ELBO's flat
  prior the initial value of a state that reaches no output is an exactly flat direction;
* the expected (Fisher) information instead of the observed one in the cross blocks of the
  new parameters with the means of added states that reach no data at the null and with
  the noise parameters: at the
  nesting point these are the equation error times a sensitivity, zero in expectation
  under the current model (Rao's form of the score test); observed, they make the
  curvature indefinite — the new gains enter only as products with the nearly free,
  integrating added-state paths, and the noise cross terms grow with the gradient itself;
* the new parameters that only move added states that reach nothing (the added mode's time
  constant while its gain is zero, the speed damping while the lift and moment couplings
  are zero) are held at their nesting values (Davies' problem, as above), found from the
  structural zeros of the exact Jacobians along the path; so are the assumed-density
  entries that couple an added state with the others (its start is not their optimum).

The statistic is then the score test of the couplings given the added states' own
dynamics at their nesting values.

Cost: candidates are screened in *batches*. A batch is one spec that adds several
candidates at once, every new parameter at its nesting value: frozen at those
values it is exactly the current model, so its gradient and Hessian at the current
optimum contain every candidate's blocks. One compilation, one Hessian assembly and
one elimination of the state means serve the whole batch; each candidate's
statistic is then a small Schur complement of the reduced (global) system
(holding a global variable fixed = deleting its row and column there). Candidates
whose new names collide, and those that add states beyond ``max_states`` per
batch, go to further batches.

The batches that add states are many models of few shapes (the current states plus one or
two added ones). They share one compilation per shape (:func:`screen_shared`): each batch's
model is padded with inert parameters to the shape's numbers of free and of all parameters
(:func:`padded_model`; held, so they change no statistic) and one
:class:`~vsidgen.estimator.core.SwitchedObjective` evaluates the Hessian blocks of the batch
whose index its configuration carries (``jax.lax.switch`` on a run-time index). The
per-batch path (:func:`screen_group`, each batch's own objective) is the reference;
``screen(shared=False)`` takes it. (XLA options that compile faster for the one evaluation
of a batch, LLVM -O0/-O1 or without its expensive passes, saved nothing measurable on the
Twin Otter batches: docs/performance.md, "Score screen".)
"""

from __future__ import annotations

import dataclasses
import math
import pathlib

import numpy as np
from scipy import stats

from ..estimator.problem import NEGATIVE_CURVATURE_TOL, SCORE_DAMPING
from ..report import finite_or_none
from .pvalues import chi2_logsf
from .refit import REFIT_DETERMINISTIC_REL


def _screen_options(det_std: float):
    """Options of the problems the score statistics are evaluated on: records unpadded, the
    quasi-deterministic added states with the refits' std (an input's lag or delay state
    relative to the input's std, :data:`.refit.REFIT_DETERMINISTIC_REL`)."""
    from ..estimator import FitOptions

    return FitOptions(deterministic_std=det_std, deterministic_input_scale=REFIT_DETERMINISTIC_REL,
                      bucket=False)


@dataclasses.dataclass(frozen=True)
class ScoreResult:
    """Score statistic of one candidate (``statistic`` ≈ 2ΔELBO of its refit)."""

    statistic: float | None
    dof: int
    p_value: float | None
    tested: tuple[str, ...] = ()      # new parameters in the test
    held: tuple[str, ...] = ()        # new parameters held (flat at the null)
    gain_full: float = math.nan
    gain_rest: float = math.nan
    step: dict = dataclasses.field(default_factory=dict)   # one-step estimates of the tested
    note: str = ""
    #: the profiled curvature along the new parameters is negative at the nesting point: the
    #: current optimum is a saddle of the candidate's ELBO, so the candidate raises the ELBO
    #: for certain, by an amount the quadratic model cannot give (no statistic)
    ascent: bool = False
    #: Bonferroni factor of a statistic maximised over ``multiplicity`` tests (a profiled
    #: nonlinear parameter: the grid of delays or time constants, :func:`screen_input_filters`): p = min(1, m·p₁)
    multiplicity: int = 1
    #: (value of the profiled parameter, statistic or None) per grid value
    profile: tuple = ()

    @property
    def log10p(self) -> float:
        """−log10 p (inf-safe, Bonferroni factor included), the screening priority."""
        if self.statistic is None or self.dof < 1:
            return math.nan
        lp = chi2_logsf(max(self.statistic, 0.0), self.dof)
        return max(-(lp + math.log(max(self.multiplicity, 1))) / math.log(10.0), 0.0)

    def to_json(self) -> dict:
        f = finite_or_none
        return {"statistic": f(self.statistic), "dof": self.dof, "p_value": f(self.p_value),
                "minus_log10_p": f(self.log10p), "tested": list(self.tested),
                "held": list(self.held), "gain_full": f(self.gain_full),
                "gain_rest": f(self.gain_rest), "one_step": {k: f(v) for k, v in self.step.items()},
                "note": self.note, "ascent": self.ascent, "multiplicity": self.multiplicity,
                "profile": [[float(v), f(st)] for v, st in self.profile]}



def _names(c) -> set:
    return ({p.name for p in c.parameters} | {s.name for s in c.states}
            | set((c.definitions or {}).keys()))


def batches(candidates, *, max_states: int = 2) -> list[list]:
    """Group screenable candidates: all that add no state in one batch; those that add
    states in batches of at most ``max_states`` added states."""
    plain = [c for c in candidates if not c.states]
    out = [plain] if plain else []
    cur, ns = [], 0
    for c in (c for c in candidates if c.states):
        if cur and ns + len(c.states) > max_states:
            out.append(cur)
            cur, ns = [], 0
        cur.append(c)
        ns += len(c.states)
    if cur:
        out.append(cur)
    return out


def _rename(obj, ren: dict):
    """Apply the name map ``ren`` to every expression text and key of a spec fragment."""
    import re
    if not ren:
        return obj
    pat = re.compile(r"\b(" + "|".join(map(re.escape, sorted(ren, key=len, reverse=True)))
                     + r")\b")
    if isinstance(obj, str):
        return pat.sub(lambda mt: ren[mt.group(1)], obj)
    if isinstance(obj, dict):
        return {(ren.get(k, k) if isinstance(k, str) else k): _rename(v, ren)
                for k, v in obj.items()}
    if isinstance(obj, list):
        return [_rename(v, ren) for v in obj]
    return obj


def batch_spec_dict(cands, base_spec, *, name, path, info) -> tuple[dict, dict]:
    """One spec adding every candidate of ``cands`` (add_terms on one equation are summed).

    Names that two candidates both create (e.g. the slope of hinges at different break
    points) are made unique with a suffix. Returns (spec mapping, {key: {name: batch name}}).
    """
    d = {"name": name, "description": "score-test batch: " + ", ".join(c.key for c in cands)[:380],
         "extends": None}
    merged: dict = {}
    used: set = set()
    names: dict = {}
    for j, c in enumerate(cands):
        dc = c.spec_dict(base_spec, name=name, candidate_path=path, info=info)
        own = _names(c)
        ren = {n: f"{n}_b{j}" for n in own if n in used}
        used |= {ren.get(n, n) for n in own}
        names[c.key] = {n: ren.get(n, n) for n in own}
        d["extends"] = dc["extends"]
        dc = {k: (_rename(v, ren) if k in ("states", "parameters", "definitions", "drift",
                                           "add_terms", "noise") else v) for k, v in dc.items()}
        for sect in ("states", "parameters", "definitions", "drift"):
            if dc.get(sect):
                d.setdefault(sect, {}).update(dc[sect])
        for sect, terms in (dc.get("add_terms") or {}).items():
            for k, v in terms.items():
                merged.setdefault(sect, {}).setdefault(k, []).append(v)
        if dc.get("noise"):
            st = d.setdefault("noise", {"process": {"states": []}})["process"]["states"]
            for n in dc["noise"]["process"]["states"]:
                if n not in st:
                    st.append(n)
    if merged:
        d["add_terms"] = {sect: {k: " + ".join(f"({t})" for t in v) for k, v in terms.items()}
                          for sect, terms in merged.items()}
    return d, names


def _reduced_system(problem, blks, lam=SCORE_DAMPING):
    """Global Schur complement S (μ eliminated) and reduced rhs, slightly damped
    (:meth:`vsidgen.estimator.problem.Problem.score_system`)."""
    return problem.score_system(blks, lam=lam)


def nesting_reach(model, new_states, new_params, X, U, theta):
    """(informative new parameters, added states that reach the data) at the nesting point.

    Structural zeros of the model's exact Jacobians along the embedded path ``X`` (inputs
    ``U``, parameters ``theta`` at their nesting values): an added state *reaches* the data
    when some base-state drift or output, or the drift of an added state that reaches,
    depends on it (∂f/∂z or ∂h/∂z ≠ 0 at some sample); a new parameter is *informative*
    when one of those equations depends on it. Every other new parameter moves only added
    states that reach nothing: the ELBO is flat along it at the null, so it carries no
    information there (Davies' problem — e.g. the time constant of a mode whose gain is
    zero, the speed damping X_V while Z_V = M_V = 0).
    """
    import jax
    import jax.numpy as jnp

    names = list(model.state_names)
    pnames = list(model.parameter_names)
    n = len(names)
    added = [names.index(z) for z in new_states]
    th = jnp.asarray(theta)

    def jac(x, u):
        fx, _, fp = model.drift_jacobian(x, u, th)
        hx, _, hp = model.output_jacobian(x, u, th)
        return jnp.concatenate([fx, hx]), jnp.concatenate([fp, hp])

    step = max(1, len(X) // 256)
    jx, jp = jax.vmap(jac)(jnp.asarray(X[::step]), jnp.asarray(U[::step]))
    nzx = np.any(np.asarray(jx) != 0.0, axis=0)        # (n + ny, n)
    nzp = np.any(np.asarray(jp) != 0.0, axis=0)        # (n + ny, np)
    rows = {i for i in range(nzx.shape[0]) if i >= n or i not in added}
    reach: list[int] = []
    grown = True
    while grown:
        grown = False
        for z in added:
            if z not in reach and any(nzx[r, z] for r in rows):
                reach.append(z)
                rows.add(z)
                grown = True
    informative = {q for q in new_params if any(nzp[r, pnames.index(q)] for r in rows)}
    return informative, [names[z] for z in reach]


def condition_added_states(blk, added, x0_precision, inert, coupling_cols, noise_cols):
    """Blocks of one record with the added states conditioned as the score test needs.

    * ``x0_precision`` (per added state): a proper prior on the added state's value at the
      first sample, centred on its nesting value — the state is at that value one sample
      before the record and its first transition adds its own process noise (precision
      1/(T·G_ii²)). With the flat prior of the ELBO the initial value of a state that
      reaches nothing at the null is an exactly flat direction (singular Hessian).
    * ``coupling_cols`` (columns of the border): the cross blocks between the means of the
      ``inert`` added states (those that reach no data at the null, see
      :func:`nesting_reach`) and the new parameters are set to their expectation under the
      null, zero. Those parameters couple such a state into the model as a product
      (``Z_V·ΔV``), so the observed cross term is the equation error times the
      sensitivity, whose expectation under the current model is zero; with
      quasi-deterministic but integrating added states it makes the observed information
      indefinite (a saddle in ``(Z_V, ΔV path)``). Using the expected information for that
      block is Rao's form of the score test; the gradient stays exact. (A state that
      reaches the data, e.g. a mode that enters its equation with a fixed coefficient and
      is driven through a new gain, keeps its exact cross blocks: they carry the test.)
    * ``noise_cols``: likewise the cross blocks between the new parameters and the noise
      parameters (``∂²/∂θ_new ∂log G = 2 ∂/∂θ_new`` of the equation's error term, zero in
      expectation). Observed, they grow with the gradient itself, so a strongly supported
      candidate (a large statistic) would make the profiled curvature negative. (A batch without added
      states takes the null expectation after the latent path is profiled out instead,
      :func:`_rao_system`.)
    """
    import jax.numpy as jnp

    D = np.asarray(blk["D"]).copy()
    for i, prec in zip(added, x0_precision):
        D[0, i, i] += prec
    W = np.asarray(blk["W"]).copy()
    H = np.asarray(blk["Hbb"]).copy()
    if len(coupling_cols):
        cc = np.asarray(coupling_cols)
        if len(inert):
            W[np.ix_(np.arange(W.shape[0]), np.asarray(inert), cc)] = 0.0
        if len(noise_cols):
            H[np.ix_(cc, np.asarray(noise_cols))] = 0.0
            H[np.ix_(np.asarray(noise_cols), cc)] = 0.0
    return {**blk, "D": jnp.asarray(D), "W": jnp.asarray(W), "Hbb": jnp.asarray(H)}


def added_state_r_index(n: int, added) -> list[int]:
    """Entries of a record's assumed-density parameters ``r = (d, L, C)`` (see
    ``Objective.cov_factors``) that couple an added state with the others (``L`` and ``C``
    entries in its row or column)."""
    tr = list(zip(*np.tril_indices(n, -1)))
    nl = len(tr)
    out = [n + j for j, (a, b) in enumerate(tr) if a in added or b in added]
    out += [n + nl + a * n + b for a in range(n) for b in range(n) if a in added or b in added]
    return out


def _batch_model(cands, current, info, path: pathlib.Path, name: str, *, generated_dir):
    """(model, {key: {name: batch name}}) of the batch spec of ``cands`` (written at ``path``)."""
    from ..model import load_model
    from .specwrite import warm_parameters, write_spec

    d, bnames = batch_spec_dict(cands, current.spec_path, name=name, path=path, info=info)
    params = warm_parameters(current.model, current.fit.theta)
    params.update(d.get("parameters") or {})
    d["parameters"] = params
    write_spec(path, "vsidgen diagnose score-test batch", d)
    return load_model(path, generated_dir=generated_dir), bnames


def screen_batch(cands, current, info, path: pathlib.Path, name: str, *, generated_dir,
                 det_std: float) -> dict:
    """Score statistics of the candidates of one batch: {key: ScoreResult} (the batch's own
    model and objective: one compilation)."""
    from ..estimator import Problem

    m, bnames = _batch_model(cands, current, info, path, name, generated_dir=generated_dir)
    # the model's own integrator, sub-steps and input hold; records unpadded
    P = Problem(m, list(current.records), _screen_options(det_std))
    return batch_statistics(cands, current, m, P, bnames, det_std=det_std)


def _rao_system(S, rhs, lay, gpos):
    """The reduced system ``S``, ``rhs`` (state means eliminated) of a batch that adds no state,
    in Rao's form: (S, rhs, positions, size) on the free parameters θ alone.

    The assumed-density parameters ``r`` of every record are eliminated too (the latent path
    profiled out: the system of the likelihood of the parameters), and the noise parameters
    are held at their estimates. Under the null the expected information between a mean
    parameter and a noise parameter is zero (``E[∂²ℓ/∂θ∂w] = 0`` for Gaussian errors), so
    Rao's statistic of a mean parameter is block-diagonal in the noise and holding the noise
    is exact there. The observed cross terms are about twice the gradient of θ and grow with
    the effect: profiled through them, strong candidates had a negative or nearly zero
    curvature (no statistic, or an inflated one), and nearly confounded ones (a sensor bias
    absorbed by a trim constant: 99.9998 % of its curvature explained by the other
    parameters) a negative one. Against an exact Kalman filter's Rao statistic: a sensor
    bias 17.193 against 17.197 (zeroing the cross terms before the path is profiled out:
    40.0; observed: 23.3; tests/test_score_states.py)."""
    off = lay.shared_offset
    keep = np.arange(off, off + lay.n_theta)
    if off:
        lat = np.arange(off)
        try:
            Lc = np.linalg.cholesky(S[np.ix_(lat, lat)])
        except np.linalg.LinAlgError:
            return None, None, gpos, 0
        B = np.linalg.solve(Lc, np.column_stack([S[np.ix_(lat, keep)], rhs[lat]]))
        S = S[np.ix_(keep, keep)] - B[:, :-1].T @ B[:, :-1]
        rhs = rhs[keep] - B[:, :-1].T @ B[:, -1]
    else:
        S, rhs = S[np.ix_(keep, keep)].copy(), rhs[keep].copy()
    return S, rhs, {n: j - off for n, j in gpos.items()}, len(keep)


#: new parameters per vmapped chunk of Hessian-vector products (:func:`blocks_by_hvp`), at
#: most; fewer on long records: the chunk's reverse-mode residuals grow with chunk × size of
#: the decision vector, kept below ``HVP_BUDGET`` (16 directions up to 40,000 variables)
HVP_CHUNK, HVP_BUDGET = 16, 16 * 40_000
#: bytes per (direction × decision variable × gated term) of a vmapped chunk, at least: the
#: chunk's reverse-mode residuals grow with all three (a new user's ATTAS lateral model, 2
#: records × 751 samples, 260 gated terms, 16 directions: killed by the OOM killer at 24 GB RSS,
#: ≥ 945 bytes per unit)
HVP_BYTES_PER_UNIT = 1000
#: share of the machine's physical memory a chunk may take (:func:`hvp_chunk`)
HVP_MEMORY_SHARE = 1 / 3


def physical_memory() -> int | None:
    """The machine's physical memory in bytes (None where the OS does not say)."""
    import os

    try:
        return int(os.sysconf("SC_PAGE_SIZE")) * int(os.sysconf("SC_PHYS_PAGES"))
    except (AttributeError, ValueError, OSError):
        return None


def hvp_chunk(k: int, size: int, *, memory: int | None = None) -> int:
    """Directions per vmapped call of :func:`blocks_by_hvp` for ``k`` new parameters (gated
    terms) on a decision vector of ``size``: at most ``HVP_CHUNK`` and ``HVP_BUDGET / size``,
    and small enough that ``chunk × size × k × HVP_BYTES_PER_UNIT`` stays within
    ``HVP_MEMORY_SHARE`` of ``memory`` (default: the machine's physical memory); at least 1."""
    memory = physical_memory() if memory is None else memory
    kc = min(HVP_CHUNK, k, HVP_BUDGET // max(size, 1))
    if memory:
        kc = min(kc, int(HVP_MEMORY_SHARE * memory) // (HVP_BYTES_PER_UNIT * max(size, 1) * max(k, 1)))
    return max(1, kc)


def blocks_by_hvp(P, current, s, recs, *, det_std: float):
    """The Hessian blocks of the batch problem ``P`` (a batch that adds no state) at the nesting
    point ``(s, recs)``, without compiling the batch model's block assembly.

    At the nesting point the batch model *is* the current model, so every block over the
    current variables (state means, assumed-density parameters, current parameters, noise) is
    the current model's: they come from the current problem's blocks (its own compiled
    assembly, one per record length, shared by every batch and with the fits). The rows of
    the new parameters γ are exact Hessian–vector products of the batch's negative ELBO,
    ``H e_γ = ∂/∂ε ∇f(v + ε e_γ)`` (forward over reverse mode on the flat decision vector;
    one compilation of its gradient, ``HVP_CHUNK`` directions per vmapped call), and their
    gradient the exact gradient there. The shared-vector entries of the new rows (sums over
    records) are put into the first record's blocks; every consumer sums over records.
    Returns None when the layouts do not match (the caller assembles the blocks itself).
    """
    import jax
    import jax.numpy as jnp

    from ..estimator import Problem

    P0 = Problem(current.model, list(current.records),
                 _screen_options(det_std))
    lay, lay0 = P.layout, P0.layout
    if ((lay.nx, lay.nq, lay.n_proc, lay.n_meas, lay.lengths)
            != (lay0.nx, lay0.nq, lay0.n_proc, lay0.n_meas, lay0.lengths)
            or P.nm.static_key() != P0.nm.static_key() or P.padded != P.lengths):
        return None
    names, names0 = P.free_names, P0.free_names
    zpos = {n: j for j, n in enumerate(names)}
    if not set(names0) <= set(zpos):
        return None
    cur = [zpos[n] for n in names0]
    new = [j for j, n in enumerate(names) if n not in set(names0)]
    nt, nq, ng = lay.n_theta, lay.nq, lay.ng
    s = np.asarray(s, float)
    blk0 = P0.blocks(np.concatenate([s[cur], s[nt:]]), recs)
    k = len(new)
    spos = lay.n_mu + lay.shared_offset + np.arange(ng)       # s in the flat vector
    v = jnp.asarray(lay.pack(s, recs))
    grad_f = jax.grad(P.flat_value)

    def hvps(v, E, cfg, data):
        def col(w):
            return jax.jvp(lambda x: grad_f(x, cfg, data), (v,), (w,))
        g, h = jax.vmap(col)(E)
        return g[0], h

    from ..estimator.core import compiler_options
    # the objective's XLA options (elemental emitters on the CPU): the forward-over-reverse
    # graph of a whole batch model is the screen's largest compilation
    fn = jax.jit(hvps, compiler_options=compiler_options())
    kc = hvp_chunk(k, lay.size)
    cols, g = [], None
    for a in range(0, k, kc):
        E = np.zeros((kc, lay.size))
        for r, j in enumerate(new[a:a + kc]):
            E[r, spos[j]] = 1.0
        gg, hh = fn(v, jnp.asarray(E), P.cfg, P.data)
        g = np.asarray(gg, float)
        cols.append(np.asarray(hh, float)[:len(new[a:a + kc])])
    Hc = np.concatenate(cols) if cols else np.zeros((0, lay.size))
    Hc[:, spos[new]] = 0.5 * (Hc[:, spos[new]] + Hc[:, spos[new]].T)
    nb = nq + ng
    src = np.full(nb, -1)                      # position in the current record border
    src[:nq] = np.arange(nq)
    src[nq + np.asarray(cur, int)] = nq + np.arange(len(cur))
    src[nq + nt:] = nq + lay0.n_theta + np.arange(ng - nt)
    keep = np.nonzero(src >= 0)[0]
    newb = nq + np.asarray(new, int)
    out, off = [], 0
    for i, b in enumerate(blk0):
        N = lay.lengths[i]
        W0, H0, gb0 = (np.asarray(b[x], float) for x in ("W", "Hbb", "gb"))
        W = np.zeros(W0.shape[:2] + (nb,))
        W[:, :, keep] = W0[:, :, src[keep]]
        W[:N, :, newb] = Hc[:, off:off + N * lay.nx].reshape(k, N, lay.nx).transpose(1, 2, 0)
        off += N * lay.nx
        H = np.zeros((nb, nb))
        H[np.ix_(keep, keep)] = H0[np.ix_(src[keep], src[keep])]
        rpos = lay.n_mu + lay.r_index(i)
        H[np.ix_(np.arange(nq), newb)] = Hc[:, rpos].T
        H[np.ix_(newb, np.arange(nq))] = Hc[:, rpos]
        gb = np.zeros(nb)
        gb[keep] = gb0[src[keep]]
        if i == 0:
            H[np.ix_(nq + np.arange(ng), newb)] = Hc[:, spos].T
            H[np.ix_(newb, nq + np.arange(ng))] = Hc[:, spos]
            gb[newb] = g[spos[new]]
        out.append({**b, "W": W, "Hbb": H, "gb": gb})
    return out


def batch_statistics(cands, current, m, P, bnames, *, det_std: float, hvp: bool = True) -> dict:
    """Score statistics of the candidates ``cands`` of the batch model ``m`` (names ``bnames``,
    :func:`batch_spec_dict`) from the problem ``P`` of ``m`` on the current records: ``P.model``
    is ``m`` or ``m`` with inert parameters appended (:func:`padded_model`; they are held, so
    the statistics are those of ``m``). ``hvp`` (default True): a batch that adds no state
    takes its blocks from the current model's and Hessian-vector products of ``m``
    (:func:`blocks_by_hvp`) instead of compiling ``m``'s own block assembly."""
    from .refit import noise_stds, stage0_start

    records = list(current.records)
    base_fit = current.fit
    z0 = P.parameter_start()
    theta = P.theta(z0)
    theta_m = theta[:m.np]
    pads = [n for n in P.model.parameter_names[m.np:]]
    proc_std, offd, meas_std = noise_stds(base_fit, current.model)
    s = np.concatenate([z0, P.noise_vector(proc_std=proc_std, proc_G=offd, meas_std=meas_std,
                                           default_std=det_std)])
    new_states = [n for n in m.state_names if n not in current.model.state_names]
    if new_states:
        # the added states embedded at the nesting point as in stage 0 of the refit (means
        # simulated along the current smoother with their own transition, stationary
        # covariance); no smoothing run: the statistic is the difference of two Newton
        # decrements, which holds at a start that is not exactly stationary
        dec, _, _, _, _ = stage0_start(m, records, base_fit, current.model, theta_m, det_std)
        recs = [(np.asarray(x["mu"], float), np.asarray(x["r"], float))
                for x in dec["records"]]
    else:
        recs = [(np.asarray(x["mu"], float), np.asarray(x["r"], float))
                for x in base_fit.decision["records"]]
    blks = None
    if not new_states and getattr(P, "_shared_obj", None) is None and hvp:
        blks = blocks_by_hvp(P, current, s, recs, det_std=det_std)
    if blks is None:
        blks = P.blocks(s, recs)
    nglob = P.layout.nglob
    free_names = P.free_names
    gpos = {n: int(j) for n, j in zip(free_names, P.layout.theta_index)}
    new_noise = [j for j in (P.process_noise_index(n) for n in new_states) if j is not None]
    new_par = {bnames[c.key][p.name] for c in cands for p in c.parameters if not p.fixed}
    Hdiag = np.diag(P.gather(blks)[1])
    curv = {n: float(Hdiag[j]) for n, j in gpos.items()}    # unprofiled curvature per name
    informative = set(new_par)
    held_r: set = set()
    lay = P.layout
    # columns of a record's border block (r_i, then the shared vector): the new parameters'
    # and the noise parameters' (their cross blocks take the null expectation, zero)
    cols = [lay.nq + gpos[q] - lay.shared_offset for q in sorted(new_par & set(gpos))]
    ncols = list(lay.nq + lay.noise_index - lay.shared_offset)
    if new_states:
        import jax.numpy as jnp

        ni = [m.state_names.index(z) for z in new_states]
        informative, reach = nesting_reach(
            m, new_states, sorted(new_par & set(gpos)),
            np.concatenate([mu for mu, _ in recs]),
            np.concatenate([np.asarray(r.u, float) for r in records]), theta_m)
        Gd = np.abs(np.diag(np.asarray(P.nm.G(jnp.asarray(s[lay.n_theta:]), P.cfg["noise"]),
                                       float)))
        inert = [m.state_names.index(z) for z in new_states if z not in reach]
        blks = [condition_added_states(b, ni, 1.0 / (float(r.dt) * Gd[ni] ** 2), inert, cols,
                                       ncols)
                for b, r in zip(blks, records)]
        held_r = {int(lay.r_index(i)[j]) for i in range(lay.nrec)
                  for j in added_state_r_index(m.nx, ni)}
    S, rhs = _reduced_system(P, blks)
    out = {}
    if S is None:
        for c in cands:
            out[c.key] = ScoreResult(None, 0, None, note="state block not positive definite")
        return out
    if not new_states:
        S, rhs, gpos, nglob = _rao_system(S, rhs, lay, gpos)
        if S is None:
            for c in cands:
                out[c.key] = ScoreResult(None, 0, None,
                                         note="assumed-density block not positive definite")
            return out
    # null: every new parameter and new-state noise held at its nesting value
    held_all = (set(gpos[n] for n in new_par if n in gpos) | set(new_noise) | held_r
                | {gpos[n] for n in pads if n in gpos})
    rest = np.array([j for j in range(nglob) if j not in held_all], int)
    try:
        L0 = np.linalg.cholesky(S[np.ix_(rest, rest)])
    except np.linalg.LinAlgError:
        for c in cands:
            # (a projection onto the positive-curvature subspace was tried, session 31: it
            # inflated the statistics of candidates coupled to the negative directions)
            out[c.key] = ScoreResult(None, 0, None, note=(
                "Hessian not positive definite: the current model is not at a minimum of its "
                "own objective along the variables profiled out (a saddle); no statistic"))
        return out

    def solve0(B):
        return np.linalg.solve(L0.T, np.linalg.solve(L0, B))

    a0 = solve0(rhs[rest])
    gain0 = 0.5 * float(rhs[rest] @ a0)
    dth = P.theta_jacobian(z0)
    free_idx = [P.model.parameter_names.index(n) for n in free_names]
    for c in cands:
        names = [p.name for p in c.parameters if not p.fixed and bnames[c.key][p.name] in gpos]
        bn = bnames[c.key]
        tested = [n for n in names if curv[bn[n]] > 1e-300 and bn[n] in informative]
        held = [n for n in names if n not in tested]
        if not tested:
            out[c.key] = ScoreResult(None, 0, None, held=tuple(held),
                                     note="no new parameter is informative at the nesting point")
            continue
        J = np.array([gpos[bn[n]] for n in tested], int)
        SJ0 = S[np.ix_(J, rest)]
        schur = S[np.ix_(J, J)] - SJ0 @ solve0(SJ0.T)
        rJ = rhs[J] - SJ0 @ a0
        try:
            dz = np.linalg.solve(schur, rJ)
        except np.linalg.LinAlgError:
            out[c.key] = ScoreResult(None, len(tested), None, tuple(tested), tuple(held),
                                     note="singular Schur complement")
            continue
        stat = float(max(rJ @ dz, 0.0))
        eig = np.linalg.eigvalsh(0.5 * (schur + schur.T))
        if not math.isfinite(stat) or np.any(eig <= 0):
            ascent = bool(eig[0] < -NEGATIVE_CURVATURE_TOL * max(float(np.max(np.abs(eig))),
                                                                  1e-300))
            out[c.key] = ScoreResult(
                None, len(tested), None, tuple(tested), tuple(held), ascent=ascent,
                note=("negative curvature along the new parameters at the nesting point: "
                      "the candidate raises the ELBO (a refit sizes it)") if ascent
                else "Schur complement not positive definite")
            continue
        step = {}
        for n, dzn in zip(tested, dz):
            j = free_names.index(bn[n])
            step[n] = float(theta[free_idx[j]] + dth[j] * dzn)
        out[c.key] = ScoreResult(stat, len(tested), float(stats.chi2.sf(stat, len(tested))),
                                 tuple(tested), tuple(held), gain0 + 0.5 * stat, gain0, step)
    return out


def screen_group(group, current, info, workdir: pathlib.Path, tag: str, name: str, *,
                 generated_dir, det_std: float) -> dict:
    """Score statistics of one batch (a task of :func:`screen`, also on an engine worker).

    A small batch (≤ 8) that fails to build or evaluate is split into single candidates
    once; a candidate that still fails gets ``statistic None`` and a note.
    """
    out: dict = {}

    def run(grp, t):
        try:
            out.update(screen_batch(grp, current, info, workdir / f"{t}.yaml", f"{name}_{t}",
                                    generated_dir=generated_dir, det_std=det_std))
            return True
        except _ERRORS as err:
            if len(grp) == 1 or len(grp) > 8:
                for c in grp:
                    out[c.key] = ScoreResult(None, 0, None,
                                             note=f"failed: {str(err).splitlines()[0][:200]}")
                return True
            return False

    if not run(group, tag):
        for j, c in enumerate(group):
            run([c], f"{tag}_{j + 1}")
    return out


def _errors():
    from ..errors import FitError, SpecError, VsidgenError

    return (SpecError, FitError, VsidgenError, ValueError, ArithmeticError,
            np.linalg.LinAlgError, KeyError)


_ERRORS = _errors()

#: name prefix of the inert parameters appended by :func:`padded_model`
PAD_PREFIX = "__screen_pad"


def padded_model(m, *, n_free: int, n_par: int):
    """``m`` with inert parameters appended: ``n_free`` free parameters in all, ``n_par`` in all.

    The appended parameters (names ``PAD_PREFIX`` + index, initial value 0, unbounded; the
    free ones first) enter neither the drift nor the output: ``drift(x, u, p) =
    m.drift(x, u, p[:m.np])``, likewise the output. Their rows and columns of every
    derivative of the objective are exactly zero, so holding them (deleting their rows and
    columns) leaves the score statistics of ``m``'s candidates exactly those of ``m``. Models
    padded to one shape share a :class:`~vsidgen.estimator.core.SwitchedObjective`.
    """
    import dataclasses

    from ..metadata import Parameter

    nf = sum(1 for p in m.parameters if not p.fixed)
    k_free, k_all = n_free - nf, n_par - m.np
    if k_free < 0 or k_all < k_free:
        raise ValueError(f"cannot pad {m.np} parameters ({nf} free) to {n_par} ({n_free} free)")
    npm = m.np
    pads = tuple(Parameter(name=f"{PAD_PREFIX}{j}", unit="1",
                           description="inert padding of the score screen", initial=0.0,
                           fixed=j >= k_free) for j in range(k_all))
    drift, output = m.drift, m.output

    def pdrift(x, u, p):
        return drift(x, u, p[:npm])

    def poutput(x, u, p):
        return output(x, u, p[:npm])

    return dataclasses.replace(m, drift=pdrift, output=poutput, parameters=m.parameters + pads,
                               jacobians=None)


def screen_shared(groups, current, info, workdir: pathlib.Path, tag: str, name: str, *,
                  generated_dir, det_std: float) -> dict:
    """Score statistics of the batches ``groups`` (lists of candidates), one compilation per shape.

    Every batch's model is built as in :func:`screen_batch`; the batches whose models have the
    same states, noise structure and transition setting form one *shape*: their models are
    padded to the same numbers of free and of all parameters (:func:`padded_model`) and share
    one :class:`~vsidgen.estimator.core.SwitchedObjective`, so the Hessian-block assembly and the
    elimination of the state means are traced and compiled once per shape instead of once per
    batch; each batch's problem selects its own model by its index. The statistics are those
    of :func:`screen_batch` up to rounding. A batch whose model or shared evaluation fails is
    screened on its own by :func:`screen_group` (which splits it once).
    """
    from ..estimator import Problem
    from ..estimator.core import SwitchedObjective
    from ..model.dynamics import transition

    records = list(current.records)
    opts = _screen_options(det_std)
    out: dict = {}
    built = []          # (batch tag, candidates, model, names, unpadded problem)
    for i, g in enumerate(groups):
        t = f"{tag}{i + 1}"
        try:
            m, bnames = _batch_model(g, current, info, workdir / f"{t}.yaml", f"{name}_{t}",
                                     generated_dir=generated_dir)
            built.append((t, g, m, bnames, Problem(m, records, opts)))
        except _ERRORS:
            out.update(screen_group(g, current, info, workdir, t, name,
                                    generated_dir=generated_dir, det_std=det_std))
    shapes: dict = {}
    for b in built:
        P0 = b[4]
        key = (P0.layout.nx, P0.nm.static_key(), P0.F.key, P0.integrator, P0.substeps)
        shapes.setdefault(key, []).append(b)
    for members in shapes.values():
        n_free = max(P0.tm.n_free for *_, P0 in members)
        n_par = max(m.np + n_free - P0.tm.n_free for _, _, m, _, P0 in members)
        try:
            pms = [padded_model(m, n_free=n_free, n_par=n_par) for _, _, m, _, _ in members]
            Pr = Problem(pms[0], records, opts)
            Fs = [transition(pm, integrator=Pr.integrator, substeps=Pr.substeps,
                             inputs=Pr.input_hold) for pm in pms]
            obj = SwitchedObjective(pms, Pr.tm, Pr.nm, Fs)
        except _ERRORS:
            pms, obj = [None] * len(members), None
        for k, ((t, g, m, bnames, _), pm) in enumerate(zip(members, pms)):
            try:
                if obj is None:
                    raise ValueError("no shared objective for this shape")
                P = Problem(pm, records, opts, objective=obj, branch=k)
                out.update(batch_statistics(g, current, m, P, bnames, det_std=det_std))
            except _ERRORS:
                out.update(screen_group(g, current, info, workdir, t, name,
                                        generated_dir=generated_dir, det_std=det_std))
    return out


#: name prefixes of the gates and difference channels of :func:`gate_bank`
GATE_PREFIX, DIFF_PREFIX = "__filter_gate_", "__filter_diff_"

#: grid of a filter time constant: geometric, ratio √2 (wider when needed to reach the upper
#: bound), from the parameter's lower bound to its upper bound (at most ``MAX_FILTER_GRID``
#: values)
FILTER_GRID_RATIO, MAX_FILTER_GRID = math.sqrt(2.0), 16
#: the grid starts no lower than half a sample (a lag's bound may be far below: a shorter
#: time constant is indistinguishable from the input hold's own half sample)
FILTER_GRID_MIN_SAMPLES = 0.5


def filter_input(kind: str, u, t, tau: float, *, hold: str = "foh") -> np.ndarray:
    """The recorded input ``u`` (N,) at times ``t`` through an input filter of parameter τ:

    * ``"delay"``: the pure transport delay ``u(t − τ)`` (:func:`vsidgen.data.delay_input`);
    * ``"lag"``: the first-order lag ``τ ż = u − z``, ``z(t₀) = u(t₀)``, exact for an input
      linear between samples: ``z_{k+1} = a z_k + (1 − a) u_k + b (u_{k+1} − u_k)`` with
      ``a = e^{−T/τ}``, ``b = 1 − (τ/T)(1 − a)``;
    * ``"pade"``: the first-order Padé delay ``2z − u`` with ``(τ/2) ż = u − z`` (the
      ``control_delay`` candidate's state).

    ``hold="zoh"``: the lag and Padé filters for an input held over each sample instead
    (``b = 0``).
    """
    from scipy import signal

    from ..data import delay_input

    u = np.asarray(u, np.float64)
    if kind == "delay":
        return delay_input(u, np.asarray(t, np.float64), tau)
    if kind not in ("lag", "pade"):
        raise ValueError(f"unknown input filter {kind!r}")
    T = float(np.median(np.diff(np.asarray(t, np.float64))))
    tc = tau if kind == "lag" else 0.5 * tau
    a = math.exp(-T / tc)
    b = 1.0 - (tc / T) * (1.0 - a) if hold != "zoh" else 0.0
    num, den = [b, (1.0 - a) - b], [1.0, -a]
    z, _ = signal.lfilter(num, den, u, zi=signal.lfilter_zi(num, den) * u[0])
    return z if kind == "lag" else 2.0 * z - u


def filter_grid(c, dt: float) -> tuple[str, list[float]]:
    """(filter kind, grid of its parameter in s) of an input-filter candidate ``c``
    (``info["filter"]``): a transport delay the delay grid (:func:`.delay.delay_grid`), a lag
    or Padé delay geometric over its time constant's bounds."""
    from .delay import delay_grid

    kind = c.info["filter"]
    if kind == "delay":
        return kind, delay_grid(dt)
    p = c.parameters[0]
    lo = max(float(p.lower if p.lower is not None else dt), FILTER_GRID_MIN_SAMPLES * dt)
    hi = float(p.upper if p.upper is not None else 1.0)
    if hi <= lo:
        return kind, [lo, lo * FILTER_GRID_RATIO]
    # ratio √2, or wider where 16 values at √2 would not reach the upper bound
    ratio = max(FILTER_GRID_RATIO, (hi / lo) ** (1.0 / (MAX_FILTER_GRID - 1)))
    n = min(MAX_FILTER_GRID, 1 + int(math.floor(math.log(hi / lo) / math.log(ratio) + 1e-9)))
    return kind, [lo * ratio ** k for k in range(max(n, 2))]


@dataclasses.dataclass(frozen=True)
class GateBank:
    """The current model with input gates (:func:`gate_bank`): ``model``, its ``records``
    (extra input channels) and the gate names in channel order."""

    model: object
    records: tuple
    gates: tuple


def gate_bank(model, records, theta, channels) -> GateBank:
    """``model`` with one gate ``g_k`` per channel of ``channels``, ``(input name, label,
    [difference (N,) per record])``, for the score test of moving input ``u_j`` by ``g_k d_k``
    (``d_k``: e.g. a filtered copy of the recorded input minus the input, :func:`filter_input`,
    an extra input channel of the returned records).

    The gate enters as the first-order change of the model in that direction, with the
    parameters of its coefficient frozen at the current estimates ``θ̂ = theta``:

        ``ẋ = f(x, u; θ) + Σ_k g_k ∂f/∂u_j(x, u; θ̂) d_k``,  ``y = h(x, u; θ) + Σ_k g_k ∂h/∂u_j(x, u; θ̂) d_k``.

    At ``g = 0`` it is exactly ``model``, and its gradient in ``g_k`` there is that of the
    family ``u_j + g_k d_k`` (whose input at ``g_k = 1`` is the filtered one); the state stays
    live in the coefficient, so the expectation over the assumed density is exact. Its cross
    derivatives of ``g_k`` with θ are the expected-information ones: the equation error times
    ``∂²f/∂u∂θ`` (e.g. ``d_k`` for ``B·u``), zero in expectation under the current model, is left
    out, as in Rao's form of the test. Observed, that term grows with the effect itself and
    made the profiled curvature of a strong lag indefinite (no statistic at 0.28–1.13 s for a
    0.3 s lag) or nearly zero next to it (an inflated 3585 at 0.2 s). ``model``'s own
    parameters start at ``theta``; the gates are free and start at 0."""
    import jax.numpy as jnp

    from ..metadata import Parameter, Variable

    nu, npm = model.nu, model.np
    names = list(model.input_names)
    idx = jnp.asarray([names.index(u) for u, _, _ in channels], dtype=jnp.int32)
    extra_in = tuple(Variable(f"{DIFF_PREFIX}{k}", model.inputs[names.index(u)].unit,
                              f"{label} minus {u}") for k, (u, label, _) in enumerate(channels))
    gates = tuple(Parameter(f"{GATE_PREFIX}{k}", "1", f"gate of {u} towards {label}",
                            initial=0.0) for k, (u, label, _) in enumerate(channels))
    base = tuple(p if p.fixed else dataclasses.replace(p, initial=_clip(float(v), p))
                 for p, v in zip(model.parameters, np.asarray(theta, float)))
    th = jnp.asarray(np.asarray(theta, float))
    drift, output = model.drift, model.output

    def gdrift(x, u, p):
        fu = model.drift_jacobian(x, u[:nu], th)[1]
        return drift(x, u[:nu], p[:npm]) + fu[:, idx] @ (u[nu:] * p[npm:])

    def goutput(x, u, p):
        hu = model.output_jacobian(x, u[:nu], th)[1]
        return output(x, u[:nu], p[:npm]) + hu[:, idx] @ (u[nu:] * p[npm:])

    m = dataclasses.replace(model, drift=gdrift, output=goutput,
                            inputs=model.inputs + extra_in, parameters=base + gates,
                            jacobians=None)
    return GateBank(m, _with_channels(records, channels, extra_in), tuple(g.name for g in gates))


def _with_channels(records, channels, extra_in) -> tuple:
    """``records`` with the channels' signals (``(_, _, [signal per record])``) appended as
    the extra inputs ``extra_in`` (read-only arrays)."""
    recs = []
    for i, r in enumerate(records):
        d = np.stack([np.asarray(sig[i], np.float64) for _, _, sig in channels], axis=1)
        ua = np.concatenate([np.asarray(r.u, np.float64), d], axis=1)
        ua.setflags(write=False)
        recs.append(dataclasses.replace(r, u=ua, input_names=tuple(r.input_names)
                                        + tuple(v.name for v in extra_in)))
    return tuple(recs)


def _clip(v: float, p) -> float:
    from .specwrite import clip_to_bounds

    return clip_to_bounds(v, [p.lower, p.upper]) if (p.lower is not None
                                                     or p.upper is not None) else v


def screen_input_filters(cands, current, *, det_std: float) -> dict:
    """Profiled score statistics of the input-filter candidates ``cands`` (transport delays,
    lags, Padé delays: ``info["filter"]``): {key: :class:`ScoreResult`}.

    For each grid value τ_k of the candidate's parameter (:func:`filter_grid`) the family
    ``u + g_k (F_{τ_k} u − u)`` (:func:`filter_input`) contains the current model at
    ``g_k = 0`` and the input through the filter at ``g_k = 1``, for any model. All gates of
    all candidates are parameters of one model (:func:`gate_bank`): one compilation and one
    Hessian assembly at the current optimum give every grid value's one-degree-of-freedom
    score statistic ``S_k`` (:func:`batch_statistics`). The candidate's statistic is
    ``max_k S_k``, its p-value ``min(1, K·P(χ²₁ > max_k S_k))`` (Bonferroni over its ``K``
    grid values: ``multiplicity``), the best τ_k is in ``step["tau_s"]`` (where the delay
    profile and the lag refit start) and every S_k in ``profile``. An input the model
    already delays (transport delay), or a failed evaluation, gets ``statistic None`` and a
    note."""
    from ..estimator import Problem
    from .base import Candidate, NewParameter

    out: dict = {}
    todo = []
    for c in cands:
        u = c.info["input"]
        j = list(current.model.input_names).index(u)
        if c.info["filter"] == "delay" and float(getattr(current.model.inputs[j], "delay", 0.0)
                                                 or 0.0) > 0.0:
            out[c.key] = ScoreResult(None, 0, None, note=f"the model already delays {u}")
        else:
            todo.append(c)
    if not todo:
        return out
    dt = float(np.median([r.dt for r in current.records]))
    grids = {c.key: filter_grid(c, dt) for c in todo}
    channels, owner = [], []
    for c in todo:
        u = c.info["input"]
        j = list(current.model.input_names).index(u)
        kind, grid = grids[c.key]
        for tau in grid:
            diffs = [filter_input(kind, r.u[:, j], r.t, tau) - np.asarray(r.u[:, j], float)
                     for r in current.records]
            channels.append((u, f"{u} through a {kind} of {tau:.4g} s", diffs))
            owner.append((c.key, tau))
    bank = gate_bank(current.model, current.records, current.fit.theta, channels)
    pseudo = [Candidate(effect="input_filter", key=g, target="", explanation="",
                        parameters=(NewParameter(g, "1", initial=0.0),)) for g in bank.gates]
    try:
        P = Problem(bank.model, list(bank.records),
                    _screen_options(det_std))
        res = batch_statistics(pseudo, current, bank.model, P,
                               {p.key: {p.key: p.key} for p in pseudo}, det_std=det_std)
    except _ERRORS as err:
        for c in todo:
            out[c.key] = ScoreResult(None, 0, None, note=f"input-filter screen failed: "
                                                         f"{str(err).splitlines()[0][:200]}")
        return out
    for c in todo:
        kind, grid = grids[c.key]
        rows = [(tau, res[g]) for (key, tau), g in zip(owner, bank.gates) if key == c.key]
        prof = tuple((float(tau), r.statistic) for tau, r in rows)
        ok = [(tau, r) for tau, r in rows if r.statistic is not None]
        if not ok:
            notes = sorted({r.note for _, r in rows if r.note})
            out[c.key] = ScoreResult(None, 1, None, ("tau",), profile=prof,
                                     multiplicity=len(grid),
                                     ascent=any(r.ascent for _, r in rows),
                                     note=f"no grid {kind} has a statistic: " + "; ".join(notes))
            continue
        tau, best = max(ok, key=lambda tr: tr[1].statistic)
        p = float(min(1.0, len(grid) * stats.chi2.sf(best.statistic, 1)))
        out[c.key] = ScoreResult(best.statistic, 1, p, ("tau",), (), best.gain_full,
                                 best.gain_rest, {"tau_s": float(tau)}, profile=prof,
                                 multiplicity=len(grid),
                                 note=f"best of {len(grid)} grid values of the {kind}: "
                                      f"{tau:.4g} s")
    return out


#: fewest candidates of a part of the batch without added states (:func:`split_plain`)
PLAIN_MIN_PART = 24


def split_plain(plain: list[list], slots: int) -> list[list]:
    """The batch of candidates that add no state in up to ``slots`` parts of at least
    ``PLAIN_MIN_PART`` candidates, when the engine runs several tasks at once.

    The statistics do not change: every new parameter of a batch is held at its nesting value
    in the null, so a candidate's Schur complement involves only its own parameters and the
    current model's (:func:`batch_statistics`). What changes is the wall time: the batch's
    Hessian–vector products are one compilation whose time grows with the number of
    candidates (170 HFB-320 candidates: 83 s of XLA compile against 28 s for 40), and as the
    screen's largest task it was its critical path; the parts compile side by side.
    """
    if slots < 2:
        return plain
    out = []
    for g in plain:
        parts = max(1, min(slots, len(g) // PLAIN_MIN_PART))
        size = -(-len(g) // parts)
        out.extend(g[i:i + size] for i in range(0, len(g), size))
    return out


def screen(candidates, current, info, workdir: pathlib.Path, name: str, *, generated_dir,
           det_std: float, include_states: bool = True, shared: bool = True, progress=None,
           engine=None, deadline: float | None = None) -> dict:
    """Score-screen every screenable candidate: {key: ScoreResult} (see the module docstring).

    ``include_states`` (default True): also screen candidates that add states (unsteady
    aerodynamics, missing modes, speed dynamics, delays and lags as states, wind): their
    batches (at most two added states each: the compilation of the block assembly grows
    steeply with the number of states — a batch of seven candidates with eight added states
    had not compiled after 10 min on the loaded 2-core machine) need no smoothing run (see
    "Candidates that add states" in the module docstring).

    ``shared`` (default True): the batches that add states share one compilation per shape
    (:func:`screen_shared`), one task per number of added states; False: one compilation
    per batch (:func:`screen_group`, the reference path), one task each.

    Input-filter candidates (transport delays, lags, Padé delays: ``info["filter"]``) get the
    profiled score statistic of :func:`screen_input_filters` (one more task).

    ``engine`` (:class:`vsidgen.engine.Engine`, entered): the tasks run in parallel on its
    workers (``deadline``: :func:`time.monotonic` instant after which no task starts);
    without one they run here, one after another. A batch that fails (:func:`screen_group`)
    or is not run leaves its candidates without a statistic (a note says why): they are
    ranked after the tested ones.

    The candidates are batched in the order of their keys, not of their ranking: a batch's
    model (its parameter order, its generated code) then depends only on the current model
    and the candidate set, not on the record's locate scores, so diagnose runs of one spec on
    other records of the same length reuse the persistent compilation cache's programs of
    the screen (the statistics do not depend on the order, :func:`batch_statistics`).
    """
    candidates = sorted(candidates, key=lambda c: c.key)
    modes = [c for c in candidates if c.screenable and include_states and is_mode_candidate(c)]
    speeds = [c for c in candidates if c.screenable and include_states and is_speed_candidate(c)]
    todo = [c for c in candidates if c.screenable and (include_states or not c.states)
            and not is_mode_candidate(c) and not is_speed_candidate(c)]
    filters = [c for c in candidates if (c.info or {}).get("filter")]
    groups = batches(todo)
    out: dict = {}
    if progress is not None:
        progress(f"    score screen: {len(todo)} candidates in {len(groups)} batches "
                 f"({sum(1 for c in todo if c.states)} add states)"
                 + (f", {len(filters)} input filters profiled" if filters else "")
                 + (f", {len(modes)} missing modes through their low-passed drivers"
                    if modes else "")
                 + (f", {len(speeds)} speed candidates through their profiled speed damping"
                    if speeds else ""))
    slots = engine_slots(engine)
    plain = split_plain([g for g in groups if not any(c.states for c in g)], slots)
    with_states = [g for g in groups if any(c.states for c in g)]
    groups = plain + with_states
    if shared and with_states:
        tasks = [(f"b{i + 1}", ("batch", group, current, info, workdir, f"b{i + 1}", name))
                 for i, group in enumerate(plain)]
        by_states: dict = {}        # batches of one number of added states: one shape, one task
        for g in with_states:
            by_states.setdefault(sum(len(c.states) for c in g), []).append(g)
        # a shape's batches split over the engine's workers (one switched objective per part:
        # the trace grows with the number of branches, so the parts compile side by side)
        shared_tasks = []
        for k, gs in sorted(by_states.items(), reverse=True):
            parts = min(len(gs), slots)
            size = -(-len(gs) // parts)
            for j in range(0, len(gs), size):
                tag = f"s{k}_" if parts == 1 else f"s{k}p{j // size + 1}_"
                shared_tasks.append((tag.rstrip("_"), ("shared", gs[j:j + size], current, info,
                                                       workdir, tag, name)))
        # the largest first (they take longest)
        tasks = sorted(shared_tasks, key=lambda t: -len(t[1][1])) + tasks
    else:
        tasks = [(f"b{i + 1}", ("batch", group, current, info, workdir, f"b{i + 1}", name))
                 for i, group in enumerate(groups)]
    if filters:
        tasks.append(("filters", ("filters", filters, current, info, workdir, "f", name)))
    if modes:
        tasks.append(("modes", ("modes", modes, current, info, workdir, "m", name)))
    if speeds:
        tasks.append(("speed", ("speed", speeds, current, info, workdir, "v", name)))
    if engine is None or engine.serial:
        for _, args in tasks:
            out.update(_screen_task(*args, generated_dir, det_std))
        return out
    from ..engine import TaskStatus

    outcomes = engine.run(_screen_task, [(k, a + (generated_dir, det_std)) for k, a in tasks],
                          deadline=deadline)
    for (_, args), oc in zip(tasks, outcomes):
        if oc.status is TaskStatus.DONE:
            out.update(oc.value)
        else:
            cands = [c for g in args[1] for c in g] if args[0] == "shared" else args[1]
            for c in cands:
                out[c.key] = ScoreResult(None, 0, None, note=f"{oc.status.value}: {oc.error}")
    return out


#: name prefixes of the gates and channels of :func:`mode_bank`
MODE_GATE_PREFIX, MODE_CHANNEL_PREFIX = "__mode_gate_", "__mode_channel_"


def is_mode_candidate(c) -> bool:
    """A first-order missing mode driven by one state or input (``missing_dynamics``), screened
    through its low-passed driver (:func:`screen_modes`) instead of an added state."""
    return bool((c.info or {}).get("mode_driver")) and len(c.states) == 1


def mode_bank(model, records, theta, channels) -> GateBank:
    """``model`` with gates ``g_k`` adding known signals ``c_k`` to state equations:
    ``ẋ_{s_k} = f_{s_k}(x, u; θ) + g_k c_k(t)``, ``channels`` = ``(state, label, [c_k (N,) per
    record])`` (extra input channels of the returned records). At ``g = 0`` it is ``model``."""
    import jax.numpy as jnp

    from ..metadata import Parameter, Variable

    nu, npm = model.nu, model.np
    S = np.zeros((model.nx, len(channels)))
    for k, (st, _, _) in enumerate(channels):
        S[list(model.state_names).index(st), k] = 1.0
    Sj = jnp.asarray(S)
    extra_in = tuple(Variable(f"{MODE_CHANNEL_PREFIX}{k}", "1", label)
                     for k, (_, label, _) in enumerate(channels))
    gates = tuple(Parameter(f"{MODE_GATE_PREFIX}{k}", "1", f"gate of {label} into d{st}/dt",
                            initial=0.0) for k, (st, label, _) in enumerate(channels))
    base = tuple(p if p.fixed else dataclasses.replace(p, initial=_clip(float(v), p))
                 for p, v in zip(model.parameters, np.asarray(theta, float)))
    drift, output = model.drift, model.output

    def gdrift(x, u, p):
        return drift(x, u[:nu], p[:npm]) + Sj @ (u[nu:] * p[npm:])

    def goutput(x, u, p):
        return output(x, u[:nu], p[:npm])

    m = dataclasses.replace(model, drift=gdrift, output=goutput,
                            inputs=model.inputs + extra_in, parameters=base + gates,
                            jacobians=None)
    return GateBank(m, _with_channels(records, channels, extra_in), tuple(g.name for g in gates))


def screen_modes(cands, current, *, det_std: float) -> dict:
    """Score statistics of missing-mode candidates (:func:`is_mode_candidate`) without adding
    their states: {key: :class:`ScoreResult`}.

    The candidate adds ``ṁ = −m/τ + k v`` feeding ``ẋ_s`` and tests the gain ``k`` with τ held
    at its start (flat at ``k = 0``: Davies' problem). At ``k = 0`` the mode is ``m = k τ
    lp_τ(v)`` with ``lp_τ`` the unit first-order lag, so ``ẋ_s`` gains ``k τ lp_τ(v)``: the
    family ``ẋ_s + g lp_τ(v)`` has the same score for ``g ∝ k``. For an input ``v`` the channel
    ``lp_τ(v)`` is known exactly; for a state it is the low-passed smoothed mean, whose
    dependence on the path enters the cross information only as the equation error times a
    sensitivity, zero in expectation under the current model (Rao's form of the test). The lag
    starts at equilibrium (a mode in steady state at the first sample; its constant part is
    the equation's own). All channels are gates of one model (:func:`mode_bank`): one
    compilation, and the plain-batch statistics (:func:`batch_statistics`, Hessian-vector
    products), one degree of freedom each; ``step`` converts the gate's one-step estimate to
    ``k``."""
    from ..estimator import Problem
    from .base import Candidate, NewParameter

    out: dict = {}
    recs = list(current.records)
    names = list(current.model.state_names)
    inputs = list(current.model.input_names)
    dec = current.fit.decision
    # the mode as the model's own transition would carry it: held over each sample (zero-order
    # hold: states and inputs at the sample) or linear between samples (first-order hold)
    hold = getattr(current.model, "input_hold", "zoh") or "zoh"
    channels, scale = [], []
    for c in cands:
        v, tau = c.info["mode_driver"], float(c.info["mode_tau"])
        sig = []
        for i, r in enumerate(recs):
            N = np.asarray(r.y).shape[0]
            if v in inputs:
                x = np.asarray(r.u, float)[:, inputs.index(v)]
            elif v in names and dec is not None:
                x = np.asarray(dec["records"][i]["mu"], float)[:N, names.index(v)]
            else:
                x = None
            if x is None:
                break
            sig.append(filter_input("lag", x, np.asarray(r.t, float), tau, hold=hold))
        if len(sig) != len(recs):
            out[c.key] = ScoreResult(None, 0, None, note=f"no signal of {v}")
            continue
        rms = float(np.sqrt(np.mean(np.concatenate(sig) ** 2))) or 1.0
        channels.append((c.info["state"], f"{v} through a {tau:.4g} s lag",
                         [z / rms for z in sig]))
        scale.append((c, rms, tau))
    if not channels:
        return out
    bank = mode_bank(current.model, recs, current.fit.theta, channels)
    pseudo = [Candidate(effect="mode", key=g, target="", explanation="",
                        parameters=(NewParameter(g, "1", initial=0.0),)) for g in bank.gates]
    try:
        P = Problem(bank.model, list(bank.records),
                    _screen_options(det_std))
        res = batch_statistics(pseudo, current, bank.model, P,
                               {p.key: {p.key: p.key} for p in pseudo}, det_std=det_std)
    except _ERRORS as err:
        for c, _, _ in scale:
            out[c.key] = ScoreResult(None, 0, None, note=f"mode screen failed: "
                                                         f"{str(err).splitlines()[0][:200]}")
        return out
    for (c, rms, tau), g in zip(scale, bank.gates):
        r = res[g]
        kname = c.info["mode_gain"]
        held = tuple(p.name for p in c.parameters if p.name != kname)
        step = {kname: r.step[g] / (rms * tau)} if g in r.step else {}
        out[c.key] = dataclasses.replace(
            r, tested=(kname,) if r.statistic is not None else (), held=held, step=step,
            note=(r.note + "; " if r.note else "")
            + f"screened through the low-passed {c.info['mode_driver']} (τ = {tau:.4g} s held)")
    return out


#: number of time constants of the speed damping X_V profiled by :func:`screen_speed`
SPEED_GRID_MAX = 8
#: shortest speed time constant −1/X_V profiled (s): phugoid damping is slower than this
SPEED_TAU_MIN = 2.0


def is_speed_candidate(c) -> bool:
    """A speed (phugoid) candidate (``speed_dynamics``), screened through its profiled linear
    family (:func:`screen_speed`) instead of an added state pair."""
    return c.effect == "speed_dynamics" and bool((c.info or {}).get("closure"))


def speed_grid(duration: float) -> list[float]:
    """Profiled values of the speed damping ``X_V`` (1/s): 0 (no damping) and ``−1/τ`` for
    time constants τ halving from the record's duration down to :data:`SPEED_TAU_MIN`."""
    out = [0.0]
    tau = float(duration)
    while tau >= SPEED_TAU_MIN and len(out) < SPEED_GRID_MAX:
        out.append(-1.0 / tau)
        tau *= 0.5
    return out


def lag_response(s, dt: float, a: float) -> np.ndarray:
    """``y`` with ``ẏ = a y + s(t)``, ``y(t₀) = 0``, exact for ``s`` linear between samples:
    ``y_{k+1} = e^{aT} y_k + (I₀ − I₁) s_k + I₁ s_{k+1}``, ``I₀ = ∫₀ᵀ e^{a(T−τ)} dτ``,
    ``I₁ = ∫₀ᵀ e^{a(T−τ)} τ/T dτ`` (``a = 0``: the trapezoidal integral)."""
    from scipy import signal

    s = np.asarray(s, np.float64)
    T = float(dt)
    x = a * T
    e = math.exp(x)
    if abs(x) < 1e-6:
        i0, i1 = T * (1.0 + x / 2.0), T * (0.5 + x / 6.0)
    else:
        i0 = (e - 1.0) / a
        i1 = i0 - e / a + (e - 1.0) / (a * a * T)
    y = signal.lfilter([i1, i0 - i1], [1.0, -e], s)
    return y - i1 * s[0] * e ** np.arange(len(s))


def speed_path(c, current) -> list | None:
    """Per record of speed candidate ``c``: ``(dt, α − α₀, γ_rel)`` along the current
    smoothed path, or None (no path, or a non-finite one).

    ``γ_rel`` is the path angle from the record's start, in α's unit: ``∫ q`` for the attitude
    closure, ``∫ (q − f_α)`` with ``f_α`` the model's α equation along the path for the
    air-relative one (:func:`lag_response` with ``a = 0``; q converted to α's unit per second,
    ``info["q_in_alpha_units"]``, for a model in degrees with q in rad/s)."""
    import jax
    import jax.numpy as jnp

    a, q = c.info["states"]
    names = list(current.model.state_names)
    dec = current.fit.decision
    if dec is None or a not in names or q not in names:
        return None
    ja, jq = names.index(a), names.index(q)
    theta = jnp.asarray(np.asarray(current.fit.theta, float))
    drift = jax.jit(jax.vmap(lambda x, uu: current.model.drift(x, uu, theta)))
    out = []
    for i, r in enumerate(current.records):
        N = np.asarray(r.y).shape[0]
        mu = np.asarray(dec["records"][i]["mu"], float)[:N]
        dt = float(r.dt)
        al, rate = mu[:, ja], mu[:, jq] * float(c.info.get("q_in_alpha_units", 1.0))
        if c.info["closure"] == "air":
            fa = np.asarray(drift(jnp.asarray(mu), jnp.asarray(np.asarray(r.u, float)[:N])),
                            float)[:, ja]
            rate = rate - fa
        if not (np.all(np.isfinite(al)) and np.all(np.isfinite(rate))):
            return None
        out.append((dt, al - al[0], lag_response(rate, dt, 0.0)))
    return out


def speed_channels(path, xv: float) -> list:
    """The three signals ``[F[α − α₀], F[γ_rel], F[1]]`` per record of a speed candidate's
    :func:`speed_path` at speed damping ``X_V = xv`` (``F``: :func:`lag_response` with
    ``a = X_V``).

    At the nesting point (``Z_V = M_V = 0``) the candidate's speed perturbation is a known
    function of the smoothed path: ``ΔV̇ = X_V ΔV + κ (α − α₀) − g γ_rel + c`` with κ = X_α + g
    (attitude closure) or X_α (air-relative) and ``c`` the unknown trim of the speed equation
    (its path-angle start). So ``ΔV = κ F[α − α₀] − g F[γ_rel] + c F[1]`` (ΔV starting at 0:
    the speed at the record's start is the trim speed)."""
    return [[lag_response(s1, dt, xv), lag_response(gam, dt, xv),
             lag_response(np.ones(len(s1)), dt, xv)] for dt, s1, gam in path]


def screen_speed(cands, current, *, det_std: float) -> dict:
    """Profiled score statistics of the speed (phugoid) candidates (:func:`is_speed_candidate`)
    without adding their states: {key: :class:`ScoreResult`}.

    At the candidate's nesting point the speed perturbation is ``ΔV = κ F[α − α₀] − g F[γ_rel]
    + c F[1]`` (:func:`speed_channels`), linear in κ and c and nonlinear only in the speed
    damping ``X_V`` (the filter ``F``), and the candidate adds ``Z_V ΔV`` to the α equation
    and ``M_V ΔV`` to the q equation. For each ``X_V`` of :func:`speed_grid` the linear family
    ``ẋ_α += Σ_j a_j F_j``, ``ẋ_q += Σ_j b_j F_j`` (six gates of one model,
    :func:`mode_bank`; it contains the candidate at every κ, c) gets its six-degree-of-freedom
    score statistic (:func:`batch_statistics`, Rao's form); the candidate's statistic is the
    largest, its p-value Bonferroni-corrected over the grid (``multiplicity``). The one-step
    estimates of the best ``X_V`` give κ from the rank-one fit ``[a; b] ≈ [Z_V; M_V] [κ, −g, c]``;
    ``step`` holds the start of the refit: ``X_V`` and ``X_α`` (flat at the nesting point, so
    the refit still starts exactly at the current model) — the speed refit started at X_V = X_α
    = 0 stalled far below its optimum on a short-period model of the real HFB-320 record."""
    from ..estimator import Problem
    from .base import Candidate, NewParameter

    out: dict = {}
    dur = min(float(np.asarray(r.t)[-1] - np.asarray(r.t)[0]) for r in current.records)
    grid = speed_grid(dur)
    channels, owner = [], []
    for c in cands:
        a, q = c.info["states"]
        try:
            path = speed_path(c, current)
        except (*_ERRORS, TypeError, IndexError) as err:   # a model the path breaks
            out[c.key] = ScoreResult(None, 0, None, note=f"speed screen failed: "
                                                         f"{str(err).splitlines()[0][:200]}")
            continue
        if path is None:
            out[c.key] = ScoreResult(None, 0, None, note="no smoothed path of α and q")
            continue
        for xv in grid:
            sig = speed_channels(path, xv)
            cols = []
            for j, lab in enumerate(("α − α₀", "γ", "1")):
                per = [s[j] for s in sig]
                rms = float(np.sqrt(np.mean(np.concatenate(per) ** 2))) or 1.0
                for st in (a, q):
                    channels.append((st, f"F[{lab}] (X_V = {xv:.4g}) into d{st}/dt",
                                     [z / rms for z in per]))
                    cols.append((j, st, rms))
            owner.append((c, xv, cols))
    if not owner:
        return out
    bank = mode_bank(current.model, list(current.records), current.fit.theta, channels)
    pseudo, k = [], 0
    for c, xv, cols in owner:
        gs = bank.gates[k:k + len(cols)]
        k += len(cols)
        pseudo.append(Candidate(effect="speed", key=f"{c.key}@{xv!r}", target="", explanation="",
                                parameters=tuple(NewParameter(g, "1", initial=0.0) for g in gs)))
    try:
        P = Problem(bank.model, list(bank.records),
                    _screen_options(det_std))
        res = batch_statistics(pseudo, current, bank.model, P,
                               {p.key: {q.name: q.name for q in p.parameters} for p in pseudo},
                               det_std=det_std)
    except _ERRORS as err:
        for c, _, _ in owner:
            out[c.key] = ScoreResult(None, 0, None, note=f"speed screen failed: "
                                                         f"{str(err).splitlines()[0][:200]}")
        return out
    for c in {o[0].key: o[0] for o in owner}.values():
        rows = [(xv, cols, ps, res[ps.key]) for (cc, xv, cols), ps in zip(owner, pseudo)
                if cc.key == c.key]
        prof = tuple((float(xv), r.statistic) for xv, _, _, r in rows)
        ok = [row for row in rows if row[3].statistic is not None]
        if not ok:
            notes = sorted({r.note for *_, r in rows if r.note})
            out[c.key] = ScoreResult(None, 6, None, profile=prof, multiplicity=len(grid),
                                     ascent=any(r.ascent for *_, r in rows),
                                     note="no speed damping of the grid has a statistic: "
                                          + "; ".join(notes))
            continue
        xv, cols, ps, best = max(ok, key=lambda row: row[3].statistic)
        # gravity per unit of α, as in the candidate's speed equation (g·π/180 in degrees)
        g = float(c.info["gravity"]) * float(c.info.get("angle_radians", 1.0))
        C = np.zeros((2, 3))
        a_name = c.info["states"][0]
        for (j, st, rms), par in zip(cols, ps.parameters):   # the gates start at 0
            C[0 if st == a_name else 1, j] = best.step.get(par.name, 0.0) / rms
        kappa = 0.0
        rn = np.linalg.norm(C, axis=1)
        if np.all(np.isfinite(C)) and rn.max() > 0:
            W = C / np.where(rn > 0, rn, 1.0)[:, None]
            v = np.linalg.svd(W)[2][0]
            if abs(v[1]) > 1e-12:
                kappa = float(np.clip(-g * v[0] / v[1], -10 * g, 10 * g))
        names = [p.name for p in c.parameters]
        xv_name, xa_name = names[0], names[1]
        xa = kappa - g if c.info["closure"] == "attitude" else kappa
        p = float(min(1.0, len(grid) * stats.chi2.sf(best.statistic, 6)))
        out[c.key] = ScoreResult(
            best.statistic, 6, p, tuple(names[2:]), (xv_name, xa_name), best.gain_full,
            best.gain_rest,
            {xv_name: float(xv), xa_name: float(xa)}, profile=prof, multiplicity=len(grid),
            note=(f"best of {len(grid)} speed dampings: X_V = {xv:.4g} /s (κ = {kappa:.4g}); "
                  "the linear family of the speed perturbation's three signals into the "
                  "α and q equations (6 degrees of freedom)"))
    return out


def engine_slots(engine) -> int:
    """Tasks the engine runs at once (1 without one or when serial)."""
    if engine is None or engine.serial:
        return 1
    client = getattr(engine, "client", None)
    if client is not None:
        try:
            return max(1, int(sum(client.nthreads().values())))
        except Exception:  # noqa: BLE001 - a scheduler that cannot say: its configured size
            pass
    return max(1, int(getattr(engine, "workers", 1) or 1))


def _screen_task(kind, payload, current, info, workdir, tag, name, generated_dir, det_std):
    """One task of :func:`screen`: ``kind`` "shared": the batches ``payload`` through
    :func:`screen_shared`; "batch": the one batch ``payload`` through :func:`screen_group`;
    "filters": the input-filter candidates ``payload`` through :func:`screen_input_filters`."""
    if kind == "shared":
        return screen_shared(payload, current, info, workdir, tag, name,
                             generated_dir=generated_dir, det_std=det_std)
    if kind == "filters":
        return screen_input_filters(payload, current, det_std=det_std)
    if kind == "modes":
        return screen_modes(payload, current, det_std=det_std)
    if kind == "speed":
        return screen_speed(payload, current, det_std=det_std)
    return screen_group(payload, current, info, workdir, tag, name, generated_dir=generated_dir,
                        det_std=det_std)
