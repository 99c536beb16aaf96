"""Outputs that measure a state directly, up to a unit factor and an offset (y = c + k·x).

A new user writes outputs the way the instrumentation reports them: an angle in degrees as
``57.29577951308232*alpha``, an airspeed as ``V0 + u`` around the trim speed. Such an output
still measures the state directly, and the estimator's starts must use it as it uses y = x:
the state's start μ = (y − c)/k, its process-noise data start spread(Δy)/(|k|√T). The fit
of a model whose output is k·x to data k·y must then take the same iterates as the fit of
y = x to y (the density of the scaled data differs by the constant N ln k only).
"""

from __future__ import annotations

import dataclasses
import math
import types

import jax.numpy as jnp
import numpy as np
import pytest

from vsidgen.estimator import DirectMeasurement, FitOptions, direct_measurements, fit, measured_states
from vsidgen.metadata import MeasurementNoiseSpec, Parameter, ProcessNoiseSpec, Variable
from vsidgen.model import Model, load_model

USER_SPEC = """\
name: user_units
description: a short-period model written with outputs in the instruments' units
states:
  alpha: {unit: rad}
  q: {unit: rad/s}
  u: {unit: m/s, description: speed perturbation}
inputs:
  de: {unit: rad}
outputs:
  alpha_deg: {unit: deg}
  q_deg: {unit: deg/s}
  V: {unit: m/s}
  az: {unit: m/s^2}
  alpha_sq: {unit: rad^2}
  q_plus_bias: {unit: rad/s}
constants:
  R2D: {value: 57.29577951308232, unit: deg/rad}
  V0: {value: 80.0, unit: m/s}
parameters:
  Za: {unit: 1/s}
  Zq: {}
  Ma: {unit: 1/s^2}
  Mq: {unit: 1/s}
  Mde: {unit: 1/s^2}
  Xu: {unit: 1/s}
  bq: {unit: rad/s}
definitions:
  lift: Za*alpha
drift:
  alpha: lift + (1 + Zq)*q
  q: Ma*alpha + Mq*q + Mde*de
  u: Xu*u
observations:
  alpha_deg: R2D*alpha
  q_deg: q*180/3.141592653589793
  V: V0 + u
  az: V0*lift
  alpha_sq: alpha**2
  q_plus_bias: q + bq
data:
  time: t
  inputs: {de: de}
  outputs: {alpha_deg: a, q_deg: qd, V: v, az: az, alpha_sq: a2, q_plus_bias: qb}
"""


@pytest.fixture(scope="module")
def user_model(tmp_path_factory):
    d = tmp_path_factory.mktemp("user_units")
    (d / "user_units.yaml").write_text(USER_SPEC)
    return load_model(d / "user_units.yaml", generated_dir=d / "gen")


def test_affine_outputs_are_direct_measurements(user_model):
    dm = direct_measurements(user_model)
    names = user_model.state_names
    got = {names[i]: (user_model.output_names[m.output], m.gain, m.offset) for i, m in dm.items()}
    assert set(got) == {"alpha", "q", "u"}
    assert got["alpha"][0] == "alpha_deg" and got["alpha"][1] == pytest.approx(57.29577951308232, rel=1e-15)
    assert got["q"][0] == "q_deg" and got["q"][1] == pytest.approx(180 / math.pi, rel=1e-15)
    assert got["u"] == ("V", 1.0, 80.0)
    # az (a parameter times a state), alpha² (not affine) and q + bq (an estimated offset) are not
    assert measured_states(user_model) == {i: m.output for i, m in dm.items()}
    assert DirectMeasurement(2, 1.0, 80.0).state_of(np.array([80.5])) == pytest.approx([0.5])


def test_numerical_test_agrees_with_the_symbolic_one(user_model):
    bare = dataclasses.replace(user_model, symbolic=None)
    sym = direct_measurements(user_model)
    num = direct_measurements(bare)
    assert set(num) == set(sym)
    for i in sym:
        assert num[i].output == sym[i].output
        assert num[i].gain == pytest.approx(sym[i].gain, rel=1e-10)
        assert num[i].offset == pytest.approx(sym[i].offset, rel=1e-10, abs=1e-10)


def test_a_fixed_parameter_is_a_number_an_estimated_one_is_not(user_model):
    bq_fixed = tuple(dataclasses.replace(p, fixed=True, initial=0.01) if p.name == "bq" else p
                     for p in user_model.parameters)
    m = dataclasses.replace(user_model, parameters=bq_fixed)
    q = user_model.state_names.index("q")
    # q_deg comes first, so q stays measured by it; the fixed offset is recognised for a
    # model without q_deg (numerical path: the symbolic one substitutes the same values)
    assert direct_measurements(m)[q].output == user_model.output_names.index("q_deg")
    bare = dataclasses.replace(m, symbolic=None)
    assert direct_measurements(bare)[q].output == user_model.output_names.index("q_deg")


# ----------------------------------------------------------------- unit invariance of a fit
T = 0.05
N = 400
K = 57.29577951308232


def _drift(x, u, p):
    return jnp.stack([p[0] * x[0] + x[1] + p[1] * u[0], p[2] * x[0] + p[3] * x[1] + p[4] * u[0]])


def _output(x, u, p):
    return jnp.stack([p[5] * x[0], p[5] * x[1]])


def _model(k):
    """Short period with both outputs k·state; k a fixed parameter, so that the models share code."""
    return Model(
        name="units", drift=_drift, output=_output,
        states=(Variable("alpha"), Variable("q")), inputs=(Variable("de"),),
        outputs=(Variable("alpha_m"), Variable("q_m")),
        parameters=tuple(Parameter(n) for n in ("Za", "Zde", "Ma", "Mq", "Mde")) + (
            Parameter("k", initial=k, fixed=True),),
        process_noise=ProcessNoiseSpec(states=("alpha", "q")),
        measurement_noise=tuple(MeasurementNoiseSpec(o, floor=0.0) for o in ("alpha_m", "q_m")))


def _record(scale):
    """Euler-discretised short period with process and measurement noise (numpy, written here)."""
    rng = np.random.default_rng(7)
    t = np.arange(N) * T
    de = np.where((t % 4.0) < 1.0, 0.05, np.where((t % 4.0) < 2.0, -0.05, 0.0))
    A = np.array([[-1.2, 1.0], [-6.0, -1.5]])
    B = np.array([-0.1, -8.0])
    x = np.zeros(2)
    X = np.zeros((N, 2))
    for k in range(N):
        X[k] = x
        x = x + T * (A @ x + B * de[k]) + np.sqrt(T) * np.array([0.01, 0.05]) * rng.normal(size=2)
    y = X + np.array([0.002, 0.004]) * rng.normal(size=(N, 2))
    return types.SimpleNamespace(t=t, dt=T, u=de[:, None], y=scale * y, name=f"units{scale:g}")


def test_fit_iterates_do_not_depend_on_the_outputs_unit_factor():
    opts = FitOptions(max_iter=150, noise_start="data")
    r1 = fit(_model(1.0), [_record(1.0)], options=opts)
    rk = fit(_model(K), [_record(K)], options=opts)
    assert r1.converged and rk.converged
    assert rk.iterations == r1.iterations
    free = r1.free_mask
    se = np.asarray(r1.std_errors)[free]
    assert np.all(np.abs(np.asarray(rk.theta)[free] - np.asarray(r1.theta)[free]) <= 1e-6 * se)
    for o in ("alpha_m", "q_m"):
        assert rk.measurement_std[o] == pytest.approx(K * r1.measurement_std[o], rel=1e-6)
    for s in ("alpha", "q"):
        assert rk.process_std[s] == pytest.approx(r1.process_std[s], rel=1e-6)
    # the scaled data's density differs by the constant −N ln k per output
    assert rk.elbo - r1.elbo == pytest.approx(-2 * N * math.log(K), abs=1e-6 * abs(r1.elbo) + 1e-6)
