"""Diagnose's validation gate with each validation record's own noise
(:func:`vsidgen.discrepancy.fitstate.validate_own_noise`, :func:`.search.validation_improved`).

Noise (the day's turbulence, a sensor's noise) is a property of a flight, not of the physics:
with the estimation's noise fixed, a model that lacks a term but carries inflated process noise
can validate better than the right model on a flight whose sensors are noisier (ATTAS without
M_q, docs/diagnose.md, "Session 30")."""

from __future__ import annotations

import dataclasses
import pathlib
import types

import numpy as np
import pytest

from vsidgen.discrepancy.fitstate import validate_own_noise
from vsidgen.discrepancy.search import validation_improved

ROOT = pathlib.Path(__file__).resolve().parents[1]


def _st(fixed, own):
    return types.SimpleNamespace(val_elbo=fixed, val_elbo_own_noise=own)


def test_the_gate_compares_own_noise_elbos_when_both_have_them():
    # own noise: the candidate wins (6861.6 > 6559.7) though it loses with fixed noise
    assert validation_improved(_st(6284.7, 6861.6), _st(6437.1, 6559.7))
    assert not validation_improved(_st(6500.0, 6500.0), _st(6437.1, 6559.7))
    # one side without it: both with the estimation's noise
    assert not validation_improved(_st(6284.7, 6861.6), _st(6437.1, None))
    assert validation_improved(_st(6284.7, None), _st(6200.0, 6559.7))
    # the added states' initial-value entropy is taken off the candidate's
    assert not validation_improved(_st(0.0, 10.0), _st(0.0, 9.0), x0_entropy=1.5)


def test_own_noise_validation_is_at_least_the_fixed_noise_smoothing():
    """A superset of the smoothing problem (the noise free as well): its optimum is not lower;
    on a validation record 10× noisier in its sensors than the estimation record, much higher."""
    from vsidgen.data import load_record
    from vsidgen.estimator import FitOptions, fit, smooth
    from vsidgen.model import load_model

    model = load_model(ROOT / "specs" / "attas_sp.yaml")
    est = load_record(model, ROOT / "data" / "attas_sp_synthetic.csv")
    val = load_record(model, ROOT / "data" / "attas_sp_synthetic_val.csv")
    rng = np.random.default_rng(0)
    noisy = dataclasses.replace(val, y=val.y + rng.normal(size=val.y.shape) * np.array([0.005, 0.01]))
    res = fit(model, [est], options=FitOptions(max_iter=200))
    fixed = smooth(model, [noisy], res.theta, res)
    own = validate_own_noise(model, [noisy], res.theta, max_iter=200)
    assert own is not None and own.converged
    assert own.elbo >= fixed.elbo - 1e-6 * abs(fixed.elbo)
    assert own.elbo > fixed.elbo + 100.0
    np.testing.assert_allclose(own.theta, res.theta, rtol=0, atol=0)   # the physics is held


@pytest.mark.slow
@pytest.mark.flight
def test_attas_without_pitch_damping_loses_on_own_noise_validation(flight_data_dir, tmp_path):
    """The real case (estimation attas_elv1, validation attas_elv2): with the estimation's
    noise the model without M_q validates higher than the textbook model; with each
    record's own noise, lower."""
    from vsidgen.data import load_record
    from vsidgen.estimator import fit, smooth
    from vsidgen.model import load_model

    out = {}
    for spec in (ROOT / "specs" / "attas_sp.yaml",
                 ROOT / "benchmarks" / "real_records" / "attas_sp_no_mq.yaml"):
        m = load_model(spec, generated_dir=tmp_path)
        r1 = load_record(m, flight_data_dir / "attas_elv1.csv")
        r2 = load_record(m, flight_data_dir / "attas_elv2.csv")
        res = fit(m, [r1])
        out[spec.stem] = (smooth(m, [r2], res.theta, res).elbo,
                          validate_own_noise(m, [r2], res.theta, max_iter=200).elbo)
    full, no_mq = out["attas_sp"], out["attas_sp_no_mq"]
    assert no_mq[0] > full[0]                 # the confounded comparison
    assert full[1] > no_mq[1] + 100.0         # the physics, at each flight's own noise
