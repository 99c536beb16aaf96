"""The noise model re-tested after a round accepts an effect (session 48).

The first noise-model test runs on the base fit, whose path still carries the missing physics:
on an independent lateral record a roll-gyro bias hid the turbulence's correlation (S = 8.4 <
11.3) and the recommended spec kept diagonal noise, while the same record without the bias
adopts the full factor. Diagnose now repeats the test after every round that accepted an
effect while the noise is still diagonal. Here: when it runs and when it is skipped (the
orchestration, with the stage itself stubbed), and that the conclusion, the CLI summary and the
report agree on an adopted re-test. The end-to-end case (a numpy simulation with a gyro bias
and a correlated gust) is the slow test at the end.
"""

from __future__ import annotations

import math
import pathlib
import types

import pytest

from vsidgen.discrepancy import noisemodel, search
from vsidgen.discrepancy.findings import noise_retest_text, report_section, summary_lines
from vsidgen.discrepancy.noisemodel import (NoiseAlternative, NoiseModelResult, NoiseModelTrial,
                                            NoiseModelVerdict, decide)


def _model(structure="diagonal"):
    pn = types.SimpleNamespace(states=("a", "b"), structure=structure, estimate=True)
    return types.SimpleNamespace(process_noise=pn, state_names=("a", "b"), name="m")


def _trial(gain, *, converged=True, verdict=None):
    st = types.SimpleNamespace(elbo=100.0 + gain)
    t = decide(NoiseModelTrial(NoiseAlternative.CORRELATED, pathlib.Path("n.yaml"), 1, st,
                               converged=converged, correlations=(("a", "b", -0.7),)),
               100.0, 0.01)
    return t


def _result(*trials, adopted=None):
    return NoiseModelResult("diagonal", ("a", "b"), 100.0, tuple(trials), 0.01, adopted)


@pytest.fixture
def stubbed(monkeypatch):
    """search._noise_retest with the stage, the checkpoint and locate stubbed: returns the
    list of calls of the stage and a function that runs the re-test on a state."""
    calls = []
    outcome = {}

    def fake_run(current, out, **kw):
        calls.append(kw["after_round"])
        return outcome["result"]

    monkeypatch.setattr(noisemodel, "run_noise_model", fake_run)
    monkeypatch.setattr(search, "_checkpoint", lambda run, st, stop, **kw: {})
    monkeypatch.setattr(search, "locate_state", lambda st: ("evidence of", st))
    run = types.SimpleNamespace(out=pathlib.Path("o"), alpha=0.01, gen=pathlib.Path("g"),
                                max_iter=10, engine=None, deadline=None, progress=None)

    def go(st, after_round, result):
        outcome["result"] = result
        search._noise_retest(run, st, after_round)

    return calls, go


def test_a_significant_retest_is_adopted_and_the_search_continues_with_it(stubbed):
    calls, go = stubbed
    current = types.SimpleNamespace(model=_model())
    adopted_state = types.SimpleNamespace(model=_model("full"), elbo=120.0)
    t = NoiseModelTrial(NoiseAlternative.CORRELATED, pathlib.Path("r1_n01.yaml"), 1,
                        adopted_state, statistic=40.0, threshold=6.6, converged=True,
                        verdict=NoiseModelVerdict.ADOPTED)
    st = search._RunState(current=current, noiseres=_result(_trial(1.0)))
    go(st, 1, _result(t, adopted=t))
    assert calls == [1]
    assert st.current is adopted_state and st.evidence == ("evidence of", adopted_state)
    assert [k for k, _ in st.noise_retests] == [1]


def test_not_significant_keeps_the_model(stubbed):
    calls, go = stubbed
    current = types.SimpleNamespace(model=_model())
    st = search._RunState(current=current, noiseres=_result(_trial(1.0)))
    go(st, 2, _result(_trial(2.0)))
    assert calls == [2] and st.current is current and len(st.noise_retests) == 1


@pytest.mark.parametrize("case", ["full", "unresolved_first", "unresolved_retest", "gust"])
def test_the_retest_is_skipped_where_it_cannot_change_anything(stubbed, case):
    calls, go = stubbed
    current = types.SimpleNamespace(model=_model("full" if case == "full" else "diagonal"))
    unresolved = _trial(50.0, converged=False)
    assert unresolved.verdict is NoiseModelVerdict.SIGNIFICANT_NOT_CONVERGED
    st = search._RunState(current=current,
                          noiseres=_result(unresolved if case == "unresolved_first"
                                           else _trial(1.0)),
                          gustres={"adopted": {"x": 1}} if case == "gust" else None)
    if case == "unresolved_retest":
        st.noise_retests.append((1, _result(unresolved)))
    go(st, 2, _result(_trial(20.0)))
    assert calls == [] and st.current is current


def test_an_adopted_retest_agrees_in_conclusion_summary_and_report():
    t = _trial(20.0)
    assert t.verdict is NoiseModelVerdict.ADOPTED
    r = {"after_round": 1, **_result(t, adopted=t).to_json()}
    text = noise_retest_text([r])
    assert "re-tested after round 1" in text and "ρ(a, b) = -0.70" in text
    assert "40" in text and "structure: full" in text
    doc = {"noise_model": _result(_trial(1.0)).to_json(), "noise_model_retests": [r],
           "findings": [], "conclusion": "Something accepted." + text}
    lines = summary_lines(doc, "f.json")
    assert lines[0].startswith("+ noise model re-tested after round 1 (not physics): "
                               "use noise: {process: {structure: full}}")
    assert "40" in lines[0] and "-0.70" in lines[1]
    assert lines[-1].startswith(doc["conclusion"])
    html = report_section({**doc, "locate": {}})
    assert "Noise model re-tested after round 1" in html and "adopted" in html
    # a re-test that kept the diagonal noise adds no sentence, only its table
    kept = {"after_round": 2, **_result(_trial(1.0)).to_json()}
    assert noise_retest_text([kept]) == ""
    html = report_section({**doc, "noise_model_retests": [kept], "locate": {}})
    assert "still not significant" in html


# ---------------------------------------------------------------- end to end (slow)

@pytest.mark.slow
def test_a_gyro_bias_that_hid_the_gust_correlation_is_followed_by_the_noise_model(tmp_path):
    """Independent reference: the numpy simulation of tests/test_diagnose_noise_model.py (the
    Euler-discrete short period, one gust with ρ = 0.4 between the α and q equations), with a
    q-gyro bias of 0.02 rad/s added to the recorded q. On the biased base fit the score test
    of correlated noise is far below its threshold (measured S = 0.21 < 6.63): the bias, not
    the gust, dominates the path. Round 1 names the bias; the re-test then adopts the full
    factor with ρ̂ near the simulation's (measured S = 48.4, 2ΔELBO 42.1, ρ̂ = +0.43), and the
    final spec carries it. Before session 48 the final spec kept the diagonal noise."""
    import yaml

    from test_diagnose_noise_model import SPEC, _simulate
    from vsidgen.discrepancy import run_diagnose

    spec = tmp_path / "sp2.yaml"
    spec.write_text(SPEC)
    t, u, y, G = _simulate(0.4, seed=3)
    y = y.copy()
    y[:, 1] += 0.02
    csv = tmp_path / "rec.csv"
    csv.write_text("t,de,alpha,q\n" + "".join(
        f"{float(t[k])!r},{float(u[k])!r},{float(y[k, 0])!r},{float(y[k, 1])!r}\n"
        for k in range(len(t))))
    Q = G @ G.T
    rho = float(Q[0, 1] / math.sqrt(Q[0, 0] * Q[1, 1]))
    res = run_diagnose(spec, [csv], out=tmp_path / "o", max_rounds=1, max_candidates=2,
                       effects=["sensor_bias"], numerics=False)
    doc = res.document
    first = doc["noise_model"]
    assert first["adopted"] is None
    (t0,) = first["trials"]
    assert t0["decided_by"] == "score" and t0["score"]["statistic"] < t0["score"]["threshold"]
    (f,) = doc["findings"]
    assert f["key"] == "sensor_bias:q"
    b = f["parameters"]["D_BIAS_q"]
    assert abs(b["estimate"] - 0.02) < 3 * b["std_error"]
    (r,) = doc["noise_model_retests"]
    assert r["after_round"] == 1 and r["adopted"] is not None
    assert r["adopted"]["statistic"] > r["adopted"]["threshold"]
    (c,) = r["adopted"]["correlations"]
    assert abs(c["rho"] - rho) < 0.1
    final = pathlib.Path(doc["final_spec"])
    assert final == pathlib.Path(r["adopted"]["spec"]) and final.name.startswith("r1_n01_")
    assert yaml.safe_load(final.read_text())["noise"]["process"]["structure"] == "full"
    assert "NOISE MODEL re-tested after round 1" in doc["conclusion"]
