"""Vuong's test of two non-nested models on the same records: do the data separate them?

Two candidates of one round extend the current model by different terms, so neither nests
the other and their likelihood ratio has no χ² reference. Vuong (1989, Econometrica 57:307)
tests ``H0: both models are equally close to the truth`` (in Kullback–Leibler divergence) with
the per-sample log-likelihood differences ``d_k = ℓ1_k − ℓ2_k``:

.. math::

    z = \\frac{\\sum_k d_k − (p_1 − p_2)}{\\sqrt{\\sum_r n_r\\,\\hat ω_r^2}} \\;\\to\\; N(0, 1),

where ``p_i`` are the free-parameter counts (the AIC-type correction of Vuong's eq. 5.7) and
``ω̂_r²`` is the long-run variance of ``d`` within record ``r`` — Newey–West (Bartlett
kernel, bandwidth ``⌊4 (n/100)^{2/9}⌋``): the one-step prediction errors of a misspecified
model are not white, and an i.i.d. variance would overstate the evidence. ``ℓ_k`` are the
one-step predictive log-likelihoods of each model's steady-state Kalman filter
(:func:`vsidgen.evaluation.predictive_loglik`), the exact decomposition of a linear model's
likelihood. ``|z|`` below the normal quantile: the records do not separate the two
explanations; a large positive ``z`` favours model 1.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Sequence

import numpy as np
from scipy import stats

#: two-sided level at which the records are said to separate two explanations
VUONG_ALPHA = 0.05


@dataclasses.dataclass(frozen=True)
class VuongResult:
    """``z`` (> 0 favours model 1), its two-sided ``p_value``, the summed log-likelihood
    difference ``lr`` (nats, before the parameter correction) and the sample count ``n``."""

    z: float
    p_value: float
    lr: float
    n: int

    def separated(self, alpha: float = VUONG_ALPHA) -> bool:
        """The records separate the two models at two-sided level ``alpha``."""
        return self.p_value < alpha

    def to_json(self) -> dict:
        return {"z": self.z, "p_value": self.p_value, "loglik_difference": self.lr, "n": self.n}


def newey_west_variance(d: np.ndarray) -> float:
    """Long-run variance of the series ``d`` (Bartlett kernel, bandwidth ⌊4 (n/100)^{2/9}⌋),
    about its own mean; never below zero."""
    d = np.asarray(d, dtype=np.float64)
    n = d.size
    if n < 2:
        return 0.0
    e = d - d.mean()
    var = float(e @ e) / n
    lags = min(int(4.0 * (n / 100.0) ** (2.0 / 9.0)), n - 1)
    for lag in range(1, lags + 1):
        var += 2.0 * (1.0 - lag / (lags + 1.0)) * float(e[lag:] @ e[:-lag]) / n
    return max(var, 0.0)


def vuong_test(ll1: Sequence[np.ndarray], ll2: Sequence[np.ndarray], *, p1: int = 0,
               p2: int = 0) -> VuongResult | None:
    """Vuong's statistic of model 1 against model 2 from their per-sample log-likelihoods,
    one array per record (the same records, in the same order; samples where either is not
    finite are dropped). None when there is nothing to compare (no sample, or both models
    give identical log-likelihoods: z is undefined)."""
    num, var, n = 0.0, 0.0, 0
    for a, b in zip(ll1, ll2, strict=True):
        d = np.asarray(a, dtype=np.float64) - np.asarray(b, dtype=np.float64)
        d = d[np.isfinite(d)]
        if d.size == 0:
            continue
        num += float(d.sum())
        var += d.size * newey_west_variance(d)
        n += d.size
    if n == 0 or not var > 0.0:
        return None
    z = (num - (p1 - p2)) / math.sqrt(var)
    return VuongResult(z=z, p_value=float(2.0 * stats.norm.sf(abs(z))), lr=num, n=n)
