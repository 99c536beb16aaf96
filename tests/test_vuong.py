"""Vuong's test of non-nested models (vsidgen.discrepancy.vuong) and its use for a finding's
alternatives (search.alternatives_of).

References: the test on two Gaussian regressions with known per-sample log-likelihoods, one
model the truth (z grows like √n) and two equally wrong ones (z ~ N(0, 1) across seeds); the
Newey–West variance against its hand-written formula; the null rejection rate at 5 % on
independent draws."""

from __future__ import annotations

import dataclasses
import math
import types

import numpy as np
import pytest
from scipy import stats

from vsidgen.discrepancy import search
from vsidgen.discrepancy.vuong import newey_west_variance, vuong_test


def _normal_ll(e, s):
    return stats.norm(0.0, s).logpdf(e)


def test_newey_west_variance_matches_its_formula():
    rng = np.random.default_rng(0)
    d = rng.normal(size=250) + 0.3
    n = d.size
    L = int(4 * (n / 100) ** (2 / 9))
    e = d - d.mean()
    ref = e @ e / n + 2 * sum((1 - l / (L + 1)) * (e[l:] @ e[:-l]) / n for l in range(1, L + 1))
    assert newey_west_variance(d) == pytest.approx(ref, rel=1e-12)
    # a positively autocorrelated series has a larger long-run variance than its variance
    ar = np.zeros(2000)
    for k in range(1, ar.size):
        ar[k] = 0.8 * ar[k - 1] + rng.normal()
    assert newey_west_variance(ar) > 2.0 * ar.var()


def test_the_true_model_is_separated_from_a_wrong_one_and_two_equally_wrong_are_not():
    rng = np.random.default_rng(1)
    x = rng.normal(size=400)
    y = 1.0 * x + rng.normal(scale=0.5, size=x.size)
    true = _normal_ll(y - x, 0.5)
    wrong = _normal_ll(y - 0.7 * x, 0.5)
    v = vuong_test([true], [wrong])
    assert v.z > 3.0 and v.separated() and v.n == 400
    assert vuong_test([wrong], [true]).z == pytest.approx(-v.z)
    # two models equally far from the truth (slopes 0.9 and 1.1): z ~ N(0, 1) over seeds
    zs, rejected = [], 0
    for seed in range(200):
        r = np.random.default_rng(100 + seed)
        x = r.normal(size=300)
        y = x + r.normal(scale=0.5, size=x.size)
        res = vuong_test([_normal_ll(y - 0.9 * x, 0.5)], [_normal_ll(y - 1.1 * x, 0.5)])
        zs.append(res.z)
        rejected += res.separated()
    assert abs(np.mean(zs)) < 0.25 and 0.7 < np.std(zs) < 1.3
    assert rejected <= 22              # 5 % of 200 is 10; binomial upper tail ~ 0.1 %


def test_records_are_pooled_and_parameters_penalised():
    rng = np.random.default_rng(2)
    a = [rng.normal(size=100), rng.normal(size=150)]
    b = [a[0] - 0.05, a[1] - 0.05]              # model 1 better by 0.05 nats per sample
    a[0] = a[0] + rng.normal(scale=0.2, size=100)
    v = vuong_test(a, b)
    assert v.n == 250 and v.lr == pytest.approx(sum(x.sum() for x in a) - sum(x.sum() for x in b))
    vp = vuong_test(a, b, p1=5, p2=0)           # 5 more parameters cost 5 nats
    assert vp.z < v.z
    assert vuong_test([np.zeros(5)], [np.zeros(5)]) is None       # identical: undefined
    with pytest.raises(ValueError):
        vuong_test([np.zeros(5)], [np.zeros(5), np.zeros(5)])     # records must match


@dataclasses.dataclass(frozen=True)
class _Trial:
    """What alternatives_of reads of a search.Trial (replaced as one: dataclasses.replace)."""

    candidate: object
    comparison: float
    statistic: float
    dof: int
    state: object
    vuong: object = None


def _trial(key, comparison, ll, *, effect=None, params=None):
    """A refit with one new parameter ``x`` (``params``: (estimate, std error)) of the effect
    ``effect`` (default: its own, ``key``)."""
    theta, se = params or (0.0, 1.0)
    cand = types.SimpleNamespace(key=key, effect=effect or key, target="drift:q", add_terms={},
                                 parameters=(types.SimpleNamespace(name="x", fixed=False),))
    state = types.SimpleNamespace(signals=(types.SimpleNamespace(ll=ll),),
                                  model=types.SimpleNamespace(parameter_names=("a", "x")),
                                  fit=types.SimpleNamespace(theta=np.array([1.0, theta]),
                                                            std_errors=np.array([0.1, se])))
    return _Trial(cand, comparison, comparison, 1, state)


def test_alternatives_are_the_refits_the_records_do_not_separate(monkeypatch):
    """A refit 20 nats behind whose per-sample evidence is spread thinly (not separated) is an
    alternative; one 4 nats behind but consistently worse at every sample is not — where the
    fixed margin (2·3 nats) said the opposite for both."""
    from vsidgen import evaluation

    monkeypatch.setattr(evaluation, "predictive_loglik", lambda sig: sig.ll)
    rng = np.random.default_rng(3)
    base = rng.normal(size=800)
    best = _trial("best", 500.0, base)
    noisy = _trial("noisy", 480.0, base - 10.0 / 800 + rng.normal(scale=1.0, size=800))
    # 2 nats in total, about 0.0025 at every sample
    steady = _trial("steady", 496.0, base - 0.0025 + rng.normal(scale=1e-3, size=800))
    alts = search.alternatives_of(best, [best, noisy, steady])
    assert [a.candidate.key for a in alts] == ["noisy"]
    assert alts[0].vuong is not None and not alts[0].vuong.separated()
    # without predictive log-likelihoods, the fixed margin decides
    monkeypatch.setattr(evaluation, "predictive_loglik", lambda sig: None)
    alts = search.alternatives_of(best, [best, noisy, steady])
    assert [a.candidate.key for a in alts] == ["steady"] and alts[0].vuong is None


def test_one_fitted_model_from_two_starts_is_not_its_own_alternative(monkeypatch):
    """Two refits of one term (a break point started at two grid values) that converged to the
    same estimates (within a tenth of a standard error) are one explanation, not a tie: the
    second is not listed as the first's alternative, nor twice among the alternatives; the
    same terms at estimates several standard errors apart are two fits, and stay."""
    from vsidgen import evaluation

    monkeypatch.setattr(evaluation, "predictive_loglik", lambda sig: sig.ll)
    rng = np.random.default_rng(5)
    base = rng.normal(size=600)
    best = _trial("hinge:0.12", 300.0, base, effect="hinge", params=(0.133, 0.001))
    twin = _trial("hinge:0.14", 299.99, base + rng.normal(scale=1e-4, size=600),
                  effect="hinge", params=(0.13305, 0.001))
    other = _trial("vane", 299.0, base + rng.normal(scale=0.5, size=600), params=(2.0, 0.2))
    other_twin = _trial("vane:b", 298.99, base + rng.normal(scale=0.5, size=600),
                        effect="vane", params=(2.01, 0.2))
    alts = search.alternatives_of(best, [best, twin, other, other_twin])
    assert [a.candidate.key for a in alts] == ["vane"]
    assert search.same_fitted_model(best, twin) and not search.same_fitted_model(best, other)
    apart = _trial("hinge:0.2", 299.5, base + rng.normal(scale=0.5, size=600),
                   effect="hinge", params=(0.2, 0.001))
    assert not search.same_fitted_model(best, apart)
    assert "hinge:0.2" in [a.candidate.key for a in search.alternatives_of(best, [best, apart])]
