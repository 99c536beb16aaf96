"""Transition functions against exact solutions of a linear ODE."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

from vsidgen.dynamics import transition, transition_fn
from vsidgen.errors import VsidgenError
from vsidgen.metadata import Parameter, ProcessNoiseSpec, Variable
from vsidgen.model import Model

jax.config.update("jax_enable_x64", True)

A = np.array([[-0.8, 1.0], [-3.0, -1.2]])
B = np.array([[0.1], [-2.0]])


def _model():
    def drift(x, u, p):
        return jnp.array([[p[0], 1.0], [-3.0, -1.2]]) @ x + jnp.asarray(B) @ u

    def output(x, u, p):
        return x

    return Model(name="lin", drift=drift, output=output,
                 states=(Variable("a"), Variable("q")), inputs=(Variable("de"),),
                 outputs=(Variable("a"), Variable("q")),
                 parameters=(Parameter("A11", initial=-0.8),),
                 process_noise=ProcessNoiseSpec(states=("a", "q")), measurement_noise=())


def _exact(x, u, dt):
    # zero-order hold: augmented matrix exponential
    M = np.zeros((3, 3))
    M[:2, :2] = A
    M[:2, 2:] = B
    E = scipy.linalg.expm(M * dt)
    return E[:2, :2] @ x + E[:2, 2:] @ u


x0 = np.array([0.3, -0.5])
u0 = np.array([0.7])
p0 = np.array([-0.8])


def test_euler_is_one_step():
    F = transition(_model())
    np.testing.assert_allclose(F(x0, u0, p0, 0.1), x0 + 0.1 * (A @ x0 + B @ u0), rtol=0, atol=1e-15)


def test_euler_substeps_matrix_power():
    m, dt = 4, 0.2
    F = transition(_model(), substeps=m)
    h = dt / m
    Ad = np.eye(2) + h * A
    ref = np.linalg.matrix_power(Ad, m) @ x0 + sum(
        np.linalg.matrix_power(Ad, j) @ (h * B @ u0) for j in range(m))
    np.testing.assert_allclose(F(x0, u0, p0, dt), ref, rtol=0, atol=1e-14)
    # substeps converge to the exact solution (first order)
    e1 = np.abs(np.asarray(transition(_model(), substeps=10)(x0, u0, p0, dt)) - _exact(x0, u0, dt)).max()
    e2 = np.abs(np.asarray(transition(_model(), substeps=20)(x0, u0, p0, dt)) - _exact(x0, u0, dt)).max()
    assert 1.7 < e1 / e2 < 2.3


def test_rk4_fifth_order_local_error():
    F = jax.jit(transition(_model(), integrator="rk4"))
    errs = []
    for dt in (0.1, 0.05, 0.025):
        errs.append(np.abs(np.asarray(F(x0, u0, p0, dt)) - _exact(x0, u0, dt)).max())
    assert errs[0] < 1e-5
    r1, r2 = errs[0] / errs[1], errs[1] / errs[2]
    assert 25 < r1 < 40 and 25 < r2 < 40  # 2^5 = 32
    # rk4 with substeps is much more accurate
    F4 = transition(_model(), integrator="rk4", substeps=4)
    assert np.abs(np.asarray(F4(x0, u0, p0, 0.1)) - _exact(x0, u0, 0.1)).max() < errs[0] / 100


def test_vmap_grad_and_model_defaults():
    model = _model()
    F = transition(model, integrator=None, substeps=None)  # model.integrator = euler
    X = np.stack([x0, 2 * x0, -x0])
    out = jax.vmap(lambda x: F(x, u0, p0, 0.1))(X)
    assert out.shape == (3, 2)
    g = jax.grad(lambda p: F(x0, u0, p, 0.1)[0])(p0)
    np.testing.assert_allclose(g, [0.1 * x0[0]], atol=1e-15)


@pytest.mark.parametrize("kw", [dict(integrator="heun"), dict(substeps=0), dict(substeps=1.5)])
def test_bad_options(kw):
    with pytest.raises(VsidgenError):
        transition_fn(lambda x, u, p: x, **kw)
