"""Modelling numerics before physics (vsidgen.discrepancy.numerics): the settings proposed,
the decision rule and how findings.json, the CLI summary and the report carry an adopted
setting."""

from __future__ import annotations

import math
import pathlib
import types

import pytest

from scipy import stats

from vsidgen.discrepancy.findings import numerics_text, report_section, summary_lines
from vsidgen.discrepancy.numerics import (NumericsResult, NumericsSetting, NumericsTrial,
                                          NumericsVerdict, decide, numerics_settings)


def test_settings_change_one_thing_and_skip_the_foh_no_op():
    cur = NumericsSetting("euler", 1, "zoh")
    got = {s.text for s in numerics_settings(cur)}
    assert got == {"integrator: {method: euler, substeps: 4, inputs: zoh}",
                   "integrator: {method: euler, substeps: 4, inputs: foh}",
                   "integrator: {method: rk4, substeps: 1, inputs: zoh}",
                   "integrator: {method: rk4, substeps: 1, inputs: foh}"}
    # one Euler step with a first-order hold evaluates the input at u_k only: never proposed
    assert NumericsSetting("euler", 1, "foh") not in numerics_settings(cur)
    assert numerics_settings(NumericsSetting("rk4", 4, "foh")) == []
    assert [s.text for s in numerics_settings(NumericsSetting("rk4", 4, "zoh"))] == [
        "integrator: {method: rk4, substeps: 4, inputs: foh}"]


def _trial(setting, gain, converged=True):
    st = types.SimpleNamespace(elbo=100.0 + gain)
    return NumericsTrial(setting, pathlib.Path("x.yaml"), st, 2.0 * gain, converged=converged)


def test_decide_holm_threshold_of_one_parameter_and_cheapest_of_near_ties():
    a = NumericsSetting("rk4", 1, "foh")
    b = NumericsSetting("euler", 4, "foh")
    c = NumericsSetting("rk4", 1, "zoh")
    trials = [_trial(a, 30.0), _trial(b, 29.8), _trial(c, 1.0)]
    out, adopted = decide(trials, 100.0, 0.01)
    thr = [t.threshold for t in out]
    # ranks by statistic: a (α/3), b (α/2), c (α/1), χ²₁ quantiles
    assert math.isclose(thr[0], stats.chi2.isf(0.01 / 3, 1))
    assert math.isclose(thr[1], stats.chi2.isf(0.01 / 2, 1))
    assert math.isclose(thr[2], stats.chi2.isf(0.01, 1))
    # a and b are within 0.5 nats and cost the same (4 drift evaluations per sample): the
    # larger ELBO; c is not significant
    assert adopted is not None and adopted.verdict is NumericsVerdict.ADOPTED
    assert adopted.setting == a and out[1].verdict is NumericsVerdict.SIGNIFICANT
    d = NumericsSetting("euler", 4, "zoh")
    e = NumericsSetting("rk4", 4, "zoh")  # 16 evaluations: loses the near tie
    _, adopted = decide([_trial(e, 30.0), _trial(d, 29.9)], 100.0, 0.01)
    assert adopted.setting == d
    assert [t.verdict for t in out].count(NumericsVerdict.ADOPTED) == 1
    assert out[2].verdict is NumericsVerdict.NOT_SIGNIFICANT


def test_decide_never_adopts_an_unconverged_or_small_gain():
    a = NumericsSetting("rk4", 1, "foh")
    out, adopted = decide([_trial(a, 50.0, converged=False)], 100.0, 0.01)
    assert adopted is None and out[0].verdict is NumericsVerdict.NOT_CONVERGED
    thr1 = stats.chi2.isf(0.01, 1)
    out, adopted = decide([_trial(a, 0.49 * thr1)], 100.0, 0.01)
    assert adopted is None and out[0].verdict is NumericsVerdict.NOT_SIGNIFICANT
    out, adopted = decide([_trial(a, 0.51 * thr1)], 100.0, 0.01)
    assert adopted is out[0]
    failed = NumericsTrial(a, pathlib.Path("x.yaml"), None, error="failed: boom")
    out, adopted = decide([failed], 100.0, 0.01)
    assert adopted is None and out[0].verdict is NumericsVerdict.FAILED


def test_adopted_setting_in_findings_summary_and_report_agree():
    cur = NumericsSetting("euler", 1, "zoh")
    t = _trial(NumericsSetting("rk4", 1, "foh"), 40.0)
    trials, adopted = decide([t], 100.0, 0.01)
    doc_num = NumericsResult(cur, 100.0, tuple(trials), 0.01, adopted).to_json()
    rec = doc_num["adopted"]["recommendation"]
    assert rec == "use integrator: {method: rk4, substeps: 1, inputs: foh}"
    assert doc_num["adopted"]["statistic"] == 80.0
    text = numerics_text(doc_num)
    assert text.startswith("MODELLING NUMERICS (not a physical effect): " + rec)
    doc = {"numerics": doc_num, "findings": [], "conclusion": text + "No significant discrepancy."}
    lines = summary_lines(doc, "f.json")
    assert lines[0].startswith("0. modelling numerics (not physics): " + rec)
    assert "80" in lines[0] and rec in lines[-1]
    html = report_section({**doc, "locate": {}})
    assert "Modelling numerics (tested before physics)" in html and "adopted" in html
    assert numerics_text(NumericsResult(cur, 100.0, (), 0.01).to_json()) == ""


class _FakeEngine:
    """Runs nothing: each numerics refit returns a state with the ELBO gain given per setting."""

    def __init__(self, gains):
        self.gains, self.asked = gains, []

    def run(self, fn, tasks, deadline=None):
        from vsidgen.engine import TaskOutcome, TaskStatus
        out = []
        for key, args in tasks:
            self.asked.append(key)
            fit = types.SimpleNamespace(converged=True, stop_reason=None)
            st = types.SimpleNamespace(elbo=100.0 + self.gains[key], fit=fit)
            out.append(TaskOutcome(key, TaskStatus.DONE, st))
        return out


def _run(tmp_path, gains):
    from vsidgen.discrepancy.numerics import run_numerics
    model = types.SimpleNamespace(integrator="euler", substeps=1, input_hold="zoh", name="m")
    current = types.SimpleNamespace(model=model, elbo=100.0,
                                    fit=types.SimpleNamespace(converged=True, stop_reason=None))
    eng = _FakeEngine(gains)
    res = run_numerics(current, tmp_path, alpha=0.01, generated_dir=None, max_iter=10, engine=eng)
    return res, eng


def test_most_accurate_setting_first_and_the_rest_only_when_it_is_significant(tmp_path):
    """With m = 4 settings Holm adopts nothing unless the largest 2ΔELBO clears χ²₁ at α/4:
    the most accurate setting of each input hold (rk4 with the first-order hold, rk4 with the
    held inputs) is refitted first and, when both stay below that level, the two coarser ones
    are not refitted; the decision is unchanged."""
    labels = [s.label for s in numerics_settings(NumericsSetting("euler", 1, "zoh"))]
    strictest = float(stats.chi2.isf(0.01 / 4, 1))
    low = {k: 0.5 * 0.9 * strictest for k in labels}
    res, eng = _run(tmp_path, low)
    assert eng.asked == ["rk4x1_foh", "rk4x1_zoh"]
    assert res.adopted is None
    verdicts = {t.setting.label: t.verdict for t in res.trials}
    assert verdicts.pop("rk4x1_foh") is NumericsVerdict.NOT_SIGNIFICANT
    assert verdicts.pop("rk4x1_zoh") is NumericsVerdict.NOT_SIGNIFICANT
    assert set(verdicts.values()) == {NumericsVerdict.NOT_TRIED}
    assert {t["verdict"] for t in res.to_json()["trials"]} == {"not_significant", "not_tried"}
    # significant: every setting is refitted and the cheapest within 0.5 nats is adopted
    high = {"rk4x1_foh": 50.0, "rk4x1_zoh": 20.0, "eulerx4_foh": 49.9, "eulerx4_zoh": 10.0}
    res, eng = _run(tmp_path, high)
    assert sorted(eng.asked) == sorted(labels) and eng.asked[:2] == ["rk4x1_foh", "rk4x1_zoh"]
    assert res.adopted is not None and res.adopted.setting.label in ("rk4x1_foh", "eulerx4_foh")
    assert not any(t.verdict is NumericsVerdict.NOT_TRIED for t in res.trials)


def test_a_held_input_setting_is_not_skipped_because_the_first_order_hold_lost(tmp_path):
    """The input hold is not an accuracy (session 46, a new user's Twin Otter lateral record:
    rk4 with the first-order hold lost 620.6 while rk4 with held inputs gained): the held-input
    probe is refitted beside it, and when it is significant every setting is refitted and the
    best adopted."""
    gains = {"rk4x1_foh": -310.0, "rk4x1_zoh": 30.0, "eulerx4_foh": -200.0, "eulerx4_zoh": 12.0}
    res, eng = _run(tmp_path, gains)
    assert eng.asked[:2] == ["rk4x1_foh", "rk4x1_zoh"] and sorted(eng.asked) == sorted(gains)
    assert res.adopted is not None and res.adopted.setting.label == "rk4x1_zoh"
    assert res.adopted.statistic == 60.0


@pytest.mark.slow
def test_null_record_from_continuous_time_adopts_interpolated_inputs(tmp_path):
    """The independent simulator's null short-period record (continuous time, elevator moving
    between samples, no concealed effect): the numerics stage adopts a first-order hold
    (measured: rk4 + foh, 2ΔELBO 242 > 9.1) and no physical effect is named."""
    import sys
    ROOT = pathlib.Path(__file__).resolve().parents[1]
    sys.path.insert(0, str(ROOT / "benchmarks" / "independent"))
    import sim

    from vsidgen.discrepancy import run_diagnose

    cols, _ = sim.simulate_sp(effect="none", magnitude=0.0, seed=0)
    csv = tmp_path / "rec.csv"
    sim.write_csv(csv, cols)
    res = run_diagnose(ROOT / "specs" / "attas_sp.yaml", [csv], out=tmp_path / "o", max_rounds=0)
    ad = res.document["numerics"]["adopted"]
    assert ad is not None and ad["setting"]["inputs"] == "foh"
    assert ad["statistic"] > ad["threshold"]
    assert res.findings == ()
    # the final spec carries the setting, in its own text or through the spec it extends
    # (the noise-model spec adopted after the numerics stage extends the numerics spec; the
    # text check predated that stage and failed before session 47 too)
    from vsidgen.spec import compile_spec
    assert compile_spec(res.document["final_spec"]).input_hold == "foh"
