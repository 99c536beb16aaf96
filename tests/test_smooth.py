"""Validation-mode smoothing (θ and noise fixed) on a real record: the assumed density starts
at the prior's conditional covariance, so the smoother reaches the physical optimum.

Regression: at the filter-error estimates of HFB-320 (θ, F, R from
../shared/reference/hfb320_reference.json) with Euler, the smoother used to start at Σ = I
and stop, "converged", at ELBO −9.2e5 instead of +14627.
"""

import json
import pathlib

import numpy as np
import pytest

from vsidgen import FitOptions, load_model, load_record, smooth


@pytest.mark.slow
def test_smoothing_at_fixed_filter_error_estimates_reaches_physical_optimum(flight_data_dir):
    ref = json.loads((flight_data_dir.parent.parent / "reference" / "hfb320_reference.json").read_text())
    fem = ref["fem"]
    m = load_model(pathlib.Path(__file__).resolve().parents[1] / "specs" / "hfb320.yaml")
    rec = load_record(m, flight_data_dir / "hfb320_1_10.csv")
    theta = np.array([fem["parameters"][p.name]["value"] for p in m.parameters])
    noise = {"G": np.diag([fem["process_noise_F_diag"][s] for s in m.state_names]),
             "R": np.diag([fem["R_diag"][o] for o in m.output_names])}
    res = smooth(m, [rec], theta, noise, options=FitOptions(integrator="euler", max_iter=100))
    assert res.converged, res.status
    assert res.elbo > 14000.0, res.elbo
    # the smoothed states follow their measurements (no far stationary point)
    mu = res.smoothers[0].mu
    y = np.asarray(rec.y)
    for i, name in enumerate(m.state_names):
        j = m.output_names.index(name)
        rms = float(np.sqrt(np.nanmean((mu[:, i] - y[:, j]) ** 2)))
        assert rms < 5 * np.sqrt(fem["R_diag"][name]), (name, rms)
