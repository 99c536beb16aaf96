"""Physical parameterisations of the diagnose catalogue: sensor positions in metres with the
model's own airspeed (local air velocity v + ω × r; specific force a + ω̇ × r)."""

from __future__ import annotations

import pathlib

import pytest
import sympy

from vsidgen.discrepancy.base import model_info, propose

ROOT = pathlib.Path(__file__).resolve().parents[1]
HFB = ROOT / "specs" / "hfb320.yaml"
ATTAS = ROOT / "specs" / "attas_sp.yaml"
LAT = ROOT / "benchmarks" / "independent" / "specs" / "lat_beta.yaml"


def _candidate(spec, key):
    info = model_info(spec, dt=0.05)
    return info, next(c for c in propose(info) if c.key == key)


def _observation(spec, cand, output, tmp_path):
    from vsidgen.spec import compile_spec

    p = tmp_path / "cand.yaml"
    p.write_text(cand.spec_yaml(spec, name="cand_pos", candidate_path=p))
    sym = compile_spec(p)
    i = [v.name for v in sym.outputs].index(output)
    return sym, sym.observations_expanded()[i]


def _subs(sym, values):
    names = {s.name: s for s in sym.observations_expanded()[0].free_symbols}
    for e in sym.observations_expanded() + sym.drift_expanded():
        names.update({s.name: s for s in e.free_symbols})
    return {names[k]: v for k, v in values.items() if k in names}


def test_alpha_vane_lever_arm_in_metres_with_the_model_airspeed(tmp_path):
    _, c = _candidate(HFB, "sensor_position:alpha:q")
    (p,) = c.parameters
    assert p.unit == "m" and "ahead of the CG" in p.description
    sym, h = _observation(HFB, c, "alpha", tmp_path)
    vals = {"alpha": 0.1, "q": 0.05, "V": 100.0, "theta": 0.0, p.name: 8.0}
    got = float(h.xreplace(_subs(sym, vals)))
    # a vane 8 m ahead of the CG pitching up at 0.05 rad/s at 100 m/s reads 0.004 rad less
    assert got == pytest.approx(0.1 - 8.0 * 0.05 / 100.0, abs=1e-15)


def test_beta_vane_on_a_nose_boom_uses_the_trim_speed_constant(tmp_path):
    _, c = _candidate(LAT, "sensor_position:beta:r")
    (p,) = c.parameters
    assert p.unit == "m"
    sym, h = _observation(LAT, c, "beta", tmp_path)
    vals = {"beta": 0.02, "r": 0.1, "V0": 100.0, p.name: 6.0}
    got = float(h.xreplace(_subs(sym, vals)))
    # v + r x: a yaw rate to the right raises the sideslip seen ahead of the CG
    assert got == pytest.approx(0.02 + 6.0 * 0.1 / 100.0, abs=1e-15)


def test_accelerometer_ahead_of_the_cg_reads_minus_x_qdot(tmp_path):
    _, c = _candidate(HFB, "sensor_position:az:q")
    (p,) = c.parameters
    assert p.unit == "m" and "ahead of the CG" in p.description
    sym, h = _observation(HFB, c, "az", tmp_path)
    slope = sympy.diff(h, [s for s in h.free_symbols if s.name == p.name][0])
    i_q = [v.name for v in sym.states].index("q")
    assert sympy.simplify(slope + sym.drift_expanded()[i_q]) == 0   # ∂az/∂x = −q̇


def test_vane_without_an_airspeed_keeps_seconds():
    _, c = _candidate(ATTAS, "sensor_position:alpha:q")
    assert c.parameters[0].unit == "s"


# ---------------------------------------------------------------------------
# decisions: optimizer failures and non-causal estimates are not test results
# ---------------------------------------------------------------------------

def test_refit_verdicts():
    from vsidgen.discrepancy.refit import RefitVerdict, refit_verdict

    # the refit ended 286 nats below its nesting point: an optimizer failure, not a rejection
    assert refit_verdict(-572.0, {"D": 0.1}, {}) is RefitVerdict.BELOW_NESTING_POINT
    assert refit_verdict(-0.01, {"D": 0.1}, {}) is RefitVerdict.ORDINARY   # at the start
    # a β channel "early" by 0.035 s is non-causal under the time-skew label
    assert refit_verdict(11.3, {"D_SKEW_beta": -0.035}, {"D_SKEW_beta": 1}) \
        is RefitVerdict.NON_CAUSAL
    assert refit_verdict(11.3, {"D_SKEW_beta": 0.035}, {"D_SKEW_beta": 1}) \
        is RefitVerdict.ORDINARY


def test_a_lag_at_the_end_of_its_labels_range_is_not_accepted_as_that_label():
    """An actuator lag whose time constant ended at the catalogue's upper limit (5 s: the
    spec value 4.99999917 of a new user's Tu-144 model without trim terms) is beyond the
    label's range; an interior one (0.15 s) and a Padé delay inside its 1 s are ordinary."""
    import types

    import numpy as np

    from vsidgen.discrepancy.refit import RefitVerdict, refit_verdict
    from vsidgen.discrepancy.search import trial_verdict

    assert refit_verdict(3022.0, {"T": 4.99999917}, {}, {"T": 5.0}) is RefitVerdict.BEYOND_RANGE
    assert refit_verdict(3022.0, {"T": 0.15}, {}, {"T": 5.0}) is RefitVerdict.ORDINARY
    for key, upper in (("actuator_lag:de", 5.0), ("control_delay:de", 1.0)):
        _, c = _candidate(ATTAS, key)
        (p,) = c.parameters
        assert c.info["label_upper"] == {p.name: upper} and p.upper == upper
        st = types.SimpleNamespace(model=types.SimpleNamespace(parameter_names=("MQ", p.name)),
                                   fit=types.SimpleNamespace(theta=np.array([-2.0, upper])))
        assert trial_verdict(c, st, 3022.0) is RefitVerdict.BEYOND_RANGE
        st.fit.theta[1] = 0.3 * upper
        assert trial_verdict(c, st, 3022.0) is RefitVerdict.ORDINARY
        # an interior estimate whose 95 % interval reaches the label's end is beyond it too
        st.fit.theta[1] = 0.97 * upper
        st.fit.std_errors = np.array([0.1, 0.03 * upper])
        assert trial_verdict(c, st, 3022.0) is RefitVerdict.BEYOND_RANGE
        st.fit.std_errors = np.array([0.1, 0.01 * upper])
        assert trial_verdict(c, st, 3022.0) is RefitVerdict.ORDINARY


def test_an_estimate_within_its_interval_of_the_labels_end_is_beyond_range():
    """The 95 % rule (upper − θ̂ < 1.96 s.e.): a new user's ATTAS roll model accepted a
    left-aileron Padé delay of 0.970 ± 0.030 s under a 1-s label; an unknown s.e. leaves
    only the relative rule; a delay profile whose best grid value is its last is at the end."""
    from vsidgen.discrepancy.delay import delay_grid
    from vsidgen.discrepancy.refit import RANGE_Z, RefitVerdict, refit_verdict

    assert refit_verdict(20.0, {"D": 0.970}, {}, {"D": 1.0}, {"D": 0.030}) \
        is RefitVerdict.BEYOND_RANGE
    assert refit_verdict(20.0, {"D": 0.970}, {}, {"D": 1.0}, {"D": 0.015}) \
        is RefitVerdict.ORDINARY
    assert refit_verdict(20.0, {"D": 0.970}, {}, {"D": 1.0}, {"D": float("nan")}) \
        is RefitVerdict.ORDINARY
    # the boundary is the quantile itself
    se = 0.03 / RANGE_Z
    assert refit_verdict(20.0, {"D": 0.97}, {}, {"D": 1.0}, {"D": se * 1.001}) \
        is RefitVerdict.BEYOND_RANGE
    assert refit_verdict(20.0, {"D": 0.97}, {}, {"D": 1.0}, {"D": se * 0.999}) \
        is RefitVerdict.ORDINARY
    # a non-positive statistic is an optimiser failure first
    assert refit_verdict(-5.0, {"D": 0.99}, {}, {"D": 1.0}, {"D": 0.03}) \
        is RefitVerdict.BELOW_NESTING_POINT
    g = delay_grid(0.05)
    assert refit_verdict(20.0, {"D": g[-1]}, {}, {"D": g[-1]}, {"D": float("nan")}) \
        is RefitVerdict.BEYOND_RANGE


def test_time_skew_is_causal_and_its_explanation_has_no_unfilled_number():
    _, c = _candidate(HFB, "time_skew:alpha")
    (p,) = c.parameters
    assert c.info["causal_sign"] == {p.name: 1}
    assert "lag of 0 s" not in c.explanation and "peaks at" not in c.explanation


def test_trial_verdict_reads_the_refitted_estimates():
    import types

    import numpy as np

    from vsidgen.discrepancy.refit import RefitVerdict
    from vsidgen.discrepancy.search import trial_verdict

    _, c = _candidate(LAT, "time_skew:beta")
    (p,) = c.parameters
    st = types.SimpleNamespace(model=types.SimpleNamespace(parameter_names=("YB", p.name)),
                               fit=types.SimpleNamespace(theta=np.array([-0.1, -0.035])))
    assert trial_verdict(c, st, 11.3) is RefitVerdict.NON_CAUSAL
    st.fit.theta[1] = 0.02
    assert trial_verdict(c, st, 11.3) is RefitVerdict.ORDINARY
    assert trial_verdict(c, st, -40.0) is RefitVerdict.BELOW_NESTING_POINT


def _trial(key, stat, thr, *, converged=True, verdict="ordinary", significant=False):
    return {"key": key, "statistic": stat, "threshold": thr, "converged": converged,
            "verdict": verdict, "significant": significant, "validation_ok": None,
            "status": "converged" if converged else "iteration limit"}


def test_conclusion_flags_failures_and_the_cli_prints_it_last(tmp_path):
    from vsidgen.discrepancy.findings import conclusion_text, summary_lines

    rounds = [{"round": 1, "trials": [
        _trial("control_delay:de", -1017.0, 15.8, verdict="below_nesting_point"),
        _trial("time_skew:beta", 11.3, 10.9, verdict="non_causal"),
        _trial("sensor_position:beta:r", 6.1, 11.0),
        _trial("actuator_lag:de", 3022.0, 13.9, verdict="beyond_range", converged=False)]}]
    text = conclusion_text([], rounds, alpha=0.01, validated=False, final_spec="x.yaml")
    assert "optimizer failure" in text and "control_delay:de" in text
    assert "non-causal" in text and "time_skew:beta" in text
    assert "upper end of the range its label allows" in text and "actuator_lag:de (2ΔELBO = 3022)" in text
    assert "did not converge" not in text     # named once, as refused under its label
    doc = {"conclusion": text, "findings": []}
    lines = summary_lines(doc, tmp_path / "findings.json")
    assert lines[-1].startswith(text)
    # an inconclusive run says so on the CLI's last line, exactly as findings.json does
    rounds = [{"round": 1, "trials": [_trial("unmodelled_wind:alpha", 6627.0, 13.6,
                                             converged=False)]}]
    text = conclusion_text([], rounds, alpha=0.01, validated=False, final_spec="x.yaml")
    lines = summary_lines({"conclusion": text, "findings": []}, tmp_path / "findings.json")
    assert text.startswith("INCONCLUSIVE") and lines[-1].startswith("INCONCLUSIVE")


def test_cli_lines_show_estimates_with_units(tmp_path):
    from vsidgen.discrepancy.findings import summary_lines

    f = {"rank": 1, "effect": "sensor_position", "target": "output:beta",
         "explanation": "The beta sensor is not at the centre of gravity.",
         "parameters": {"D_POS_beta_r": {"estimate": 7.93, "std_error": 0.21, "unit": "m",
                                         "fixed": False}},
         "evidence": {"statistic": 52.0, "threshold": 11.0}, "alternatives": [],
         "ambiguous": False}
    doc = {"findings": [f], "conclusion": "1 significant discrepancy found: sensor_position on "
                                          "output:beta. Final augmented spec: c.yaml."}
    lines = summary_lines(doc, tmp_path / "findings.json")
    assert any("D_POS_beta_r = 7.93 ± 0.21 m" in ln for ln in lines)
    assert lines[-1].startswith(doc["conclusion"])


def test_an_alternative_accepted_in_a_later_round_is_complementary_not_ambiguous(tmp_path):
    """A new user's Twin Otter model without trim constants and without an a_z bias: the a_z
    bias (round 1) was reported AMBIGUOUS with the trim constants, whose one-step predictions
    were far better (Vuong z −4.5); round 2 accepts the trim constants on top of it — both
    were missing, so they are complementary, and the conclusion, the CLI lines and the
    report say so; an alternative that no later round accepted stays one."""
    from vsidgen.discrepancy.findings import (complementary_findings, conclusion_text,
                                              report_section, summary_lines)

    def alt(key, effect, stat, added=None):
        return {"key": key, "effect": effect, "target": "drift:q", "statistic": stat,
                "added_terms": added,
                "vuong": {"z": -4.5, "p_value": 7.8e-6, "loglik_difference": -86005.8, "n": 376}}

    def finding(rank, key, effect, target, stat, alternatives):
        return {"rank": rank, "key": key, "effect": effect, "target": target,
                "title": effect, "explanation": "x", "parameters": {}, "added_terms": {},
                "evidence": {"statistic": stat, "threshold": 14.4, "dof": 1, "alpha": 0.01,
                             "n_candidates": 51, "elbo_before": 1.0, "elbo_after": 2.0},
                "alternatives": alternatives,
                "ambiguous": any(a["effect"] != effect for a in alternatives)}

    both = {"drift": {"alpha": "D_TRIM_alpha", "q": "D_TRIM_q"}}
    findings = [finding(1, "sensor_bias:az", "sensor_bias", "output:az", 3238.1,
                        [alt("trim_term:all", "trim_term", 781.9, both),
                         alt("trim_term:q", "trim_term", 659.1, {"drift": {"q": "D_TRIM_q"}}),
                         alt("missing_derivative:q:theta", "missing_derivative", 324.4,
                             {"drift": {"q": "D_q_theta*theta"}})]),
                finding(2, "trim_term:all", "trim_term", "drift:all", 950.0, [])]
    findings[1]["added_terms"] = both
    complementary_findings(findings)
    f1 = findings[0]
    assert [a["key"] for a in f1["alternatives"]] == ["missing_derivative:q:theta"]
    assert f1["ambiguous"]                         # the one no later round accepted
    # the same candidate, and one whose terms the later finding contains
    assert [(c["key"], c["accepted_in_round"]) for c in f1["complementary"]] == [
        ("trim_term:all", 2), ("trim_term:q", 2)]
    text = conclusion_text(findings, [], alpha=0.01, validated=False, final_spec="x.yaml")
    assert "trim_term:all, not separated from sensor_bias:az in its round, was accepted on " \
           "top of it in round 2" in text
    assert "AMBIGUOUS: sensor_bias:az" in text and "is not clearly better than " \
           "missing_derivative:q:theta" in text
    lines = summary_lines({"conclusion": text, "findings": findings}, tmp_path / "f.json")
    assert any(ln.strip().startswith("complementary: trim_term on drift:q") for ln in lines)
    html_text = report_section({"conclusion": text, "findings": findings, "rounds": []},
                               base=None, final=None, accepted=[])
    assert "Complementary:" in html_text
    # nothing accepted later: the alternative stays
    again = [finding(1, "sensor_bias:az", "sensor_bias", "output:az", 3238.1,
                     [alt("trim_term:all", "trim_term", 781.9)])]
    complementary_findings(again)
    assert again[0]["alternatives"] and "complementary" not in again[0]


# ---------------------------------------------------------------------------
# locate scores: exact −log10 p, no saturation
# ---------------------------------------------------------------------------

def test_locate_scores_do_not_saturate_and_keep_their_order():
    import math

    import numpy as np
    from scipy import stats

    from vsidgen.discrepancy.locate import _score, corr_test

    rng = np.random.default_rng(0)
    n = 4000
    seg = [slice(0, n)]
    r = rng.standard_normal(n)
    strong = corr_test(r + 0.05 * rng.standard_normal(n), r, seg, name="strong")
    weaker = corr_test(r + 0.3 * rng.standard_normal(n), r, seg, name="weaker")
    moderate = corr_test(0.05 * r + rng.standard_normal(n), r, seg, name="moderate")
    assert strong.p == 0.0 and weaker.p == 0.0            # both underflow in double precision
    assert _score(strong.log10_p(), 10) > _score(weaker.log10_p(), 10) > 30.0
    # where p does not underflow, the log is the textbook two-sided t-test p-value
    c2 = moderate.corr ** 2
    t = math.sqrt(c2 * (moderate.n_eff - 2) / (1 - c2))
    ref = math.log10(2 * stats.t.sf(t, moderate.n_eff - 2))
    assert moderate.log10_p() == pytest.approx(ref, rel=1e-9)
    assert _score(moderate.log10_p(), 10) == pytest.approx(max(0.0, -ref - 1.0), rel=1e-9)


def test_t_tail_in_logs_matches_scipy_where_scipy_is_finite():
    import math

    from scipy import special, stats

    from vsidgen.discrepancy.locate import _t_log10p

    for t, df in ((5.0, 30.0), (30.0, 400.0), (37.0, 3000.0)):
        ref = math.log10(2.0) + stats.t.logsf(t, df) / math.log(10.0)
        assert math.isfinite(ref)
        # DLMF 8.17.8, the form used beyond scipy's range, agrees with scipy inside it
        a, b, x = 0.5 * df, 0.5, df / (df + t * t)
        series = (a * math.log(x) + b * math.log1p(-x) - math.log(a) - special.betaln(a, b)
                  + math.log(special.hyp2f1(a + b, 1.0, a + 1.0, x))) / math.log(10.0)
        assert series == pytest.approx(ref, rel=1e-9)
        assert _t_log10p(t, df) == pytest.approx(ref, rel=1e-12)
    assert math.isfinite(_t_log10p(60.0, 3000.0)) and _t_log10p(60.0, 3000.0) < -240


def test_a_continued_lead_without_progress_is_decided_on_its_lower_bound():
    """The round's unconverged lead, continued, that rose by less than the optimizer's
    convergence tolerance per iteration sits on a ridge or kink (the speed candidate on the real
    HFB-320 record: 7064.72 → 7064.73 in 800 iterations): on_plateau, and stopped_at_kink
    then decides it on its lower bound; a continuation that climbs is not a plateau."""
    import dataclasses as dc
    from types import SimpleNamespace as NS

    from vsidgen.discrepancy.search import Trial, on_plateau, stopped_at_kink
    from vsidgen.estimator import StopReason

    def state(elbo, it, reason=StopReason.ITERATION_LIMIT):
        return NS(elbo=elbo, fit=NS(iterations=it, stop_reason=reason, converged=False,
                                    newton_decrement=float("nan")))
    before = state(7064.72, 800)
    assert on_plateau(before, state(7064.73, 1600))
    assert not on_plateau(before, state(7070.0, 1600))            # 5.3 nats: climbing
    assert on_plateau(before, before, budget=800)                  # continuation ended lower
    assert not on_plateau(before, state(7064.73, 1600, StopReason.NEWTON_DECREMENT))
    t = Trial(candidate=None, score=0.0, spec_path=None, state=state(7064.73, 1600),
              statistic=394.1, dof=4, p_value=1e-80)
    assert not stopped_at_kink(t)
    assert stopped_at_kink(dc.replace(t, plateau=True))


def test_input_filters_are_ranked_with_the_size_of_their_search():
    """A transport delay found over a grid of delays and a lag whose time constant the screen
    profiled are ranked each with its own search's Bonferroni factor (sp_de_delay_0.04_s0: the
    delay's 214.9 against the lag's 211.2 over the current model; with the delay's grid alone
    penalised the lag was named)."""
    from types import SimpleNamespace as NS

    from vsidgen.discrepancy.base import Candidate
    from vsidgen.discrepancy.search import Trial, _search_size

    def trial(effect, info=None, multiplicity=None):
        c = Candidate(effect=effect, key=f"{effect}:de", target="input:de", explanation="",
                      info=info or {})
        screen = None if multiplicity is None else NS(multiplicity=multiplicity)
        return Trial(candidate=c, score=0.0, spec_path=None, state=None, statistic=1.0,
                     dof=1, p_value=0.5, screen=screen)
    assert _search_size(trial("transport_delay", {"profile_result": {"grid_s": [0.02] * 11}},
                              multiplicity=11)) == 11
    assert _search_size(trial("actuator_lag", multiplicity=16)) == 16
    assert _search_size(trial("control_delay", multiplicity=8)) == 8
    assert _search_size(trial("actuator_lag")) == 1                 # not screened
    assert _search_size(trial("sensor_bias", multiplicity=4)) == 1  # not an input filter
