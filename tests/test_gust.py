"""The air-relative gust alternative of the noise-model stage (:mod:`vsidgen.discrepancy.gust`):
which models it applies to, what it writes, and its test's reference distribution."""

import math
import pathlib
import types

import numpy as np
import pytest
from scipy import stats

from vsidgen.discrepancy.base import model_info
from vsidgen.discrepancy.gust import gust_dof, gust_plans, write_gust_spec
from vsidgen.discrepancy.noisemodel import NoiseAlternative, NoiseModelTrial, decide
from vsidgen.spec import compile_spec

ROOT = pathlib.Path(__file__).resolve().parents[1]
BODY = ROOT / "benchmarks" / "independent" / "specs" / "hfb_body.yaml"


def _current(spec, mean):
    """The parts of a diagnose FitState that the gust plan reads (a fit at ``mean``)."""
    sym = compile_spec(spec)
    model = types.SimpleNamespace(
        name=sym.name, state_names=tuple(v.name for v in sym.states),
        parameter_names=tuple(p.name for p in sym.parameters), parameters=sym.parameters,
        process_noise=sym.process_noise)
    fit = types.SimpleNamespace(smoothers=[types.SimpleNamespace(mu=np.tile(mean, (8, 1)))],
                                theta=np.zeros(len(model.parameter_names)))
    return types.SimpleNamespace(spec_path=spec, fit=fit, model=model)


def test_body_axis_model_gets_a_gust_in_its_flow_angle_definitions(tmp_path):
    """A user's body-axis model (α = atan2(w, u), V = sqrt(u² + w²) as definitions): the gust
    perturbs w, the component α is most sensitive to, in both definitions, and nowhere else
    (the kinematic drift keeps the inertial w)."""
    cur = _current(BODY, [104.0, 8.0, 0.0, 0.08])
    (p,) = gust_plans(cur, model_info(BODY, dt=0.05))
    assert (p.role, p.velocity, p.unit) == ("alpha", "w", "m/s")
    assert set(p.definitions) == {"Vt", "a"}
    assert p.tau_start == pytest.approx(0.05) and p.tau_bounds[0] == pytest.approx(0.025)
    path = write_gust_spec(cur, [p], tmp_path / "gust.yaml", "hfb_body_gust")
    sym = compile_spec(path)
    assert [v.name for v in sym.states] == ["u", "w", "q", "theta", p.gust]
    assert sym.process_noise.states == ("u", "w", "q", "theta", p.gust)
    defs = dict(sym.definitions)
    W, w, u = (next(s for s in defs["a"].free_symbols if s.name == n) for n in (p.gust, "w", "u"))
    assert defs["a"].equals(__import__("sympy").atan2(w - W, u))
    drift = dict(zip((v.name for v in sym.states), sym.drift))
    assert W not in drift["w"].free_symbols and W not in drift["u"].free_symbols
    # noise std and correlation time (diagonal structure)
    assert gust_dof(cur, [p]) == 2


@pytest.mark.parametrize("spec", ["specs/hfb320.yaml", "specs/attas_lat.yaml",
                                  "benchmarks/independent/specs/lat_beta.yaml",
                                  "benchmarks/users/hfb_sp.yaml"])
def test_no_gust_where_the_flow_angles_are_states(spec):
    path = ROOT / spec
    n = len(compile_spec(path).states)
    assert gust_plans(_current(path, np.ones(n)), model_info(path, dt=0.05)) == []


def test_gust_multiplicity_counts_the_correlation_times_in_its_range():
    """The gust's p-value is multiplied by the number of √2-spaced correlation times between
    half an integration step and the upper bound: counted here on the grid itself (24 at
    20 Hz), and the threshold that gives is above χ²_k at α alone."""
    cur = _current(BODY, [104.0, 8.0, 0.0, 0.08])
    (p,) = gust_plans(cur, model_info(BODY, dt=0.05))
    lo, hi = p.tau_bounds
    grid = [lo * math.sqrt(2.0) ** k for k in range(200) if lo * math.sqrt(2.0) ** k <= hi]
    assert p.multiplicity == len(grid) == 24
    k, alpha = gust_dof(cur, [p]), 0.01
    lam = float(stats.chi2.isf(alpha, k)) + 1.0
    t = decide(NoiseModelTrial(NoiseAlternative.AIR_GUST, pathlib.Path("g.yaml"), k,
                               types.SimpleNamespace(elbo=lam / 2), converged=True),
               0.0, alpha / p.multiplicity)
    assert t.verdict.value == "not_significant"


def test_adopted_gust_is_reported_as_noise_model_not_physics():
    """The CLI lines and the conclusion sentence name an adopted gust as a noise-model finding,
    with its numbers (findings.json ``noise_gust``)."""
    from vsidgen.discrepancy.findings import noise_gust_text, summary_lines

    ng = {"gusts": [{"velocity": "w", "gust_state": "D_GUST_w", "definitions": {"a": "", "Vt": ""}}],
          "trials": [{}],
          "adopted": {"statistic": 361.4, "threshold": 15.2, "dof": 7,
                      "recommendation": "add the gust state(s) of r0_g01.yaml",
                      "explanation": "Noise model, not physics: the turbulence enters ..."}}
    text = noise_gust_text(ng)
    assert text.startswith("NOISE MODEL (not a physical effect)") and "w − D_GUST_w" in text
    assert "361.4 > 15.2" in text
    lines = summary_lines({"noise_gust": ng, "findings": [], "conclusion": "c."}, "findings.json")
    assert any(l.startswith("0. noise model (not physics): add the gust state") for l in lines)
    assert noise_gust_text({"trials": [{}], "adopted": None}) == ""


@__import__("dataclasses").dataclass(frozen=True)
class _Cand:
    key: str
    explanation: str


def _check_setup(monkeypatch, *, adopted: bool, lam_with: float | None, converged=True):
    """A run state whose round lead (Λ 26.1 > 19.2, a pitch mode) is checked against a
    mocked gust alternative and a mocked refit on the gust model."""
    from vsidgen.discrepancy import gust, search
    from vsidgen.discrepancy.noisemodel import NoiseModelResult
    from vsidgen.discrepancy.refit import RefitVerdict

    g = types.SimpleNamespace(elbo=16415.6, val_elbo=None, model=None, name="gust")
    cur = types.SimpleNamespace(elbo=16234.9, name="current")
    gtrial = types.SimpleNamespace(state=g, spec_path=pathlib.Path("r0_g01.yaml"))
    res = NoiseModelResult("diagonal", ("u", "w", "q", "theta"), cur.elbo,
                           (object(),), 0.01, gtrial if adopted else None)
    monkeypatch.setattr(gust, "run_gust_model", lambda *a, **k: (res, ["plan"]))
    monkeypatch.setattr(gust, "to_json", lambda r, plans: {
        "trials": [{"statistic": 361.4 if adopted else 3.0, "threshold": 24.5}],
        "adopted": {"statistic": 361.4, "threshold": 24.5, "dof": 2,
                    "recommendation": "add the gust state(s) of r0_g01.yaml",
                    "explanation": "Noise model, not physics"} if adopted else None,
        "gusts": [{"velocity": "w", "gust_state": "D_GUST_w", "definitions": {"a": ""}}]})
    monkeypatch.setattr(search, "model_info_of", lambda st: None)
    monkeypatch.setattr(search, "locate_state", lambda st: ("evidence of", st.name))
    monkeypatch.setattr(search, "_checkpoint", lambda *a, **k: None)
    cand = _Cand("missing_dynamics:q:q", "A mode.")
    best = search.Trial(cand, 3.0, pathlib.Path("r1_01.yaml"), object(), 26.1, 3, 1e-4,
                        threshold=19.2, significant=True, converged=True,
                        verdict=RefitVerdict.ORDINARY)
    refits = []

    def refit_on(run, b, gg, rnd):
        refits.append((b.candidate.key, gg.name))
        if lam_with is None:
            return None
        return search.Trial(_Cand(cand.key, "A mode."), 3.0, pathlib.Path("r1_gust.yaml"),
                            types.SimpleNamespace(vfit=None, fit=types.SimpleNamespace(
                                stop_reason=None)), lam_with, 3, 1e-3,
                            converged=converged,
                            verdict=RefitVerdict.BELOW_NESTING_POINT if lam_with < -0.1
                            else RefitVerdict.ORDINARY)

    monkeypatch.setattr(search, "_refit_on", refit_on)
    monkeypatch.setattr(search, "_continue_lead", lambda run, rnd, trials, cur, n, dl: trials)
    run = types.SimpleNamespace(alpha=0.01, gen=None, max_iter=200, engine=None, out=None,
                                deadline=None, progress=None, past_deadline=lambda: False,
                                say=lambda m: None)
    st = search._RunState(current=cur, rounds=[{"round": 1, "trials": []}])
    return search, run, st, best, g, refits


@pytest.mark.parametrize("lam_with, converged, outcome", [
    (7.0, True, "explained_by_gust"), (25.0, False, "undecided_with_gust"),
    (12.0, False, "explained_by_gust"),
    (None, True, "explained_by_gust"), (-2.17, True, "explained_by_gust"),
    (40.0, True, "significant_with_gust")])
def test_a_lead_the_air_relative_gust_explains_is_not_accepted(monkeypatch, lam_with, converged,
                                                               outcome):
    """The gust check (:func:`vsidgen.discrepancy.search._gust_check`): with the gust
    significant it is adopted as the current model and the lead is refitted on it; the lead is
    kept only when it is still above the round's threshold there (converged), and the
    conclusion sentence says which, with the numbers."""
    from vsidgen.discrepancy.findings import noise_gust_text

    search, run, st, best, g, refits = _check_setup(monkeypatch, adopted=True,
                                                    lam_with=lam_with, converged=converged)
    out = search._gust_check(run, st, 1, best)
    assert st.current is g and st.evidence == ("evidence of", "gust")
    assert refits == [("missing_dynamics:q:q", "gust")]
    ch = st.gustres["checked"]
    assert ch["outcome"] == outcome and ch["statistic_without_gust"] == 26.1
    text = noise_gust_text(st.gustres)
    assert text.startswith("NOISE MODEL (not a physical effect)")
    if outcome == "undecided_with_gust":
        assert out is None and "UNDECIDED" in text
    elif outcome == "explained_by_gust":
        assert out is None and st.rounds[-1]["gust_check"]["outcome"] == outcome
        assert "NOT ACCEPTED" in text and "missing_dynamics:q:q was significant" in text
        if lam_with is not None and not converged:
            assert "stayed at 2ΔELBO = 12 ≤ 19.2 without converging" in text
        assert "26.1 > 19.2" in text
        if lam_with is not None and lam_with < 0:
            # a refit below its nesting point is flagged as an optimizer failure, not a test
            assert "did not rise above its nesting point (2ΔELBO = -2.17: an optimizer " \
                   "failure, flagged, not a test result)" in text and "≤" not in text
            assert st.gustres["checked"]["verdict_with_gust"] == "below_nesting_point"
        elif lam_with is not None and converged:
            assert f"2ΔELBO = {lam_with:.4g} ≤ 19.2" in text
    else:
        trial, own = out
        assert own and trial.statistic == 40.0 and trial.threshold == 19.2 and trial.significant
        assert "40 > 19.2 (without the gust 26.1)" in trial.candidate.explanation
        assert "stays significant with the gust (2ΔELBO = 40 > 19.2" in text
        assert st.rounds[-1]["gust_check"]["outcome"] == outcome


def test_a_gust_that_is_not_significant_leaves_the_lead_as_it_is(monkeypatch):
    from vsidgen.discrepancy.findings import noise_gust_text

    search, run, st, best, g, refits = _check_setup(monkeypatch, adopted=False, lam_with=7.0)
    cur = st.current
    trial, own = search._gust_check(run, st, 1, best)
    assert trial is best and not own and st.current is cur and refits == []
    assert st.gustres["checked"]["outcome"] == "gust_not_significant"
    assert st.rounds[-1]["gust_check"]["outcome"] == "gust_not_significant"
    text = noise_gust_text(st.gustres)
    assert "rival explanation of missing_dynamics:q:q" in text and "3 ≤ 24.5" in text


def test_the_conclusion_names_significant_candidates_the_gust_model_did_not_retest():
    """A run that ends on the round whose lead the gust explained says which of that round's
    other significant candidates were never refitted on the gust model, and how to test them."""
    from vsidgen.discrepancy.findings import conclusion_text

    check = {"round": 1, "key": "missing_dynamics:q:q", "outcome": "explained_by_gust"}
    trials = [{"key": "missing_dynamics:q:q", "significant": True},
              {"key": "coefficient_derivative:CL:q", "significant": True},
              {"key": "time_skew:alpha", "significant": False}]
    rounds = [{"round": 1, "trials": trials, "gust_check": check, "n_candidates": 40}]
    text = conclusion_text([], rounds, alpha=0.01, validated=False, final_spec="x.yaml")
    assert "once the turbulence in the air-relative velocity is modelled" in text
    assert "not re-tested on the adopted gust model" in text
    assert "coefficient_derivative:CL:q" in text and "time_skew:alpha" not in text
    assert "--max-rounds 2" in text
    # a later round searched on the gust model: nothing to add
    rounds.append({"round": 2, "trials": [], "n_candidates": 40})
    assert "not re-tested" not in conclusion_text([], rounds, alpha=0.01, validated=False, final_spec="x.yaml")


def test_a_lead_accepted_without_time_for_the_gust_check_says_so(monkeypatch):
    """Past the time limit the check is not run; on a model it applies to, the accepted
    effect's explanation says it was not tested against the gust (and how to test it)."""
    from vsidgen.discrepancy import gust, search

    search_, run, st, best, g, refits = _check_setup(monkeypatch, adopted=True, lam_with=7.0)
    monkeypatch.setattr(gust, "applicable_plans", lambda cur, info: ["plan"])
    out = search._gust_not_checked(st, best)
    assert "Not tested against turbulence in the air-relative velocity" in out.candidate.explanation
    assert "--time-limit" in out.candidate.explanation and refits == []
    monkeypatch.setattr(gust, "applicable_plans", lambda cur, info: [])
    assert search._gust_not_checked(st, best) is best


def test_a_lead_still_climbing_on_the_gust_model_is_undecided_not_explained(monkeypatch):
    """A refit on the gust model above the threshold that neither converged nor stopped at a
    kink or a limit with a positive-definite Hessian (continued once, still climbing) is
    undecided: not accepted, not called explained by the turbulence, and the conclusion is
    INCONCLUSIVE (hfbb_lift_stall_1_s0: a stall break 442.5 > 19.2 on the gust model, not
    converged, had been reported as explained)."""
    from vsidgen.discrepancy.findings import conclusion_text, noise_gust_text

    search, run, st, best, g, refits = _check_setup(monkeypatch, adopted=True, lam_with=442.5,
                                                    converged=False)
    continued = []
    monkeypatch.setattr(search, "_continue_lead",
                        lambda run, rnd, trials, cur, n, dl: continued.append(cur) or trials)
    assert search._gust_check(run, st, 1, best) is None
    assert continued == [g]
    ch = st.gustres["checked"]
    assert ch["outcome"] == "undecided_with_gust"
    text = noise_gust_text(st.gustres)
    assert "UNDECIDED" in text and "explained by the turbulence:" not in text
    assert "≥ 442.5" in text
    c = conclusion_text([], st.rounds, alpha=0.01, validated=False, final_spec="x.yaml")
    assert c.startswith("INCONCLUSIVE") and "once the turbulence" not in c


def test_a_lead_at_a_kink_on_the_gust_model_is_kept(monkeypatch):
    """A hinge refit that stops at a kink (no further progress) is decided on its Λ, a lower
    bound, as in the round itself."""
    from vsidgen.discrepancy import search as s
    from vsidgen.estimator import StopReason

    search, run, st, best, g, refits = _check_setup(monkeypatch, adopted=True, lam_with=442.5,
                                                    converged=False)
    orig = s._refit_on

    def at_kink(*a, **k):
        t = orig(*a, **k)
        t.state.fit.stop_reason = StopReason.NO_PROGRESS
        return t

    monkeypatch.setattr(s, "_refit_on", at_kink)
    trial, own = search._gust_check(run, st, 1, best)
    assert own and trial.statistic == 442.5
    assert st.gustres["checked"]["outcome"] == "significant_with_gust"
