"""Fits that start on a saddle leave it along negative curvature (estimator.fit._saddle_step).

The reference is independent of the saddle machinery: the same linear model written with one
input gain ``b2`` (identifiable; its fit never meets a zero gradient). Written with the gain
as a product ``b2a·b2b`` of two parameters that both start at 0, the gradient in both is zero
at the start and the damped Newton step cannot move them; with the saddle step the fit reaches
the reference's ELBO and ``b2a·b2b`` its ``b2``. Without it (monkeypatched away) the product
stays 0 and the ELBO far below: the test can fail.
"""

from __future__ import annotations

import importlib

import jax.numpy as jnp
import pytest

from tests.test_estimator import C_OUT, lin_model, make_record
from vsidgen.estimator import FitOptions, fit
from vsidgen.metadata import Parameter
from vsidgen.model import Model


def _product_model():
    base = lin_model()

    def drift(x, u, p):
        A = jnp.array([[p[0], 1.0], [p[1], p[2]]])
        return A @ x + jnp.array([0.0, p[3] * p[4]]) * u[0]

    def output(x, u, p):
        return jnp.asarray(C_OUT) @ x

    pars = base.parameters[:3] + (Parameter("b2a"), Parameter("b2b"))
    return Model(name="lin_product", drift=drift, output=output, states=base.states,
                 inputs=base.inputs, outputs=base.outputs, parameters=pars,
                 process_noise=base.process_noise, measurement_noise=base.measurement_noise)


@pytest.fixture(scope="module")
def rec():
    return make_record(300, seed=4)


@pytest.mark.slow
def test_a_product_of_parameters_starting_at_zero_leaves_the_saddle(rec, monkeypatch):
    opts = FitOptions(noise_start="data", max_iter=200)
    ref = fit(lin_model(), [rec], options=opts)
    assert ref.converged
    b2 = float(ref.theta[3])
    res = fit(_product_model(), [rec], options=opts)
    assert res.converged, res.status
    assert any(h.get("saddle_step") for h in res.history)
    assert float(res.theta[3] * res.theta[4]) == pytest.approx(b2, rel=1e-4)
    assert res.elbo == pytest.approx(ref.elbo, abs=1e-3)
    fit_module = importlib.import_module("vsidgen.estimator.fit")
    monkeypatch.setattr(fit_module, "_saddle_step", lambda *a, **k: None)
    stuck = fit(_product_model(), [rec], options=opts)
    assert float(stuck.theta[3] * stuck.theta[4]) == 0.0
    assert stuck.elbo < ref.elbo - 10.0
