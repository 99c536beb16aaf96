"""The round's unconverged lead refit is continued before the round is decided
(``search.lead_to_continue``, ``search.polish``, ``search.continued_trial``)."""

from __future__ import annotations

import math
import pathlib
from types import SimpleNamespace

import pytest

from vsidgen.discrepancy import search
from vsidgen.discrepancy.refit import RefitOutcome, RefitVerdict
from vsidgen.estimator import StopReason

ROOT = pathlib.Path(__file__).resolve().parents[1]


def _trial(key, lam, stop, *, verdict=RefitVerdict.ORDINARY, dof=1):
    """A refitted candidate with 2ΔELBO ``lam`` over the current model that stopped by ``stop``."""
    cand = SimpleNamespace(key=key, states=(), parameters=())
    state = SimpleNamespace(fit=SimpleNamespace(stop_reason=stop), elbo=lam / 2.0)
    return search.Trial(cand, 0.0, pathlib.Path(key), state, lam, dof, math.nan,
                        converged=stop.converged, statistic_vs_base=lam, verdict=verdict)


LIMIT, DONE = StopReason.ITERATION_LIMIT, StopReason.NEWTON_DECREMENT


@pytest.mark.parametrize("trials, expected", [
    # lat_p_bias_0.002_s2: the bias at its limit (≥ 166) above every converged refit
    ([("skew", 5.8, DONE), ("bias", 166.0, LIMIT), ("arm", 3.0, LIMIT)], 1),
    # a converged refit above it: the round is decided without it
    ([("skew", 200.0, DONE), ("bias", 166.0, LIMIT)], None),
    # below the first Holm threshold (χ²₁ at 0.01/100 ≈ 15.1): not worth the iterations
    ([("skew", 5.8, DONE), ("bias", 12.0, LIMIT)], None),
    # of two unconverged leads, the higher one
    ([("a", 40.0, StopReason.INDEFINITE_HESSIAN), ("b", 90.0, StopReason.STALLED)], 1),
    # a non-finite stop is a failure, not a crawl; nor is a rejected (non-causal) estimate
    ([("a", 90.0, StopReason.NONFINITE)], None),
    ([("a", 90.0, LIMIT, RefitVerdict.NON_CAUSAL)], None),
])
def test_which_refit_is_continued(trials, expected):
    ts = [_trial(k, lam, stop, **({"verdict": rest[0]} if rest else {}))
          for k, lam, stop, *rest in trials]
    assert search.lead_to_continue(ts, alpha=0.01, n_examined=100) == expected


def test_polish_finishes_a_refit_stopped_at_its_limit(tmp_path):
    spec, data = ROOT / "specs" / "attas_sp.yaml", ROOT / "data" / "attas_sp_synthetic.csv"
    st = search.fit_spec(spec, [data], generated_dir=tmp_path / "gen", max_iter=4)
    assert not st.fit.converged and st.fit.stop_reason is StopReason.ITERATION_LIMIT
    ref = st.elbo - 10.0
    cand = SimpleNamespace(key="k", states=(), parameters=(), info={})
    t = search.Trial(cand, 0.0, st.spec_path, st, 2.0 * (st.elbo - ref), 1, 0.5,
                     refit=RefitOutcome(state=st, elbo_ref=ref),
                     statistic_vs_base=2.0 * (st.elbo - ref), converged=False,
                     verdict=RefitVerdict.ORDINARY)
    st2 = search.polish(st, iterations=300, max_iter=200)
    assert st2.fit.converged and st2.elbo > st.elbo
    ct = search.continued_trial(t, st2, st, 300)
    assert ct.converged and ct.statistic == pytest.approx(2.0 * (st2.elbo - ref))
    assert ct.refit.state is st2 and "continued for up to 300" in ct.refit.notes[-1]
    assert t.refit.notes == []                   # the original outcome is not modified
