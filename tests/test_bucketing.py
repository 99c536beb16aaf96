"""Length bucketing of the structured optimizer (issue 6).

Each record is padded to ``bucket_length(N)`` samples with the padding masked out of the
observations, the transitions and the entropy count, so (a) the objective, its gradient and
the fitted optimum equal those of the unpadded record, and (b) two records whose lengths fall
in one bucket share the compiled functions (counted with the Objective's trace counter, a
Python side effect that runs once per jit trace, i.e. once per compilation).
"""

from __future__ import annotations

import numpy as np
import pytest
from test_estimator import lin_model, make_record

from vsidgen.estimator import FitOptions, fit
from vsidgen.estimator.core import bucket_length
from vsidgen.estimator import Problem


def test_bucket_ladder_padding_at_most_one_eighth():
    seen = set()
    for n in list(range(3, 2000)) + [10 ** 5, 10 ** 6, 123457, 999_999]:
        b = bucket_length(n)
        assert b >= n
        assert b - n <= n / 8
        seen.add(b)
    assert bucket_length(15) == 15 and bucket_length(400) == 416
    assert len([b for b in seen if b < 2000]) < 100  # few distinct shapes, not one per length


def test_padded_objective_gradient_equal_unpadded():
    model = lin_model(structure="full")
    rec = make_record(203, seed=4)
    rng = np.random.default_rng(1)
    out = {}
    for bucket in (False, True):
        P = Problem(model, [rec], FitOptions(bucket=bucket))
        s, recs = P.initial(FitOptions())
        r2 = np.random.default_rng(0)
        s = s + 0.2 * r2.normal(size=s.shape)
        recs = [(m + 0.1 * r2.normal(size=m.shape), r + 0.1 * r2.normal(size=r.shape)) for m, r in recs]
        b = P.blocks(s, recs)[0]
        out[bucket] = (P.value(s, recs), b, P.padded[0])
    (v0, b0, L0), (v1, b1, L1) = out[False], out[True]
    assert L0 == 203 and L1 == bucket_length(203) > 203
    np.testing.assert_allclose(v1, v0, rtol=1e-13)
    np.testing.assert_allclose(float(b1["f"]), float(b0["f"]), rtol=1e-13)
    np.testing.assert_allclose(np.asarray(b1["gb"]), np.asarray(b0["gb"]), rtol=1e-11, atol=1e-9)
    np.testing.assert_allclose(np.asarray(b1["Hbb"]), np.asarray(b0["Hbb"]), rtol=1e-11, atol=1e-9)
    np.testing.assert_allclose(np.asarray(b1["gmu"])[:203], np.asarray(b0["gmu"]), rtol=1e-11, atol=1e-9)
    np.testing.assert_allclose(np.asarray(b1["D"])[:203], np.asarray(b0["D"]), rtol=1e-11, atol=1e-9)
    np.testing.assert_allclose(np.asarray(b1["W"])[:203], np.asarray(b0["W"]), rtol=1e-11, atol=1e-9)
    # the padding: zero gradient and couplings, identity diagonal blocks, no link to the record
    assert np.all(np.asarray(b1["gmu"])[203:] == 0) and np.all(np.asarray(b1["W"])[203:] == 0)
    assert np.all(np.asarray(b1["B"])[202:] == 0)
    np.testing.assert_array_equal(np.asarray(b1["D"])[203:], np.broadcast_to(np.eye(2), (L1 - 203, 2, 2)))
    del rng


def test_padded_fit_equals_unpadded_fit():
    model = lin_model()
    rec = make_record(300, seed=5)  # bucket 304
    res = {b: fit(model, [rec], options=FitOptions(bucket=b, noise_start="data")) for b in (False, True)}
    r0, r1 = res[False], res[True]
    assert r0.converged and r1.converged
    np.testing.assert_allclose(r1.elbo, r0.elbo, rtol=1e-10)
    np.testing.assert_allclose(r1.theta, r0.theta, rtol=1e-6, atol=1e-8)
    np.testing.assert_allclose(r1.std_errors, r0.std_errors, rtol=1e-5)
    assert r1.smoothers[0].mu.shape == (300, 2)
    np.testing.assert_allclose(r1.smoothers[0].mu, r0.smoothers[0].mu, rtol=1e-6, atol=1e-8)
    for k in r0.measurement_std:
        np.testing.assert_allclose(r1.measurement_std[k], r0.measurement_std[k], rtol=1e-6)


@pytest.mark.parametrize("lengths", [(290, 301)])
def test_records_in_one_bucket_compile_once(lengths):
    assert bucket_length(lengths[0]) == bucket_length(lengths[1])
    model = lin_model(floor=1e-9)  # a model object of its own: its Objective is not shared with other tests
    opts = FitOptions(noise_start="data", max_iter=30)
    res = fit(model, [make_record(lengths[0], seed=6)], options=opts)
    P = Problem(model, [make_record(lengths[0], seed=6)], opts)
    before = dict(P.obj.traces)
    assert before.get("blocks", 0) >= 1 and before.get("factor", 0) >= 1
    res2 = fit(model, [make_record(lengths[1], seed=7)], options=opts)
    assert dict(P.obj.traces) == before  # the second length reused every compiled function
    assert res.iterations > 0 and res2.iterations > 0
    assert res2.smoothers[0].mu.shape == (lengths[1], 2)
    # a length in another bucket does compile (the counter works)
    fit(model, [make_record(2 * lengths[1], seed=8)], options=opts)
    assert P.obj.traces["blocks"] > before["blocks"]
