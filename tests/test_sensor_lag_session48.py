"""A sensor's first-order dynamics (``sensor_lag``, session 48).

An independent short-period simulator gave its α vane a first-order lag of 0.15 s (vane
inertia, pneumatic tubing, a filter); diagnose had no such candidate and named a vane position
of 6.9 m, then two output derivatives of α that absorbed the attenuation a position cannot
give. The lag is now a candidate, refitted beside a time skew or a position of the same channel
(the forms it equals to first order). Independent reference for the slow test: a numpy
simulation written here (the two-state short period, the vane read through ``τ ẏ = α − y``
integrated at a step 40 × finer than the record's).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from test_score_states import _cand, _sr

from vsidgen.discrepancy.search import Ranked, choose_refits


def test_the_lag_of_a_channel_is_refitted_beside_its_skew_or_position():
    rows = [Ranked(_cand("skew:a", "time_skew", "output:alpha"), 0, _sr(80.0)),
            Ranked(_cand("pos:az", "sensor_position", "output:az"), 0, _sr(60.0)),
            Ranked(_cand("bias:q", "sensor_bias", "output:q"), 0, _sr(40.0)),
            Ranked(_cand("lag:a", "sensor_lag", "output:alpha"), 0.0, None),
            Ranked(_cand("lag:az", "sensor_lag", "output:az"), 0.0, None),
            Ranked(_cand("lag:q", "sensor_lag", "output:q"), 0.0, None)]
    rows = sorted(rows, key=Ranked.sort_key)
    got = [r.candidate.key for r in choose_refits(rows, max_candidates=3, min_score=1.0,
                                                  alpha=0.01, n_examined=6)]
    assert sorted(got) == sorted(["skew:a", "pos:az", "bias:q", "lag:a", "lag:az"])


DT = 0.04


def _simulate(tau, *, n=750, seed=5, fine=40):
    """The short period of tests/test_diagnose_noise_model.py (white diagonal process noise),
    integrated with Euler at ``DT/fine`` with the input held per sample; the α vane reads
    through a first-order lag ``tau`` integrated exactly at the fine step."""
    rng = np.random.default_rng(seed)
    A = np.array([[-0.6, 1.0], [-5.0, -2.0]])
    B = np.array([-0.1, -7.0])
    from test_diagnose_noise_model import elevator_pulses

    t = np.arange(n) * DT
    u = elevator_pulses(t)
    h = DT / fine
    decay = math.exp(-h / tau)
    x, yv = np.zeros(2), 0.0
    xs, vane = np.empty((n, 2)), np.empty(n)
    G = np.diag([0.002, 0.01])
    for k in range(n):
        xs[k], vane[k] = x, yv
        for _ in range(fine):
            x = x + h * (A @ x + B * u[k]) + math.sqrt(h) * G @ rng.standard_normal(2)
            yv = x[0] + (yv - x[0]) * decay
    y = np.column_stack([vane, xs[:, 1]]) + 0.0005 * rng.standard_normal((n, 2))
    return t, u, y


@pytest.mark.slow
def test_a_lagged_vane_is_named_a_sensor_lag_with_its_time_constant(tmp_path):
    from test_diagnose_noise_model import SPEC

    from vsidgen.discrepancy import run_diagnose

    spec = tmp_path / "sp2.yaml"
    spec.write_text(SPEC)
    t, u, y = _simulate(0.15)
    csv = tmp_path / "rec.csv"
    csv.write_text("t,de,alpha,q\n" + "".join(
        f"{float(t[k])!r},{float(u[k])!r},{float(y[k, 0])!r},{float(y[k, 1])!r}\n"
        for k in range(len(t))))
    res = run_diagnose(spec, [csv], out=tmp_path / "o", max_rounds=1, max_candidates=3,
                       effects=["sensor_lag", "time_skew", "sensor_position"], numerics=False,
                       noise_model=False)
    (f,) = res.document["findings"]
    assert f["key"] == "sensor_lag:alpha", [(t["key"], t["statistic"]) for r in
                                            res.document["rounds"] for t in r["trials"]]
    (name, p), = f["parameters"].items()
    assert p["unit"] == "s" and abs(p["estimate"] - 0.15) < 3 * p["std_error"], p
