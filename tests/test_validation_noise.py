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
    np.testing.assert_allclose(own.fits[0].theta, res.theta, rtol=0, atol=0)   # physics held


def test_trim_constants_are_those_that_enter_additively_alone():
    """Z0, M0 (and a sensor bias az0) are properties of the flight condition; a parameter that
    also multiplies a state (Z_q in (1 + Z_q) q) or enters a coefficient scaled by the dynamic
    pressure (HFB-320's C_L0) is not."""
    from vsidgen.spec import compile_spec

    assert compile_spec(ROOT / "specs" / "attas_sp.yaml").trim_parameters() == ("Z0", "M0")
    assert compile_spec(ROOT / "specs" / "tu144_sp.yaml").trim_parameters() == ("Z0", "M0", "az0")
    assert compile_spec(ROOT / "specs" / "hfb320.yaml").trim_parameters() == ()


REF = {"Z0": -0.00898779, "ZAL": -0.483362, "ZQ": 0.104198, "ZDE": 0.676322,
       "M0": 0.475234, "MAL": -4.92651, "MQ": -2.00573, "MDE": -7.20806}


def _simulate_attas(path, de, dt, m0, seed):
    """Independent numpy simulation (Euler, 10 substeps) of the textbook ATTAS short-period
    model at the output-error estimates with pitch-moment constant ``m0``, trimmed at the
    start, small process and sensor noise; written as a CSV with the spec's columns."""
    rng = np.random.default_rng(seed)
    p = dict(REF, M0=m0)
    A = np.array([[p["ZAL"], 1 + p["ZQ"]], [p["MAL"], p["MQ"]]])
    b = np.array([p["Z0"], p["M0"]]) + np.array([p["ZDE"], p["MDE"]]) * de[0]
    x = -np.linalg.solve(A, b)
    h = dt / 10
    out = np.empty((len(de), 2))
    for k, u in enumerate(de):
        out[k] = x
        for _ in range(10):
            f = A @ x + np.array([p["Z0"], p["M0"]]) + np.array([p["ZDE"], p["MDE"]]) * u
            x = x + h * f + np.sqrt(h) * np.array([2e-4, 1e-3]) * rng.standard_normal(2)
    y = out + rng.standard_normal(out.shape) * np.array([2e-4, 5e-4])
    t = np.arange(len(de)) * dt
    np.savetxt(path, np.column_stack([t, de, y]), delimiter=",",
               header="t_s,de_rad,alpha_rad,q_radps", comments="")
    return path


@pytest.mark.slow
def test_validation_re_estimates_the_trim_constants_of_another_flight(tmp_path):
    """Two records of the textbook ATTAS short period (independent numpy simulation), the
    validation one flown at another trim (M0 larger by 0.05 rad/s²): with the trim constants
    Z0 and M0 free, validation re-estimates M0 near its own value, holds every other parameter
    at the estimate, and its ELBO is far above the one with them held."""
    import csv

    from vsidgen.data import load_record
    from vsidgen.errors import FitError
    from vsidgen.estimator import FitOptions, fit
    from vsidgen.estimator import validate_own_noise as own
    from vsidgen.model import load_model

    rows = list(csv.DictReader((ROOT / "data" / "attas_sp_synthetic.csv").open()))
    de = np.array([float(r["de_rad"]) for r in rows])
    dt = float(rows[1]["t_s"]) - float(rows[0]["t_s"])
    model = load_model(ROOT / "specs" / "attas_sp.yaml", generated_dir=tmp_path / "gen")
    est = load_record(model, _simulate_attas(tmp_path / "est.csv", de, dt, REF["M0"], 1))
    val = load_record(model, _simulate_attas(tmp_path / "val.csv", de, dt, REF["M0"] + 0.05, 2))
    res = fit(model, [est], options=FitOptions(max_iter=200))
    names = list(model.parameter_names)
    m0 = res.theta[names.index("M0")]
    assert abs(m0 - REF["M0"]) < 0.03
    held = validate_own_noise(model, [val], res.theta, max_iter=200)
    free = validate_own_noise(model, [val], res.theta, max_iter=200, free=("Z0", "M0"))
    assert held is not None and free is not None and free.converged
    print("validation ELBO, trim held", held.elbo, "free", free.elbo,
          "M0", free.fits[0].theta[names.index("M0")])
    assert free.elbo > held.elbo + 50.0
    # the shift of the trim (0.05) recovered within 0.02 from the estimate's own error
    assert abs(free.fits[0].theta[names.index("M0")] - m0 - 0.05) < 0.02
    for j, n in enumerate(names):
        if n not in ("Z0", "M0"):
            assert free.fits[0].theta[j] == res.theta[j], n
    with pytest.raises(FitError, match="not parameters"):
        own(model, [val], res.theta, free=("nope",))
    # two validation flights at two trims: each fitted on its own (its own noise and trim),
    # the ELBOs summed — not one noise level and one trim for both
    both = validate_own_noise(model, [est, val], res.theta, max_iter=200, free=("Z0", "M0"))
    from vsidgen.discrepancy.fitstate import diag_options
    alone = [own(model, [r], res.theta, free=("Z0", "M0"), options=diag_options(200))
             for r in (est, val)]
    assert len(both.fits) == 2 and both.converged
    assert both.elbo == pytest.approx(sum(a.elbo for a in alone), rel=1e-9)
    m0s = [f.theta[names.index("M0")] for f in both.fits]
    assert abs(m0s[1] - m0s[0] - 0.05) < 0.02      # each record its own M0


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
                          validate_own_noise(m, [r2], res.theta, max_iter=200).elbo,
                          validate_own_noise(m, [r2], res.theta, max_iter=200,
                                             free=("Z0", "M0")).elbo)
    full, no_mq = out["attas_sp"], out["attas_sp_no_mq"]
    print("validation ELBOs (fixed noise, own noise, own noise and trim):", out)
    assert no_mq[0] > full[0]                 # the confounded comparison
    assert full[1] > no_mq[1] + 100.0         # the physics, at each flight's own noise
    assert full[2] > no_mq[2] + 100.0         # and at its own trim (what diagnose compares)
