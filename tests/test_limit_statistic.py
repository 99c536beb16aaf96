"""The statistic of a candidate that adds an input-carrying state, taken in the deterministic
limit of that state (``search.limit_correction``): the refits hold it quasi-deterministic, a
small fixed noise that is also an input-noise channel; the decision uses the limit.

References: a true lag (simulated independently, as in test_delay_screen) keeps its
statistic — the fixed noise explains nothing there — and the estimator's continuation starts
at the std a warm start's decision belongs to."""

from __future__ import annotations

import numpy as np
import pytest

import test_delay_screen as T
from vsidgen.discrepancy import propose
from vsidgen.discrepancy.refit import REFIT_DETERMINISTIC_STD, quasi_stds
from vsidgen.discrepancy.score import screen
from vsidgen.discrepancy.search import filter_start, staged_refit
from vsidgen.estimator import FitOptions, WarmStart, fit


@pytest.fixture(scope="module")
def lag_refit(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("limit_stat")
    t, u, y = T._simulate_lag(0.12, seed=7)
    st, info = T.fit_lin1(tmp, t, u, y)
    cand = next(c for c in propose(info) if c.effect == "actuator_lag")
    res = screen([cand], st, info, tmp / "screen", "t", generated_dir=tmp / "gen",
                 det_std=REFIT_DETERMINISTIC_STD)[cand.key]
    out = staged_refit(filter_start(cand, res), st, info, tmp / "lag.yaml", "lin1_lag",
                       generated_dir=tmp / "gen", max_iter=200)
    return cand, out


def test_a_true_lag_keeps_its_statistic_in_the_limit(lag_refit):
    cand, out = lag_refit
    assert out.state.fit.converged
    d = out.limit_detail
    assert d is not None and out.limit_correction is not None, out.notes
    # the noise at the quasi std explained nothing the lag does not: the same statistic
    assert d["statistic_limit"] > 50.0
    assert abs(out.limit_correction) < 1e-3 * d["statistic_limit"]
    assert out.limit_correction == pytest.approx(d["statistic_limit"] - d["statistic_quasi"])
    # taken at least one decade further down than the quasi std
    q = quasi_stds(out.state.model, out.state.records, REFIT_DETERMINISTIC_STD)
    (name, std), = d["std"].items()
    assert std < 0.1 * q[out.state.model.state_names.index(name)]
    assert d["stages"] > 1
    # the lag's estimate in the limit is the quasi refit's (within its standard error)
    p = cand.parameters[0].name
    i = out.state.model.parameter_names.index(p)
    se = out.state.fit.std_errors[i]
    assert abs(d["estimates"][p] - out.state.fit.theta[i]) < se


def test_a_warm_limit_fit_starts_at_the_std_of_its_decision(lag_refit):
    """``WarmStart.deterministic_limit``: the continuation's first stage is the std the
    decision was fitted at (not the data scale), so the warm start is that stage's optimum."""
    _, out = lag_refit
    st = out.state
    q = quasi_stds(st.model, st.records, REFIT_DETERMINISTIC_STD)
    names = st.fit.deterministic_states
    start = {"std": {n: float(q[st.model.state_names.index(n)]) for n in names}}
    ws = WarmStart.from_decision(st.fit.decision)
    res = fit(st.model, list(st.records), options=FitOptions(
        deterministic="limit", deterministic_std=REFIT_DETERMINISTIC_STD, max_iter=200,
        warm_start=WarmStart(ws.shared, ws.records, deterministic_limit=start)))
    first = res.deterministic_limit["stages"][0]
    assert first["std"] == pytest.approx(start["std"])
    assert first["iterations"] <= 3          # already at that stage's optimum
    assert res.converged and res.deterministic_limit["reached"]
