"""``vsidgen diagnose`` never loses what it found: time limit, interruption, SIGTERM.

The base fit is real (ATTAS short period, synthetic record, fitted once per module); the
candidate refits are replaced by stand-ins that return a known outcome instantly, raise an
interrupt, or let a simulated clock run past the time limit, so the checkpoint logic is
tested without the cost of real refits. The candidates are ranked by their locate scores
(``screen=False``, ``--no-screen``): on this clean synthetic record no score test reaches
``--min-score``, so the default ranking would refit nothing, and the ranking is not what
these tests check.
"""

from __future__ import annotations

import dataclasses
import json
import os
import pathlib
import signal
import time

import pytest

from vsidgen.discrepancy import findings, search
from vsidgen.discrepancy.refit import RefitOutcome

# one worker runs the whole module: its module-scoped fixtures are computed once
pytestmark = pytest.mark.xdist_group("test_diagnose_resilience")

ROOT = pathlib.Path(__file__).resolve().parents[1]
SPEC = ROOT / "specs" / "attas_sp.yaml"
DATA = ROOT / "data" / "attas_sp_synthetic.csv"
EFFECTS = ["sensor_bias", "time_skew", "missing_derivative"]


@pytest.fixture(scope="module")
def base_state(tmp_path_factory):
    gen = tmp_path_factory.mktemp("gen")
    st = search.fit_spec(SPEC, [DATA], generated_dir=gen, max_iter=200)
    assert st.fit.converged
    return st


class _Refits:
    """Stand-in for ``staged_refit``: the n-th call (0-based) does ``actions[n]``.

    "same": the current model's own fit (Λ = 0); "gain": the same fit with the ELBO raised
    by 50 nats (Λ = 100, significant); "short": that gain stopped at the iteration limit with
    an indefinite Hessian (undecidable as it is); "interrupt": KeyboardInterrupt; "sigterm": SIGTERM to
    this process; ("slow", s[, action]): advance the simulated clock by s seconds, then do
    ``action`` ("same" when not given).
    """

    def __init__(self, actions, clock=None):
        self.actions = list(actions)
        self.calls = []
        self.clock = clock

    def __call__(self, c, current, info, path, name, *, generated_dir, max_iter, progress=None,
                 model=None):
        n = len(self.calls)
        self.calls.append(c.key)
        act = self.actions[n] if n < len(self.actions) else "same"
        if act == "interrupt":
            raise KeyboardInterrupt
        if act == "sigterm":
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(5)
            raise AssertionError("SIGTERM did not interrupt")
        if isinstance(act, tuple) and act[0] == "slow":
            self.clock.offset += act[1]
            act = act[2] if len(act) > 2 else "same"
        st = current
        if act == "gain":
            st = dataclasses.replace(current, fit=dataclasses.replace(current.fit,
                                                                       elbo=current.elbo + 50.0))
        if act == "short":     # 50 nats up, stopped at its iteration limit, Hessian indefinite
            from vsidgen.estimator import StopReason

            st = dataclasses.replace(current, fit=dataclasses.replace(
                current.fit, elbo=current.elbo + 50.0, converged=False,
                stop_reason=StopReason.ITERATION_LIMIT, newton_decrement=float("nan")))
        return RefitOutcome(state=st, elbo_ref=current.elbo, warm="stand-in")


class _Clock:
    def __init__(self, real):
        self.real = real
        self.offset = 0.0

    def __call__(self):
        return self.real() + self.offset


@pytest.fixture
def patched(monkeypatch, base_state):
    monkeypatch.setattr(search, "fit_spec", lambda *a, **k: base_state)
    monkeypatch.setattr(search, "projected_refit", lambda t, current, *a, **k: current)
    from vsidgen.discrepancy import gated, noisemodel, numerics

    # the integrator settings and noise-model stages keep the current model without refitting
    monkeypatch.setattr(numerics, "run_numerics", lambda current, out, *, alpha, **k:
                        numerics.NumericsResult(numerics.NumericsSetting.of(current.model),
                                                current.elbo, (), alpha))
    monkeypatch.setattr(noisemodel, "run_noise_model", lambda current, out, *, alpha, **k:
                        noisemodel.NoiseModelResult("diagonal", (), current.elbo, (), alpha))

    def install(actions, clock=None):
        r = _Refits(actions, clock)
        monkeypatch.setattr(search, "staged_refit", r)
        # the stand-ins replace the per-candidate refit: no candidate goes to the gated model
        monkeypatch.setattr(gated, "gateable", lambda c: False)
        return r
    return install


def _doc(out):
    return json.loads((out / "findings.json").read_text())


def test_time_limit_stops_between_refits_and_keeps_the_accepted_effect(patched, monkeypatch,
                                                                       tmp_path):
    clock = _Clock(time.monotonic)
    monkeypatch.setattr(time, "monotonic", clock)
    # round 1: first candidate significant (accepted); round 2: the first refit "takes"
    # 1000 s of the 600 s limit, so the second one does not start
    # (min_score 0: an accepted candidate is not proposed again, so round 2 needs a second
    # candidate above the locate threshold beside the one it refits)
    refits = patched(["gain", "same", ("slow", 1000.0)], clock)
    res = search.run_diagnose(SPEC, [DATA], out=tmp_path / "o", max_rounds=3, max_candidates=2,
                              screen=False, effects=EFFECTS, time_limit=600.0, workers=1,
                              min_score=0.0)
    assert res.stop is search.StopReason.TIME_LIMIT
    assert len(refits.calls) == 3                  # 2 in round 1, 1 in round 2, none after
    doc = _doc(tmp_path / "o")
    assert doc["stop"]["reason"] == "time_limit" and doc["stop"]["time_limit_s"] == 600.0
    assert [f["key"] for f in doc["findings"]] == [refits.calls[0]]
    assert doc["findings"][0]["evidence"]["statistic"] == pytest.approx(100.0)
    # round 2 is decided on its one refit (nothing significant); the other is named
    assert doc["unfinished_round"] is None and len(doc["rounds"]) == 2
    r2 = doc["rounds"][1]
    assert [t["key"] for t in r2["trials"]] == [refits.calls[2]]
    assert len(r2["not_refitted"]) == 1 and refits.calls[2] not in r2["not_refitted"]
    assert doc["stop"]["partial_round"]["not_refitted"] == r2["not_refitted"]
    assert doc["conclusion"].startswith("STOPPED at the time limit")
    assert "after deciding round 2 on the 1 of 2 candidates" in doc["conclusion"]
    assert "1 effect accepted" in doc["conclusion"]
    assert (tmp_path / "o" / "diagnose.html").read_text().count("STOPPED") >= 1


def test_a_round_cut_by_its_refit_deadline_is_decided_on_what_it_refitted(patched, monkeypatch,
                                                                         base_state, tmp_path):
    """The round keeps the current model's fit time for its decision: a refit that ends
    after the round's refit deadline (limit − that time) but before the limit cuts the rest,
    and the round is decided on it (the lead's projected refit runs in the time kept): the
    significant gain is accepted, its explanation naming the candidate not refitted."""
    clock = _Clock(time.monotonic)
    monkeypatch.setattr(time, "monotonic", clock)
    slow_base = dataclasses.replace(base_state, fit=dataclasses.replace(base_state.fit,
                                                                         wall_time_s=200.0))
    monkeypatch.setattr(search, "fit_spec", lambda *a, **k: slow_base)
    refits = patched([("slow", 450.0, "gain")], clock)
    res = search.run_diagnose(SPEC, [DATA], out=tmp_path / "o", max_rounds=3, max_candidates=2,
                              screen=False, effects=EFFECTS, time_limit=600.0, workers=1)
    assert res.stop is search.StopReason.TIME_LIMIT and len(refits.calls) == 1
    doc = _doc(tmp_path / "o")
    assert [f["key"] for f in doc["findings"]] == [refits.calls[0]]
    (r1,) = doc["rounds"]
    assert len(r1["not_refitted"]) == 1 and r1["projected_refits"]
    assert r1["not_refitted"][0] in doc["findings"][0]["explanation"]
    assert "Decided under the time limit" in doc["findings"][0]["explanation"]


def test_a_refit_running_at_the_refit_deadline_stops_there():
    """diag_options inside refit_deadline: the estimator's time limit is the time left."""
    from vsidgen.discrepancy.fitstate import diag_options, refit_deadline
    from vsidgen.discrepancy.family import TaskDeadline

    assert diag_options(10).time_limit is None
    with refit_deadline(TaskDeadline.of(time.monotonic() + 50.0)):
        assert 45.0 < diag_options(10).time_limit <= 50.0
        assert diag_options(10, time_limit=5.0).time_limit == 5.0
    with refit_deadline(TaskDeadline.of(time.monotonic() - 1.0)):
        assert diag_options(10).time_limit == 0.0          # one iteration, then TIME_LIMIT
    assert diag_options(10).time_limit is None


def test_an_unfinished_round_names_its_leading_refit_without_accepting_it(patched, monkeypatch,
                                                                          tmp_path):
    clock = _Clock(time.monotonic)
    monkeypatch.setattr(time, "monotonic", clock)
    # round 1: nothing significant; round 2 does not exist (max_rounds 1): the first refit
    # gains 50 nats and uses up the time limit, so the second one does not start
    refits = patched([("slow", 1000.0, "gain")], clock)
    res = search.run_diagnose(SPEC, [DATA], out=tmp_path / "o", max_rounds=1, max_candidates=2,
                              screen=False, effects=EFFECTS, time_limit=600.0, workers=1)
    assert res.stop is search.StopReason.TIME_LIMIT and len(refits.calls) == 1
    doc = _doc(tmp_path / "o")
    assert doc["findings"] == []                          # an unfinished round accepts nothing
    lead = findings.leading_refit(doc["unfinished_round"], 0.05)
    assert lead["key"] == refits.calls[0] and lead["statistic"] == pytest.approx(100.0)
    assert f"Leading so far, not decided: {refits.calls[0]} (2ΔELBO 100" in doc["conclusion"]


def test_leading_refit_text_checks_validation_and_skips_what_cannot_be_used():
    def trial(key, stat, p, *, conv=True, verdict="ordinary", val=None, h0=0.0):
        return {"key": key, "statistic": stat, "p_value": p, "converged": conv,
                "verdict": verdict, "val_elbo": val, "refit": {"val_x0_entropy": h0}}
    un = {"round": 1, "pending": ["c"], "base_val_elbo": 100.0,
          "refitted": [trial("a", 500.0, 1e-100, conv=False),              # unconverged
                       trial("b", 400.0, 1e-80, verdict="non_causal"),     # non-causal
                       trial("d", 3.0, 0.08),                               # not significant
                       trial("e", 40.0, 1e-9, val=120.0, h0=30.0)]}        # 90 < 100 corrected
    assert findings.leading_refit(un, 0.05)["key"] == "e"
    text = findings.stop_text({"reason": "time_limit", "time_limit_s": 60}, un, 0)
    assert "Leading so far, not decided: e (2ΔELBO 40" in text
    assert "validation ELBO 90 against the current model's 100 (not higher" in text
    un["refitted"][-1]["val_elbo"] = 140.0
    assert "110 against the current model's 100 (higher)" in findings.stop_text(
        {"reason": "time_limit"}, un, 0)
    # the gate's own-noise validation ELBOs, where both have them (search.validation_improved)
    un["base_val_elbo_own_noise"] = 200.0
    un["refitted"][-1]["val_elbo_own_noise"] = 220.0
    assert "190 against the current model's 200 (not higher" in findings.stop_text(
        {"reason": "time_limit"}, un, 0)
    del un["base_val_elbo_own_noise"]
    # the unconverged refit above the lead is named beside it, not as the lead
    assert "refitted without converging above it: a (2ΔELBO 500 when it stopped" in text
    un["refitted"] = un["refitted"][:3]
    text = findings.stop_text({"reason": "time_limit"}, un, 0)
    assert "Leading" not in text and "refitted without converging: a (2ΔELBO 500" in text


def test_interrupt_writes_the_accepted_effect_and_the_unfinished_round(patched, tmp_path):
    refits = patched(["gain", "same", "interrupt"])
    with pytest.raises(KeyboardInterrupt):
        search.run_diagnose(SPEC, [DATA], out=tmp_path / "o", max_rounds=3, max_candidates=2,
                            screen=False, effects=EFFECTS, workers=1)
    doc = _doc(tmp_path / "o")
    assert doc["stop"]["reason"] == "interrupted"
    assert [f["key"] for f in doc["findings"]] == [refits.calls[0]]
    assert len(doc["rounds"]) == 1
    un = doc["unfinished_round"]
    assert un["round"] == 2 and un["refitted"] == [] and refits.calls[2] in un["pending"]
    assert doc["conclusion"].startswith("INTERRUPTED during round 2")


def test_checkpoint_after_every_refit_says_running(patched, tmp_path):
    out = tmp_path / "o"
    seen = []

    def peek(*a, **k):
        if (out / "findings.json").is_file():
            seen.append(_doc(out))
        return refits_impl(*a, **k)
    refits_impl = patched(["same", "same"])
    import vsidgen.discrepancy.search as s
    s.staged_refit, orig = peek, s.staged_refit
    try:
        search.run_diagnose(SPEC, [DATA], out=out, max_rounds=1, max_candidates=2,
                            screen=False, effects=EFFECTS, workers=1)
    finally:
        s.staged_refit = orig
    assert [d["stop"]["reason"] for d in seen] == ["running", "running"]
    assert [len(d["unfinished_round"]["refitted"]) for d in seen] == [0, 1]
    final = _doc(out)
    assert final["stop"]["reason"] == "completed" and final["unfinished_round"] is None
    assert final["findings"] == [] and final["conclusion"].startswith("No significant")


def test_cli_sigterm_and_time_limit_exit_codes(patched, monkeypatch, tmp_path, capsys):
    from vsidgen.cli import main

    monkeypatch.setenv("VSIDGEN_CACHE_DIR", "")
    patched(["gain", "sigterm"])
    rc = main(["diagnose", str(SPEC), str(DATA), "--out", str(tmp_path / "t"), "--workers", "1",
               "--no-screen",
               "--max-candidates", "1", "--effects", *EFFECTS, "--quiet"])
    assert rc == 130
    doc = _doc(tmp_path / "t")
    assert doc["stop"]["reason"] == "interrupted" and len(doc["findings"]) == 1
    assert signal.getsignal(signal.SIGTERM) is not None
    capsys.readouterr()
    patched([])
    rc = main(["diagnose", str(SPEC), str(DATA), "--out", str(tmp_path / "l"), "--workers", "1",
               "--no-screen",
               "--time-limit", "1e-6", "--effects", *EFFECTS, "--quiet"])
    assert rc == 1
    line = capsys.readouterr().out
    assert line.startswith("STOPPED at the time limit") and "no significant" not in line
    assert _doc(tmp_path / "l")["stop"]["reason"] == "time_limit"
    assert main(["diagnose", str(SPEC), str(DATA), "--out", str(tmp_path / "x"), "--no-screen",
                 "--time-limit", "-3"]) == 2


def test_cli_exit_status_1_and_no_verdict_when_the_base_fit_did_not_converge(monkeypatch,
                                                                               tmp_path, capsys):
    """A base fit cut off at 3 iterations: diagnose says INCONCLUSIVE without a verdict on
    the model and exits 1, as `vsidgen fit` does for an unconverged fit (it exited 0 and said
    "the model is kept as it is")."""
    from vsidgen.cli import main

    monkeypatch.setenv("VSIDGEN_CACHE_DIR", "")
    rc = main(["diagnose", str(SPEC), str(DATA), "--out", str(tmp_path / "u"), "--workers", "1",
               "--max-iter", "3", "--max-rounds", "0", "--quiet"])
    assert rc == 1
    out = capsys.readouterr().out
    doc = _doc(tmp_path / "u")
    assert doc["base_fit"]["converged"] is False
    assert doc["conclusion"].startswith("INCONCLUSIVE: the base fit did not converge")
    assert "kept as it is" not in out and "No significant" not in out
    # numerics and noise model are not tested against a non-optimum (a refit would gain by
    # finishing the fit: the numerics stage adopted RK4 on such gains)
    for stage in ("numerics", "noise_model"):
        trials = doc[stage]["trials"]
        assert trials and all(t["verdict"] == "not_tested_base_unconverged"
                              and t["elbo"] is None for t in trials), stage
        assert doc[stage]["adopted"] is None
    html = findings.report_section(doc)
    assert html.count("<b>Not tested</b>: the base fit did not converge") == 2
    assert "Kept: no other setting" not in html


@pytest.mark.slow
def test_parallel_refits_give_the_serial_findings(tmp_path):
    """Real refits: the round refitted serially and on a 2-worker local dask cluster gives
    the same trials (statistics to 1e-6 relative) and the same findings."""
    docs = []
    for w in (1, 2):
        search.run_diagnose(SPEC, [DATA], out=tmp_path / f"w{w}", max_rounds=1,
                            max_candidates=2, workers=w)
        docs.append(_doc(tmp_path / f"w{w}"))
    s, p = docs
    assert s["options"]["engine"].startswith("serial") and "2 worker" in p["options"]["engine"]
    ts, tp = s["rounds"][0]["trials"], p["rounds"][0]["trials"]
    assert [t["key"] for t in ts] == [t["key"] for t in tp] and len(ts) == 2
    for a, b in zip(ts, tp):
        assert a["error"] is None and b["error"] is None
        assert b["statistic"] == pytest.approx(a["statistic"], rel=1e-6, abs=1e-6)
        assert b["elbo"] == pytest.approx(a["elbo"], rel=1e-9)
    assert [f["key"] for f in s["findings"]] == [f["key"] for f in p["findings"]]


def test_conclusion_when_every_refit_failed():
    from vsidgen.discrepancy.findings import conclusion_text

    rounds = [{"trials": [{"key": "a", "error": "lost: worker died", "converged": None},
                          {"key": "b", "error": "failed: ValueError: x", "converged": None}]}]
    text = conclusion_text([], rounds, alpha=0.01, validated=False, final_spec="s.yaml")
    assert text.startswith("INCONCLUSIVE: no refit produced a result") and "a: lost" in text
    rounds[0]["trials"].append({"key": "c", "error": None, "converged": True})
    text = conclusion_text([], rounds, alpha=0.01, validated=False, final_spec="s.yaml")
    assert text.startswith("No significant") and "failed (neither accepted nor ruled out): a, b" in text


def test_an_unreachable_cluster_is_refused_before_the_base_fit(monkeypatch, tmp_path, capsys):
    """``--scheduler`` that cannot be reached ends the run (exit 2, one line) before any fit."""
    from vsidgen import engine as engine_mod
    from vsidgen.cli import main
    from vsidgen.errors import VsidgenError

    def unreachable(self):
        raise VsidgenError(f"cannot start or reach the dask cluster ({self.scheduler}): refused")

    def no_fit(*a, **k):
        raise AssertionError("the base model was fitted before the cluster was reached")

    monkeypatch.setattr(engine_mod.Engine, "__enter__", unreachable)
    monkeypatch.setattr(search, "fit_spec", no_fit)
    rc = main(["diagnose", str(SPEC), str(DATA), "--out", str(tmp_path / "s"),
               "--scheduler", "tcp://127.0.0.1:1", "--quiet"])
    assert rc == 2
    err = capsys.readouterr().err
    assert "cannot start or reach the dask cluster (tcp://127.0.0.1:1)" in err
    assert "Traceback" not in err


def test_the_unconverged_lead_refit_is_continued_and_decides_the_round(patched, monkeypatch,
                                                                       tmp_path, base_state):
    from vsidgen.estimator import StopReason

    # lat_p_bias_0.002_s1/_s2: the right refit led its round at its iteration limit with an
    # indefinite Hessian and the run said INCONCLUSIVE; continued, it converges and is accepted
    continued = []

    def finish(st, iterations, max_iter, time_limit):
        continued.append((st.elbo, iterations))   # the "short" stand-in: 50 nats up
        return dataclasses.replace(st, fit=dataclasses.replace(
            st.fit, elbo=st.fit.elbo + 10.0, converged=True,
            stop_reason=StopReason.NEWTON_DECREMENT, newton_decrement=1e-4))

    monkeypatch.setattr(search, "_continue_task", finish)
    refits = patched(["short", "same"])
    search.run_diagnose(SPEC, [DATA], out=tmp_path / "o", max_rounds=1, max_candidates=2,
                        screen=False, effects=EFFECTS, workers=1, max_iter=50)
    assert continued == [(pytest.approx(base_state.elbo + 50.0), search.CONTINUE_FACTOR * 50)]
    doc = _doc(tmp_path / "o")
    assert [f["key"] for f in doc["findings"]] == [refits.calls[0]]
    ev = doc["findings"][0]["evidence"]
    assert ev["statistic"] == pytest.approx(120.0) and ev["converged"] is True
    assert any("continued for up to 200 more iterations" in n for n in ev["refit"]["notes"])

    # without the continuation the same round cannot decide
    monkeypatch.setattr(search, "lead_to_continue", lambda *a, **k: None)
    patched(["short", "same"])
    search.run_diagnose(SPEC, [DATA], out=tmp_path / "o2", max_rounds=1, max_candidates=2,
                        screen=False, effects=EFFECTS, workers=1, max_iter=50)
    doc2 = _doc(tmp_path / "o2")
    assert doc2["findings"] == [] and "INCONCLUSIVE" in doc2["conclusion"]


def test_conclusion_when_no_round_ran():
    """--max-rounds 0 examines no candidate: the conclusion must not say that no candidate
    improved the fit (it did, before session 35)."""
    from vsidgen.discrepancy.findings import conclusion_text

    text = conclusion_text([], [], alpha=0.01, validated=True, final_spec="s.yaml")
    assert text.startswith("No candidate effect was examined") and "--max-rounds" in text
    assert "No significant" not in text and "improved" not in text


@pytest.mark.parametrize("command", ["diagnose", "fleet"])
def test_an_unreachable_cluster_leaves_the_previous_results(monkeypatch, tmp_path, capsys,
                                                            command):
    """Red team, session 47: the previous run's files were removed before the cluster was
    contacted, so a run refused for an unreachable ``--scheduler`` lost them."""
    from vsidgen import engine as engine_mod
    from vsidgen.atomic import atomic_directory
    from vsidgen.cli import main
    from vsidgen.errors import VsidgenError

    out = tmp_path / "s"
    with atomic_directory(out, command=command) as tmp:       # the previous run's results
        (tmp / "findings.json").write_text('{"previous": true}')
    before = sorted(p.name for p in out.iterdir())

    def unreachable(self):
        raise VsidgenError(f"cannot start or reach the dask cluster ({self.scheduler}): refused")

    monkeypatch.setattr(engine_mod.Engine, "__enter__", unreachable)
    rc = main([command, str(SPEC), str(DATA), "--out", str(out),
               "--scheduler", "tcp://127.0.0.1:1", "--quiet"])
    assert rc == 2 and "cannot start or reach" in capsys.readouterr().err
    assert sorted(p.name for p in out.iterdir()) == before
    assert (out / "findings.json").read_text() == '{"previous": true}'

