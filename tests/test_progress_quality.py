"""Progress display (live line / per-start summaries) and the NRMSE fit percentage."""

from __future__ import annotations

import io
import math

import numpy as np
import pytest

from vsidgen.evaluation import fit_metrics
from vsidgen.progress import DiagnoseProgress, FitProgress


def test_log_mode_writes_one_line_per_noise_start():
    out = io.StringIO()
    p = FitProgress(out, live=False)
    for it in range(6):
        p(it, 100.0 + it, 10.0 ** -it, 0.1 * it)
    for it in range(4):  # the estimator restarts its count at the next noise start
        p(it, 200.0 + it, 10.0 ** -(it + 3), 1.0 + 0.1 * it)
    p.close()
    lines = out.getvalue().splitlines()
    assert lines == ["noise start 1: 5 iterations, ELBO 105, |grad| 1e-05, 0.5 s",
                     "noise start 2: 3 iterations, ELBO 203, |grad| 1e-06, 1.3 s"]


def test_live_mode_keeps_one_line():
    out = io.StringIO()
    p = FitProgress(out, live=True)
    for it in range(50):
        p(it, float(it), 1.0 / (it + 1), 0.01 * it)
    p.close()
    text = out.getvalue()
    assert "iter   49" in text and "noise start" not in text
    assert text.count("\n") <= 50  # redrawn in place, not appended (rich cursor control)


def test_diagnose_time_left_from_finished_refits():
    out = io.StringIO()
    p = DiagnoseProgress(out, live=False)
    first = p.refitting(1, 1, 3, "a")
    assert "1/3" in first and "after the first refit" in first
    second = p.refitting(1, 2, 3, "b")
    assert "2/3" in second and "s left in this round" in second
    assert "after the first" in p.refitting(2, 1, 2, "c")  # a new round starts over


def test_fit_percent_matches_matlab_compare_definition():
    rng = np.random.default_rng(0)
    y = np.cumsum(rng.normal(size=500))
    yhat = y + rng.normal(scale=0.3, size=500)
    expected = 100.0 * (1.0 - np.linalg.norm(y - yhat) / np.linalg.norm(y - y.mean()))
    m = fit_metrics(y, yhat)
    assert m["fit_percent"] == pytest.approx(expected, rel=1e-12)
    assert m["fit_percent"] == pytest.approx(100.0 * (1.0 - math.sqrt(1.0 - m["r2"])), rel=1e-12)
    assert fit_metrics(y, y)["fit_percent"] == 100.0
    assert fit_metrics(y, np.full_like(y, y.mean()))["fit_percent"] == pytest.approx(0.0, abs=1e-12)
    y_nan = y.copy()
    y_nan[3] = np.nan  # missing samples are left out, as for the other metrics
    keep = np.isfinite(y_nan)
    ref = 100.0 * (1.0 - np.linalg.norm(y[keep] - yhat[keep])
                   / np.linalg.norm(y[keep] - y[keep].mean()))
    assert fit_metrics(y_nan, yhat)["fit_percent"] == pytest.approx(ref, rel=1e-12)
    assert math.isnan(fit_metrics(np.ones(5), np.ones(5))["fit_percent"])


def test_log_mode_names_the_phases_the_estimator_announces():
    """Continuation stages of the deterministic limit are labelled as such, not as noise starts."""
    from vsidgen.estimator import FitPhase, PhaseKind

    out = io.StringIO()
    p = FitProgress(out, live=False)
    p.phase(FitPhase(PhaseKind.NOISE_START, start="data"))
    for it in range(3):
        p(it, 100.0 + it, 1e-3, 0.1 * it)
    p.phase(FitPhase(PhaseKind.NOISE_START, start="data"))   # a bound release: same phase, counting on
    p(3, 104.0, 1e-4, 0.4)
    for k in (1, 2):
        p.phase(FitPhase(PhaseKind.LIMIT_STAGE, stage=k, scale=10.0 ** -k, max_stages=12))
        for it in range(2):
            p(it, 90.0 - k, 1e-5, 1.0 + k)
    p.close()
    lines = out.getvalue().splitlines()
    assert lines == ["noise start data: 3 iterations, ELBO 104, |grad| 0.0001, 0.4 s",
                     "deterministic limit, stage 1 of at most 12, std × 0.1: 1 iterations, ELBO 89, "
                     "|grad| 1e-05, 2.0 s",
                     "deterministic limit, stage 2 of at most 12, std × 0.01: 1 iterations, ELBO 88, "
                     "|grad| 1e-05, 3.0 s"]
    assert "noise start 2" not in out.getvalue()


def test_status_line_names_the_next_engine_refit_not_a_profiled_delay():
    """A profiled transport delay runs after the round's engine refits: the "refitting …"
    status line named it first (a new user's roll model: "refitting transport_delay:dr (1/2)"
    while the lags were being refitted)."""
    from vsidgen.discrepancy.search import _RoundPlan

    keys = ["transport_delay:dr", "actuator_lag:dr", "actuator_lag:da"]
    plan = _RoundPlan(ranked=[], paths=[], profiled=[0], groups={}, tasks=[],
                      by_key={k: (i, 1.0, None, None) for i, k in enumerate(keys)})
    assert plan.next_refitted(keys) == "actuator_lag:dr"
    assert plan.next_refitted(keys[::2]) == "actuator_lag:da"
    assert plan.next_refitted(keys[:1]) is None


def test_diagnose_time_left_is_bounded_by_the_time_limit():
    """A 900-s run said "about 657 s left", then "about 1061 s left" (session 43): the
    average refit times the refits left, past the time limit. The limit now bounds it."""
    import time

    p = DiagnoseProgress(io.StringIO(), live=False)
    assert "ends the round in 300 s" in p.refitting(1, 1, 4, "a", limit_left=300.0)
    time.sleep(0.02)
    text = p.refitting(1, 2, 4, "b", limit_left=1e-3)
    assert "ends the round in 0 s" in text and "s left in this round" not in text
    time.sleep(0.02)
    assert "s left in this round" in p.refitting(1, 3, 4, "c", limit_left=1e6)


def test_an_unfinished_rounds_refit_is_undecided_not_insignificant():
    """findings.json listed a refit of an unfinished round with 2ΔELBO 39.2, p 3.7e-10 as
    `significant: false` next to `threshold: null` (session 43): undecided is null."""
    import types

    from vsidgen.discrepancy.search import _undecided_json

    t = types.SimpleNamespace(to_json=lambda: {"key": "a", "threshold": None, "significant": False})
    assert _undecided_json(t)["significant"] is None
    t = types.SimpleNamespace(to_json=lambda: {"key": "a", "threshold": 7.9, "significant": True})
    assert _undecided_json(t)["significant"] is True


def test_the_rounds_deadline_instant_gives_the_time_left():
    """The round's refit deadline is a time.monotonic() instant (round_refit_deadline); the
    progress line's bound read it as an object with .left() and ended a diagnose run with
    an internal error (caught in session 43 before it landed in a release)."""
    import time

    from vsidgen.discrepancy.search import _limit_left, round_refit_deadline

    assert _limit_left(None) == {}
    got = _limit_left(round_refit_deadline(time.monotonic() + 100.0, 10.0))["limit_left"]
    assert 85.0 < got <= 90.0
    p = DiagnoseProgress(io.StringIO(), live=False)
    assert "ends the round in" in p.refitting(1, 1, 2, "a", **_limit_left(time.monotonic() + 50.0))
