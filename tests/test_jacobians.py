"""The generated Jacobians as the run-time first derivatives of f, h and the transition F.

References are independent of the generated derivatives: forward-mode autodiff
(``jax.jacfwd``) of the generated ``drift``/``output`` and of ``dynamics.transition``,
and ``jax.hessian`` of the flat objective for the estimator's structured blocks.
"""

import dataclasses
import pathlib
import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from vsidgen.model.dynamics import transition
from vsidgen.model import load_model

jax.config.update("jax_enable_x64", True)

ROOT = pathlib.Path(__file__).resolve().parents[1]
SHIPPED = sorted((ROOT / "specs").glob("*.yaml"))
NONLINEAR = pathlib.Path(__file__).parent / "specs" / "nonlinear.yaml"

# a smooth nonlinear model with definitions that feed both f and h (pendulum with drag)
PENDULUM = """\
name: pendjac
states:
  th: {unit: rad}
  om: {unit: rad/s}
inputs:
  tq: {unit: N*m}
outputs:
  th: {unit: rad}
  acc: {unit: rad/s^2}
constants:
  G0: {value: 9.80665, unit: m/s^2}
parameters:
  k: {initial: 2.0}
  c: {initial: 0.1, bounds: [0, null]}
  b: {initial: 0.5, bounds: [-1, 3]}
definitions:
  drag: c*om*sqrt(1 + om**2)
  accel: -k*sin(th) - drag + b*tq*cos(th)
drift:
  th: om
  om: accel
observations:
  th: th
  acc: accel + 0.1*th**2
noise:
  process: {states: [th, om], structure: full}
  measurement:
    th: {floor: 0.01}
    acc: {floor: 0.01}
data:
  time: t_s
  inputs: {tq: tq_nm}
  outputs: {th: th_rad, acc: acc_radps2}
"""


def _check(got, want, what):
    want = np.asarray(want)
    scale = max(1.0, float(np.abs(want).max(initial=0.0)))
    np.testing.assert_allclose(np.asarray(got), want, rtol=1e-10, atol=1e-12 * scale, err_msg=what)


@pytest.fixture(scope="module")
def nonlinear(tmp_path_factory):
    return load_model(NONLINEAR, generated_dir=tmp_path_factory.mktemp("nonlinear"))


@pytest.fixture(scope="module")
def pendulum(tmp_path_factory):
    d = tmp_path_factory.mktemp("pendjac")
    (d / "pendjac.yaml").write_text(PENDULUM)
    return load_model(d / "pendjac.yaml", generated_dir=d / "gen")


def _points(model, seed, count=3):
    rng = np.random.default_rng(seed)
    p0 = np.array([float(p.initial) for p in model.parameters])
    for _ in range(count):
        # states in [0.5, 1.5] (away from the 1/V of the airspeed models), inputs small
        yield (jnp.asarray(rng.uniform(0.5, 1.5, model.nx)), jnp.asarray(rng.uniform(-0.5, 0.5, model.nu)),
               jnp.asarray(p0 + rng.uniform(-0.3, 0.3, model.np)))


@pytest.mark.parametrize("spec", SHIPPED, ids=lambda p: p.stem)
def test_model_jacobians_of_shipped_specs_equal_autodiff(spec):
    model = load_model(spec, generated_dir=ROOT / "generated", build=False)
    assert model.jacobians is not None
    for x, u, p in _points(model, seed=len(spec.stem)):
        for name, fun, jac in (("f", model.drift, model.drift_jacobian),
                               ("h", model.output, model.output_jacobian)):
            got = jac(x, u, p)
            want = jax.jacfwd(fun, argnums=(0, 1, 2))(x, u, p)
            for g, w, var in zip(got, want, "xup"):
                _check(g, w, f"{spec.stem}: d{name}/d{var}")


def test_model_jacobians_with_definitions_and_nonlinear_terms(nonlinear, pendulum):
    # points away from the kinks of sat/max/min/abs/sign and the interp knots
    pts = [([0.3, 0.7, 0.5], [0.2, -0.1]), ([-1.2, -0.4, -0.6], [-0.5, 0.3]),
           ([2.0, -2.5, 1.5], [1.0, 0.05])]
    p = jnp.asarray([float(q.initial) + 0.1 for q in nonlinear.parameters])
    for x, u in pts:
        x, u = jnp.asarray(x), jnp.asarray(u)
        for name, fun, jac in (("f", nonlinear.drift, nonlinear.drift_jacobian),
                               ("h", nonlinear.output, nonlinear.output_jacobian)):
            for g, w, var in zip(jac(x, u, p), jax.jacfwd(fun, argnums=(0, 1, 2))(x, u, p), "xup"):
                _check(g, w, f"nonlinear: d{name}/d{var}")
    for x, u, p in _points(pendulum, seed=5):
        for g, w in zip(pendulum.drift_jacobian(x, u, p), jax.jacfwd(pendulum.drift, argnums=(0, 1, 2))(x, u, p)):
            _check(g, w, "pendulum f")


def test_bare_model_falls_back_to_autodiff(pendulum):
    bare = dataclasses.replace(pendulum, jacobians=None)
    x, u, p = next(_points(pendulum, seed=1))
    for g, w in zip(bare.drift_jacobian(x, u, p), pendulum.drift_jacobian(x, u, p)):
        _check(g, w, "bare f")
    assert transition(bare).jac is None and transition(pendulum).jac is not None


@pytest.mark.parametrize("integrator, substeps, inputs", [
    ("euler", 1, "zoh"), ("euler", 3, "zoh"), ("rk4", 2, "zoh"), ("euler", 2, "foh"),
    ("rk4", 3, "foh")])
def test_transition_jacobian_chain_rule_equals_jacfwd(pendulum, nonlinear, integrator, substeps, inputs):
    """∂F/∂x, ∂F/∂p composed from the generated f_x, f_p equal jax.jacfwd of the transition."""
    for model, seed in ((pendulum, 2), (nonlinear, 3)):
        F = transition(model, integrator=integrator, substeps=substeps, inputs=inputs)
        assert F.jac is not None
        jac = jax.jit(F.jacobian)
        ref = jax.jit(jax.jacfwd(F.fn, argnums=(0, 2)))
        for x, u, p in _points(model, seed=seed):
            v = jnp.concatenate([u, 0.7 * u + 0.1]) if inputs == "foh" else u
            got = jac(x, v, p, 0.05)
            want = ref(x, v, p, 0.05)
            for g, w, var in zip(got, want, "xp"):
                _check(g, w, f"{model.name} {integrator}/{substeps}/{inputs}: dF/d{var}")


@pytest.mark.slow
def test_structured_hessian_exact_with_generated_jacobians(pendulum, monkeypatch):
    """The estimator's sigma-point blocks built on the generated Jacobians (the alternative
    ``core.POINT_JACOBIANS = "generated"`` that bench_jacobians measures) equal jax.hessian /
    jax.grad of the flat objective (which never calls them)."""
    from vsidgen.estimator import core

    monkeypatch.setattr(core, "POINT_JACOBIANS", "generated")
    from vsidgen.estimator import Problem
    from vsidgen.estimator.linalg import btd_to_dense
    from vsidgen.estimator.results import FitOptions

    rng = np.random.default_rng(4)
    N, dt = 7, 0.05
    y = rng.normal(size=(N, 2))
    y[2, 1] = np.nan
    rec = types.SimpleNamespace(name="p", path=None, t=np.arange(N) * dt, dt=dt, u=rng.normal(size=(N, 1)),
                                y=y, input_names=("tq",), output_names=("th", "acc"))
    P = Problem(pendulum, [rec], FitOptions(bucket=False))
    assert P.obj.point_jacobians == "generated" and P.obj.F.jac is not None
    s, recs = P.initial(FitOptions())
    s = s + 0.3 * rng.normal(size=s.shape)
    (m0, r0), = [(m + 0.2 * rng.normal(size=m.shape), r + 0.2 * rng.normal(size=r.shape)) for m, r in recs]
    sz, nq = m0.size, P.obj.nq

    def total(v):
        return P.obj._value_impl(v[:sz].reshape(m0.shape), v[sz:sz + nq], v[sz + nq:], P.data[0], P.cfg)

    v = jnp.asarray(np.concatenate([m0.ravel(), r0, s]))
    Hd = np.asarray(jax.jit(jax.hessian(total))(v))
    gd = np.asarray(jax.jit(jax.grad(total))(v))
    b = P.blocks(s, [(m0, r0)])[0]
    Hs = np.zeros_like(Hd)
    Hs[:sz, :sz] = btd_to_dense(b["D"], b["B"])
    W = np.asarray(b["W"]).reshape(sz, -1)
    Hs[:sz, sz:], Hs[sz:, :sz], Hs[sz:, sz:] = W, W.T, np.asarray(b["Hbb"])
    gs = np.concatenate([np.asarray(b["gmu"]).ravel(), np.asarray(b["gb"])])
    np.testing.assert_allclose(gs, gd, rtol=1e-9, atol=1e-9 * np.abs(gd).max())
    np.testing.assert_allclose(Hs, Hd, rtol=1e-8, atol=1e-9 * np.abs(Hd).max())


def test_evaluation_linearisation_uses_generated_jacobians(pendulum):
    """The steady-state Kalman gain of the evaluation is the same with the generated Jacobians
    as with autodiff of F and h (the model without them)."""
    from vsidgen.evaluation import evaluate

    rng = np.random.default_rng(6)
    N, dt = 40, 0.05
    rec = types.SimpleNamespace(name="e", path=None, t=np.arange(N) * dt, dt=dt, u=rng.normal(size=(N, 1)),
                                y=rng.normal(size=(N, 2)), input_names=("tq",), output_names=("th", "acc"))
    mu = 0.3 * rng.normal(size=(N, 2))
    kw = dict(mu=mu, G=np.diag([0.05, 0.2]), R=np.diag([0.01, 0.04]), integrator="rk4", substeps=2)
    theta = np.array([2.0, 0.1, 0.5])
    gen = evaluate(pendulum, rec, theta, **kw)
    auto = evaluate(dataclasses.replace(pendulum, jacobians=None), rec, theta, **kw)
    assert gen.gain is not None
    _check(gen.gain, auto.gain, "Kalman gain")
    _check(gen.y_pred, auto.y_pred, "predictions")


def test_drift_sensitivities_are_the_generated_parameter_jacobian(pendulum):
    """diagnose's ∂f_s/∂θ along the smoothed path equals jax.jacfwd of the drift."""
    from vsidgen.discrepancy.search import drift_sensitivities

    rng = np.random.default_rng(7)
    N = 9
    x = rng.uniform(0.5, 1.5, (N, 2))
    u = rng.normal(size=(N, 1))
    theta = np.array([2.0, 0.1, 0.5])
    st = types.SimpleNamespace(model=pendulum, fit=types.SimpleNamespace(theta=theta),
                               signals=[types.SimpleNamespace(x_smooth=x, t=np.arange(N) * 0.1)],
                               records=[types.SimpleNamespace(u=u)])
    got = drift_sensitivities(st)
    want = np.stack([np.asarray(jax.jacfwd(pendulum.drift, argnums=2)(jnp.asarray(x[k]), jnp.asarray(u[k]),
                                                                       jnp.asarray(theta)))
                     for k in range(N - 1)])
    assert got["th"].shape == (N - 1, 0)  # f_th = om: no parameter
    _check(got["om"], want[:, 1, :], "∂f_om/∂θ")
