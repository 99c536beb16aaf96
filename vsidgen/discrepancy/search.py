"""Candidate generation, refits, significance and iteration (``vsidgen diagnose``).

One round:

1. fit the current model (base spec first) with the variational estimator and
   evaluate the four signals; :func:`~.locate.locate` the mismatch;
2. every registered effect proposes candidates for the model
   (:func:`~.base.propose`); each is scored against the locate evidence, and every
   screenable candidate — with or without added states — also gets a score
   (Lagrange-multiplier) statistic at the current optimum (:mod:`.score`, no refit).
   All tested candidates are ranked on one scale, the score test's p-value; those
   without a statistic come after them, by locate score (:class:`Ranked`). The
   locate statistics say *where* the mismatch is; the score test decides *what* is
   refitted (:func:`choose_refits`: first the best candidate of every effect class ×
   target that clears ``α/m``, then the rest in rank order, ``max_candidates`` in
   all, priority ≥ ``min_score``). They are written as specs that ``extend`` the
   current spec (``DIR/candidates/r<round>_<i>_<key>.yaml``; the current parameter
   estimates become their initial values — warm start) and refitted;
3. significance: the likelihood-ratio-type statistic
   :math:`Λ = 2(\\mathrm{ELBO}_1 − \\mathrm{ELBO}_0)` against :math:`χ^2_k` (``k`` = new
   free parameters), Holm step-down over the ``m`` candidates *examined* in the
   round (all proposed candidates, since the screen selected the refitted ones from
   them; those not refitted enter with p = 1): the best must reach :math:`p < α/m`.
   Another significant refit (non-nested, same round) that Vuong's test on the
   per-sample one-step predictive log-likelihoods does not separate from the best
   (:func:`alternatives_of`, :mod:`.vuong`; within ``AMBIGUITY_NATS`` where the test is
   unavailable) is reported as an alternative explanation: the finding is then
   marked ambiguous. The ELBO is a lower bound of
   the log-likelihood; both fits maximise it over the same assumed-density family,
   so Λ is an approximation of the likelihood ratio, not an exact one. Before the
   decision, the refit that leads the round without an optimum is continued
   (:func:`lead_to_continue`, :func:`polish`);
4. when validation records are given the accepted candidate must also raise the
   validation ELBO (θ and noise fixed, smoothing only) — otherwise it is rejected
   as over-fitting;
5. a candidate (adding no state) that is nominally significant is checked by a
   *projected refit* (:func:`projected_refit`): the current model refitted from the
   candidate's optimum with the new terms removed. When that reaches a better optimum
   of the current model, every statistic of the round is taken against it (the gain was
   the basin, not the term) and it becomes the current fit;
6. the most significant accepted candidate becomes the new base; repeat until no
   candidate is significant or ``max_rounds`` is reached.

Under ``time_limit`` each round keeps the current model's own fit time for its decision: its
refits run in rank order until ``limit − that time`` (:func:`round_refit_deadline`; the refit in
progress then stops, :func:`.fitstate.refit_deadline`), and a round cut there is decided on the
candidates it refitted — the others enter the Holm family with p = 1, only the lead's projected
refit runs — after which the search stops (:func:`_run_round`).

Empty findings are a result: the findings file then says that no significant
discrepancy was found.
"""

from __future__ import annotations

import argparse
import dataclasses
import enum
import functools
import math
import pathlib
import sys
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from scipy import stats

from ..atomic import plan_output_dir, print_recovered, results_in_place
from ..errors import FitError, SpecError, VsidgenError
from ..estimator import WarmStart
from ..limits import check_input_file
from ..report import finite_or_none as _f
from .base import (LINEAR_TERM_EFFECTS, NONLINEAR_TERM_EFFECTS, Candidate, DiscrepancyError,
                   Effect, ModelInfo, info_from_model, load_effects_module, propose,
                   registered_effects, roles_of, same_physics, term_variables)
from .flightconst import flight_conditions_of
from .locate import Evidence, LocateRecord, break_points, locate
from .pvalues import chi2_logsf
from .refit import RefitVerdict, refit_verdict
from .family import TaskDeadline, family_chunks, family_key
from .fitstate import (FitState, conv_label, diag_options, evaluated, fit_stage2, refit_converged, refit_warm,
                       stage1_iterations)
from .specwrite import clip_to_bounds, extends_text, safe_name, warm_parameters, write_spec


#: where Vuong's test is unavailable (:func:`alternatives_of`), a refit whose Λ is within
#: 2·AMBIGUITY_NATS of the accepted one (likelihood ratio of the two explanations below e³ ≈ 20,
#: "not strong" on the Kass–Raftery scale) is reported as an alternative explanation and the
#: finding is marked ambiguous
AMBIGUITY_NATS = 3.0


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
    refit: Any = None                # RefitOutcome of the staged refit
    statistic_vs_base: float = math.nan   # 2(ELBO_candidate − ELBO_base), for reference
    converged: bool = False          # the final (stage-2) refit met the gradient criterion
    screen: Any = None               # ScoreResult of the pre-screen (None: not screenable)
    alternatives: tuple = ()         # near-equivalent significant refits (ambiguity)
    verdict: Any = None              # refit.RefitVerdict (None: no refit)
    vuong: Any = None                # as an alternative: .vuong.VuongResult of the best against it
    plateau: bool = False            # continued as the round's lead without progress (stopped_at_kink)

    @property
    def comparison(self) -> float:
        """``2(ELBO − H₀ − ELBO_current)``: the refit against the current model, the common
        reference of a round's alternatives (``statistic_vs_base`` without ``H₀``, the entropy
        of the initial values of the states the candidate adds, which its ELBO carries and the
        current model's does not; NaN without a refit).

        The test statistic (:attr:`statistic`) is taken against the candidate's own nesting
        point, which is the current model for most candidates but not for all: an actuator lag
        nests at its smallest time constant, and its discretisation over a held step there is
        not the current model under a first-order hold (``lat_dr_lag_0.15_s0``: the nesting
        point already 109 nats above the current model, so the lag's statistic, 415, ranked it
        below a Padé delay's 427 although its refit was 110 nats higher). Non-nested
        alternatives are therefore ranked by this statistic; the test of each keeps its own
        reference."""
        if self.state is None:
            return math.nan
        h0 = self.refit.x0_entropy if (self.refit is not None and self.candidate.states) else 0.0
        return self.statistic_vs_base - 2.0 * h0

    def to_json(self) -> dict:
        return {"key": self.candidate.key, "effect": self.candidate.effect,
                "target": self.candidate.target, "score": _f(self.score),
                "spec": str(self.spec_path), "elbo": None if self.state is None else _f(self.state.elbo),
                "val_elbo": None if self.state is None else _f(self.state.val_elbo),
                "val_elbo_own_noise": None if self.state is None
                else _f(self.state.val_elbo_own_noise),
                "statistic": _f(self.statistic), "dof": self.dof, "p_value": _f(self.p_value),
                "threshold": _f(self.threshold), "significant": self.significant,
                "validation_ok": self.validation_ok, "error": self.error,
                "verdict": None if self.verdict is None else self.verdict.value,
                "converged": None if self.state is None else bool(self.converged),
                "convergence": None if self.state is None else conv_label(self.state.fit),
                "status": None if self.state is None else self.state.fit.status,
                "statistic_vs_base": _f(self.statistic_vs_base),
                "statistic_vs_current": _f(self.comparison),
                "score_test": None if self.screen is None else self.screen.to_json(),
                "plateau": self.plateau,
                "refit": None if self.refit is None else self.refit.to_json()}

    def alternative_json(self, st_model=None) -> dict:
        """Summary of this trial as an alternative explanation of a finding."""
        params = {}
        if self.state is not None:
            names = list(self.state.model.parameter_names)
            for p in self.candidate.parameters:
                if p.name in names:
                    i = names.index(p.name)
                    params[p.name] = {"estimate": _f(self.state.fit.theta[i]),
                                      "std_error": _f(self.state.fit.std_errors[i]),
                                      "unit": p.unit}
        return {"key": self.candidate.key, "effect": self.candidate.effect,
                "target": self.candidate.target, "added_terms": self.candidate.added_terms(),
                "statistic": _f(self.statistic),
                "statistic_vs_current": _f(self.comparison),
                "dof": self.dof, "p_value": _f(self.p_value), "threshold": _f(self.threshold),
                "elbo": None if self.state is None else _f(self.state.elbo),
                "parameters": params, "spec": str(self.spec_path),
                "vuong": None if self.vuong is None else self.vuong.to_json()}


#: the top-level names a diagnose run writes into its results directory
DIAGNOSE_OUTPUTS = ("findings.json", "diagnose.html", "candidates", "generated", "screen")


class StopReason(enum.Enum):
    """Why a diagnose run ended (``findings.json`` → ``stop.reason``)."""

    COMPLETED = "completed"        # no significant candidate left, or max_rounds reached
    TIME_LIMIT = "time_limit"      # ``time_limit`` passed; unfinished round recorded
    INTERRUPTED = "interrupted"    # KeyboardInterrupt / SIGTERM; unfinished round recorded
    RUNNING = "running"            # a checkpoint written while the run goes on


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
    stop: StopReason = StopReason.COMPLETED


def _say(progress, msg):
    if progress is not None:
        progress(msg)


# ---------------------------------------------------------------------------
# fitting helpers
# ---------------------------------------------------------------------------

def fit_spec(spec_path, data, *, validate=(), generated_dir=None, max_iter=200,
             warm_theta: dict | None = None) -> FitState:
    """Load, fit, evaluate (and validate) one spec on the given record files."""
    from ..data import load_records
    from ..estimator import fit
    from ..model import load_model

    model = load_model(spec_path, generated_dir=generated_dir)
    records, vrecords = map(tuple, load_records(model, data, validate))
    # the user's model: its own states without process noise are fitted in the exact limit
    res = fit(model, list(records), options=diag_options(max_iter, deterministic="limit"))
    return evaluated(spec_path, model, records, res, vrecords, max_iter=max_iter)


def polish(st: FitState, *, max_iter: int, progress=None, iterations: int | None = None,
           time_limit: float | None = None) -> FitState:
    """Continue an unconverged fit from where it stopped (``iterations``, default 2 ×
    max_iter; the same model and problem, warm-started from its iterate); ``st`` itself
    when that fails or ends lower."""
    from ..estimator import fit

    _say(progress, f"fit not converged ({st.fit.status}); continuing it")
    try:
        res = fit(st.model, list(st.records), options=diag_options(
            2 * max_iter if iterations is None else iterations, warm_start=st.fit,
            time_limit=time_limit))
    except FitError:
        return st
    if res.elbo < st.elbo:
        return st
    return evaluated(st.spec_path, st.model, st.records, res, st.vrecords, max_iter=max_iter)


def staged_refit(c: Candidate, current: FitState, info: ModelInfo, path: pathlib.Path,
                 name: str, *, generated_dir, max_iter: int, progress=None, model=None):
    """Refit candidate ``c`` in stages (see :mod:`.refit`); returns a RefitOutcome.

    One spec (``path``, the new parameters at their nesting values, the current ones at their
    estimates) and one compiled problem serve every stage: stage 0 (added states only: the
    candidate at its nesting point, only the assumed density fitted), stage 1 (the current
    parameters held at their estimates, ``FitOptions.held_parameters``; for an input filter
    started at its screen's time constant, :func:`filter_start`, that time constant held
    instead: the profile there) and stage 2 (everything free, from stage 1's optimum). A
    refit started at the screen's time constant that ends below the nested reference is
    done again from the nesting point (the time constant at its lower bound, the current
    parameters held in stage 1), and the better of the two is kept (a note says so).
    ``model``: the candidate's model, already written to ``path`` and loaded (a member of a
    model family, :mod:`.family`).
    """
    from ..estimator import fit, smooth
    from ..model import load_model
    from .refit import (REFIT_DETERMINISTIC_STD as DET, RefitOutcome, noise_parameters, noise_stds,
                        parameter_start, stage0_start, x0_entropy)

    t0 = time.perf_counter()
    out = RefitOutcome()
    records = list(current.records)
    base_fit = current.fit
    if model is None:
        write_candidate(c, current, info, path, name)
        m2 = load_model(path, generated_dir=generated_dir)
    else:
        m2 = model
    new_states = [n for n in m2.state_names if n not in current.model.state_names]
    z2, theta2 = parameter_start(m2)
    base_names = set(current.model.parameter_names)
    held = tuple(p.name for p in m2.parameters if not p.fixed and p.name in base_names)
    profile = (c.info or {}).get("start_from_screen_s") is not None
    if profile:
        # an input filter started at the screen's best time constant (filter_start): stage 1
        # is the profile at that time constant (it is held, everything else is free). Holding
        # the current parameters instead let the time constant run to what the unchanged
        # gains prefer (a lag attenuates the input, which the current control derivative
        # cannot absorb), and stage 2 stopped in that local optimum: an HFB-320 elevator lag
        # of 0.15 s gained 86 nats where the model with the lagged input gains 787
        held = tuple(p.name for p in c.parameters)
    # stage 1 only brings new parameters near their optimum; a profile point is a whole
    # refit of the current parameters (and noise) and gets the full iteration budget
    it1 = max_iter if profile else stage1_iterations(max_iter)
    proc_std, offd, meas_std = noise_stds(base_fit, current.model)
    decision0 = base_fit.decision
    warm = base_fit.decision is not None
    out.elbo_ref = current.elbo
    r0_state = None     # (θ, noise, result, decision) of the nesting point's smoothing
    if new_states and warm:
        # ---- stage 0: candidate at its nesting point, only q fitted
        try:
            dec0, G1, R1, H0, notes = stage0_start(m2, records, base_fit, current.model, theta2, DET)
            out.notes += notes
            r0 = smooth(m2, records, theta2, {"G": G1, "R": R1},
                        options=diag_options(max_iter, warm_start=WarmStart.from_decision(dec0)))
            out.elbo_stage0, out.converged_stage0 = float(r0.elbo), bool(r0.converged)
            out.x0_entropy = H0
            out.elbo_ref = max(float(r0.elbo) if math.isfinite(r0.elbo) else -math.inf,
                               current.elbo + H0)
            if r0.converged:     # the limit correction's pair (a difference at one noise:
                # valid whichever of r0 and current + H0 is the quasi statistic's reference)
                r0_state = (theta2, {"G": G1, "R": R1}, r0, None)
            if profile:
                # stage 0 ran at the screen's time constant, which is not the nesting point:
                # the nested reference is the current model with the added states' copies at
                # the nesting values, whose initial-value entropy ½ log(2πe Q/(1 − a²)) differs
                # by −½ log(1 − a²) (a lag of 3 s at 20 Hz: 1.7 nats, by which the refit from
                # the nesting point appeared to end below its reference)
                th_nest = _nesting_theta(c, m2, theta2)
                dec_n, G_n, R_n, out.x0_entropy, _ = stage0_start(
                    m2, records, base_fit, current.model, th_nest, DET)
                out.elbo_ref = current.elbo + out.x0_entropy
                # the reference is not a smoothing run: the limit correction smooths the
                # nesting point itself (at the quasi std and in the limit)
                r0_state = (th_nest, {"G": G_n, "R": R_n}, None, dec_n)
            decision0 = r0.decision
            out.warm = "stage0"
        except (FitError, ValueError, ArithmeticError, np.linalg.LinAlgError) as err:
            out.notes.append(f"stage 0 failed ({str(err).splitlines()[0]}); cold start")
            warm = False
    elif new_states:
        warm = False

    def stages(z_start, held, it1, decision0):
        """Stage 1 (``held`` at their start values, ``z_start``; assumed density warm from
        ``decision0``) and stage 2 (all free)."""
        opts1 = {"held_parameters": held}
        if warm:
            try:
                s1 = np.concatenate([z_start, noise_parameters(
                    m2, records, DET, proc_std=proc_std, proc_G=offd, meas_std=meas_std)])
                opts1["warm_start"] = WarmStart.from_decision(
                    {"s": s1, "records": decision0["records"]})
                out.warm = out.warm or "base"
            except (FitError, ValueError, KeyError) as err:
                out.notes.append(f"no warm start for stage 1 ({err})")
        else:
            out.warm = "cold"
        try:
            res1 = fit(m2, records, options=diag_options(it1, **opts1))
        except FitError as err:
            if "warm_start" not in opts1:
                raise
            out.notes.append(f"warm start rejected ({str(err).splitlines()[0]}); cold start")
            res1 = fit(m2, records, options=diag_options(it1, held_parameters=held))
        if not new_states and "warm_start" not in opts1:
            out.elbo_ref = current.elbo
        # ---- stage 2: everything free from stage 1's estimates (the same problem)
        ws2 = None if res1.decision is None else WarmStart.from_decision(res1.decision)
        return res1, fit_stage2(m2, records, res1, max_iter=max_iter, notes=out.notes,
                                warm_start=ws2)

    res1, res2 = stages(z2, held, it1, decision0)
    _say(progress, f"    stage 1: ELBO {res1.elbo:.6g} (reference {out.elbo_ref:.6g}, "
                   f"{'converged' if res1.converged else 'not converged'})")
    if profile and res2.elbo < out.elbo_ref:
        # the screen's time constant was a bad start (its score statistic measures a small
        # move of the input towards the filtered one, not the filter itself: on a new user's
        # ATTAS roll model the aileron lag held there fitted 878 nats below the current model
        # and stage 2 stayed in that basin, 2ΔELBO -1515): refit from the nesting point as a
        # candidate without a screen start would be, and keep the better
        theta_nest = _nesting_theta(c, m2, theta2)
        from ..estimator.core import ThetaMap
        tm = ThetaMap(m2.parameters, values=theta_nest)
        z_nest = tm.z0
        base_held = tuple(q.name for q in m2.parameters if not q.fixed and q.name in base_names)
        dec_nest = decision0
        if new_states and warm:
            try:   # the added states embedded along their nesting-point transition
                dec_nest = stage0_start(m2, records, base_fit, current.model,
                                        tm.theta(z_nest), DET)[0]
            except (FitError, ValueError, ArithmeticError, np.linalg.LinAlgError):
                dec_nest = decision0
        res1b, res2b = stages(z_nest, base_held, stage1_iterations(max_iter), dec_nest)
        out.notes.append(
            f"the refit from the screen's time constant ended {2 * (res2.elbo - out.elbo_ref):.4g} "
            f"(2ΔELBO) below the nested reference; refitted from the nesting point: "
            f"{2 * (res2b.elbo - out.elbo_ref):.4g}"
            + (", used" if res2b.elbo > res2.elbo else ", not better"))
        _say(progress, f"    {out.notes[-1]}")
        if res2b.elbo > res2.elbo:
            res1, res2 = res1b, res2b
    out.elbo_stage1, out.converged_stage1 = float(res1.elbo), bool(res1.converged)
    if REFIT_LIMIT_STATISTIC and r0_state is not None:
        limit_correction(out, m2, records, res2, r0_state, new_states,
                         new_params=tuple(q.name for q in c.parameters), max_iter=max_iter,
                         progress=progress)
    st = evaluated(path, m2, records, res2, current.vrecords, max_iter=max_iter)
    if new_states and st.vfit is not None:
        out.val_x0_entropy = x0_entropy(st.vfit, new_states, m2, current.vrecords)
    out.state = st
    out.wall_s = time.perf_counter() - t0
    return out


#: take the statistic of a candidate that adds a state carrying an input (a lag, a Padé delay,
#: an actuator) in the deterministic limit of its added states (:func:`limit_correction`)
REFIT_LIMIT_STATISTIC = True


def limit_correction(out, m2, records, res2, r0_state, new_states, *, new_params=(),
                     max_iter: int, progress=None) -> None:
    """Correct a refit's statistic to the deterministic limit of the states it adds.

    The refits hold the added states quasi-deterministic: a small fixed process noise
    (:data:`.refit.REFIT_DETERMINISTIC_REL` of the carried input's spread per √s for a lag or
    delay state, :data:`.refit.REFIT_DETERMINISTIC_STD` for any other) keeps the objective
    smooth, but it is also a noise channel — into the input for a lag or delay state (a Padé
    "aileron delay" on a new user's Twin Otter lateral model gained 2399 at 7 % and 346 at
    0.7 %), a coloured process noise through a mode's coupling for a mode state — and the
    candidate's ELBO gains what that channel explains. The model the diagnosis writes has no
    such noise, so the statistic that decides is the limit of

        λ(ε) = 2 (ELBO_candidate(ε) − ELBO_reference(ε))

    as the added states' std ε → 0: the candidate is refitted in the limit from its
    quasi-deterministic optimum (:func:`vsidgen.estimator.fit`, ``deterministic="limit"``:
    ε ← ε/10 per stage until the ELBO and the estimates settle), and the nested reference —
    the stage-0 smoothing at the nesting point — is smoothed along the same stds down to the
    same final ε (``smooth``'s continuation with the candidate's limit record as target: both
    ELBOs at one noise, where a contracting state's collapse costs both the same ln 10 per
    stage). ``out.limit_correction`` = λ(ε_final) − λ(quasi) is added to the statistic by
    raising ``out.elbo_ref`` (and ``out.x0_entropy``, which the comparison across a round's
    candidates uses) by −½ of it; the candidate's fit itself stays the quasi-deterministic
    one (its validation and report). For candidates that add a state carrying an input (a
    lag, a Padé delay, an actuator), when every stage of both continuations converged (else a
    note, and the quasi statistic). Not for modes and the other added states: on the
    body-axis null record (hfbb_none_0_s0) their limits took 15–172 s each and changed no
    decision (a q mode 37.8 → 38.2 with its limit not reached, a thrust mode 14.0 → 2.2, both
    on the same side of their thresholds). A continuation that ran its stages out before the
    ELBO settled (``reached`` False) gives the statistic at its smallest std, both ELBOs at
    that std: closer to the limit than the quasi-deterministic one (a note says so).

    Only the added states are taken to the limit; the model's own states without process
    noise stay at their quasi-deterministic std on both sides (``WarmStart.deterministic_limit``
    ``"hold"``), where the round's reference holds them: taken down too, they cost the
    reference (its noise fixed) ~1/ε² that the candidate (its noise refitted) did not pay.
    A refit that ended below its nesting point at its own noise (2ΔELBO < −``BELOW_TOL``) gets
    no correction: it is flagged (``RefitVerdict.BELOW_NESTING_POINT``), never corrected into
    a statistic.
    """
    from ..estimator import WarmStart, fit, smooth
    from ..estimator.core import carried_inputs
    from .refit import BELOW_TOL, REFIT_DETERMINISTIC_STD, quasi_stds

    added = {m2.state_names.index(n) for n in new_states}
    if res2.decision is None or not res2.deterministic_states \
            or not any(i in added for i, _ in carried_inputs(m2)) \
            or not any(n in new_states for n in res2.deterministic_states):
        return
    theta0, noise0, r0, dec0 = r0_state
    q = quasi_stds(m2, records, REFIT_DETERMINISTIC_STD)
    std_q = {n: float(q[m2.state_names.index(n)]) for n in res2.deterministic_states}
    # only the added states go to the limit: the model's own states without process noise (a
    # user's φ̇ = p) stay at the quasi std at which the current model, the reference of every
    # refit of the round, holds them (_held_reference). Taken to the limit with them, the
    # candidate's fit re-fitted its noise at each std while the nested reference, a smoothing at
    # the current model's fixed noise, could not: on a new user's Twin Otter lateral model
    # (φ without process noise) the reference fell to ELBO −6.59e6 and a rudder lag that ended
    # at its nesting point (2e-5 s, 0.26 below its reference) was reported at 2ΔELBO 1.3e7
    start = {"std": std_q, "hold": {n: v for n, v in std_q.items() if n not in new_states}}
    t0 = time.perf_counter()
    try:
        if r0 is None:       # the nesting point smoothed at the quasi std (a profiled filter)
            r0 = smooth(m2, records, theta0, noise0,
                        options=diag_options(max_iter, warm_start=WarmStart.from_decision(dec0)))
            if not r0.converged:
                out.notes.append("the statistic in the deterministic limit was not taken: the "
                                 "nesting point's smoothing did not converge")
                return
        lam_q = 2.0 * (float(res2.elbo) - float(r0.elbo))
        below = 2.0 * (float(res2.elbo) - max(float(r0.elbo), float(out.elbo_ref)))
        if not below >= -BELOW_TOL:
            # the refit ended below its nesting point at its own noise (the smoothing there, or
            # the reference its statistic uses): an optimiser failure
            # (refit.RefitVerdict.BELOW_NESTING_POINT), not a statistic a limit can correct
            out.notes.append(f"the statistic in the deterministic limit was not taken: the refit "
                             f"ended below its nesting point at the quasi-deterministic std "
                             f"(2ΔELBO {below:.4g})")
            return
        ws = WarmStart.from_decision(res2.decision)
        resL = fit(m2, records, options=diag_options(
            max_iter, deterministic="limit",
            warm_start=dataclasses.replace(ws, deterministic_limit=start)))
        lim = resL.deterministic_limit
        if not (resL.converged and lim and len(lim.get("stages") or ()) > 1):
            out.notes.append("the statistic in the deterministic limit was not taken: the "
                             f"candidate's limit did not converge ({resL.status.splitlines()[0]})")
            return
        ws0 = dataclasses.replace(WarmStart.from_decision(r0.decision), deterministic_limit=start)
        r0L = smooth(m2, records, theta0, {**noise0, "deterministic_limit": lim},
                     options=diag_options(max_iter, deterministic="limit", warm_start=ws0))
        if not r0L.converged:
            out.notes.append("the statistic in the deterministic limit was not taken: the "
                             "nested reference's limit did not converge")
            return
    except (FitError, ValueError, ArithmeticError, np.linalg.LinAlgError) as err:
        out.notes.append(f"the statistic in the deterministic limit was not taken "
                         f"({str(err).splitlines()[0]})")
        return
    lam_l = 2.0 * (float(resL.elbo) - float(r0L.elbo))
    corr = lam_l - lam_q
    out.limit_correction = corr
    out.limit_detail = {"statistic_quasi": lam_q, "statistic_limit": lam_l,
                        "std": lim.get("std"), "stages": len(lim.get("stages") or ()),
                        "elbo_candidate": float(resL.elbo), "elbo_reference": float(r0L.elbo),
                        "estimates": {p: float(v) for p, v in zip(m2.parameter_names, resL.theta)
                                      if p in new_params},
                        "wall_s": round(time.perf_counter() - t0, 2)}
    out.elbo_ref -= 0.5 * corr
    out.x0_entropy -= 0.5 * corr
    reached = bool(lim.get("reached"))
    out.limit_detail["reached"] = reached
    out.notes.append(f"statistic in the deterministic limit of the added states: "
                     f"{lam_l:.4g} (at their quasi-deterministic std: {lam_q:.4g})"
                     + ("" if reached else
                        f"; the limit was not reached in {len(lim.get('stages') or ()) - 1} "
                        "stage(s): the statistic at the smallest std, both at that std"))
    _say(progress, f"    {out.notes[-1]}")


def _nesting_theta(c: Candidate, model, theta) -> np.ndarray:
    """``theta`` (all parameters of ``model``) with ``c``'s new parameters at their nesting
    values, the lower ends of their ranges (an input filter's smallest time constant)."""
    names = list(model.parameter_names)
    out = np.asarray(theta, float).copy()
    for p in c.parameters:
        if p.name in names and p.lower is not None:
            out[names.index(p.name)] = float(p.lower)
    return out


def drift_sensitivities(st: FitState) -> dict[str, np.ndarray]:
    """Per state, ``∂f_s/∂θ_j`` of the free parameters along the smoothed path.

    Rows align with locate's equation errors (records concatenated, the last sample of
    each dropped); columns that are zero everywhere (parameters absent from ``f_s``) are
    dropped. These are the directions in which a refit of the existing parameters can
    move the drift, i.e. what a new term must *not* be collinear with to be identifiable.
    """
    import jax
    import jax.numpy as jnp

    from ..model import theta_vector

    m = st.model
    free = [i for i, p in enumerate(m.parameters) if not p.fixed]
    if not free:
        return {}
    p = jnp.asarray(theta_vector(m, st.fit.theta))
    jac = jax.jit(jax.vmap(lambda x, u, th: m.drift_jacobian(x, u, th)[2], in_axes=(0, 0, None)))
    blocks = []
    for sig, rec in zip(st.signals, st.records):
        X = jnp.asarray(np.asarray(sig.x_smooth, float)[:-1])
        U = jnp.asarray(np.asarray(rec.u, float).reshape(len(sig.t), -1)[:-1])
        blocks.append(np.asarray(jac(X, U, p))[:, :, free])
    J = np.concatenate(blocks, axis=0)            # (n, nx, n_free)
    out = {}
    for j, s in enumerate(m.state_names):
        cols = J[:, j, :]
        nz = np.any(np.abs(cols) > 0, axis=0) & np.all(np.isfinite(cols), axis=0)
        out[s] = cols[:, nz]
    return out


#: a projected refit (see :func:`projected_refit`) that raises the current model's ELBO by
#: more than this (nats) replaces the current fit as the reference of the round
PROJECTED_TOL = 0.05


def projected_refit(t: "Trial", current: FitState, path: pathlib.Path, name: str, *,
                    generated_dir, max_iter: int) -> FitState:
    """The *current* model refitted from a candidate's optimum, its new terms removed.

    A candidate's refit can end in a better optimum of the current model's own
    parameters and noise (the noise likelihood is multimodal; the extra parameter opens a
    path out of the current basin). Such a gain belongs to the current model, not to the
    new term: measured against the old optimum it can make a term whose estimate is
    indistinguishable from zero look highly significant. This refit starts at the
    candidate's optimum with its new parameters fixed at their nesting values (the
    current model exactly; only for candidates that add no state and nest the current
    model at their initial values) and the candidate's noise and assumed density as warm
    start. When it ends above the current ELBO, the current model has a better optimum,
    which becomes the reference of every candidate of the round.

    A candidate that adds states, or that does not nest the current model at its initial
    values (an input delay), is projected by refitting the current spec itself from its
    estimates of the current parameters, its noise and its assumed density restricted to
    the current states (:func:`rebase`). On the real HFB-320 record an elevator lag refit
    ended with its time constant at the lower bound (no lag) and 2ΔELBO 151.7: the lag
    state's refit had left the current model's basin with the measurement noise of q at
    its floor.
    """
    if t.candidate.states or not t.candidate.screenable:
        return rebase(t.state, current, path, name, generated_dir=generated_dir,
                      max_iter=max_iter, iterations=2 * max_iter)
    params = warm_parameters(t.state.model, t.state.fit.theta)
    for q in t.candidate.parameters:
        params[q.name].update(initial=float(q.initial), fixed=True)
    write_spec(path, f"vsidgen diagnose: projected refit of {t.candidate.key}",
               {"name": name,
                "description": f"{t.candidate.key} with its new terms at their nesting values "
                               "(the current model), started at the candidate's optimum",
                "extends": extends_text(t.spec_path, path), "parameters": params})
    return refit_warm(path, t.state, current, generated_dir=generated_dir,
                       iterations=2 * max_iter, max_iter=max_iter)


def rebase(better: FitState, current: FitState, path: pathlib.Path, name: str, *,
           generated_dir, max_iter: int, iterations: int | None = None) -> FitState:
    """The current spec at a better optimum found by :func:`projected_refit`.

    Writes ``path`` (extends the current spec; the current parameters start at
    ``better``'s estimates) and fits it warm from ``better`` (the same point, so it
    stops at once): the next round's candidates extend a spec without the removed
    candidate's zeroed terms.
    """
    est = dict(zip(better.model.parameter_names, map(float, better.fit.theta)))
    params = warm_parameters(current.model, current.fit.theta)
    for k, v in params.items():
        if not v.get("fixed") and k in est and math.isfinite(est[k]):
            v["initial"] = clip_to_bounds(est[k], v.get("bounds"))
    write_spec(path, "vsidgen diagnose: the current model re-estimated (better optimum)",
               {"name": name,
                "description": "the current model at a better optimum of its own parameters "
                               "and noise",
                "extends": extends_text(current.spec_path, path), "parameters": params})
    return refit_warm(path, better, current, generated_dir=generated_dir,
                       iterations=iterations or max_iter, max_iter=max_iter)


def _against_better_reference(trials: Sequence["Trial"], better: FitState) -> list["Trial"]:
    """Every trial's statistic recomputed against a better optimum of the current model."""
    out = []
    for t in trials:
        if t.state is None or t.refit is None:
            out.append(t)
            continue
        h0 = t.refit.x0_entropy if t.candidate.states else 0.0
        ro = dataclasses.replace(t.refit, elbo_ref=max(t.refit.elbo_ref, better.elbo + h0))
        lam, p = lr_test(ro.elbo_ref, t.state.elbo, t.dof)
        n_grid = _grid_size(t.candidate)
        if n_grid:
            from .delay import delay_p_value
            p = delay_p_value(lam, n_grid)
        out.append(dataclasses.replace(t, statistic=lam, p_value=p, refit=ro,
                                       statistic_vs_base=2.0 * (t.state.elbo - better.elbo),
                                       verdict=trial_verdict(t.candidate, t.state, lam, ro)))
    return out


def locate_state(st: FitState) -> Evidence:
    """Run :func:`~.locate.locate` on a fitted model's estimation signals, testing every
    equation-error regressor for what the model's own free terms cannot absorb."""
    m = st.model
    recs = [LocateRecord.from_signals(s, r.u) for s, r in zip(st.signals, st.records)]
    sym = getattr(m, "symbolic", None)
    return locate(recs, state_names=m.state_names, input_names=m.input_names,
                  output_names=m.output_names, process_std=st.fit.process_std,
                  measurement_std=st.fit.measurement_std, nuisance=drift_sensitivities(st),
                  roles=roles_of(sym.states) if sym is not None else None,
                  kinematics=_kinematic_equations(m) if sym is not None else None)


def _kinematic_equations(m) -> dict[str, frozenset[str]]:
    """``{state: rates}`` of the model's exact-geometry equations (``φ̇ = p + …``): the
    variables of the rate's dimension they are made of, or every state and input where
    the units do not say (:func:`.catalogue.kinematic_rates`)."""
    from .catalogue import kinematic_rates, kinematic_state
    info = info_from_model(m)
    every = frozenset([*m.state_names, *m.input_names])
    return {s: kinematic_rates(info, s) or every for s in m.state_names
            if kinematic_state(info, s)}


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
    # a flow angle the model defines (a: atan2(w, u)) and an output measures: its break
    # points from that output at the smoother mean
    for d, (_, o) in info.defined_flow_angles.items():
        if o is not None and o in m.output_names:
            k = list(m.output_names).index(o)
            Y = np.concatenate([np.asarray(s.y_smooth)[:-1, k] for s in st.signals])
            breaks[d] = tuple(break_points(Y))
    return dataclasses.replace(info, breaks=breaks, flight=flight_conditions_of(info, st.records))


def write_candidate(c: Candidate, st: FitState, info: ModelInfo, path: pathlib.Path,
                    name: str, *, warm: bool = True, fix_base: bool = False,
                    new_initial: dict | None = None) -> pathlib.Path:
    """Write the candidate spec extending the current spec.

    ``warm``: the current estimates become the initial values; ``fix_base``: and
    they are fixed (stage 1 of the refit); ``new_initial``: initial values of the
    new parameters (stage 2 starts from stage 1's estimates).
    """

    d = c.spec_dict(st.spec_path, name=name, candidate_path=path, info=info)
    if warm:
        params = warm_parameters(st.model, st.fit.theta)
        if fix_base:
            for v in params.values():
                v["fixed"] = True
        new = d.get("parameters") or {}
        for k, v in new.items():
            if new_initial and k in new_initial and math.isfinite(new_initial[k]) and not v.get("fixed"):
                v["initial"] = clip_to_bounds(new_initial[k], v.get("bounds"))
        params.update(new)
        d["parameters"] = params
    return write_spec(path, f"vsidgen diagnose candidate {c.key}\n# effect: {c.effect}; "
                            f"target: {c.target}", d)


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
    """Locate score of every candidate of every effect, best first; keep those worth a refit."""
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


def trial_verdict(c: Candidate, st: FitState, statistic: float, refit=None):
    """:class:`.refit.RefitVerdict` of a refitted candidate (its Λ and its estimates).

    ``refit`` (its :class:`.refit.RefitOutcome`): a refit whose ELBO ended below its nesting
    point at the noise it was fitted with (:attr:`.refit.RefitOutcome.elbo_nesting`) is
    ``BELOW_NESTING_POINT`` whatever ``statistic`` says — a statistic corrected to another
    noise (the deterministic limit, :func:`limit_correction`) must not turn an optimiser
    failure into evidence: a rudder lag that ended 0.26 below its nesting point was reported
    at 2ΔELBO 1.3e7 and led its round."""
    from .refit import BELOW_TOL

    nest = getattr(refit, "elbo_nesting", None)
    if (nest is not None and st is not None and math.isfinite(nest) and math.isfinite(st.elbo)
            and 2.0 * (st.elbo - nest) < -BELOW_TOL):
        return RefitVerdict.BELOW_NESTING_POINT
    names = list(st.model.parameter_names)
    idx = {p.name: names.index(p.name) for p in c.parameters if p.name in names}
    est = {n: float(st.fit.theta[i]) for n, i in idx.items()}
    se = getattr(st.fit, "std_errors", None)
    ses = {} if se is None else {n: float(se[i]) for n, i in idx.items()}
    return refit_verdict(statistic, est, dict(c.info.get("causal_sign") or {}),
                         dict(c.info.get("label_upper") or {}), ses)


def stopped_short(t: Trial) -> float | None:
    """λ²/2 (nats) still predicted by a refit that stopped at its iteration or time limit with a
    positive-definite Hessian, else None.

    Such a refit can still be *significant*: its ELBO is a lower bound of the candidate's
    maximum (the optimiser only ascends from the nesting point), so its 2ΔELBO is a lower bound
    of the converged statistic and its p-value an upper bound — a Holm decision on it is
    conservative. What it cannot give is an estimate at the optimum: that is ``λ²/2`` away, i.e.
    within about ``√(2·λ²/2)`` standard errors (the quadratic model's step in the metric of the
    Hessian), and the finding says so. (lat_p_bias_0.0005_s0: the roll-gyro bias's refit
    crawled for 400 iterations along the noise model's funnel, λ²/2 = 0.199 nats left, at
    2ΔELBO 45.2 against a threshold of 15.8, and the run ended INCONCLUSIVE.) With an
    indefinite Hessian (no λ²/2) the refit stays undecided."""
    from ..estimator import StopReason

    if t.state is None or t.converged:
        return None
    res = t.state.fit
    dec = float(getattr(res, "newton_decrement", math.nan))
    if (getattr(res, "stop_reason", None) in (StopReason.ITERATION_LIMIT, StopReason.TIME_LIMIT)
            and math.isfinite(dec) and dec >= 0.0):
        return dec
    return None


def stopped_at_kink(t: Trial) -> bool:
    """A refit that stopped, short of the gradient test, because no step raises its ELBO any
    more — every step rejected until it vanished (the optimizer's ``NO_PROGRESS``,
    ``DAMPING_OVERFLOW``, or their form at an indefinite Hessian, ``INDEFINITE_HESSIAN``) —
    and that :func:`.fitstate.near_optimum` does not already count as converged.

    Such a point is where the ELBO has a kink: a hinge ``max(α − α_b, 0)`` whose break point
    a sample's sigma points straddle makes the expectation piecewise smooth in ``α_b``, its
    one-sided gradient stays non-zero and its Hessian is indefinite there
    (``hfb_lift_stall_4_s2``: both hinge refits stopped at 2ΔELBO 2927.8 with a relative
    gradient of 0.024, continued 800 iterations without change, and the converged quadratic
    form, 1706.2, was accepted instead). As every ELBO the optimizer reaches, its 2ΔELBO is a
    lower bound of the candidate's maximum, so it is decided on that bound — conservative for
    its significance and for its rank; its estimates are those of that point, without
    standard errors. An iteration or time limit with an indefinite Hessian, or a stall,
    stays undecided (the refit was still climbing) — unless the refit, continued as the round's
    lead, made no progress by the optimizer's own scale (:func:`on_plateau`)."""
    from ..estimator import StopReason

    if t.state is None or t.converged or not math.isfinite(t.statistic):
        return False
    return t.plateau or getattr(t.state.fit, "stop_reason", None) in (
        StopReason.NO_PROGRESS, StopReason.DAMPING_OVERFLOW, StopReason.INDEFINITE_HESSIAN)


#: an unconverged refit that leads its round (:func:`lead_to_continue`) is continued for this
#: many times the round's ``max_iter`` more iterations (within the run's time limit)
CONTINUE_FACTOR = 4


def lead_to_continue(trials: Sequence[Trial], *, alpha: float, n_examined: int) -> int | None:
    """Index of the refit to continue before the round is decided, or None.

    The rule of the estimator's noise starts (``FitOptions.noise_start``), applied to a
    round: the refit with the highest gain over the current model (:attr:`Trial.comparison`)
    that stopped without an optimum — iteration or time limit, a stall, no progress, an
    indefinite Hessian — is continued when that gain is above every converged refit's and
    its 2ΔELBO, a lower bound of the converged one (the optimiser only ascends), is above
    the round's first Holm threshold (χ²_k at α/m). Left as it is, the round can accept none
    of it: not the lead, whose estimate is not an optimum (INCONCLUSIVE when its Hessian is
    indefinite), and not a converged refit it may outrank. Measured: the roll-gyro bias of
    ``lat_p_bias_0.002_s1``/``_s2`` (correlated process noise) stopped at 800 iterations at
    2ΔELBO ≥ 96.7 and ≥ 166 while r's independent noise slid towards zero — a rank-deficient
    Q, one gust acting on β, p and r — and converged after about 1300 iterations at 199, the
    bias 0.00202 rad/s (truth 0.002)."""
    from ..estimator import StopReason

    stops = (StopReason.ITERATION_LIMIT, StopReason.TIME_LIMIT, StopReason.STALLED,
             StopReason.NO_PROGRESS, StopReason.INDEFINITE_HESSIAN)
    top = max((t.comparison for t in trials if t.state is not None and t.converged),
              default=-math.inf)
    level = alpha / max(n_examined, len(trials), 1)
    lead = None
    for i, t in enumerate(trials):
        if (t.state is None or t.converged or t.verdict is not RefitVerdict.ORDINARY
                or getattr(t.state.fit, "stop_reason", None) not in stops
                or not math.isfinite(t.comparison)):
            continue
        if (t.comparison > top and t.statistic > float(stats.chi2.isf(level, max(t.dof, 1)))
                and (lead is None or t.comparison > trials[lead].comparison)):
            lead = i
    return lead


def outranking_unconverged(trials: Sequence[Trial], best: Trial) -> list[Trial]:
    """The refits that stopped without an optimum and undecided (not :func:`stopped_short`,
    not :func:`stopped_at_kink`: an indefinite Hessian at their limit, still climbing), above
    their own threshold, whose gain over the current model (:attr:`Trial.comparison`) already
    exceeds that of ``best``, the round's most significant decided effect.

    Their ELBO is a lower bound of their maximum (the optimizer only ascends), so ``best`` is
    not the best explanation the data support, and the round accepts neither — the rule of
    :func:`lead_to_continue`, applied when the lead could not be continued (a round cut by
    the time limit) or its continuation did not converge. Measured: an engine lag of 0.5 s
    concealed by the independent simulator (``hfb_thrust_lag_0.5_s0``, a round cut at 1500 s)
    — the lag's refit stopped at 800 iterations at ELBO 19215.2 (indefinite Hessian) and a
    0.36-s transport delay of the thrust, converged at 18960.9, was named; restricted to the
    lag, the refit converges at τ = 0.5075 ± 0.0015 s."""
    out = []
    for t in trials:
        if (t.state is None or t.converged or t is best or t.verdict is not RefitVerdict.ORDINARY
                or stopped_short(t) is not None or stopped_at_kink(t)
                or not math.isfinite(t.comparison) or not math.isfinite(t.statistic)):
            continue
        if t.comparison > best.comparison and t.statistic > t.threshold:
            out.append(t)
    return out


def _continue_task(st, iterations, max_iter, time_limit):
    """A refit's state continued from where it stopped, on an engine worker: :func:`polish`
    (the same model and problem — a gated model keeps its configuration —, warm-started from
    its iterate, ``iterations`` more); a FitState."""
    return polish(st, max_iter=max_iter, iterations=iterations, time_limit=time_limit)


def continued_trial(t: Trial, st: FitState, current: FitState, iterations: int) -> Trial:
    """``t`` with its continued refit ``st`` (statistic, convergence, verdict again)."""
    ro = t.refit
    if ro is not None:
        ro = dataclasses.replace(ro, state=st, notes=list(ro.notes) + [
            f"continued for up to {iterations} more iterations as the round's unconverged "
            f"lead: ELBO {t.state.elbo:.6g} -> {st.elbo:.6g} ({conv_label(st.fit)})"])
    ref = t.refit.elbo_ref if t.refit is not None else current.elbo
    lam, p = lr_test(ref, st.elbo, t.dof)
    return dataclasses.replace(t, state=st, statistic=lam, p_value=p, refit=ro,
                               statistic_vs_base=2.0 * (st.elbo - current.elbo),
                               converged=refit_converged(st.fit),
                               verdict=trial_verdict(t.candidate, st, lam, ro),
                               plateau=on_plateau(t.state, st, iterations))


def on_plateau(before: FitState, after: FitState, budget: int = 0) -> bool:
    """Did a continuation make no progress by the optimizer's own scale?

    True when the continued refit is still not converged and its ELBO rose, over the
    continuation's iterations, by less than ``FitOptions.decrement_tol`` nats per iteration —
    the gain a single Newton step must fall below for convergence. Such a refit sits on a
    ridge or at a kink of its ELBO (the real HFB-320 record, a new user's short-period model:
    the speed candidate's refit continued 800 iterations from 7064.72 to 7064.73, the
    Hessian indefinite along the flat direction of the speed state's level against the trim
    constants): :func:`stopped_at_kink` then decides it on its 2ΔELBO, a lower bound of the
    maximum, instead of leaving it undecided while a lower, converged refit is accepted."""
    from ..estimator import FitOptions

    if refit_converged(after.fit):
        return False
    n = int(getattr(after.fit, "iterations", 0)) - int(getattr(before.fit, "iterations", 0))
    n = n if n > 0 else int(budget)        # ``iterations`` counted from the continuation's start
    return n > 0 and after.elbo - before.elbo < FitOptions().decrement_tol * n


def trial_loglik(t: Trial) -> list | None:
    """Per-record, per-sample one-step predictive log-likelihoods of a trial's refit
    (:func:`vsidgen.evaluation.predictive_loglik`); None when a record has no steady-state
    filter or the trial no refit.

    The filter runs with the noise the refit's ELBO was computed with
    (``FitResult.G_objective``): a state the candidate adds is quasi-deterministic in the
    refit, with a small fixed process noise, which the reported ``G`` (and the evaluation
    signals) set to zero. The likelihoods then belong to the model the statistic ranked —
    for a linear model Σ_k ℓ_k is its log-likelihood, which the ELBO bounds from below. (With
    the reported G, a new user's Twin Otter lateral model with a 0.29-s Padé aileron delay
    predicted 10⁴ nats per sample worse than the refit's ELBO allowed, and Vuong's test
    declared its 2ΔELBO-best explanation beaten by the second, z = −5.8.)"""
    from ..evaluation import evaluate, predictive_loglik

    if t.state is None or not t.state.signals:
        return None
    st = t.state
    Gobj = getattr(st.fit, "G_objective", None)
    if Gobj is not None and np.shape(Gobj) == np.shape(st.fit.G) and not np.array_equal(Gobj, st.fit.G):
        try:
            sigs = [evaluate(st.model, r, st.fit.theta, mu=np.asarray(sm.mu), G=Gobj, R=st.fit.R)
                    for r, sm in zip(st.records, st.fit.smoothers)]
        except (VsidgenError, ValueError, ArithmeticError, np.linalg.LinAlgError):
            return None
    else:
        sigs = st.signals
    lls = [predictive_loglik(sig) for sig in sigs]
    return None if any(ll is None for ll in lls) else lls


#: two refits of one structure are one fitted model when every new parameter's estimates
#: differ by at most this fraction of the larger standard error (:func:`same_fitted_model`)
SAME_FIT_SE = 0.1


def same_fitted_model(a: Trial, b: Trial, *, se_fraction: float = SAME_FIT_SE) -> bool:
    """Whether two refits are one fitted model reached from two starts: the same terms (effect,
    target, new parameter names and added terms; only the start values differ, e.g. a break
    point started at two grid values) and every new parameter's estimates within
    ``se_fraction`` of the larger of their standard errors. Such a pair is not an alternative
    explanation of a finding: it is the same explanation twice."""
    ca, cb = a.candidate, b.candidate
    if a.state is None or b.state is None or (ca.effect, ca.target) != (cb.effect, cb.target):
        return False
    if [q.name for q in ca.parameters] != [q.name for q in cb.parameters] \
            or getattr(ca, "add_terms", None) != getattr(cb, "add_terms", None):
        return False
    na, nb = list(a.state.model.parameter_names), list(b.state.model.parameter_names)
    for q in ca.parameters:
        if q.fixed or q.name not in na or q.name not in nb:
            continue
        ia, ib = na.index(q.name), nb.index(q.name)
        ta, tb = float(a.state.fit.theta[ia]), float(b.state.fit.theta[ib])
        se = max(float(a.state.fit.std_errors[ia]), float(b.state.fit.std_errors[ib]))
        # without standard errors (a refit stopped at a kink) only equal estimates are one fit
        tol = se_fraction * se if math.isfinite(se) else 1e-6 * max(abs(ta), abs(tb), 1e-300)
        if not abs(ta - tb) <= tol:
            return False
    return True


def linear_first(best: Trial, good: Sequence[Trial]) -> tuple[Trial, dict | None]:
    """The hierarchy principle of stepwise model building (a variable's linear term before
    its nonlinear terms): when the best refit of a round is a nonlinear term (a square, a
    break, a product) of a variable the target does not yet depend on — its linear term is
    itself a candidate of the round — and that linear term is significant too, the linear
    term is named; the nonlinear form stays as the finding's alternative and is tested on
    top of the linear term in the next round, where its own 2ΔELBO measures the
    nonlinearity. (Real ATTAS lateral records with the adverse yaw N_δa deleted: a break of
    the yaw coefficient in δa at −0.18 rad, 2ΔELBO 2816, was named before the missing linear
    derivative, 2747 — a break beyond most of the data, i.e. the linear term with a corner.)
    A linear term is a candidate only for a variable its target does not use
    (``coefficient_derivative``, ``missing_derivative``), so an existing linear term — a
    lift curve with a stall break — leaves the nonlinear form named. Returns the trial to
    name and, when it changed, ``{"note": sentence for its explanation, "over": key}``."""
    c = best.candidate
    if c.effect not in NONLINEAR_TERM_EFFECTS:
        return best, None
    names = set(term_variables(c))
    linear = [t for t in good
              if t.candidate.effect in LINEAR_TERM_EFFECTS and t.candidate.target == c.target
              and (t.candidate.info or {}).get("var") in names]
    if not linear:
        return best, None
    pick = max(linear, key=lambda t: t.comparison)
    lc = pick.candidate
    note = (f" Named before the nonlinear form {c.key} (2ΔELBO {best.comparison:.4g} against "
            f"{pick.comparison:.4g}) by the hierarchy principle: a variable's linear term comes "
            f"before its nonlinear terms, and {c.target_name} does not yet depend on "
            f"{lc.info['var']}; a further round (--max-rounds 2 or more) tests the nonlinear "
            "form on top of the linear term.")
    return pick, {"note": note, "over": c.key}


def alternatives_of(best: Trial, good: Sequence[Trial], nats: float = AMBIGUITY_NATS) -> tuple:
    """Accepted-quality refits (significant, converged, validated) of the same round that the
    records do not separate from the best: Vuong's test of non-nested models (:mod:`.vuong`,
    on the per-sample one-step predictive log-likelihoods) does not favour the best at
    :data:`.vuong.VUONG_ALPHA` — a z that favours the other one counts as not separated too,
    the ELBO and the predictions then disagree. Candidates of one round each extend the
    current model by different terms, so none nests another and the likelihood ratio has no
    χ² reference. Where the test is unavailable (a record without a steady-state filter),
    a comparison statistic (:attr:`Trial.comparison`) within ``2·nats`` of the best one's.
    Each alternative carries its test (:attr:`Trial.vuong`; both extend the current model, so
    their parameter counts differ by their new free parameters). A refit that is the best's
    own fitted model reached from another start (:func:`same_fitted_model`), or that of an
    alternative already listed, is not listed again."""
    from .vuong import vuong_test

    ll_best = trial_loglik(best)
    out = []
    for t in sorted(good, key=lambda t: -t.comparison if math.isfinite(t.comparison) else math.inf):
        if t is best or same_fitted_model(best, t) or any(same_fitted_model(o, t) for o in out):
            continue
        ll = None if ll_best is None else trial_loglik(t)
        v = None if ll is None else vuong_test(ll_best, ll, p1=best.dof, p2=t.dof)
        close = (not (v.z > 0.0 and v.separated()) if v is not None
                 else t.comparison >= best.comparison - 2.0 * nats)
        if close:
            out.append(t if v is None else dataclasses.replace(t, vuong=v))
    return tuple(sorted(out, key=lambda t: -t.comparison))


class ScreenTier(enum.Enum):
    """How a candidate is ranked for refitting (``rounds[].screen[].tier``).

    ``SCORE_TEST``: by the p-value of its score (Lagrange-multiplier) statistic at the
    current optimum (:mod:`.score`) — one scale for every tested candidate, whether it adds
    states or not. ``LOCATE``: no score statistic (not screenable, or the test could not
    be computed: its note says why); ranked after every tested candidate, by its locate
    score, never mixed into the p-value scale. ``ASCENT``: no statistic because the profiled
    curvature along the candidate's parameters is negative at the current optimum — a
    saddle of the candidate's ELBO, so the candidate certainly raises the ELBO and only a
    refit can say by how much; ranked by its locate score, refitted before every candidate
    whose score test is not significant (:func:`choose_refits`).
    """

    SCORE_TEST = "score_test"
    ASCENT = "ascent"
    LOCATE = "locate"


@dataclasses.dataclass(frozen=True)
class Ranked:
    """One examined candidate with its screening result."""

    candidate: Candidate
    locate_score: float
    screen: Any = None               # ScoreResult, or None when not screened

    @property
    def tier(self) -> ScreenTier:
        sr = self.screen
        if sr is not None and sr.statistic is not None and sr.dof >= 1 \
                and math.isfinite(sr.log10p):
            return ScreenTier.SCORE_TEST
        if sr is not None and sr.ascent:
            return ScreenTier.ASCENT
        return ScreenTier.LOCATE

    @property
    def priority(self) -> float:
        """−log10 p of the score test (tier SCORE_TEST), else the locate score."""
        return float(self.screen.log10p) if self.tier is ScreenTier.SCORE_TEST \
            else float(self.locate_score)

    def sort_key(self) -> tuple:
        """Tier first (tested, then ascent, then untested), then priority."""
        pr = self.priority
        return (_TIER_ORDER[self.tier], -pr if math.isfinite(pr) else math.inf)


_TIER_ORDER = {ScreenTier.SCORE_TEST: 0, ScreenTier.ASCENT: 1, ScreenTier.LOCATE: 2}


def screen_priority(loc_score: float, sr) -> float:
    """Screening priority within a tier (see :class:`Ranked`)."""
    return Ranked(None, loc_score, sr).priority


def _physics_check(t: "Trial") -> str:
    """The effect's comparison of the refit's estimates with physics
    (:meth:`.base.Effect.check_estimates`), "" without one or on any failure."""
    from .base import get_effect

    if t.state is None:
        return ""
    try:
        eff = get_effect(t.candidate.effect)
        fit = t.state.fit
        se = np.asarray(fit.std_errors, float)
        if stopped_at_kink(t):      # its finding says: estimates without standard errors
            se = np.full_like(se, np.nan)
        est = {n: (float(v), float(e) if math.isfinite(e) else None)
               for n, v, e in zip(fit.parameter_names, np.asarray(fit.theta, float), se)}
        return eff.check_estimates(t.candidate, est)
    except Exception:  # noqa: BLE001 - a remark must never break the decision
        return ""


def choose_refits(rows: Sequence[Ranked], *, max_candidates: int, min_score: float,
                  alpha: float, n_examined: int) -> list[Ranked]:
    """The candidates to refit, from ``rows`` sorted by :meth:`Ranked.sort_key`.

    First the best-ranked candidate of every effect class × target (``Candidate.effect``,
    ``Candidate.target``) whose score test clears the family-wise level of the round,
    ``p < α/m`` (Bonferroni over the ``m`` examined candidates, Holm's first level), so
    that competing explanations of one mismatch are all refitted and the refits, not the
    screening order, decide between them; then the candidates of tier ``ASCENT`` (the
    current optimum is a saddle of their ELBO: they certainly improve the fit, a
    non-significant score test says it will likely not); then the remaining rows in rank
    order with priority ≥ ``min_score``; at most ``max_candidates`` in all, in rank order.

    Past ``max_candidates``: a disturbance model (``info['disturbance']``, coloured
    turbulence), always; the sensor lag of a channel whose time skew or position is
    chosen; every other class × target best whose score statistic is
    within ``2·AMBIGUITY_NATS`` of the largest one. The statistic approximates its refit's
    Λ, and the round compares the refits' Λ with that margin (:func:`alternatives_of`), so
    such a candidate may be the best explanation or the alternative that makes the finding
    ambiguous; leaving it out lets the screening order decide. (lat_beta_vane_3_s0, a β
    vane 3 m ahead of the CG: its position was the fourth class at S = 71.7 against 77.1,
    not refitted with three candidates, and a side-force derivative was named.)
    """
    level = -math.log10(alpha / max(n_examined, 1))
    # ``min_score`` gates a priority, not the ascent tier: an ascent candidate's priority is
    # its locate score, and sp_phugoid_1_s1's speed dynamics (a saddle: ascent, locate score
    # 0.055) was never refitted while two non-significant score tests were
    eligible = [r for r in rows if r.tier is ScreenTier.ASCENT
                or (math.isfinite(r.priority) and r.priority >= min_score)]
    chosen: list[Ranked] = []
    bests: list[Ranked] = []
    classes: set = set()
    for r in eligible:
        cls = (r.candidate.effect, r.candidate.target)
        if r.tier is ScreenTier.SCORE_TEST and r.priority > level and cls not in classes:
            classes.add(cls)
            bests.append(r)
    chosen = bests + [r for r in eligible if r.tier is ScreenTier.ASCENT]
    chosen = chosen[:max_candidates]
    stat = {id(r): r.screen.statistic for r in bests
            if r.screen is not None and r.screen.statistic is not None
            and math.isfinite(r.screen.statistic)}
    if stat:
        top = max(stat.values())
        first = {id(r) for r in chosen}
        chosen += [r for r in bests if id(r) not in first and id(r) in stat
                   and stat[id(r)] >= top - 2.0 * AMBIGUITY_NATS]
    taken = {id(r) for r in chosen}
    for r in eligible:
        if len(chosen) >= max_candidates:
            break
        if id(r) not in taken:
            chosen.append(r)
    # a disturbance model (coloured turbulence: a gust state) is refitted in every round,
    # whatever its rank: a physical candidate is accepted only where it beats it (an
    # independent short-period null record with Dryden turbulence of 1.7 s correlation time:
    # the α gust, not refitted in round 1, was 1014 nats better than the accelerometer arm
    # round 1 accepted at 27.4, session 48)
    taken = {id(r) for r in chosen}
    targets = {r.candidate.target for r in chosen if (r.candidate.info or {}).get("disturbance")}
    for r in rows:
        if (r.candidate.info or {}).get("disturbance") and id(r) not in taken \
                and r.candidate.target not in targets:
            targets.add(r.candidate.target)
            chosen.append(r)
    # a sensor's lag is refitted beside a time skew or a position of the same channel: to
    # first order in frequency the three are one term (an independent short-period record
    # with a 0.15-s α-vane lag: a vane position of 6.9 m was named, then two output
    # derivatives of α absorbed the attenuation the position cannot give, session 48)
    taken = {id(r) for r in chosen}
    rivals = {r.candidate.target for r in chosen
              if r.candidate.effect in ("time_skew", "sensor_position")}
    for r in rows:
        if r.candidate.effect == "sensor_lag" and r.candidate.target in rivals \
                and id(r) not in taken:
            rivals.discard(r.candidate.target)
            chosen.append(r)
    pos = {id(r): i for i, r in enumerate(rows)}
    return sorted(chosen, key=lambda r: pos[id(r)])


def select_candidates(info: ModelInfo, evidence: Evidence, effects: Sequence[Effect],
                      current: FitState | None, *, max_candidates: int, min_score: float,
                      screen: bool, alpha: float = 0.01, workdir: pathlib.Path | None = None,
                      generated_dir=None, progress=None, engine=None,
                      deadline: float | None = None, exclude: frozenset = frozenset()):
    """(selected [(priority, locate score, Candidate, ScoreResult|None)], n examined, table).

    ``exclude``: keys of candidates already accepted in earlier rounds, not proposed again (a
    second gyro scale factor on q, a second lag of the same sensor: the same term twice;
    they took refit slots of rounds the time limit then cut, independent short-period
    simulator, session 48).

    Every candidate gets its locate score; with ``screen`` every screenable one also gets
    its score statistic at the current fit (:func:`.score.screen`, candidates that add
    states included; its batches run on ``engine``'s workers when given). The table ranks
    them by :meth:`Ranked.sort_key`; the refitted ones are chosen by :func:`choose_refits`.
    """
    from .refit import REFIT_DETERMINISTIC_STD
    from .score import screen as score_screen

    every = [(s, c) for s, c in rank_candidates(info, evidence, effects, max_candidates=10 ** 9,
                                                 min_score=-math.inf) if c.key not in exclude]
    scores = {}
    if screen and current is not None and current.fit.decision is not None and every:
        scores = score_screen([c for _, c in every], current, info, workdir,
                              f"{safe_name(current.model.name)[:30]}_sc",
                              generated_dir=generated_dir, det_std=REFIT_DETERMINISTIC_STD,
                              progress=progress, engine=engine, deadline=deadline)
    rows = sorted((Ranked(c, loc, scores.get(c.key)) for loc, c in every),
                  key=Ranked.sort_key)
    chosen = choose_refits(rows, max_candidates=max_candidates, min_score=min_score,
                           alpha=alpha, n_examined=len(every))
    picked = {id(r) for r in chosen}
    table = [{"key": r.candidate.key, "effect": r.candidate.effect,
              "target": r.candidate.target, "tier": r.tier.value, "priority": _f(r.priority),
              "locate_score": _f(r.locate_score), "refitted": id(r) in picked,
              "score_test": None if r.screen is None else r.screen.to_json()} for r in rows]
    return ([(r.priority, r.locate_score, r.candidate, r.screen) for r in chosen], len(every),
            table)


# ---------------------------------------------------------------------------
# the job
# ---------------------------------------------------------------------------

def _refit_task(c, current, info, path, name, generated_dir, max_iter, group=None, *,
                model=None):
    """One candidate's staged refit (runs on an engine worker); (RefitOutcome, messages).

    ``group`` (a :class:`.gated.GatedGroup`): refit it as a fit of the round's gated model
    (compiled once per process and round) and write its own spec at ``path``. ``model``:
    the candidate's model, already loaded from ``path`` (a family member)."""
    from .refit import compile_seconds

    msgs: list[str] = []
    c0 = compile_seconds()
    if group is None:
        ro = staged_refit(c, current, info, path, name, generated_dir=generated_dir,
                          max_iter=max_iter, progress=msgs.append, model=model)
    else:
        from .gated import candidate_spec, gated_refit

        ro = gated_refit(c, current, group, path, generated_dir=generated_dir,
                         max_iter=max_iter, progress=msgs.append)
        candidate_spec(c, ro.state, current, info, path, name)
    return dataclasses.replace(ro, compile_s=compile_seconds() - c0), msgs


def _family_task(members, current, info, generated_dir, max_iter, deadline=None):
    """The staged refits of ``members`` [(candidate, spec path, model name)], candidates of
    one shape that add states, as fits of one :class:`~vsidgen.estimator.ModelFamily` (one
    compilation for all; :mod:`.family`). Runs on an engine worker; one
    :class:`~vsidgen.engine.TaskOutcome` per member: DONE with ``_refit_task``'s value,
    FAILED with the error of a refit that raised, CANCELLED for the members not started
    when ``deadline`` (a :class:`.family.TaskDeadline`) had passed. Models that cannot form
    a family are refitted with their own compilations."""
    import contextlib

    from ..engine import TaskOutcome, TaskStatus, error_line
    from ..estimator import ModelFamily
    from ..model import load_model

    models, broken = [], {}          # a member whose spec cannot be built fails alone
    for c, path, name in members:
        t0 = time.perf_counter()
        try:
            write_candidate(c, current, info, pathlib.Path(path), name)
            models.append(load_model(path, generated_dir=generated_dir))
        except Exception as err:  # noqa: BLE001 - as the engine reports a failed task
            models.append(None)
            broken[c.key] = TaskOutcome(c.key, TaskStatus.FAILED, error=error_line(err),
                                        wall_s=time.perf_counter() - t0)
    try:
        family = ModelFamily([m for m in models if m is not None])
    except FitError:
        family = None
    out = []
    with family.active() if family is not None else contextlib.nullcontext():
        for (c, path, name), m in zip(members, models):
            if m is None:
                out.append(broken[c.key])
                continue
            if deadline is not None and deadline.passed():
                out.append(TaskOutcome(c.key, TaskStatus.CANCELLED, error="time limit reached"))
                continue
            t0 = time.perf_counter()
            try:
                value = _refit_task(c, current, info, path, name, generated_dir, max_iter,
                                    model=m)
            except Exception as err:  # noqa: BLE001 - one member's failure is its own outcome
                out.append(TaskOutcome(c.key, TaskStatus.FAILED, error=error_line(err),
                                       wall_s=time.perf_counter() - t0))
            else:
                out.append(TaskOutcome(c.key, TaskStatus.DONE, value=value,
                                       wall_s=time.perf_counter() - t0))
    return out


def _round_task(kind, deadline, *args):
    """An engine task of a round's refits: ``"one"`` candidate (:func:`_refit_task`) or a
    ``"family"`` of candidates that add states (:func:`_family_task`), its fits stopped at
    ``deadline`` (a :class:`.family.TaskDeadline`, the round's refit deadline; None: none,
    :func:`.fitstate.refit_deadline`)."""
    from .fitstate import refit_deadline

    with refit_deadline(deadline):
        if kind == "family":
            return _family_task(*args, deadline=deadline)
        return _refit_task(*args)


def _projected_task(t, current, path, name, generated_dir, max_iter, group=None):
    """One trial's projected refit (runs on an engine worker); a FitState."""
    if group is not None:
        from .gated import gated_projected

        return gated_projected(t.candidate, t.state, current, group, path,
                               generated_dir=generated_dir, max_iter=max_iter)
    return projected_refit(t, current, path, name, generated_dir=generated_dir, max_iter=max_iter)


def _trial_of(oc, c, score, sr, path, current) -> Trial:
    """The Trial of a finished refit task (an error trial when it failed or was lost)."""
    from ..engine import TaskStatus

    if oc.status is not TaskStatus.DONE:
        return Trial(c, score, path, None, math.nan, c.n_free, 1.0,
                     error=f"{oc.status.value}: {oc.error}", screen=sr)
    ro, _ = oc.value
    st = ro.state
    lam, p = lr_test(ro.elbo_ref, st.elbo, c.n_free)
    return Trial(c, score, path, st, lam, c.n_free, p, refit=ro,
                 statistic_vs_base=2.0 * (st.elbo - current.elbo),
                 converged=refit_converged(st.fit), screen=sr,
                 verdict=trial_verdict(c, st, lam, ro))


def _grid_size(c: Candidate) -> int:
    """Number of delays profiled for a transport-delay candidate (0 for any other)."""
    return len(((c.info or {}).get("profile_result") or {}).get("grid_s") or ())


def _search_size(t: Trial) -> int:
    """How many values of an input filter's time parameter were searched before its refit,
    for ranking alternatives: a transport delay's profile grid (:func:`_grid_size`), a lag's
    or Padé delay's screened time constants (its score test's ``multiplicity``); 1 for every
    other candidate. The three filters of one input are alternatives of one parameter each,
    each found by a search over its time: ranking them with the delay's search alone
    penalised (``sp_de_delay_0.04_s0``: the true delay 214.9 over the current model, a lag
    211.2 named first) tilts the choice by the size of the delay's grid."""
    g = _grid_size(t.candidate)
    if g:
        return g
    if t.candidate.effect in ("actuator_lag", "control_delay") and t.screen is not None:
        return max(int(getattr(t.screen, "multiplicity", 1) or 1), 1)
    return 1


def hold_alternative(current, path: pathlib.Path, name: str, *, engine, generated_dir,
                     max_iter: int, deadline=None):
    """``current`` refitted (warm, on the engine) with :func:`.numerics.accurate_alternative`
    of its setting — the other input hold (zero ↔ first order) for RK4, RK4 with a first-order
    hold for Euler: a FitState, or None when the refit failed or the time ran out."""
    from ..engine import TaskStatus
    from .numerics import NumericsSetting, accurate_alternative, refit_setting

    cur = NumericsSetting.of(current.model)
    other = accurate_alternative(cur)
    oc = engine.run(refit_setting, [(f"hold:{other.inputs}", (other, current, path, name,
                                                               generated_dir, max_iter))],
                    deadline=deadline)[0]
    return oc.value if oc.status is TaskStatus.DONE else None


def delay_trial(c, score, current, path, name, *, engine, generated_dir, max_iter,
                deadline, screen=None, alpha: float = 0.01) -> Trial | None:
    """The Trial of a transport-delay candidate: its profile (:mod:`.delay`), the refit at the
    estimate and the test (Bonferroni over the grid; None when the time ran out).
    ``screen``: its :class:`.score.ScoreResult` (:func:`.score.screen_input_filters`); the profile
    starts at its best grid delay.

    How the records' inputs move between samples decides what the spec's delay means: a
    zero-order hold already delays an input that moves continuously by half a sample
    (:func:`.delay.hold_lag`), and adds nothing to one that steps at the samples. Whether the
    inputs step or move cannot be read off the fits without the delay (the hold's own half
    sample absorbs part of a delay, so a zero-order hold fits a delayed record better even
    when its inputs move continuously). So when the two holds time the input differently, the
    delay is profiled under both — the other one refitted first (:func:`hold_alternative`) and
    profiled from the delay that gives the same timing. An input is taken to move
    continuously (a control surface cannot step; first-order hold) unless the zero-order hold
    fits significantly better at its own best delay (2ΔELBO above the χ²₁ quantile at
    ``alpha``: the inputs step at the samples, and the hold adds no delay). That decides the
    spec (it carries the chosen ``integrator.inputs``) and the physical delay. The statistic
    stays the one against the current model (the hold change counted in the gain)."""
    from .delay import delay_p_value, hold_lag, profile_delay
    from .numerics import NumericsSetting, accurate_alternative
    from .refit import RefitOutcome

    u = c.info["input"]
    j = list(current.model.input_names).index(u)
    if float(getattr(current.model.inputs[j], "delay", 0.0) or 0.0) > 0.0:
        return Trial(c, score, path, None, math.nan, 1, 1.0, screen=screen,
                     error=f"the model already delays {u}")
    dt = float(np.median([r.dt for r in current.records]))
    base = current
    try:
        start = (screen.step or {}).get("tau_s") if screen is not None \
            and screen.statistic is not None else None
        prof = profile_delay(current, u, path, name, engine=engine, generated_dir=generated_dir,
                             max_iter=max_iter, deadline=deadline, start=start)
        if prof is None:
            return None
        hold_note = None
        cur_set = NumericsSetting.of(current.model)
        alt_set = accurate_alternative(cur_set)
        alt_hold = alt_set.inputs
        alt = None
        if not prof.at_zero and prof.state is not None:
            lag0, lag1 = hold_lag(current.model, dt), alt_set.hold_lag(dt)
            if lag0 != lag1 or alt_set.method != cur_set.method:
                hpath = path.with_name(f"{path.stem}_hold_{alt_hold}.yaml")
                alt = hold_alternative(current, hpath, f"{name}_h", engine=engine,
                                       generated_dir=generated_dir, max_iter=max_iter,
                                       deadline=deadline)
        if alt is not None:
            dpath = path.with_name(f"{path.stem}_{alt_hold}.yaml")
            prof2 = profile_delay(alt, u, dpath, f"{name}_{alt_hold}", engine=engine,
                                  generated_dir=generated_dir, max_iter=max_iter,
                                  deadline=deadline,
                                  start=max(prof.estimate + lag0 - lag1, 0.5 * dt))
            if prof2 is None:
                return None
            if prof2.state is not None and not prof2.at_zero:
                d = 2.0 * (prof2.state.elbo - prof.state.elbo)
                hold_note = (alt_hold, d, prof.estimate, prof2.estimate, cur_set, alt_set)
                # an input moves continuously (a control surface cannot step) unless the
                # records say otherwise: the zero-order hold is kept only when it fits
                # significantly better (chi2_1 at alpha; with the delay absorbing the hold's
                # half sample the two differ only where the inputs change within a sample)
                zoh_gain = d if alt_hold == "zoh" else -d
                use_zoh = zoh_gain > float(stats.chi2.isf(alpha, 1))
                if use_zoh == (alt_hold == "zoh"):
                    prof, base, path = prof2, alt, dpath
    except (FitError, SpecError, VsidgenError, ValueError, ArithmeticError) as err:
        return Trial(c, score, path, None, math.nan, 1, 1.0, screen=screen,
                     error=f"failed: {str(err).splitlines()[0]}")
    if prof.at_zero:
        # no delay: every delayed fit is below the current model (τ = 0); nothing to refit
        c0 = dataclasses.replace(c, info={**c.info, "profile_result": prof.to_json()})
        best = max((e for e in prof.elbos if math.isfinite(e)), default=math.nan)
        return Trial(c0, score, path, None, 0.0, 1, 1.0, screen=screen,
                     refit=RefitOutcome(elbo_ref=current.elbo, warm="delay profile",
                                        notes=[f"profile highest at τ = 0 (the current model): "
                                               f"best delayed fit {best - current.elbo:+.4g} nats"
                                               ], wall_s=prof.wall_s))
    if prof.state is None:
        return Trial(c, score, path, None, math.nan, 1, 1.0, screen=screen,
                     error="failed: no grid fit or final refit succeeded")
    st = prof.state
    lam = 2.0 * (st.elbo - current.elbo)
    hold = getattr(base.model, "input_hold", "zoh") or "zoh"
    # a zero-order hold that fits better than a first-order one, both with their delays,
    # says the inputs step at the samples: the hold then adds no delay of its own
    stepped = hold_note is not None and hold == "zoh"
    lag = 0.0 if stepped else hold_lag(base.model, dt)
    ent = {"name": f"D_DELAY_{u}", "estimate": prof.estimate + lag,
           "std_error": prof.std_error if math.isfinite(prof.std_error) else None, "unit": "s",
           "spec_value": prof.estimate, "hold_lag": lag, "inputs_held": stepped,
           "input_hold": hold,
           "integrator_method": getattr(base.model, "integrator", "euler") or "euler"}
    if hold_note is not None:
        ent["hold_comparison"] = {"current_hold": hold_note[4].inputs,
                                  "other_hold": hold_note[0],
                                  "current": hold_note[4].to_json(),
                                  "other": hold_note[5].to_json(),
                                  "two_delta_elbo_other_minus_current": hold_note[1],
                                  "spec_delay_current_hold": hold_note[2],
                                  "spec_delay_other_hold": hold_note[3]}
    from .base import get_effect
    text = get_effect(c.effect).explain(input=u, delay=f"{prof.estimate + lag:.4g}",
                                        spec_delay=f"{prof.estimate:.4g}")
    if hold_note is not None:
        other, d = hold_note[0], hold_note[1]
        zoh_gain = d if other == "zoh" else -d
        thr = float(stats.chi2.isf(alpha, 1))
        both = ("both input holds" if hold_note[4].method == hold_note[5].method else
                f"{hold_note[4].text} and {hold_note[5].text} (one Euler step per sample has "
                "a phase error of the order of the hold's half sample)")
        if hold == "zoh":
            text += (f" Profiled under {both}, the zero-order hold (inputs held over "
                     f"each sample) fits better than a first-order hold at its own best delay "
                     f"by 2ΔELBO = {zoh_gain:.4g} > {thr:.4g}.")
        else:
            text += (f" Profiled under {both}, a zero-order hold at its own best "
                     f"delay fits {'better' if zoh_gain > 0 else 'worse'} by 2ΔELBO = "
                     f"{abs(zoh_gain):.4g}"
                     + (f", not significantly (≤ {thr:.4g})" if zoh_gain > 0 else "")
                     + ": the inputs are taken to move continuously between samples "
                       "(first-order hold, `integrator: {"
                     + ("method: rk4, " if getattr(base.model, "integrator", "") == "rk4"
                        and hold_note[4].method != "rk4" else "") + "inputs: foh}`"
                     + ("; the spec uses it)." if other == "foh" else ")."))
    if stepped:
        text += (" The records' inputs move in steps at the samples, so the model's hold adds "
                 f"no delay of its own: the transport delay is the spec's {prof.estimate:.4g} s.")
    elif lag > 0:
        text += (f" The model's transition uses {u} at the start of each step, which by itself "
                 f"delays it by {lag:.4g} s on average; the spec's delay is therefore "
                 f"{prof.estimate:.4g} s for a physical transport delay of "
                 f"{prof.estimate + lag:.4g} s.")
    if (getattr(base.model, "integrator", "euler") == "euler"
            and int(getattr(base.model, "substeps", 1) or 1) == 1):
        text += (" The model integrates with one Euler step per sample, whose own phase error is "
                 "of the order of a sample too: the physical value is reliable only with an "
                 "accurate integrator (integrator: {method: rk4}).")
    c2 = dataclasses.replace(c, explanation=text,
                             info={**c.info, "delay": ent, "profile_result": prof.to_json()})
    ro = RefitOutcome(state=st, elbo_ref=current.elbo, warm="delay profile",
                      notes=[f"profile over {sum(map(math.isfinite, prof.elbos))} of "
                             f"{len(prof.grid)} grid delays ({hold} hold); best grid value "
                             f"{prof.best_grid:.4g} s, refined {prof.estimate:.4g} s"],
                      wall_s=prof.wall_s)
    return Trial(c2, score, path, st, lam, 1, delay_p_value(lam, len(prof.grid)), refit=ro,
                 statistic_vs_base=lam, converged=refit_converged(st.fit), screen=screen,
                 verdict=refit_verdict(lam, {ent["name"]: prof.estimate}, {},
                                       {ent["name"]: prof.grid[-1]},
                                       {ent["name"]: prof.std_error}))


def run_diagnose(spec, data, *, validate=(), out, max_rounds: int = 3, max_candidates: int = 8,
                 alpha: float = 0.01, min_score: float = 1.0, effects: Sequence[str] | None = None,
                 effects_module=None, max_iter: int = 200, screen: bool = True,
                 time_limit: float | None = None, workers: int | None = 1,
                 scheduler: str | None = None, numerics: bool = True, gated: bool = True,
                 noise_model: bool = True, gust_noise: bool = False, gust_check: bool = True,
                 progress: Callable[[str], None] | None = None,
                 overwrite: bool = False, overrides=None) -> DiagnoseResult:
    """Locate, explain, model and confirm discrepancies of ``spec`` on ``data``.

    Writes ``out/findings.json``, ``out/diagnose.html`` (report section, also
    returned in the document), ``out/candidates/*.yaml`` (every refitted
    candidate spec) and ``out/generated/`` (their compiled modules), directly into
    ``out`` with a manifest (:func:`vsidgen.atomic.results_in_place`): ``out`` is
    checked before any computation, and a non-empty directory that is not a
    vsidgen results directory needs ``overwrite`` (its other files are kept).
    ``overrides`` (:class:`vsidgen.spec.overrides.Overrides`, from ``--fix`` etc.):
    the fits use ``out/overrides.yaml``, a spec that extends ``spec`` with them.

    Nothing found is lost: ``findings.json`` is rewritten (atomically) after every
    refit and ``diagnose.html`` after every round, with the accepted findings, the
    finished rounds and the state of the unfinished one (candidates refitted, pending);
    ``stop.reason`` says whether the run completed, is still running, ran out of
    ``time_limit`` seconds (no refit starts after it; running ones are abandoned) or was
    interrupted (KeyboardInterrupt, re-raised after the files are written). An effect is
    only accepted at the end of a round, so an unfinished round accepts nothing.

    The candidates of a round are independent refits: ``workers`` > 1 (None: every local
    core) runs them on a local ``dask.distributed`` cluster, ``scheduler`` on an existing
    one (see :mod:`vsidgen.engine`); ``workers=1`` runs them in this process. Both give
    the same findings.

    ``numerics``: before any physics candidate the current model is refitted with other
    integrator settings (rk4, sub-steps, first-order hold of the inputs; :mod:`.numerics`);
    a setting that removes a significant part of the mismatch is adopted for the rest of
    the run and reported as a modelling-numerics finding (``findings.json`` → ``numerics``).

    ``noise_model``: then, still before any physics candidate, the current model is refitted
    with correlated process noise (a full factor G on the same states; :mod:`.noisemodel`);
    when 2ΔELBO exceeds χ²_k at ``alpha`` (k added off-diagonal entries) it is adopted for
    the rest of the run and reported as a noise-model finding (``findings.json`` →
    ``noise_model``), never as a physical effect.

    ``gust_noise`` (off by default): after it, a model whose flow angles and airspeed are
    definitions of its velocity states is refitted with a gust state in those definitions
    (turbulence in the air-relative velocity, :mod:`.gust`) and adopts it when significant
    (``findings.json`` → ``noise_gust``). Off by default: on the independent benchmark's
    body-axis model it is adopted on every record (2ΔELBO ≈ 400), but its larger model slows
    the refits and a true curved lift (``hfbb_lift_square_2_s1``) left the round's refitted
    set (docs/diagnose.md, session 38).

    ``gust_check`` (default; without ``gust_noise``): the same alternative is tested when a
    round is about to accept a physical effect on such a model, and only then — as a rival
    explanation of the lead's gain (:func:`_gust_check`). When the gust is significant it is
    adopted as the noise model and the lead is refitted on it; the lead is accepted only if
    it is still significant there (same threshold), else it is reported as explained by the
    turbulence and the next round searches on the gust model. (On the benchmark's body-axis
    null records a pitch mode driven by q was named at 2ΔELBO 25–26 against 19.2 without the
    gust and 7.0 with it.)

    ``gated`` (default): the candidates of a round that add no state are refitted as
    fits of one gated model (:mod:`.gated`; compiled once per round and process, the other
    candidates' terms fixed at their nesting values), and those that add states of one
    shape as one model family per worker (:mod:`.family`); ``False`` compiles every
    candidate's own model (the reference path). Both give the same findings up to the
    optimizer's tolerance.

    Raises:
        VsidgenError: bad spec, data, options or effect plugin.
    """
    from .. import __version__
    from ..engine import Engine
    from .findings import build_document, write_findings

    if not data:
        raise VsidgenError("no data records given: `vsidgen diagnose SPEC DATA [DATA...] --out DIR`")
    if not (0 < alpha < 1):
        raise VsidgenError(f"--alpha must be in (0, 1), got {alpha}")
    if not math.isfinite(min_score):
        raise VsidgenError(f"--min-score must be a finite number, got {min_score}")
    if max_rounds < 0 or max_candidates < 1:
        raise VsidgenError("--max-rounds must be >= 0 and --max-candidates >= 1")
    if time_limit is not None and not (time_limit > 0 and math.isfinite(time_limit)):
        raise VsidgenError(f"--time-limit must be a positive number of seconds, got {time_limit}")
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
    if max_iter < 1:
        raise VsidgenError(f"--max-iter must be >= 1, got {max_iter}")
    from ..data import as_paths

    data, validate = as_paths(data), as_paths(validate)
    engine = Engine(workers=workers, scheduler=scheduler)
    for p in list(data) + list(validate):
        check_input_file(p, what="data file")
    init_from = getattr(overrides, "init_from", None)
    plan = plan_output_dir(out, overwrite=overwrite,
                           reads=[spec, *data, *validate, *([init_from] if init_from else [])])
    print_recovered(plan)
    from ..data import load_record
    from ..spec import compile_spec

    symbolic = compile_spec(spec)  # bad records are refused before any fit
    if overrides is not None and not overrides.empty:
        from ..spec.overrides import apply_overrides

        apply_overrides(symbolic, overrides)  # unknown names, bounds
    for p in list(data) + list(validate):
        load_record(symbolic, p)
    # the cluster is reached before the previous results are cleared (an unreachable
    # --scheduler cost them: red team, session 47); the run enters the engine again
    with engine, results_in_place(plan, command="diagnose", owns=DIAGNOSE_OUTPUTS) as out:
        if overrides is not None and not overrides.empty:
            from ..spec.overrides import write_override_spec

            spec = write_override_spec(spec, overrides, out)
        return _run_diagnose(spec, data, validate=validate, out=out, max_rounds=max_rounds,
                             max_candidates=max_candidates, alpha=alpha, min_score=min_score,
                             catalogue=catalogue, max_iter=max_iter, screen=screen,
                             progress=progress, version=__version__,
                             build_document=build_document, write_findings=write_findings,
                             time_limit=time_limit, engine=engine, numerics=numerics,
                             gated=gated, noise_model=noise_model, gust_noise=gust_noise,
                             gust_check=gust_check)


@dataclasses.dataclass(frozen=True)
class _RunConfig:
    """The fixed settings of one diagnose run (what every phase reads, nothing it writes)."""

    out: pathlib.Path
    gen: pathlib.Path
    data: Sequence
    validate: Sequence
    catalogue: Sequence[Effect]
    max_rounds: int
    max_candidates: int
    alpha: float
    min_score: float
    max_iter: int
    screen: bool
    numerics: bool
    gated: bool
    noise_model: bool
    gust_noise: bool
    gust_check: bool
    time_limit: float | None
    deadline: float | None          # time.monotonic() value after which no refit starts
    engine: Any
    progress: Callable[[str], None] | None
    version: str
    build_document: Callable
    write_findings: Callable
    options: dict
    t_start: float                  # time.perf_counter() at the start of the run
    compile0: float                 # refit.compile_seconds() at the start of the run

    def past_deadline(self) -> bool:
        return self.deadline is not None and time.monotonic() >= self.deadline

    def say(self, msg: str) -> None:
        _say(self.progress, msg)


@dataclasses.dataclass
class _RunState:
    """What a diagnose run has found so far; every checkpoint writes it.

    ``base``/``evidence0``: the base fit and its locate evidence (None until done);
    ``current``/``evidence``: the model the next round extends and its evidence;
    ``rounds``: the finished rounds' records; ``accepted``: (trial, fit it was tested
    against, that fit's evidence) per accepted effect; ``unfinished``: the record of the
    round under way (None between rounds); ``numres``: the integrator-settings stage;
    ``noiseres``: the noise-model stage; ``partial_round``: the round the time limit cut
    and that was decided on the candidates refitted (:func:`_run_round`), or None.
    """

    base: FitState | None = None
    current: FitState | None = None
    evidence0: Evidence | None = None
    evidence: Evidence | None = None
    numres: Any = None
    noiseres: Any = None
    #: the noise model re-tested after a round accepted an effect: (round, NoiseModelResult)
    noise_retests: list = dataclasses.field(default_factory=list)
    gustres: dict | None = None          # the air-relative gust alternative (.gust.to_json)
    rounds: list[dict] = dataclasses.field(default_factory=list)
    accepted: list[tuple[Trial, FitState, Evidence]] = dataclasses.field(default_factory=list)
    unfinished: dict | None = None
    partial_round: dict | None = None
    #: the reference of every refit when the model has states without process noise
    #: (:func:`_held_reference`), else None
    reference: dict | None = None


class _RoundEnd(enum.Enum):
    """How one round of :func:`_run_round` ended."""

    ACCEPTED = "accepted"          # an effect was accepted: the next round extends it
    DONE = "done"                  # nothing to refit or nothing accepted: the search ends
    TIME_LIMIT = "time_limit"      # the time limit cancelled a refit of the round
    NOISE_MODEL = "noise_model"    # the round's lead was explained by a noise model, which
                                   # was adopted: the next round searches on it


@dataclasses.dataclass(frozen=True)
class _RoundPlan:
    """The refits of one round: ``ranked`` as from :func:`select_candidates`, the spec path
    of each, the indices of the profiled delays, the gated model of each gated candidate's
    key, the engine tasks of the other refits (one candidate each, or a family of
    candidates that add states: :mod:`.family`), ``by_key``: key → (index, locate score,
    candidate, score result), and ``families``: family task key → its candidates' keys."""

    ranked: list
    paths: list[pathlib.Path]
    profiled: list[int]
    groups: dict
    tasks: list
    by_key: dict
    families: dict = dataclasses.field(default_factory=dict)
    deadline: float | None = None    # time.monotonic() after which the round's refits stop

    @property
    def n_refits(self) -> int:
        """Number of candidates the engine tasks refit."""
        return sum(len(self.families.get(k, (k,))) for k, _ in self.tasks)

    def next_refitted(self, pending) -> str | None:
        """The first key of ``pending`` that an engine task refits (a profiled delay is not an
        engine task of its own)."""
        return next((k for k in pending if self.by_key[k][0] not in self.profiled), None)

    def task_rank(self, key: str) -> int:
        """Rank index of an engine task: its candidate's, or a family's first member's."""
        return min(self.by_key[k][0] for k in self.families.get(key, (key,)))

    def outcomes(self, oc) -> list:
        """The per-candidate outcomes of a finished engine task (:func:`.family.member_outcomes`)."""
        from .family import member_outcomes

        return member_outcomes(oc, self.families.get(oc.key, ()))


def _round_name(current: FitState, rnd: int, tag) -> str:
    """Model name of a spec written in round ``rnd`` from the current model."""
    return f"{safe_name(current.model.name)[:30]}_dg{rnd}_{tag}"


def _document(run: _RunConfig, st: _RunState, stop: StopReason) -> dict:
    """The findings document of the run so far (:func:`.findings.build_document`) with the
    compile time spent in this process and in the refits."""
    from .refit import compile_seconds

    doc = run.build_document(base=st.base, final=st.current, accepted=st.accepted,
                             rounds=st.rounds, evidence=st.evidence0,
                             final_evidence=st.evidence, alpha=run.alpha, version=run.version,
                             wall_time_s=time.perf_counter() - run.t_start, out=run.out,
                             options=run.options,
                             stop={"reason": stop.value, "time_limit_s": run.time_limit,
                                   **({"partial_round": st.partial_round}
                                      if st.partial_round else {})},
                             unfinished_round=st.unfinished,
                             numerics=None if st.numres is None else st.numres.to_json(),
                             noise_model=None if st.noiseres is None else st.noiseres.to_json(),
                             noise_retests=[{"after_round": k, **r.to_json()}
                                            for k, r in st.noise_retests],
                             noise_gust=st.gustres)
    # the fit every refit is compared with: states without process noise held like the
    # refits', or (not converged) the exact limit, which favours the refits
    doc["reference"] = st.reference
    refit_c = [t["refit"].get("compile_s") for r in st.rounds for t in r.get("trials", ())
               if t.get("refit")]
    doc["compile_s"] = {"this_process": round(compile_seconds() - run.compile0, 2),
                        "refits": round(sum(c for c in refit_c if c is not None), 2)}
    return doc


def _checkpoint(run: _RunConfig, st: _RunState, stop: StopReason, *,
                report: bool = True) -> dict:
    """Write ``findings.json`` (and with ``report`` ``diagnose.html``); the document."""
    from .findings import write_findings_json

    doc = _document(run, st, stop)
    if report:
        run.write_findings(run.out, doc, base=st.base, final=st.current, accepted=st.accepted)
    else:
        write_findings_json(run.out, doc)
    return doc


def _fit_base(run: _RunConfig, st: _RunState, spec) -> None:
    """Fit the base spec (continued once when unconverged) and locate its mismatch."""
    from ..spec import compile_spec
    from ..spec.identifiability import symmetry_warnings
    from ..spec.symbolic import data_map_warnings

    sym = compile_spec(spec)
    for w in data_map_warnings(sym):
        run.say(str(w))       # a column read in another unit than its name says
    for w in symmetry_warnings(sym):
        run.say(str(w))       # a combination the data cannot separate: the base fit may stall
    run.say(f"fitting the base model {spec}")
    base = fit_spec(spec, run.data, validate=run.validate, generated_dir=run.gen,
                    max_iter=run.max_iter)
    for w in (w for r in tuple(base.records) + tuple(base.vrecords or ()) for w in r.warnings):
        run.say(str(w))       # the records' data warnings (units, constants, missing samples)
    if not base.fit.converged and not run.past_deadline():
        base = polish(base, max_iter=run.max_iter, progress=run.progress)
    base = _held_reference(run, spec, base, st)
    st.base = st.current = base
    st.evidence0 = st.evidence = locate_state(base)
    run.say("locate:\n" + st.evidence0.summary())
    _checkpoint(run, st, StopReason.RUNNING)


def _limit_left(deadline: float | None) -> dict:
    """``{"limit_left": seconds}`` to a round's refit deadline (a ``time.monotonic()``
    instant, :func:`round_refit_deadline`) for the progress line; empty without one."""
    if deadline is None:
        return {}
    left = deadline.left() if hasattr(deadline, "left") else float(deadline) - time.monotonic()
    return {"limit_left": float(left)}


def _undecided_json(t: "Trial") -> dict:
    """A refit of a round not decided yet, as the unfinished round lists it: its test has no
    Holm threshold before the round ends, so ``significant`` is null (undecided), not false."""
    d = t.to_json()
    if d.get("threshold") is None:
        d["significant"] = None
    return d


def _held_reference(run: _RunConfig, spec, base: FitState, st: "_RunState") -> FitState:
    """The base fit every refit is compared with, at the refits' process noise.

    A state the user's model gives no process noise (θ̇ = q, φ̇ = p) is fitted in the exact
    limit of vanishing process noise by ``vsidgen fit`` and by the base fit here; the refits
    hold it quasi-deterministic instead (a small fixed std, :func:`.fitstate.diag_options`,
    like the states candidates add): the limit at every refit would cost its continuation.
    A refit's 2ΔELBO against the limit's ELBO would then count the difference between the two
    noise levels as the candidate's gain (a new user's HFB-320 model with θ̇ = q: base 12995.0
    in the limit, 13438.6 held, so every candidate, and the integrator settings, gained ~900
    on the difference alone). The base is therefore refitted once, warm, with those states
    held like the refits' (the limit's ELBO is said, and kept in the base fit's notes);
    without such states, or when that refit does not converge, ``base`` itself.
    """
    res = base.fit
    if not getattr(res, "deterministic_states", ()) or getattr(res, "deterministic_limit", None) is None:
        return base
    names = ", ".join(res.deterministic_states)
    if run.past_deadline():
        return base          # no refit will be compared with it
    try:
        held = refit_warm(pathlib.Path(spec), base, base, generated_dir=run.gen,
                          iterations=2 * run.max_iter, max_iter=run.max_iter, keep_theta=True)
    except (VsidgenError, ValueError, ArithmeticError, np.linalg.LinAlgError) as exc:
        run.say(f"the base fit with {names} held quasi-deterministic failed ({exc}); refits are "
                f"compared with the limit fit, which favours them")
        return base
    if not refit_converged(held.fit) and not run.past_deadline():
        # continued once from where it stopped, as the base fit is (a new user's model: the
        # held fit stopped at 800 iterations, and the refits were then measured against the
        # limit's ELBO: an integrator setting's 2ΔELBO came out 1406 where it is ~160)
        more = polish(held, max_iter=run.max_iter, progress=run.progress)
        if more.elbo >= held.elbo:
            held = more
    if not refit_converged(held.fit):
        st_note = (f"the base fit with {names} held quasi-deterministic did not converge "
                   f"({held.fit.status}); refits are compared with the limit fit (ELBO "
                   f"{res.elbo:.6g}; the held fit reached {held.fit.elbo:.6g}), which favours "
                   "them: their 2ΔELBO may be overstated")
        run.say(st_note)
        st.reference = {"held": False, "states": list(res.deterministic_states),
                         "elbo_limit": float(res.elbo), "elbo_held": float(held.fit.elbo),
                         "held_converged": False, "note": st_note}
        return base
    st.reference = {"held": True, "states": list(res.deterministic_states),
                     "elbo_limit": float(res.elbo), "elbo_held": float(held.fit.elbo),
                     "held_converged": True}
    run.say(f"states without process noise ({names}): the refits hold them quasi-deterministic "
            f"(a small fixed process noise, as the states candidates add), so the base is refitted "
            f"that way to compare at the same noise: ELBO {held.fit.elbo:.6g} "
            f"(in the exact limit: {res.elbo:.6g})")
    return held


def _numerics_stage(run: _RunConfig, st: _RunState) -> None:
    """Refit the current model with other integrator settings (:mod:`.numerics`); adopt a
    setting that removes a significant part of the mismatch."""
    from .numerics import run_numerics

    st.numres = run_numerics(st.current, run.out, alpha=run.alpha, generated_dir=run.gen,
                             max_iter=run.max_iter, engine=run.engine, deadline=run.deadline,
                             progress=run.progress)
    if st.numres.adopted is not None:
        st.current = st.numres.adopted.state
        st.evidence = locate_state(st.current)
    _checkpoint(run, st, StopReason.RUNNING)


def _noise_model_stage(run: _RunConfig, st: _RunState) -> None:
    """Refit the current model with correlated process noise (:mod:`.noisemodel`); adopt it
    when the nested likelihood-ratio test is significant."""
    from .noisemodel import run_noise_model

    st.noiseres = run_noise_model(st.current, run.out, alpha=run.alpha, generated_dir=run.gen,
                                  max_iter=run.max_iter, engine=run.engine,
                                  deadline=run.deadline, progress=run.progress)
    if st.noiseres.adopted is not None:
        st.current = st.noiseres.adopted.state
        st.evidence = locate_state(st.current)
    _checkpoint(run, st, StopReason.RUNNING)


def _noise_retest(run: _RunConfig, st: _RunState, after_round: int) -> None:
    """Test the noise model again after round ``after_round`` accepted an effect, when the
    current process noise is still diagonal.

    The first test (:func:`_noise_model_stage`) runs on the base fit, whose residual still
    carries the concealed effect: a missing sensor bias or term distorts the path the noise is
    estimated on and can hide a correlation the turbulence has (an independent lateral record
    with a roll-gyro bias: S = 8.4 below the threshold 11.3 before the bias was found, while the
    same record without the bias adopts the full factor at 2ΔELBO 19.3). The model the search
    recommends would then depend on whether something physical was missing. The test is the
    same (score test at the current optimum, a refit only when it is significant); it is
    skipped when the structure is already full, when an earlier test was significant but its
    refit did not converge (the refit would be repeated to the same end), or after an adopted
    air-relative gust."""
    from .noisemodel import NoiseModelVerdict, noise_alternatives, run_noise_model

    earlier = ([st.noiseres] if st.noiseres is not None else []) + [r for _, r in st.noise_retests]
    if (not noise_alternatives(st.current.model)
            or (st.gustres or {}).get("adopted")
            or any(t.verdict is NoiseModelVerdict.SIGNIFICANT_NOT_CONVERGED
                   for r in earlier for t in r.trials)):
        return
    res = run_noise_model(st.current, run.out, alpha=run.alpha, generated_dir=run.gen,
                          max_iter=run.max_iter, engine=run.engine, deadline=run.deadline,
                          progress=run.progress, after_round=after_round)
    st.noise_retests.append((after_round, res))
    if res.adopted is not None:
        st.current = res.adopted.state
        st.evidence = locate_state(st.current)
    _checkpoint(run, st, StopReason.RUNNING)


def _gust_stage(run: _RunConfig, st: _RunState) -> None:
    """Refit the current model with turbulence in its air-relative velocity (:mod:`.gust`),
    where it applies; adopt it when significant."""
    from . import gust

    res, plans = gust.run_gust_model(st.current, model_info_of(st.current), run.out,
                                     alpha=run.alpha, generated_dir=run.gen,
                                     max_iter=run.max_iter, engine=run.engine,
                                     deadline=run.deadline, progress=run.progress)
    if res.trials:
        st.gustres = gust.to_json(res, plans)
        if res.adopted is not None:
            st.current = res.adopted.state
            st.evidence = locate_state(st.current)
        _checkpoint(run, st, StopReason.RUNNING)


def _say_screen(run: _RunConfig, table: list[dict]) -> None:
    """One progress line with the round's screen ranking (refitted ones starred)."""
    run.say(("screen (-log10 p of the score test; [locate score] where no "
             "score statistic, ^ where the fit is a saddle of the candidate's ELBO): "
             if run.screen else "locate scores: ")
            + ", ".join(f"{r['key']} " + (f"{r['priority']:.3g}"
                                          if r['tier'] == ScreenTier.SCORE_TEST.value
                                          else f"[{r['priority']:.3g}]"
                                          + ("^" if r['tier'] == ScreenTier.ASCENT.value
                                             else ""))
                        + ("*" if r["refitted"] else "")
                        for r in table[:run.max_candidates + 4] if r['priority'] is not None)
            + " (* refitted)")


def _gated_round_models(run: _RunConfig, current: FitState, info: ModelInfo, rnd: int,
                        cands: Sequence[Candidate]) -> dict:
    """Key → gated model (:mod:`.gated`) of the gateable ``cands``, each group's module
    built once before the refits; a group whose model cannot be built is left out (its
    candidates compile their own models). The candidates are grouped in the order of their
    keys, so that one set of candidates gives one model whatever the record's ranking (the
    persistent compilation cache then serves it again, as for the screen's batches)."""
    from .gated import gateable, gated_groups, gated_model, write_gated_spec

    groups = {}
    for g, grp in enumerate(gated_groups(sorted((c for c in cands if gateable(c)),
                                                key=lambda c: c.key))):
        try:
            gg = write_gated_spec(grp, current, info,
                                  run.out / "candidates" / f"r{rnd}_gated_{g + 1}.yaml",
                                  _round_name(current, rnd, f"g{g + 1}"))
            gated_model(gg, run.gen)
        except (SpecError, VsidgenError, ValueError, KeyError) as err:
            run.say(f"    gated model of {', '.join(c.key for c in grp)} "
                    f"not built ({str(err).splitlines()[0]}); their "
                    "refits compile their own models")
            continue
        groups.update({c.key: gg for c in grp})
    if groups:
        run.say(f"round {rnd}: {len(groups)} candidates are gated terms of "
                f"{len(set(groups.values()))} compiled model(s) "
                "(the others compile their own)")
    return groups


def _plan_round(run: _RunConfig, current: FitState, info: ModelInfo, rnd: int,
                ranked: list, refit_until: float | None = None) -> _RoundPlan:
    """Spec paths, gated models and engine tasks of the round's selected candidates;
    transport delays are profiled over a grid of delays (:mod:`.delay`), not refitted; lags
    and Padé delays are refitted from the screen's best time constant (:func:`filter_start`).
    ``refit_until``: the round's refit deadline (:func:`round_refit_deadline`)."""
    ranked = [(pr, loc, filter_start(c, sr), sr) for pr, loc, c, sr in ranked]
    paths = [run.out / "candidates" / f"r{rnd}_{i + 1:02d}_{safe_name(c.key)}.yaml"
             for i, (_, _, c, _) in enumerate(ranked)]
    profiled = [i for i, (_, _, c, _) in enumerate(ranked) if c.info.get("profile") == "delay"]
    groups = {}
    if run.gated:
        groups = _gated_round_models(run, current, info, rnd,
                                     [c for i, (_, _, c, _) in enumerate(ranked)
                                      if i not in profiled])
    index = {c.key: i for i, (_, _, c, _) in enumerate(ranked)}
    # candidates of one shape that add states: one family (one compilation) per chunk
    chunks = [] if not run.gated else [
        ch for ch in family_chunks([c for i, (_, _, c, _) in enumerate(ranked)
                                    if i not in profiled], 1 if run.engine.serial else
                                   run.engine.workers) if len(ch) > 1]
    in_family = {c.key: ch for ch in chunks for c in ch}
    deadline = TaskDeadline.of(refit_until)
    tasks, families = [], {}
    for i, (_, _, c, _) in enumerate(ranked):
        if i in profiled:
            continue
        ch = in_family.get(c.key)
        if ch is None:
            tasks.append((c.key, ("one", deadline, c, current, info, paths[i],
                                  _round_name(current, rnd, i + 1), run.gen, run.max_iter,
                                  groups.get(c.key))))
        elif ch[0] is c:
            members = [(m, paths[index[m.key]], _round_name(current, rnd, index[m.key] + 1))
                       for m in ch]
            key = family_key(ch)
            families[key] = [m.key for m in ch]
            tasks.append((key, ("family", deadline, members, current, info, run.gen,
                                run.max_iter)))
    # a trial carries the candidate's locate score (findings: locate_score) and its score
    # test (score_test); the priority that ranked it is in the round's screen
    by_key = {c.key: (i, loc, c, sr) for i, (_, loc, c, sr) in enumerate(ranked)}
    return _RoundPlan(ranked, paths, profiled, groups, tasks, by_key, families, refit_until)


def filter_start(c: Candidate, sr) -> Candidate:
    """``c`` with its time constant starting at the best grid value of its screen
    (:func:`.score.screen_input_filters`) when ``c`` is a lag or Padé delay of an input that
    has one: the likelihood of a time constant is multimodal and a refit from the smallest
    (a sample) stops in the nearest optimum. A speed candidate starts at its screen's speed
    damping and X_α (:func:`.score.screen_speed`). Any other candidate is returned unchanged."""
    from .score import is_speed_candidate
    from .specwrite import clip_to_bounds

    if is_speed_candidate(c) and sr is not None and sr.statistic is not None:
        # the speed damping and X_alpha of the best profiled speed damping (screen_speed):
        # both are flat at the nesting point (Z_V = M_V = 0), so the refit still starts at
        # the current model; from X_V = X_alpha = 0 the refit stalled far below its optimum
        start = {k: float(v) for k, v in (sr.step or {}).items() if math.isfinite(v)}
        if start:
            return dataclasses.replace(c, parameters=tuple(
                dataclasses.replace(p, initial=clip_to_bounds(start[p.name], [p.lower, p.upper]))
                if p.name in start else p for p in c.parameters))
        return c
    kind = (c.info or {}).get("filter")
    tau = (getattr(sr, "step", None) or {}).get("tau_s") if sr is not None else None
    if kind not in ("lag", "pade") or tau is None or sr.statistic is None \
            or not math.isfinite(tau) or not c.parameters:
        return c
    p = c.parameters[0]
    start = clip_to_bounds(float(tau), [p.lower, p.upper])
    return dataclasses.replace(c, parameters=(dataclasses.replace(p, initial=start),)
                               + tuple(c.parameters[1:]),
                               info={**c.info, "start_from_screen_s": start})


def _refit_done(run: _RunConfig, st: _RunState, rnd: int, plan: _RoundPlan,
                current: FitState, task) -> None:
    """Engine callback of one finished refit task: per candidate it refitted, progress
    lines and a checkpoint with the refit moved from pending to refitted (a cancelled one
    stays pending); then the line of what the round does next."""
    from ..engine import TaskStatus

    outs = plan.outcomes(task)
    for oc in outs:
        _candidate_done(run, st, rnd, plan, current, oc)
    # the next refit's line once the task's candidates are all in (a family's second member
    # was refitted in this task: it is not "next")
    if any(oc.status is not TaskStatus.CANCELLED for oc in outs):
        _say_next(run, st, rnd, plan)


def _candidate_done(run: _RunConfig, st: _RunState, rnd: int, plan: _RoundPlan,
                    current: FitState, oc) -> None:
    from ..engine import TaskStatus

    i, score, c, sr = plan.by_key[oc.key]
    t = _trial_of(oc, c, score, sr, plan.paths[i], current)
    if oc.status is TaskStatus.DONE:
        for m in oc.value[1]:
            run.say(f"    [{c.key}] {m.strip()}")
        run.say(f"round {rnd}: {c.key}: ELBO {t.state.elbo:.6g}, 2ΔELBO "
                f"vs nested reference {t.statistic:.4g}, "
                f"{conv_label(t.state.fit)} ({oc.wall_s:.0f} s, "
                f"compile {t.refit.compile_s:.0f} s)")
    else:
        run.say(f"round {rnd}: {c.key}: {oc.status.value.upper()} ({oc.error})")
    if oc.status is not TaskStatus.CANCELLED:
        un = st.unfinished
        un["pending"].remove(c.key)
        un["refitted"].append(_undecided_json(t))
        _checkpoint(run, st, StopReason.RUNNING, report=False)


def _say_next(run: _RunConfig, st: _RunState, rnd: int, plan: _RoundPlan, *,
              profile: str | None = None) -> None:
    """The progress line (``run.progress.refitting``) of the engine refit the round starts
    next, numbered among all the round's candidates (refits and delay profiles: the headline
    counts both), or with ``profile`` of that delay profile. None when the round's refit
    deadline has passed (no refit starts then: :func:`_refit_round`), nor for a refit when a
    delay profile ranks before it (the profile runs first and has its own line)."""
    status = getattr(run.progress, "refitting", None)
    pending = st.unfinished["pending"]
    limit = _limit_left(plan.deadline)
    if status is None or not pending or (limit and limit["limit_left"] <= 0):
        return
    n_done = len(st.unfinished["refitted"])
    total = n_done + len(pending)
    if profile is not None:
        run.say(status(rnd, n_done + 1, total, profile, **limit,
                       action=f"profiling the delay of {profile} over a grid"))
        return
    nxt = plan.next_refitted(pending)
    if nxt is None or plan.by_key[pending[0]][0] in plan.profiled:
        return
    members = next((ks for ks in plan.families.values() if nxt in ks), (nxt,))
    members = [k for k in pending if k in members]   # a family's members refitted together
    run.say(status(rnd, n_done + 1, total, " + ".join(members), **limit, n=len(members)))


def round_refit_deadline(deadline: float | None, reserve_s: float) -> float | None:
    """The instant (``time.monotonic()``) after which a round's refits stop: the run's
    ``deadline`` less ``reserve_s``, the time kept for deciding the round (its lead's projected
    refit, a fit of the current model: diagnose reserves the current model's own fit time).
    None without a deadline."""
    if deadline is None:
        return None
    return deadline - max(float(reserve_s), 0.0)


def _refit_round(run: _RunConfig, st: _RunState, rnd: int, plan: _RoundPlan,
                 current: FitState) -> tuple[list[Trial], list[str]]:
    """The round's refits on the engine and its delay profiles, in the round's rank order (the
    refits ranked above a delay run before its profile, the rest after it, so that under a time
    limit the most promising candidates are examined first), until the round's refit deadline
    (``plan.deadline``; a refit running then stops there, unconverged). Returns the trials
    (the refits in rank order, then the profiled delays) and the keys of the candidates the
    deadline left unrefitted, in rank order (none started after the first was cut)."""
    from ..engine import TaskStatus

    _say_next(run, st, rnd, plan)          # live status line with time left
    on_done = functools.partial(_refit_done, run, st, rnd, plan, current)
    remaining = sorted(plan.tasks, key=lambda task: plan.task_rank(task[0]))
    outcomes, profiles, cut = [], [], []

    def refit(batch) -> None:
        """Run ``batch`` on the engine (nothing once the deadline has cut a refit); the
        cancelled candidates go to ``cut``."""
        if cut:
            cut.extend(k for task in batch for k in plan.families.get(task[0], (task[0],)))
            return
        if not batch:
            return
        done = run.engine.run(_round_task, batch, deadline=plan.deadline, on_done=on_done)
        for o in (o for t in done for o in plan.outcomes(t)):
            if o.status is TaskStatus.CANCELLED:
                cut.append(o.key)
            else:
                outcomes.append(o)

    for i in plan.profiled:
        refit([task for task in remaining if plan.task_rank(task[0]) < i])
        remaining = [task for task in remaining if plan.task_rank(task[0]) >= i]
        _, score, c, sr = plan.ranked[i]
        if cut or (plan.deadline is not None and time.monotonic() >= plan.deadline):
            # as the engine: nothing starts after the round's refit deadline
            cut.append(c.key)
            continue
        if getattr(run.progress, "refitting", None) is not None:
            _say_next(run, st, rnd, plan, profile=c.key)
        else:
            run.say(f"round {rnd}: {c.key}: profiling the delay over a grid")
        t = delay_trial(c, score, current, plan.paths[i], _round_name(current, rnd, i + 1),
                        engine=run.engine, generated_dir=run.gen, max_iter=run.max_iter,
                        deadline=plan.deadline, screen=sr, alpha=run.alpha)
        if t is None:
            cut.append(c.key)
            continue
        st.unfinished["pending"].remove(c.key)
        st.unfinished["refitted"].append(_undecided_json(t))
        if t.state is not None:
            from .findings import estimate_text

            d = t.candidate.info["delay"]
            run.say(f"round {rnd}: {c.key}: {estimate_text(d['name'], d)}, "
                    f"2ΔELBO {t.statistic:.4g}")
        elif t.refit is not None:
            run.say(f"round {rnd}: {c.key}: {t.refit.notes[0]}")
        profiles.append(t)
        _say_next(run, st, rnd, plan)      # the refits ranked after the profile
    refit(remaining)
    # per candidate, in the round's rank order (a family's members come back together)
    trials = []
    for o in sorted(outcomes, key=lambda o: plan.by_key[o.key][0]):
        i, score, c, sr = plan.by_key[o.key]
        trials.append(_trial_of(o, c, score, sr, plan.paths[i], current))
    return trials + profiles, sorted(cut, key=lambda k: plan.by_key[k][0])


def _continue_lead(run: _RunConfig, rnd: int, trials: list[Trial], current: FitState,
                   n_examined: int, deadline: float | None) -> list[Trial]:
    """The round's unconverged lead refit (:func:`lead_to_continue`) continued once, until
    the round's refit ``deadline``; the trials with it replaced (unchanged when there is none,
    or the continuation failed or was cut by the deadline before it started)."""
    from ..engine import TaskStatus

    i = lead_to_continue(trials, alpha=run.alpha, n_examined=n_examined)
    if i is None:
        return trials
    t = trials[i]
    n = CONTINUE_FACTOR * run.max_iter
    left = None if deadline is None else deadline - time.monotonic()
    if left is not None and left <= 0:
        return trials
    run.say(f"round {rnd}: continuing {t.candidate.key} (2ΔELBO ≥ {t.statistic:.4g}, "
            f"{conv_label(t.state.fit)}: {t.state.fit.stop_reason.value}) for up to {n} more "
            "iterations: it leads the round without an optimum")
    (o,) = run.engine.run(_continue_task, [(t.candidate.key, (t.state, n, run.max_iter, left))],
                          deadline=deadline)
    if o.status is not TaskStatus.DONE:
        run.say(f"    continuation {o.status.value}: {o.error}")
        return trials
    ct = continued_trial(t, o.value, current, n)
    run.say(f"    {t.candidate.key}: 2ΔELBO {ct.statistic:.4g} ({conv_label(ct.state.fit)})")
    return [ct if j == i else x for j, x in enumerate(trials)]


def _multistart_task(t, current, max_iter):
    """A trial's model fitted cold from every noise start (:func:`multistart_refit`; runs on an
    engine worker); a FitState, or None when no start ends above the trial's refit."""
    return multistart_refit(t, current, max_iter=max_iter)


def multistart_refit(t: "Trial", current: FitState, *, max_iter: int) -> FitState | None:
    """The trial's model fitted from the estimator's own noise starts (``noise_start="auto"``:
    release, data, data-meas, unit; θ from the spec, i.e. the current estimates and the
    candidate's nesting values) instead of warm from the current optimum.

    The noise likelihood is multimodal: a refit warm-started at the current model's noise can
    stay in that basin when the candidate's own optimum lies elsewhere. On a new user's Tu-144
    short period (`tu144_lon_f20_4d`, validation `4f`) the missing pitch-rate term of the
    normal-acceleration output (`output_derivative:NZ:Q`) refitted warm to ELBO 2268.0, whose
    estimates validated worse than the current model (1807.6 against 1846.0), while the unit
    noise start of the same model reached 2293.2, validating at 2353.1. Returns the better
    state (evaluated and validated as the refit's), or None when no start ends converged above
    the warm refit by more than ``PROJECTED_TOL``."""
    from ..estimator import fit

    st = t.state
    res = fit(st.model, list(st.records), options=diag_options(max_iter, noise_start="auto"))
    if not refit_converged(res) or not (res.elbo > st.elbo + PROJECTED_TOL):
        return None
    return evaluated(st.spec_path, st.model, st.records, res, current.vrecords, max_iter=max_iter)


def _multistart_round(run: "_RunConfig", st: "_RunState", rnd: int, trials: list["Trial"]) -> list["Trial"]:
    """Trials significant at the round's level whose validation did not improve and whose
    statistic exceeds every validated trial's, refitted from every noise start
    (:func:`multistart_refit`): a rejection by validation must not rest on a local optimum of
    the candidate's noise. A better optimum replaces the trial's state and
    statistic (against the same nested reference); the others are kept. Cancelled or failed
    tasks keep the warm refit."""
    from ..engine import TaskStatus

    current = st.current
    failed, lead = [], -math.inf
    for i, t in enumerate(trials):
        if (t.state is None or t.refit is None or t.state.vfit is None or not (t.p_value < run.alpha)
                or t.verdict is not RefitVerdict.ORDINARY):
            continue
        corr = t.refit.val_x0_entropy if t.candidate.states else 0.0
        if validation_improved(t.state, current, corr):
            lead = max(lead, t.statistic)
        else:
            failed.append(i)
    # only where it can change the round's decision: a rejected trial already outranked by a
    # validated one is not refitted again (each multi-start is a cold fit from four starts)
    eligible = [i for i in failed if trials[i].statistic > lead]
    if not eligible:
        return trials
    run.say(f"round {rnd}: significant but not validated, refitted from every noise start: "
            + ", ".join(trials[i].candidate.key for i in eligible))
    outs = run.engine.run(_multistart_task, [(trials[i].candidate.key, (trials[i], current, run.max_iter))
                                             for i in eligible], deadline=run.deadline)
    trials = list(trials)
    for i, o in zip(eligible, outs):
        t = trials[i]
        if o.status is not TaskStatus.DONE or o.value is None:
            continue
        ns = o.value
        lam, p = lr_test(t.refit.elbo_ref, ns.elbo, t.dof)
        n_grid = _grid_size(t.candidate)
        if n_grid:
            from .delay import delay_p_value
            p = delay_p_value(lam, n_grid)
        run.say(f"    {t.candidate.key}: ELBO {t.state.elbo:.6g} -> {ns.elbo:.6g} from the noise starts "
                f"(2ΔELBO {lam:.4g})")
        ro = dataclasses.replace(t.refit, notes=list(t.refit.notes) + [
            f"refitted from every noise start (significant, validation not improved): ELBO "
            f"{t.state.elbo:.6g} -> {ns.elbo:.6g}, used"])
        if t.candidate.states and ns.vfit is not None:
            ro = dataclasses.replace(ro, val_x0_entropy=x0_entropy_of(ns, t.candidate))
        trials[i] = dataclasses.replace(t, state=ns, statistic=lam, p_value=p, refit=ro,
                                        statistic_vs_base=2.0 * (ns.elbo - current.elbo),
                                        converged=refit_converged(ns.fit),
                                        verdict=trial_verdict(t.candidate, ns, lam, ro))
    return trials


def x0_entropy_of(state: FitState, c) -> float:
    """The validation initial-value term of candidate ``c``'s added states at ``state``
    (:func:`.refit.x0_entropy`)."""
    from .refit import x0_entropy

    names = [n for n in state.model.state_names if n in {s.name for s in c.states}]
    return x0_entropy(state.vfit, names, state.model, state.vrecords)


def projected_path(out: pathlib.Path, rnd: int, i: int, t: "Trial") -> pathlib.Path:
    """Where the projected refit of trial ``t`` (the ``i``-th of its round) is written: beside
    the candidate's own spec, which it extends, with ``.projected`` added (the trial's position
    in the round's list is not the spec's rank number: ``r1_03_x.projected.yaml`` extended
    ``r1_04_x.yaml``; session 47)."""
    sp = getattr(t, "spec_path", None)
    if sp:
        sp = pathlib.Path(sp)
        return sp.with_name(sp.stem + ".projected.yaml")
    return (pathlib.Path(out) / "candidates"
            / f"r{rnd}_{i + 1:02d}_{safe_name(t.candidate.key)}.projected.yaml")


def _projected_round(run: _RunConfig, st: _RunState, rnd: int, plan: _RoundPlan,
                     trials: list[Trial], *, lead_only: bool = False
                     ) -> tuple[list[Trial], list[dict], FitState | None] | None:
    """Projected refits (:func:`projected_refit`) of the nominally significant trials (converged
    or not): a candidate's gain may be a better optimum of the current model itself
    (``lead_only``: only the one with the largest 2ΔELBO, in a round cut by the time limit:
    the time kept for its decision is one fit's).
    When one is found it becomes ``st.current`` (re-based on the current spec,
    :func:`rebase`) and every trial's statistic is taken against it. Returns (trials,
    projected-refit records, the better optimum or None); None when the time limit
    cancelled one."""
    from ..engine import TaskStatus

    current = st.current
    ptasks = []
    eligible = [t for t in trials if t.state is not None and t.p_value < run.alpha]
    if lead_only:
        eligible = sorted(eligible, key=lambda t: -t.statistic)[:1]
    chosen = {id(t) for t in eligible}
    for i, t in enumerate(trials):
        if id(t) not in chosen:
            continue
        ppath = projected_path(run.out, rnd, i, t)
        ptasks.append((t.candidate.key, (t, current, ppath, _round_name(current, rnd, f"{i + 1}p"),
                                         run.gen, run.max_iter, plan.groups.get(t.candidate.key))))
    if ptasks:
        st.unfinished["projected_pending"] = [k for k, _ in ptasks]
        run.say(f"round {rnd}: projected refits of " + ", ".join(k for k, _ in ptasks))
    pouts = run.engine.run(_projected_task, ptasks, deadline=run.deadline)
    if any(o.status is TaskStatus.CANCELLED for o in pouts):
        return None
    projected = []
    better = None
    for (key, (_, _, ppath, *_)), o in zip(ptasks, pouts):
        if o.status is not TaskStatus.DONE:
            projected.append({"key": key, "error": f"{o.status.value}: {o.error}"})
            continue
        ps = o.value
        ok = refit_converged(ps.fit)
        projected.append({"key": key, "spec": str(ppath), "elbo": _f(ps.elbo), "converged": ok,
                          "gain_over_current": _f(ps.elbo - current.elbo)})
        if ok and ps.elbo > current.elbo + PROJECTED_TOL and (
                better is None or ps.elbo > better.elbo):
            better = ps
    if better is not None:
        run.say(f"    the current model has a better optimum (ELBO "
                f"{current.elbo:.6g} -> {better.elbo:.6g}, reached from a "
                "candidate's optimum with its new terms removed): every "
                "statistic of the round is taken against it")
        try:
            rb = rebase(better, current, run.out / "candidates" / f"r{rnd}_00_current.yaml",
                        _round_name(current, rnd, 0), generated_dir=run.gen,
                        max_iter=run.max_iter)
            if refit_converged(rb.fit) and rb.elbo >= better.elbo - PROJECTED_TOL:
                better = rb
        except (SpecError, FitError, VsidgenError, ValueError, KeyError) as err:
            run.say(f"    (re-basing on the current spec failed: {err}; the "
                    "projected spec is kept)")
        trials = _against_better_reference(trials, better)
        st.current = better
    return trials, projected, better


def _gust_check(run: _RunConfig, st: _RunState, rnd: int, best: Trial):
    """Test the round's lead against turbulence in the air-relative velocity (:mod:`.gust`).

    A body-axis model that defines its flow angles from its velocity states takes the state
    as the air-relative velocity; in turbulence its rate then receives a differentiated gust
    that white process noise cannot represent, and a physical candidate may absorb part of
    that misfit (a pitch mode driven by q on the benchmark's body-axis null records). The
    gust is a noise-model alternative: it is refitted here (only where it applies, and only
    when a round is about to accept an effect — where it could change a decision) and
    decided as in :func:`.gust.run_gust_model`. Not significant: the lead is accepted as it
    is. Significant: the gust model ``g`` is adopted, and the lead is refitted on ``g`` as
    a candidate of ``g`` (same terms, starts and threshold): with Λ_g = 2(ELBO_{g+c} −
    ELBO_ref(g)) above the round's threshold (converged, its validation ELBO not lower than
    ``g``'s), it is accepted with that refit; else it was an artefact of the white noise
    model and is not accepted (None: the next round searches on ``g``).

    Returns ``(trial, own_spec)`` — the trial to accept and whether its state is its own
    spec's — or None."""
    from . import gust

    current = st.current
    res, plans = gust.run_gust_model(current, model_info_of(current), run.out,
                                     alpha=run.alpha, generated_dir=run.gen,
                                     max_iter=run.max_iter, engine=run.engine,
                                     deadline=run.deadline, progress=run.progress)
    if not res.trials:
        return best, False
    doc = gust.to_json(res, plans)
    check = {"round": rnd, "key": best.candidate.key,
             "statistic_without_gust": _f(best.statistic), "threshold": _f(best.threshold)}
    doc["checked"] = check
    st.gustres = doc

    def record(outcome: str) -> None:
        """The outcome in findings.json's noise_gust and in the round's record; a checkpoint."""
        check["outcome"] = outcome
        if st.rounds and st.rounds[-1].get("round") == rnd:
            st.rounds[-1]["gust_check"] = dict(check)
        _checkpoint(run, st, StopReason.RUNNING)

    if res.adopted is None:
        record("gust_not_significant")
        return best, False
    g = res.adopted.state
    st.current, st.evidence = g, locate_state(g)
    t2 = None if run.past_deadline() else _refit_on(run, best, g, rnd)

    def above(t) -> bool:
        return (t is not None and t.state is not None and t.verdict is RefitVerdict.ORDINARY
                and t.statistic > best.threshold)

    if above(t2) and not _decidable(t2) and not run.past_deadline():
        # above the threshold but still climbing: continued once, as a round's lead is
        t2 = _continue_lead(run, rnd, [t2], g, 1, run.deadline)[0]
    ok = above(t2) and _decidable(t2)
    climbing = above(t2) and not ok
    vok = None
    if ok and t2.state.vfit is not None and g.val_elbo is not None:
        corr = t2.refit.val_x0_entropy if t2.refit is not None else 0.0
        vok = validation_improved(t2.state, g, corr)
    check.update({"statistic_with_gust": None if t2 is None else _f(t2.statistic),
                  "converged_with_gust": None if t2 is None else bool(t2.converged),
                  "verdict_with_gust": None if t2 is None or t2.verdict is None
                  else t2.verdict.value,
                  "validation_ok_with_gust": vok,
                  "spec_with_gust": None if t2 is None else str(t2.spec_path),
                  "error_with_gust": None if t2 is None else t2.error})
    lam2 = "not refitted (time limit)" if t2 is None else f"{t2.statistic:.4g}"
    if ok and vok is not False:
        run.say(f"round {rnd}: {best.candidate.key} tested with the air-relative gust adopted: "
                f"2ΔELBO {lam2} > {best.threshold:.4g} (was {best.statistic:.4g}): kept")
        note = (f" Tested with turbulence in the air-relative velocity adopted as the noise "
                f"model (a rival explanation on a body-axis model): 2ΔELBO = {t2.statistic:.4g}"
                f" > {best.threshold:.4g} (without the gust {best.statistic:.4g}).")
        t2 = dataclasses.replace(t2, candidate=dataclasses.replace(
            t2.candidate, explanation=t2.candidate.explanation + note),
            threshold=best.threshold, significant=True, validation_ok=vok,
            alternatives=best.alternatives)
        record("significant_with_gust")
        return t2, True
    if climbing:
        # Λ is a lower bound above the threshold, but the refit has no optimum: neither
        # accepted nor explained by the gust (the run says which refit to continue)
        run.say(f"round {rnd}: {best.candidate.key} refitted with the air-relative gust "
                f"adopted: 2ΔELBO ≥ {lam2} > {best.threshold:.4g} without converging: "
                "undecided, not accepted")
        record("undecided_with_gust")
        return None
    run.say(f"round {rnd}: {best.candidate.key} (2ΔELBO {best.statistic:.4g} > "
            f"{best.threshold:.4g}) refitted with the air-relative gust adopted: {lam2}"
            + (" (not converged)" if t2 is not None and not t2.converged else "")
            + ": not significant there, not accepted")
    record("explained_by_gust")
    return None


def _decidable(t: Trial) -> bool:
    """A refit the round decides on (as :func:`_decide_round`): converged, or stopped at its
    limit with a positive-definite Hessian, or at a kink (its Λ a lower bound)."""
    return bool(t.converged or stopped_short(t) is not None or stopped_at_kink(t))


def _gust_not_checked(st: _RunState, best: Trial) -> Trial:
    """``best`` with a sentence saying that the gust check applied but the time limit left no
    time for it (unchanged where the gust does not apply)."""
    from .gust import applicable_plans

    if not applicable_plans(st.current, model_info_of(st.current)):
        return best
    c = best.candidate
    note = (" Not tested against turbulence in the air-relative velocity (the gust check): the "
            "time limit left no time for it. On a model whose flow angles are defined from its "
            "velocity states such an effect can be an artefact of white process noise; rerun "
            "with a longer --time-limit to test it.")
    return dataclasses.replace(best, candidate=dataclasses.replace(
        c, explanation=c.explanation + note))


def _refit_on(run: _RunConfig, best: Trial, g: FitState, rnd: int) -> Trial | None:
    """``best``'s candidate refitted as a candidate of ``g`` (the current model with a noise
    alternative adopted): the same terms and starts when its new names are free in ``g``,
    else the catalogue's candidate of the same key proposed for ``g``. None when the time
    ran out or no such candidate exists."""
    from ..engine import TaskStatus
    from .base import get_effect

    c = best.candidate
    info = model_info_of(g)
    taken = set(g.model.state_names) | set(g.model.parameter_names)
    if any(x.name in taken for x in (*c.parameters, *c.states)):
        again = [x for x in propose(info, [get_effect(c.effect)]) if x.key == c.key]
        if not again:
            return None
        c = filter_start(again[0], best.screen)
    path = run.out / "candidates" / f"r{rnd}_gust_{safe_name(c.key)}.yaml"
    name = _round_name(g, rnd, "g")
    if (c.info or {}).get("profile") == "delay":
        return delay_trial(c, best.score, g, path, name, engine=run.engine,
                           generated_dir=run.gen, max_iter=run.max_iter,
                           deadline=run.deadline, screen=best.screen, alpha=run.alpha)
    (o,) = run.engine.run(_refit_task, [(c.key, (c, g, info, path, name, run.gen,
                                                 run.max_iter))], deadline=run.deadline)
    if o.status is TaskStatus.CANCELLED:
        return None
    return _trial_of(o, c, best.score, best.screen, path, g)


def _accept(run: _RunConfig, st: _RunState, rnd: int, plan: _RoundPlan, info: ModelInfo,
            best: Trial, *, own_spec: bool = False) -> None:
    """Record the accepted trial and make it the current model (a gated candidate is
    refitted as its own spec first, unless ``own_spec``: the next round extends its own spec
    and model)."""
    run.say(f"round {rnd}: accepted {best.candidate.key} "
            f"(2ΔELBO = {best.statistic:.4g} > {best.threshold:.4g})"
            + ((f"; AMBIGUOUS with " if any(not same_physics(best.candidate, t.candidate)
                                             for t in best.alternatives)
                else "; form uncertain: ") + ", ".join(t.candidate.key for t in best.alternatives)
               if best.alternatives else ""))
    if best.candidate.key in plan.groups and not own_spec:
        from .gated import adopt

        ia = plan.by_key[best.candidate.key][0]
        own = adopt(best.candidate, best.state, st.current, info, best.spec_path,
                    _round_name(st.current, rnd, ia + 1), generated_dir=run.gen,
                    max_iter=run.max_iter)
        run.say(f"    {best.candidate.key} as its own spec: ELBO "
                f"{own.elbo:.6g} (gated fit {best.state.elbo:.6g})")
        best = dataclasses.replace(best, state=own)
    if ((best.candidate.info or {}).get("filter") in HOLD_FILTERS and best.state is not None
            and "hold_comparison" not in (best.candidate.info or {})):
        best = lag_hold(run, best, st.current, f"{_round_name(st.current, rnd, 0)}_hold")
    st.accepted.append((best, st.current, st.evidence))
    st.current = best.state
    st.evidence = locate_state(st.current)
    _checkpoint(run, st, StopReason.RUNNING)


#: input filters whose candidate is the exact discretisation of a held step and that are
#: refitted in their continuous form under RK4 with a first-order hold (:func:`lag_hold`)
HOLD_FILTERS = ("lag", "pade")


def _lag_setting_task(c, base, lagged, setting, path, name, generated_dir, max_iter):
    """Engine task of :func:`lag_hold`: the accepted lag ``lagged`` (a FitState) refitted
    warm with the integrator ``setting``. ``c``: the lag candidate written for that setting
    (the continuous form: the accepted lag is the exact discretisation of a held step,
    which a first-order hold must not integrate), extending ``base``'s spec; None: the
    lagged spec itself with ``setting``."""
    from .numerics import write_setting_spec
    from .fitstate import refit_warm

    src, bounds = lagged, None
    if c is not None:
        info = info_from_model(base.model, dt=float(np.median([r.dt for r in base.records])))
        first = write_candidate(c, base, info, path.with_name(f"{path.stem}_terms.yaml"),
                                f"{name}_t")
        src = dataclasses.replace(lagged, spec_path=first)
        bounds = {p.name: [p.lower, p.upper] for p in c.parameters}
    write_setting_spec(src, setting, path, name, bounds=bounds)
    return refit_warm(path, lagged, lagged, generated_dir=generated_dir,
                      iterations=2 * max_iter, max_iter=max_iter)


def lag_hold(run: _RunConfig, best: Trial, base: FitState, name: str) -> Trial:
    """An accepted actuator lag (or Padé delay, a lag of τ/2 seen as 2z − u:
    :class:`.catalogue.ContinuousControlDelay`) refitted under an accurate discretisation of
    its input.

    The numerics stage chose the integrator and input hold for the model *without* the lag,
    and the lag's time constant is only as good as the timing of the input it filters:

    * a zero-order hold delays a continuously moving input by half a sample, which a lag that
      is left out partly absorbs, so the stage may keep the zero-order hold only because of
      the missing lag (hfb_de_lag_0.15_s0: with the lag in the model the first-order hold
      fitted 168.6 nats (2Δ) better and moved τ from 0.113 + 0.025 to 0.149 s, truth 0.15);
    * one Euler step per sample adds a phase error of the same order as that half sample,
      which depends on the model, so no correction of the held input's timing is right for
      all models (HFB-320's 0.05 s lag: 0.0445 s fitted, 0.0695 s with the half sample).

    * the candidate is the lag's exact discretisation over a held step
      (:class:`.catalogue.ActuatorLag`), which nests the current model under any integrator
      but is exact only under Euler steps with held inputs.

    So the lag is refitted warm in its continuous form (``τ ż = u − z``,
    :class:`.catalogue.ContinuousActuatorLag`) under RK4 with a first-order hold (an RK4
    model keeps its sub-steps), and that setting is used unless the current one fits
    significantly better (χ²₁ at the run's α: the inputs step at the samples, or the data
    prefer the current discretisation, e.g. a lag below RK4's bound of 0.4 steps) — the rule
    of the transport delay (:func:`delay_trial`). When the alternative is used, its refit is
    the accepted state and its gain is added to the statistic (against the same reference).
    The comparison goes into the candidate's ``info`` (findings.json →
    ``evidence.hold_comparison``) and its explanation; the reported time constant adds the
    chosen setting's own input delay (:func:`.delay.hold_lag`: none for a first-order
    hold)."""
    from ..engine import TaskStatus
    from .catalogue import ContinuousActuatorLag, ContinuousControlDelay
    from .numerics import NumericsSetting

    cur = best.state
    now = NumericsSetting.of(cur.model)
    c = best.candidate
    pade = (c.info or {}).get("filter") == "pade"
    form = "(τ/2) ż = u − z, delayed input 2z − u" if pade else "τ ż = u − z"
    cont = ContinuousControlDelay() if pade else ContinuousActuatorLag()
    alt = NumericsSetting("rk4", now.substeps if now.method == "rk4" else 1, "foh")
    info = dataclasses.replace(info_from_model(
        base.model, dt=float(np.median([r.dt for r in base.records]))),
        integrator="rk4", substeps=alt.substeps)
    c_alt = next((x for x in cont.applies_to(info) if x.key == c.key), None)
    if c_alt is None:
        return best
    if run.past_deadline():
        return best
    path = best.spec_path.with_name(f"{best.spec_path.stem}_{alt.label}.yaml")
    run.say(f"    {c.key}: refitting in its continuous form with {alt.text} (the lag's "
            "discretisation and the numerics were chosen without it)")
    oc = run.engine.run(_lag_setting_task, [(f"lag:{alt.label}", (
        c_alt, base, cur, alt, path, name, run.gen, run.max_iter))], deadline=run.deadline)[0]
    got = oc.value if oc.status is TaskStatus.DONE else None
    if got is None or not refit_converged(got.fit):
        run.say(f"    {c.key}: the refit with {alt.text} "
                + ("failed or ran out of time" if got is None else "did not converge")
                + f"; {now.text} is kept")
        return best
    d = 2.0 * (got.elbo - cur.elbo)
    thr = float(stats.chi2.isf(run.alpha, 1))
    switch = -d <= thr
    held = f"its exact discretisation over a held step with {now.text}"
    if switch:
        note = (f" Refitted in its continuous form ({form}) under {alt.text} (a "
                "first-order hold: inputs moving between samples), which is used: "
                f"{held} fits "
                + (f"better by 2ΔELBO = {-d:.4g}, not significantly (≤ {thr:.4g})." if d < 0
                   else f"worse by 2ΔELBO = {d:.4g}."))
    else:
        note = (f" Refitted in its continuous form ({form}) under {alt.text}; {held} "
                f"fits significantly better (2ΔELBO = {-d:.4g} > {thr:.4g}), so it is kept"
                + (" (the inputs step at the samples)." if now.inputs == "zoh" else "."))
    comparison = {"current": now.to_json(), "other": alt.to_json(),
                  "current_hold": now.inputs, "other_hold": alt.inputs,
                  "two_delta_elbo_other_minus_current": d,
                  "chosen": (alt if switch else now).to_json(), "threshold": thr,
                  "spec": str(path)}
    c = dataclasses.replace(c, explanation=c.explanation + note,
                            info={**(c.info or {}), "hold_comparison": comparison})
    # the two sides differ in the lag's form, and in the setting where the hold changes
    # ("rk4x1_foh − rk4x1_foh = +83.03" read as a setting against itself: session 47)
    sides = ((f"continuous form, {alt.label}", f"exact discretisation, {now.label}")
             if alt.label == now.label else (alt.label, now.label))
    run.say(f"    {c.key}: {(alt if switch else now).text} (2ΔELBO {sides[0]} − {sides[1]} "
            f"= {d:+.4g})")
    if not switch:
        return dataclasses.replace(best, candidate=c)
    # the accepted terms are now the continuous-form lag's (its bounds, its explanation)
    c = dataclasses.replace(c_alt, explanation=c_alt.explanation + note,
                            info={**(c_alt.info or {}), "hold_comparison": comparison})
    lam = best.statistic + d
    return dataclasses.replace(
        best, candidate=c, state=got, spec_path=path, statistic=lam,
        p_value=float(stats.chi2.sf(max(lam, 0.0), max(best.dof, 1))) if lam > 0 else 1.0,
        statistic_vs_base=best.statistic_vs_base + d, converged=True)


def _lags_with_their_hold(run: _RunConfig, trials: Sequence[Trial], current: FitState,
                          rnd: int) -> list[Trial]:
    """The round's actuator lags refitted under an accurate input discretisation
    (:func:`lag_hold`) *before* the round decides, where a transport or Padé delay of the same
    input has the larger gain over the current model.

    A transport delay is profiled under both input holds (:func:`delay_trial`) and a lag got
    that choice only once accepted. When a lag is what the records hide, the numerics stage
    may keep the zero-order hold because the hold's half sample stands in for part of the
    missing lag; the delay then competes with the first-order hold and the lag without it
    (hfb_de_lag_0.05_s1, an elevator lag of 0.05 s: the first-order hold was worth 2ΔELBO
    464.5 to the delay, which was named, 0.0385 s). Both now decide with the same choice of
    discretisation; a lag that already wins keeps its acceptance-time refit (:func:`_accept`).
    A Padé delay is the same kind of candidate (a lag of τ/2 in the held-step discretisation)
    and gets the same treatment against a transport delay or a lag of its input
    (sp_de_delay_0.04_s0: held-step Padé 0.0203 s under Euler with a held input, 215.7, beside
    the transport delay's 0.0405 s, 214.9; truth 0.04 s)."""
    out = list(trials)
    for i, t in enumerate(trials):
        info = t.candidate.info or {}
        if (info.get("filter") not in HOLD_FILTERS or t.state is None or not t.converged
                or not t.statistic > 0 or "hold_comparison" in info):
            continue
        rivals = [r for r in trials if r is not t and r.state is not None and r.converged
                  and (r.candidate.info or {}).get("filter") in ("delay", "pade", "lag")
                  and (r.candidate.info or {}).get("filter") != info.get("filter")
                  and (r.candidate.info or {}).get("input") == info.get("input")
                  and r.comparison > t.comparison]
        # only where the choice decides something: the lag or a rival is significant (on
        # the real HFB-320 record a lag of 2ΔELBO 1.2 was refitted behind a Padé delay of 1.2)
        if not any(x.p_value < run.alpha for x in [t, *rivals]):
            continue
        if rivals and not run.past_deadline():
            out[i] = lag_hold(run, t, current, f"{_round_name(current, rnd, 0)}_hold{i + 1}")
    return out


def _filter_states(st: _RunState) -> frozenset[str]:
    """The filter states earlier rounds added to the current model (:attr:`NewState.physical`
    False: lags, Padé delays, missing modes) and the gust states of an adopted air-relative
    gust model: the catalogue does not extend their equations (:attr:`ModelInfo.filter_states`)."""
    names = {ns.name for t, _, _ in st.accepted for ns in t.candidate.states if not ns.physical}
    if st.gustres and st.gustres.get("adopted") is not None:
        names |= {g["gust_state"] for g in st.gustres.get("gusts") or ()}
    return frozenset(names) & frozenset(st.current.model.state_names)


def _run_round(run: _RunConfig, st: _RunState, rnd: int) -> _RoundEnd:
    """One round: screen and select → refits → projected refits → decide → accept."""
    current = st.current
    info = dataclasses.replace(model_info_of(current), filter_states=_filter_states(st))
    ranked, n_examined, table = select_candidates(
        info, st.evidence, run.catalogue, current, max_candidates=run.max_candidates,
        min_score=run.min_score, screen=run.screen, alpha=run.alpha,
        workdir=run.out / "screen" / f"r{rnd}", generated_dir=run.gen, progress=run.progress,
        engine=run.engine, deadline=run.deadline,
        exclude=frozenset(t.candidate.key for t, _, _ in st.accepted))
    if not ranked:
        st.rounds.append({"round": rnd, "base_spec": str(current.spec_path),
                          "base_elbo": current.elbo, "trials": [],
                          "n_examined": n_examined, "screen": table,
                          "note": "no candidate is supported by the locate evidence or "
                                  "the score test"})
        return _RoundEnd.DONE
    _say_screen(run, table)
    plan = _plan_round(run, current, info, rnd, ranked,
                       round_refit_deadline(run.deadline, current.fit.wall_time_s))
    st.unfinished = {"round": rnd, "base_spec": str(current.spec_path),
                     "base_elbo": current.elbo, "base_val_elbo": current.val_elbo,
                     "base_val_elbo_own_noise": current.val_elbo_own_noise,
                     "n_candidates": n_examined,
                     "refitted": [], "pending": [c.key for _, _, c, _ in ranked],
                     "screen": table}
    _checkpoint(run, st, StopReason.RUNNING, report=False)
    fams = [f" ({' + '.join(ks)}: one compilation)" for ks in plan.families.values()]
    profiled = [c.key for i, (_, _, c, _) in enumerate(ranked) if i in plan.profiled]
    # the delay profiles are candidates of the round too (its progress lines count them)
    run.say(f"round {rnd}: refitting {plan.n_refits} candidates "
            f"({run.engine.describe()}): "
            + ", ".join(c.key for i, (_, _, c, _) in enumerate(ranked)
                        if i not in plan.profiled) + "".join(fams)
            + (f"; profiling the delay of {', '.join(profiled)} over a grid "
               f"({len(ranked)} candidates in all)" if profiled else ""))
    trials, cut = _refit_round(run, st, rnd, plan, current)
    if cut:
        # decided on what was refitted: the others enter the Holm family as not significant
        # (n_examined counts them), which keeps the round's error rate; nothing refitted,
        # or no time left for the lead's projected refit, leaves the round unfinished
        if not any(t.state is not None for t in trials):
            return _RoundEnd.TIME_LIMIT
        run.say(f"round {rnd}: the time limit left {len(cut)} of {len(ranked)} candidates "
                f"unrefitted ({', '.join(cut)}): deciding on the {len(trials)} refitted, the "
                "others counted as not significant")
    else:
        trials = _continue_lead(run, rnd, trials, current, n_examined, plan.deadline)
        trials = _multistart_round(run, st, rnd, trials)
    before = st.current
    checked = _projected_round(run, st, rnd, plan, trials, lead_only=bool(cut))
    if checked is None:
        if cut:
            run.say(f"round {rnd}: no time left to check the lead's refit (projected refit): "
                    "the round is left undecided after all (an unfinished round accepts nothing)")
        return _RoundEnd.TIME_LIMIT
    trials, projected, better = checked
    trials = _lags_with_their_hold(run, trials, st.current, rnd)
    st.unfinished = None
    finished = _decide_round(rnd, trials, st.current, n_examined, run.alpha, table,
                             projected, better_reference(before, better, projected),
                             not_refitted=cut)
    st.rounds.append(finished.record)
    if cut:
        st.partial_round = {"round": rnd, "refitted": len(trials), "not_refitted": cut}
    if finished.base_unconverged or finished.best is None:
        return _RoundEnd.TIME_LIMIT if cut else _RoundEnd.DONE
    best, own = finished.best, False
    if run.gust_check and not run.gust_noise and st.gustres is None:
        if not run.past_deadline():
            checked = _gust_check(run, st, rnd, best)
            if checked is None:
                return _RoundEnd.TIME_LIMIT if cut else _RoundEnd.NOISE_MODEL
            best, own = checked
        else:
            best = _gust_not_checked(st, best)
    _accept(run, st, rnd, plan, info, best, own_spec=own)
    return _RoundEnd.TIME_LIMIT if cut else _RoundEnd.ACCEPTED


def _run_diagnose(spec, data, *, validate, out, max_rounds, max_candidates, alpha, min_score,
                  catalogue, max_iter, screen, progress, version, build_document,
                  write_findings, time_limit, engine, numerics=True,
                  gated=True, noise_model=True, gust_noise=False,
                  gust_check=True) -> DiagnoseResult:
    """The diagnose run in ``out`` (see :func:`run_diagnose`): base fit, integrator
    settings, then rounds until one ends the search, the time limit or ``max_rounds``;
    a checkpoint after every phase, the interrupted state written before re-raising."""
    from .refit import compile_seconds

    t_start = time.perf_counter()
    deadline = None if time_limit is None else time.monotonic() + float(time_limit)
    options = {"max_rounds": max_rounds, "max_candidates": max_candidates, "alpha": alpha,
               "min_score": min_score, "screen": screen, "effects": [e.id for e in catalogue],
               "time_limit_s": time_limit, "engine": engine.describe(), "numerics": numerics,
               "gated": gated, "noise_model": noise_model, "gust_noise": gust_noise,
               "gust_check": gust_check and not gust_noise}
    run = _RunConfig(out=out, gen=out / "generated", data=data, validate=validate,
                     catalogue=catalogue, max_rounds=max_rounds, max_candidates=max_candidates,
                     alpha=alpha, min_score=min_score, max_iter=max_iter, screen=screen,
                     numerics=numerics, gated=gated, noise_model=noise_model,
                     gust_noise=gust_noise, gust_check=gust_check, time_limit=time_limit,
                     deadline=deadline,
                     engine=engine, progress=progress, version=version,
                     build_document=build_document, write_findings=write_findings,
                     options=options, t_start=t_start, compile0=compile_seconds())
    st = _RunState()
    stop = StopReason.COMPLETED
    try:
        with engine:  # entered first: an unreachable cluster is refused before any fit
            _fit_base(run, st, spec)
            if not engine.serial:
                run.say(f"refits run on a {engine.describe()}")
            if numerics and not run.past_deadline():
                _numerics_stage(run, st)
            if noise_model and not run.past_deadline():
                _noise_model_stage(run, st)
            if gust_noise and not run.past_deadline():
                _gust_stage(run, st)
            end, rnd, physical_rounds = None, 0, 0
            # a round that accepts coloured turbulence (a disturbance model, not physics)
            # does not count against max_rounds: the physics search still has its rounds
            while physical_rounds < max_rounds:
                rnd += 1
                if noise_model and end is _RoundEnd.ACCEPTED and not run.past_deadline():
                    _noise_retest(run, st, rnd - 1)
                if run.past_deadline():
                    stop = StopReason.TIME_LIMIT
                    break
                n_accepted = len(st.accepted)
                end = _run_round(run, st, rnd)
                if not (len(st.accepted) > n_accepted
                        and (st.accepted[-1][0].candidate.info or {}).get("disturbance")):
                    physical_rounds += 1
                if end is _RoundEnd.TIME_LIMIT:
                    stop = StopReason.TIME_LIMIT
                if end not in (_RoundEnd.ACCEPTED, _RoundEnd.NOISE_MODEL):
                    break
            else:   # the last round accepted an effect: the recommended model's noise too
                if noise_model and end is _RoundEnd.ACCEPTED and not run.past_deadline():
                    _noise_retest(run, st, rnd)
    except KeyboardInterrupt:
        if st.evidence0 is not None:          # the base fit and its locate step are done
            _checkpoint(run, st, StopReason.INTERRUPTED)
            run.say(f"interrupted: {len(st.accepted)} accepted finding(s) and the unfinished "
                    f"round written to {out / 'findings.json'}")
        raise
    if stop is StopReason.TIME_LIMIT:
        run.say(f"time limit of {time_limit:g} s reached: stopping between refits")
    doc = _checkpoint(run, st, stop)
    return DiagnoseResult(out, tuple(doc["findings"]), pathlib.Path(doc["final_spec"]), doc,
                          st.base, st.current, st.evidence0, stop)


@dataclasses.dataclass(frozen=True)
class RoundDecision:
    """The decision at the end of a round: its record, the accepted trial (or None)."""

    record: dict
    best: Trial | None
    base_unconverged: bool = False


def validation_improved(state: FitState, current: FitState, x0_entropy: float = 0.0) -> bool:
    """The validation gate: the candidate's validation ELBO (less ``x0_entropy``, the entropy
    of its added states' initial values, which the current model's ELBO does not carry) above
    the current model's — each with the validation records' own noise when both have it
    (:func:`.fitstate.validate_own_noise`: noise is a property of the flight, the physics must
    carry over), else with the estimation's noise."""
    both = state.val_elbo_own_noise is not None and current.val_elbo_own_noise is not None
    vt = state.val_elbo_own_noise if both else state.val_elbo
    vc = current.val_elbo_own_noise if both else current.val_elbo
    return bool(vt - x0_entropy > vc)


def better_reference(before: FitState, better: FitState | None,
                     projected: Sequence[dict]) -> dict | None:
    """The round record's account of a better optimum of the current model (None when the
    projected refits found none): ELBO and validation ELBO before and after, the spec at the
    better optimum, and the candidate whose optimum, its new terms removed, led there."""
    if better is None:
        return None
    found = [p for p in projected if p.get("converged") and p.get("elbo") is not None]
    return {"elbo_before": _f(before.elbo), "elbo": _f(better.elbo),
            "val_elbo_before": _f(before.val_elbo), "val_elbo": _f(better.val_elbo),
            "spec": str(better.spec_path),
            "found_from": max(found, key=lambda p: p["elbo"])["key"] if found else None}


def _decide_round(rnd, trials, current, n_examined, alpha, table, projected,
                  reference: dict | None, *, not_refitted: Sequence[str] = ()) -> RoundDecision:
    """Holm over the round's family, validation check, best and its alternatives.
    ``reference``: :func:`better_reference` (the current model re-estimated at a better
    optimum, which ``current`` then is) or None. ``not_refitted``: the candidates the time
    limit left unrefitted (in the family with p = 1, as every examined candidate not refitted;
    the accepted effect's explanation says it was the best of those refitted)."""
    # an unconverged refit enters the Holm family with p = 1 — unless it stopped at its limit
    # with a positive-definite Hessian (stopped_short) or where no step raises its ELBO
    # (stopped_at_kink): its Λ is then a lower bound and its p an upper bound; so do the
    # candidates examined (screened) but not refitted
    n_family = max(n_examined, len(trials))
    decisions = holm([t.p_value if _decidable(t) and t.verdict is RefitVerdict.ORDINARY
                      else 1.0 for t in trials]
                     + [1.0] * (n_family - len(trials)), alpha)[:len(trials)]
    final_trials = []
    for t, (sig, level) in zip(trials, decisions):
        # a profiled delay's p-value carries the Bonferroni factor of its grid (.delay)
        thr = float(stats.chi2.isf(level / max(_grid_size(t.candidate), 1), max(t.dof, 1)))
        vok = None
        if sig and t.state is not None and t.state.vfit is not None:
            corr = t.refit.val_x0_entropy if t.refit is not None else 0.0
            vok = validation_improved(t.state, current, corr)
        final_trials.append(dataclasses.replace(t, threshold=thr, significant=bool(sig),
                                                validation_ok=vok))
    good = [t for t in final_trials if t.significant and t.validation_ok is not False
            and t.state is not None]
    record = {"round": rnd, "base_spec": str(current.spec_path),
              "base_elbo": current.elbo, "alpha": alpha, "n_candidates": n_family,
              "n_refitted": len(trials),
              "trials": [t.to_json() for t in final_trials], "screen": table,
              "projected_refits": projected}
    if not_refitted:
        record["not_refitted"] = list(not_refitted)
    if good and not refit_converged(current.fit):
        # an unconverged base ELBO is below its optimum: Λ would be inflated by the
        # refit merely finishing the base fit (a false positive), so nothing is accepted
        record["note"] = f"not accepted: the base fit did not converge ({current.fit.status})"
        return RoundDecision(record, None, base_unconverged=True)
    record["reference_improved"] = reference is not None
    if reference is not None:
        record["reference"] = reference
    if not good:
        return RoundDecision(record, None)
    # most significant = smallest p of the gain over the current model (the alternatives'
    # common reference, Trial.comparison), in logs that do not underflow (scipy's
    # chi2.logsf is −∞ beyond Λ ≈ 1400, where every strong candidate would tie: .pvalues), a
    # profiled delay's with the Bonferroni factor of its grid; fewer parameters win ties
    best = min(good, key=lambda t: (chi2_logsf(max(t.comparison, 0.0), max(t.dof, 1))
                                    + math.log(_search_size(t)), t.dof))
    best, hierarchy = linear_first(best, good)
    above = outranking_unconverged(final_trials, best)
    if above:
        # the round cannot accept an effect that a refit without an optimum already outranks
        # by its lower bound (lead_to_continue): neither is decided
        record["undecided"] = {"outranked": best.candidate.key,
                               "by": [t.candidate.key for t in above]}
        record["note"] = (
            f"not accepted: {best.candidate.key} (2ΔELBO {best.statistic:.4g}) is outranked by "
            + ", ".join(f"{t.candidate.key} (ELBO {t.state.elbo:.6g} against "
                        f"{best.state.elbo:.6g}, {conv_label(t.state.fit)})" for t in above)
            + ", whose refit stopped without an optimum: its 2ΔELBO is a lower bound, so the "
              "lower, converged effect is not the best explanation the data support")
        return RoundDecision(record, None)
    alternatives = alternatives_of(best, good)
    if hierarchy:
        c = best.candidate
        best = dataclasses.replace(best, candidate=dataclasses.replace(
            c, explanation=c.explanation + hierarchy["note"],
            info={**(c.info or {}), "hierarchy_over": hierarchy["over"]}))
    short = stopped_short(best)
    if short is not None:
        from ..estimator import StopReason

        c = best.candidate
        limit = "time" if best.state.fit.stop_reason is StopReason.TIME_LIMIT else "iteration"
        note = (f" Its refit stopped at its {limit}"
                f" limit before converging (positive-definite Hessian, λ²/2 = {short:.3g} nats "
                "predicted left): its 2ΔELBO is a lower bound of the converged one, so the effect "
                f"is significant, and its estimates are within about {math.sqrt(2 * short):.2g} "
                "standard errors of the optimum (rerun with a larger --max-iter to converge).")
        best = dataclasses.replace(best, candidate=dataclasses.replace(
            c, explanation=c.explanation + note,
            info={**(c.info or {}), "stopped_short_nats": short}))
    elif stopped_at_kink(best):
        c = best.candidate
        note = (" Its refit stopped where no step raises the ELBO, short of the gradient test "
                "(the Hessian indefinite there: a kink of the ELBO, e.g. a break point that "
                "samples straddle, or a direction along which it is flat, e.g. the level of an "
                "added state that the model's constant terms absorb): its 2ΔELBO is a lower "
                "bound of the maximum, so the effect "
                "is significant; its estimates are those of that point, without standard "
                "errors.")
        best = dataclasses.replace(best, candidate=dataclasses.replace(
            c, explanation=c.explanation + note, info={**(c.info or {}), "stopped_at_kink": True}))
    check = _physics_check(best)
    if check:
        c = best.candidate
        best = dataclasses.replace(best, candidate=dataclasses.replace(
            c, explanation=c.explanation + check, info={**(c.info or {}), "physics_check": check}))
    if not_refitted:
        c = best.candidate
        note = (f" Decided under the time limit on the {len(trials)} candidates refitted: "
                f"{', '.join(not_refitted)} were not refitted and count as not "
                "significant; rerun with a longer --time-limit to compare them with it.")
        best = dataclasses.replace(best, candidate=dataclasses.replace(
            c, explanation=c.explanation + note,
            info={**(c.info or {}), "not_refitted": list(not_refitted)}))
    return RoundDecision(record, dataclasses.replace(best, alternatives=alternatives))


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
    p.add_argument("data", nargs="+", help="estimation record(s) (CSV or MATLAB .mat)")
    p.add_argument("--validate", nargs="+", default=[], metavar="DATA",
                   help="validation record(s): an accepted effect must raise their ELBO too")
    p.add_argument("-o", "--out", required=True, help="output directory")
    p.add_argument("--max-rounds", type=int, default=3, help="maximum accepted physical effects (default 3; a round that "
                        "accepts coloured turbulence, a noise model, does not count)")
    p.add_argument("--max-candidates", type=int, default=8,
                   help="candidates refitted per round (default 8)")
    p.add_argument("--alpha", type=float, default=0.01,
                   help="family-wise significance level per round (default 0.01)")
    p.add_argument("--min-score", type=float, default=1.0,
                   help="minimum priority to refit a candidate: -log10 p of its score test, "
                        "or its locate score where it has no score statistic (default 1)")
    p.add_argument("--effects", nargs="+", default=None, metavar="ID",
                   help="restrict the catalogue to these effect ids")
    p.add_argument("--effects-module", action="append", default=None, metavar="PATH.py",
                   help="Python file defining extra Effect subclasses (repeatable)")
    p.add_argument("--max-iter", type=int, default=200, help="optimizer iterations per fit")
    p.add_argument("--no-numerics", action="store_true",
                   help="do not test the integrator settings (rk4, sub-steps, first-order hold "
                        "of the inputs) before the physical candidates")
    p.add_argument("--no-noise-model", action="store_true",
                   help="do not test correlated process noise (one gust acting on several "
                        "state equations) before the physical candidates")
    p.add_argument("--gust-noise", action="store_true",
                   help="also test turbulence in the air-relative velocity (a gust state in the "
                        "flow-angle and airspeed definitions of a body-axis model) before the "
                        "physical candidates (off by default; docs/diagnose.md, session 38)")
    p.add_argument("--no-gust-check", action="store_true",
                   help="do not test that turbulence in the air-relative velocity explains a "
                        "physical effect before accepting it (by default, on a body-axis model "
                        "whose flow angles are definitions, the gust alternative is refitted "
                        "when a round is about to accept an effect, and the effect must stay "
                        "significant with it)")
    p.add_argument("--per-candidate-models", action="store_true",
                   help="compile every candidate's own model (the reference path; by default "
                        "the candidates that add no state are gated terms of one model per "
                        "round, compiled once, and those that add states of one shape share "
                        "one compilation per worker)")
    p.add_argument("--screen", action=argparse.BooleanOptionalAction, default=True,
                   help="rank every candidate by the p-value of its score (Lagrange-multiplier) "
                        "statistic at the current fit before refitting (default; "
                        "--no-screen: by the locate score only)")
    from ..spec.overrides import add_override_arguments

    add_override_arguments(p)
    p.add_argument("--time-limit", type=float, default=None, metavar="SECONDS",
                   help="stop cleanly between refits after this many seconds; the effects "
                        "accepted so far and the unfinished round are written (exit status 1). "
                        "The base fit always runs to its end, so a run may take longer than "
                        "the limit when the base fit alone does")
    from ..engine import add_engine_arguments

    add_engine_arguments(p, what="candidate refits of a round")
    p.add_argument("--quiet", action="store_true", help="no progress messages")
    p.add_argument("--overwrite", action="store_true",
                   help="write into a non-empty DIR that is not a vsidgen results directory "
                        "(only vsidgen's files are replaced; other files are kept)")
    p.set_defaults(handler=diagnose_command)
    return p


def diagnose_command(args) -> int:
    """Handler of ``vsidgen diagnose``; exit status 0 (completed) or 1 (stopped at the time
    limit, or the base fit did not converge: inconclusive; what was found is written). An
    interrupt (Ctrl-C, SIGTERM) writes the findings and propagates (status 130)."""
    from ..compilecache import enable_compilation_cache
    from ..engine import terminate_as_interrupt
    from ..spec.overrides import overrides_of
    from ..progress import DiagnoseProgress

    ov = overrides_of(args)
    enable_compilation_cache()
    progress = None if args.quiet else DiagnoseProgress(sys.stderr)
    try:
        with terminate_as_interrupt():
            res = run_diagnose(args.spec, args.data, validate=args.validate, out=args.out,
                               max_rounds=args.max_rounds, max_candidates=args.max_candidates,
                               alpha=args.alpha, min_score=args.min_score, effects=args.effects,
                               effects_module=args.effects_module, max_iter=args.max_iter,
                               screen=args.screen, time_limit=args.time_limit,
                               workers=args.workers, scheduler=args.scheduler, progress=progress,
                               numerics=not args.no_numerics,
                               noise_model=not args.no_noise_model,
                               gust_noise=args.gust_noise,
                               gust_check=not args.no_gust_check,
                               gated=not args.per_candidate_models,
                               overwrite=args.overwrite, overrides=ov)
    finally:
        if progress is not None:
            progress.close()
    from .findings import summary_lines  # the conclusion says when the run stopped early
    for line in summary_lines(res.document, res.out_dir / "findings.json"):
        print(line)
    base_ok = bool((res.document.get("base_fit") or {}).get("converged", True))
    return 0 if res.stop is StopReason.COMPLETED and base_ok else 1
