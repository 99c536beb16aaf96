"""Candidate generation, refits, significance and iteration (``vsidgen diagnose``).

One round:

1. fit the current model (base spec first) with the variational estimator and
   evaluate the four signals; :func:`~.locate.locate` the mismatch;
2. every registered effect proposes candidates for the model
   (:func:`~.base.propose`); each is scored against the locate evidence and the
   ``max_candidates`` best with score ≥ ``min_score`` are written as specs that
   ``extend`` the current spec (``DIR/candidates/r<round>_<i>_<key>.yaml``; the
   current parameter estimates become their initial values — warm start) and
   refitted;
3. significance: the likelihood-ratio-type statistic
   :math:`Λ = 2(\\mathrm{ELBO}_1 − \\mathrm{ELBO}_0)` against :math:`χ^2_k` (``k`` = new
   free parameters), Holm step-down over the ``m`` candidates tried in the round
   (the best candidate must reach :math:`p < α/m`). The ELBO is a lower bound of
   the log-likelihood; both fits maximise it over the same assumed-density family,
   so Λ is an approximation of the likelihood ratio, not an exact one;
4. when validation records are given the accepted candidate must also raise the
   validation ELBO (θ and noise fixed, smoothing only) — otherwise it is rejected
   as over-fitting;
5. the most significant accepted candidate becomes the new base; repeat until no
   candidate is significant or ``max_rounds`` is reached.

Empty findings are a result: the findings file then says that no significant
discrepancy was found.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import pathlib
import re
import sys
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from scipy import stats

from ..errors import FitError, SpecError, VsidgenError
from .base import (Candidate, DiscrepancyError, Effect, ModelInfo, info_from_model,
                   load_effects_module, propose, registered_effects)
from .locate import Evidence, LocateRecord, break_points, locate


@dataclasses.dataclass(frozen=True)
class DiagnoseOptions:
    """Options of :func:`run_diagnose` (all keyword, defaults shown).

    Attributes:
        max_rounds: maximum number of accepted effects (rounds of the search).
        max_candidates: candidates refitted per round (the best-scoring ones).
        alpha: family-wise significance level per round (Holm over the candidates tried).
        min_score: minimum locate score (−log10 p) for a candidate to be refitted.
        effects: restrict the catalogue to these effect ids (None: all registered).
        max_iter: optimizer iteration limit of each fit.
    """

    max_rounds: int = 3
    max_candidates: int = 8
    alpha: float = 0.01
    min_score: float = 1.0
    effects: tuple[str, ...] | None = None
    max_iter: int = 200


@dataclasses.dataclass(frozen=True)
class FitState:
    """A fitted model: spec, model, fit, evaluation signals (estimation and validation)."""

    spec_path: pathlib.Path
    model: Any
    records: tuple
    fit: Any
    signals: tuple
    vrecords: tuple = ()
    vfit: Any = None
    vsignals: tuple = ()

    @property
    def elbo(self) -> float:
        return float(self.fit.elbo)

    @property
    def val_elbo(self) -> float | None:
        return None if self.vfit is None else float(self.vfit.elbo)


@dataclasses.dataclass(frozen=True)
class Trial:
    """One refitted candidate and its test."""

    candidate: Candidate
    score: float
    spec_path: pathlib.Path
    state: FitState | None
    statistic: float
    dof: int
    p_value: float
    threshold: float = math.nan     # χ²_k quantile at the Holm level of its rank
    significant: bool = False
    validation_ok: bool | None = None
    error: str | None = None

    def to_json(self) -> dict:
        return {"key": self.candidate.key, "effect": self.candidate.effect,
                "target": self.candidate.target, "score": _f(self.score),
                "spec": str(self.spec_path), "elbo": None if self.state is None else _f(self.state.elbo),
                "val_elbo": None if self.state is None else _f(self.state.val_elbo),
                "statistic": _f(self.statistic), "dof": self.dof, "p_value": _f(self.p_value),
                "threshold": _f(self.threshold), "significant": self.significant,
                "validation_ok": self.validation_ok, "error": self.error,
                "converged": None if self.state is None else bool(self.state.fit.converged)}


@dataclasses.dataclass(frozen=True)
class DiagnoseResult:
    """What :func:`run_diagnose` produced (``findings`` as written to findings.json)."""

    out_dir: pathlib.Path
    findings: tuple[dict, ...]
    final_spec: pathlib.Path
    document: dict
    base: FitState
    final: FitState
    evidence: Evidence


def _f(v):
    if v is None:
        return None
    try:
        v = float(v)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def _say(progress, msg):
    if progress is not None:
        progress(msg)


# ---------------------------------------------------------------------------
# fitting helpers
# ---------------------------------------------------------------------------

def fit_spec(spec_path, data, *, validate=(), generated_dir=None, max_iter=200,
             warm_theta: dict | None = None) -> FitState:
    """Load, fit, evaluate (and validate) one spec on the given record files."""
    from ..data import load_record
    from ..estimator import FitOptions, fit, smooth
    from ..evaluation import evaluate
    from ..model import load_model
    from ..pipeline import _unique_names

    model = load_model(spec_path, generated_dir=generated_dir)
    records = tuple(_unique_names([load_record(model, p) for p in data]))
    vrecords = tuple(_unique_names([load_record(model, p) for p in validate]))
    options = FitOptions(max_iter=max_iter)
    res = fit(model, list(records), options=options)
    signals = tuple(evaluate(model, r, res.theta, mu=np.asarray(sm.mu), G=res.G, R=res.R)
                    for r, sm in zip(records, res.smoothers))
    vfit, vsignals = None, ()
    if vrecords:
        vfit = smooth(model, list(vrecords), res.theta, res, options=options)
        vsignals = tuple(evaluate(model, r, res.theta, mu=np.asarray(sm.mu), G=res.G, R=res.R)
                         for r, sm in zip(vrecords, vfit.smoothers))
    return FitState(pathlib.Path(spec_path), model, records, res, signals, vrecords, vfit, vsignals)


def locate_state(st: FitState) -> Evidence:
    """Run :func:`~.locate.locate` on a fitted model's estimation signals."""
    m = st.model
    recs = [LocateRecord.from_signals(s, r.u) for s, r in zip(st.signals, st.records)]
    return locate(recs, state_names=m.state_names, input_names=m.input_names,
                  output_names=m.output_names, process_std=st.fit.process_std,
                  measurement_std=st.fit.measurement_std)


def model_info_of(st: FitState) -> ModelInfo:
    """ModelInfo of the fitted model with the data's sample period and break points."""
    m = st.model
    dt = float(np.median([r.dt for r in st.records]))
    X = np.concatenate([np.asarray(s.x_smooth)[:-1] for s in st.signals])
    U = np.concatenate([np.asarray(r.u)[:-1] for r in st.records])
    info = info_from_model(m, dt=dt)
    breaks = {}
    for j, s in enumerate(m.state_names):
        if info.flow_angle("alpha") == s or info.flow_angle("beta") == s:
            breaks[s] = tuple(break_points(X[:, j]))
    for j, u in enumerate(m.input_names):
        breaks[u] = tuple(break_points(U[:, j]))
    return dataclasses.replace(info, breaks=breaks)


def _warm_parameters(st: FitState) -> dict:
    """Parameter entries of the current model with the estimates as initial values."""
    out = {}
    for p, v in zip(st.model.parameters, st.fit.theta):
        d: dict[str, Any] = {"unit": p.unit if p.unit is not None else "1",
                             "description": p.description or "",
                             "initial": float(p.initial if p.fixed else v)}
        if p.lower is not None or p.upper is not None:
            d["bounds"] = [p.lower, p.upper]
            lo = -np.inf if p.lower is None else p.lower
            hi = np.inf if p.upper is None else p.upper
            d["initial"] = float(min(max(d["initial"], lo), hi))
        if p.fixed:
            d["fixed"] = True
        out[p.name] = d
    return out


def _safe(key: str) -> str:
    return re.sub(r"[^A-Za-z0-9_]+", "_", key).strip("_")[:60]


def write_candidate(c: Candidate, st: FitState, info: ModelInfo, path: pathlib.Path,
                    name: str, *, warm: bool = True) -> pathlib.Path:
    import yaml

    d = c.spec_dict(st.spec_path, name=name, candidate_path=path, info=info)
    if warm:
        params = _warm_parameters(st)
        params.update(d.get("parameters") or {})
        d["parameters"] = params
    text = (f"# vsidgen diagnose candidate {c.key}\n# effect: {c.effect}; target: {c.target}\n"
            + yaml.safe_dump(d, sort_keys=False, width=100, allow_unicode=True))
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text, encoding="utf-8")
    return path


def lr_test(elbo0: float, elbo1: float, dof: int) -> tuple[float, float]:
    """Λ = 2(ELBO₁ − ELBO₀) and its χ²_dof upper-tail p-value."""
    lam = 2.0 * (float(elbo1) - float(elbo0))
    if not math.isfinite(lam):
        return lam, 1.0
    return lam, float(stats.chi2.sf(max(lam, 0.0), max(dof, 1))) if lam > 0 else 1.0


def holm(p_values: Sequence[float], alpha: float) -> list[tuple[bool, float]]:
    """Holm step-down: (significant, level) per p-value, in the input order."""
    m = len(p_values)
    order = sorted(range(m), key=lambda i: p_values[i])
    out = [(False, alpha / max(m, 1))] * m
    going = True
    for rank, i in enumerate(order):
        level = alpha / (m - rank)
        ok = going and p_values[i] < level
        out[i] = (ok, level)
        going = ok
    return out


def rank_candidates(info: ModelInfo, evidence: Evidence, effects: Sequence[Effect], *,
                    max_candidates: int, min_score: float) -> list[tuple[float, Candidate]]:
    """Score every candidate of every effect, best first; keep those worth a refit."""
    scored = []
    for eff in effects:
        for c in propose(info, [eff]):
            try:
                s = float(eff.score(c, evidence))
            except Exception as err:  # noqa: BLE001 - plugin bug → clear error
                raise DiscrepancyError(f"effect '{eff.id}' failed to score {c.key}: "
                                       f"{type(err).__name__}: {err}") from None
            if math.isfinite(s) and s >= min_score:
                scored.append((s, c))
    scored.sort(key=lambda sc: -sc[0])
    return scored[:max_candidates]


# ---------------------------------------------------------------------------
# the job
# ---------------------------------------------------------------------------

def run_diagnose(spec, data, *, validate=(), out, max_rounds: int = 3, max_candidates: int = 8,
                 alpha: float = 0.01, min_score: float = 1.0, effects: Sequence[str] | None = None,
                 effects_module=None, max_iter: int = 200,
                 progress: Callable[[str], None] | None = None) -> DiagnoseResult:
    """Locate, explain, model and confirm discrepancies of ``spec`` on ``data``.

    Writes ``out/findings.json``, ``out/diagnose.html`` (report section, also
    returned in the document), ``out/candidates/*.yaml`` (every refitted
    candidate spec) and ``out/generated/`` (their compiled modules).

    Raises:
        VsidgenError: bad spec, data, options or effect plugin.
    """
    from .. import __version__
    from .findings import build_document, write_findings

    if not data:
        raise VsidgenError("no data records given: `vsidgen diagnose SPEC DATA [DATA...] --out DIR`")
    if not (0 < alpha < 1):
        raise VsidgenError(f"--alpha must be in (0, 1), got {alpha}")
    if max_rounds < 0 or max_candidates < 1:
        raise VsidgenError("--max-rounds must be >= 0 and --max-candidates >= 1")
    if effects_module is not None:
        mods = effects_module if isinstance(effects_module, (list, tuple)) else [effects_module]
        for m in mods:
            load_effects_module(m)
    catalogue = list(registered_effects())
    if effects:
        known = {e.id for e in catalogue}
        bad = [e for e in effects if e not in known]
        if bad:
            raise VsidgenError(f"unknown effect(s) {', '.join(bad)}; known: {', '.join(sorted(known))}")
        catalogue = [e for e in catalogue if e.id in set(effects)]
    out = pathlib.Path(out)
    out.mkdir(parents=True, exist_ok=True)
    gen = out / "generated"
    t_start = time.perf_counter()

    _say(progress, f"fitting the base model {spec}")
    base = fit_spec(spec, data, validate=validate, generated_dir=gen, max_iter=max_iter)
    current = base
    evidence0 = locate_state(base)
    evidence = evidence0
    _say(progress, "locate:\n" + evidence0.summary())
    rounds: list[dict] = []
    accepted: list[tuple[Trial, FitState, Evidence]] = []
    for rnd in range(1, max_rounds + 1):
        info = model_info_of(current)
        ranked = rank_candidates(info, evidence, catalogue, max_candidates=max_candidates,
                                 min_score=min_score)
        if not ranked:
            rounds.append({"round": rnd, "base_spec": str(current.spec_path),
                           "base_elbo": current.elbo, "trials": [],
                           "note": "no candidate is supported by the locate evidence"})
            break
        trials: list[Trial] = []
        for i, (score, c) in enumerate(ranked):
            path = out / "candidates" / f"r{rnd}_{i + 1:02d}_{_safe(c.key)}.yaml"
            name = f"{_safe(current.model.name)[:30]}_dg{rnd}_{i + 1}"
            _say(progress, f"round {rnd}: refitting {c.key} (score {score:.3g})")
            try:
                write_candidate(c, current, info, path, name)
                st = fit_spec(path, data, validate=validate, generated_dir=gen,
                              max_iter=max_iter)
            except (SpecError, FitError, VsidgenError) as err:
                trials.append(Trial(c, score, path, None, math.nan, c.n_free, 1.0,
                                    error=str(err).splitlines()[0]))
                continue
            lam, p = lr_test(current.elbo, st.elbo, c.n_free)
            trials.append(Trial(c, score, path, st, lam, c.n_free, p))
        decisions = holm([t.p_value for t in trials], alpha)
        final_trials = []
        for t, (sig, level) in zip(trials, decisions):
            thr = float(stats.chi2.isf(level, max(t.dof, 1)))
            vok = None
            if sig and t.state is not None and t.state.vfit is not None:
                vok = bool(t.state.val_elbo > current.val_elbo)
            final_trials.append(dataclasses.replace(t, threshold=thr, significant=bool(sig),
                                                    validation_ok=vok))
        good = [t for t in final_trials if t.significant and t.validation_ok is not False
                and t.state is not None]
        rounds.append({"round": rnd, "base_spec": str(current.spec_path),
                       "base_elbo": current.elbo, "alpha": alpha, "n_candidates": len(trials),
                       "trials": [t.to_json() for t in final_trials]})
        if not good:
            break
        # most significant = smallest p (log scale: no underflow); fewer parameters win ties
        best = min(good, key=lambda t: (float(stats.chi2.logsf(max(t.statistic, 0.0), max(t.dof, 1))),
                                        t.dof))
        _say(progress, f"round {rnd}: accepted {best.candidate.key} "
                       f"(2ΔELBO = {best.statistic:.4g} > {best.threshold:.4g})")
        accepted.append((best, current, evidence))
        current = best.state
        evidence = locate_state(current)
    doc = build_document(base=base, final=current, accepted=accepted, rounds=rounds,
                         evidence=evidence0, final_evidence=evidence, alpha=alpha,
                         version=__version__, wall_time_s=time.perf_counter() - t_start,
                         out=out, options={"max_rounds": max_rounds,
                                           "max_candidates": max_candidates,
                                           "alpha": alpha, "min_score": min_score,
                                           "effects": [e.id for e in catalogue]})
    write_findings(out, doc, base=base, final=current, accepted=accepted)
    return DiagnoseResult(out, tuple(doc["findings"]), pathlib.Path(doc["final_spec"]), doc,
                          base, current, evidence0)


# ---------------------------------------------------------------------------
# command line
# ---------------------------------------------------------------------------

def add_diagnose_parser(subparsers) -> argparse.ArgumentParser:
    """Register ``vsidgen diagnose`` on an argparse subparsers object (sets ``handler``)."""
    p = subparsers.add_parser(
        "diagnose", help="find, explain and add physics the model leaves out",
        description="Fit SPEC, locate where model and records disagree (equation errors, "
                    "process noise, output residuals), propose effects from the catalogue "
                    "(missing derivatives, nonlinear/unsteady aerodynamics, delays and lags, "
                    "sensor bias/scale/position/skew, missing dynamics, wind), refit them as "
                    "specs that extend SPEC and accept an effect only when 2ΔELBO is "
                    "significant after a Holm correction (and holds on --validate records). "
                    "Writes DIR/findings.json, DIR/diagnose.html and DIR/candidates/.")
    p.add_argument("spec", help="model spec (YAML)")
    p.add_argument("data", nargs="+", help="estimation record(s) (CSV)")
    p.add_argument("--validate", nargs="+", default=[], metavar="DATA",
                   help="validation record(s): an accepted effect must raise their ELBO too")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--max-rounds", type=int, default=3, help="maximum accepted effects (default 3)")
    p.add_argument("--max-candidates", type=int, default=8,
                   help="candidates refitted per round (default 8)")
    p.add_argument("--alpha", type=float, default=0.01,
                   help="family-wise significance level per round (default 0.01)")
    p.add_argument("--min-score", type=float, default=1.0,
                   help="minimum locate score (-log10 p) to refit a candidate (default 1)")
    p.add_argument("--effects", nargs="+", default=None, metavar="ID",
                   help="restrict the catalogue to these effect ids")
    p.add_argument("--effects-module", action="append", default=None, metavar="PATH.py",
                   help="Python file defining extra Effect subclasses (repeatable)")
    p.add_argument("--max-iter", type=int, default=200, help="optimizer iterations per fit")
    p.add_argument("--quiet", action="store_true", help="no progress messages")
    p.set_defaults(handler=diagnose_command)
    return p


def diagnose_command(args) -> int:
    """Handler of ``vsidgen diagnose``; returns the exit status (0)."""
    progress = None if args.quiet else (lambda msg: print(msg, file=sys.stderr, flush=True))
    res = run_diagnose(args.spec, args.data, validate=args.validate, out=args.out,
                       max_rounds=args.max_rounds, max_candidates=args.max_candidates,
                       alpha=args.alpha, min_score=args.min_score, effects=args.effects,
                       effects_module=args.effects_module, max_iter=args.max_iter,
                       progress=progress)
    if not res.findings:
        print(f"no significant discrepancy found; findings in {res.out_dir / 'findings.json'}")
    else:
        for f in res.findings:
            ev = f["evidence"]
            print(f"{f['rank']}. {f['effect']} on {f['target']}: 2ΔELBO = "
                  f"{ev['statistic']:.4g} > {ev['threshold']:.4g}")
            print(f"   {f['explanation']}")
        print(f"final spec: {res.final_spec}; findings in {res.out_dir / 'findings.json'}")
    return 0
