"""Log tail probabilities of χ² that do not underflow (:mod:`vsidgen.discrepancy.pvalues`),
checked against mpmath's incomplete gamma function at 40 digits, and the round's decision that
depends on them."""

from __future__ import annotations

import math
import pathlib
import types

import mpmath
import pytest
from scipy import stats

from vsidgen.discrepancy.pvalues import chi2_log10sf, chi2_logsf


@pytest.mark.parametrize("dof", [1, 2, 3, 4, 7, 20, 60])
@pytest.mark.parametrize("x", [0.5, 10.0, 300.0, 1300.0, 1500.0, 3794.0, 2.5e4, 1e7])
def test_chi2_logsf_equals_the_incomplete_gamma_function(x, dof):
    mpmath.mp.dps = 40
    ref = float(mpmath.log(mpmath.gammainc(dof / 2, x / 2, mpmath.inf, regularized=True)))
    got = chi2_logsf(x, dof)
    assert math.isfinite(got)
    assert got == pytest.approx(ref, rel=1e-13, abs=1e-13)
    assert chi2_log10sf(x, dof) == pytest.approx(ref / math.log(10.0), rel=1e-13, abs=1e-13)


def test_chi2_logsf_edges_and_where_scipy_underflows():
    assert math.isinf(stats.chi2.logsf(1800.0, 1))          # what this module is for
    assert chi2_logsf(1800.0, 1) > chi2_logsf(3800.0, 1) > -math.inf
    assert chi2_logsf(0.0, 3) == 0.0 and chi2_logsf(-2.0, 1) == 0.0
    assert chi2_logsf(math.inf, 2) == -math.inf
    assert math.isnan(chi2_logsf(math.nan, 2)) and math.isnan(chi2_logsf(3.0, 0))


def test_round_accepts_the_stronger_of_two_candidates_beyond_the_underflow():
    """hfb_de_delay_0.15_s0 (session 20): the Padé delay (Λ = 1762) was accepted ahead of the
    transport delay (Λ = 3794): both p-values were 0 in scipy's logs and the first one won."""
    from vsidgen.discrepancy.base import Candidate
    from vsidgen.discrepancy.refit import RefitVerdict
    from vsidgen.discrepancy.search import Trial, _decide_round

    fit = types.SimpleNamespace(converged=True, stop_reason=None, status="converged")
    current = types.SimpleNamespace(fit=fit, val_elbo=None, val_elbo_own_noise=None, elbo=0.0,
                                    spec_path=pathlib.Path("base.yaml"))

    def trial(key, lam, grid=()):
        c = Candidate(effect=key.split(":")[0], key=key, target="input:de",
                      explanation="", info={"profile_result": {"grid_s": list(grid)}})
        st = types.SimpleNamespace(fit=fit, vfit=None, elbo=lam / 2, val_elbo=None, val_elbo_own_noise=None, signals=())
        return Trial(c, 1.0, pathlib.Path(f"{key}.yaml"), st, lam, 1,
                     float(stats.chi2.sf(lam, 1)), converged=True, statistic_vs_base=lam,
                     verdict=RefitVerdict.ORDINARY)

    trials = [trial("control_delay:de", 1761.6), trial("actuator_lag:de", 1380.3),
              trial("transport_delay:de", 3794.5, grid=[0.05 * k for k in range(1, 11)])]
    got = _decide_round(1, trials, current, 176, 0.01, [], [], None)
    assert got.best is not None and got.best.candidate.key == "transport_delay:de"
    # and the order does not depend on the order of the trials
    got = _decide_round(1, trials[::-1], current, 176, 0.01, [], [], None)
    assert got.best.candidate.key == "transport_delay:de"
