"""Transition functions against exact solutions of a linear ODE."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

from vsidgen.model.dynamics import transition, transition_fn
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


def _exact_ramp(x, u0, u1, dt):
    """Exact solution for an input ramping linearly from u0 to u1 over dt: the augmented state
    (x, u, u̇) with u̇ = (u1 − u0)/dt constant, propagated by one matrix exponential."""
    M = np.zeros((4, 4))
    M[:2, :2] = A
    M[:2, 2:3] = B
    M[2, 3] = 1.0
    E = scipy.linalg.expm(M * dt)
    z = E @ np.concatenate([x, u0, (u1 - u0) / dt])
    return z[:2]


u1 = np.array([-0.4])


def test_foh_rk4_fifth_order_local_error_against_exact_ramp():
    F = jax.jit(transition(_model(), integrator="rk4", inputs="foh"))
    rate = -11.0  # input rate (1/s), the same for every step length
    errs = [np.abs(np.asarray(F(x0, np.concatenate([u0, u0 + rate * dt]), p0, dt))
                   - _exact_ramp(x0, u0, u0 + rate * dt, dt)).max() for dt in (0.1, 0.05, 0.025)]
    assert errs[0] < 5e-5  # measured 1.7e-5
    r1, r2 = errs[0] / errs[1], errs[1] / errs[2]
    assert 25 < r1 < 40 and 25 < r2 < 40  # 2^5
    # the zero-order hold misses the ramp by O(dt^2): far worse than rk4's own error
    Fz = transition(_model(), integrator="rk4")
    ez = np.abs(np.asarray(Fz(x0, u0, p0, 0.1)) - _exact_ramp(x0, u0, u0 + rate * 0.1, 0.1)).max()
    assert ez > 100 * errs[0]


def test_foh_euler_substeps_converge_first_order_and_stage_times():
    dt = 0.2
    v = np.concatenate([u0, u1])
    ex = _exact_ramp(x0, u0, u1, dt)
    e1 = np.abs(np.asarray(transition(_model(), substeps=10, inputs="foh")(x0, v, p0, dt)) - ex).max()
    e2 = np.abs(np.asarray(transition(_model(), substeps=20, inputs="foh")(x0, v, p0, dt)) - ex).max()
    assert 1.7 < e1 / e2 < 2.3
    # two Euler sub-steps: the second one sees the input at mid-interval
    h = dt / 2
    z = x0 + h * (A @ x0 + B @ u0)
    z = z + h * (A @ z + B @ (0.5 * (u0 + u1)))
    np.testing.assert_allclose(transition(_model(), substeps=2, inputs="foh")(x0, v, p0, dt), z,
                               rtol=0, atol=1e-15)


def test_foh_with_constant_input_is_zoh_and_step_inputs():
    for integ, m in (("euler", 1), ("euler", 3), ("rk4", 2)):
        Ff = transition(_model(), integrator=integ, substeps=m, inputs="foh")
        Fz = transition(_model(), integrator=integ, substeps=m)
        np.testing.assert_allclose(Ff(x0, np.concatenate([u0, u0]), p0, 0.1), Fz(x0, u0, p0, 0.1),
                                   rtol=0, atol=1e-15)
    U = np.arange(8.0).reshape(4, 2)
    Ff = transition(_model(), inputs="foh")
    np.testing.assert_array_equal(Ff.step_inputs(U), np.hstack([U[:-1], U[1:]]))
    np.testing.assert_array_equal(transition(_model()).step_inputs(U), U[:-1])
    assert Ff.scan_inputs(U).shape == (4, 4) and Ff.step_width(2) == 4
    with pytest.raises(VsidgenError, match="input hold"):
        transition_fn(lambda x, u, p: x, inputs="cubic")


def test_zoh_is_the_previous_transition_bit_for_bit():
    """The default hold runs the previous code path: identical floating-point results."""
    model = _model()

    def old(x, u, p, dt, integrator, m):
        h = dt / m
        z = jnp.asarray(x)
        for _ in range(m):
            if integrator == "euler":
                z = z + h * model.drift(z, u, p)
            else:
                k1 = model.drift(z, u, p)
                k2 = model.drift(z + 0.5 * h * k1, u, p)
                k3 = model.drift(z + 0.5 * h * k2, u, p)
                k4 = model.drift(z + h * k3, u, p)
                z = z + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        return z

    for integ, m in (("euler", 1), ("euler", 3), ("rk4", 1), ("rk4", 2)):
        F = transition(model, integrator=integ, substeps=m)
        assert F.inputs == "zoh"
        np.testing.assert_array_equal(np.asarray(F(x0, u0, p0, 0.07)),
                                      np.asarray(old(x0, u0, p0, 0.07, integ, m)))
