"""Discrete-time transition of the continuous model.

The model is the Itô SDE ``dx = f(x, u, θ) dt + G dW``. Between two samples the
input is reconstructed from the recorded samples by one of two holds:

* ``"zoh"`` (zero-order hold, the default): ``u(t_k + sT) = u_k`` for ``0 <= s < 1``;
* ``"foh"`` (first-order hold): ``u(t_k + sT) = u_k + s (u_{k+1} − u_k)``, the
  linear interpolation between the samples (what a continuously moving control
  surface, recorded at discrete times, looks like to first order).

The estimator, the simulator and the evaluation all use the same *mean* transition

.. math::

    x_{k+1} = F(x_k, v_k, θ, T) + \\sqrt{T}\\, G\\, w_k,\\qquad w_k \\sim N(0, I),

with the *step input* ``v_k = u_k`` (zoh) or ``v_k = (u_k, u_{k+1})`` concatenated
(foh, length ``2 nu``); :meth:`Transition.step_inputs` builds the ``v_k`` of a record.
``F`` integrates ``ż = f(z, u(t), θ)`` over one sample in ``m = substeps`` sub-steps of
``h = T/m``; sub-step ``j`` starts at the fraction ``s_j = j/m`` of the interval, and
``u(s)`` is the hold above:

* ``"euler"`` (Euler–Maruyama, the paper's choice):

  .. math:: z_0 = x_k,\\quad z_{j+1} = z_j + h\\, f(z_j, u(s_j), θ),\\quad F = z_m

  (``m = 1`` with zoh gives ``F = x + T f(x, u_k, θ)``).
* ``"rk4"``: the classic fourth-order Runge–Kutta step, each stage at its own time:

  .. math::

      k_1 = f(z, u(s_j)),\\ k_2 = f(z + \\tfrac h2 k_1, u(s_j + \\tfrac{1}{2m})),\\
      k_3 = f(z + \\tfrac h2 k_2, u(s_j + \\tfrac{1}{2m})),\\ k_4 = f(z + h k_3, u(s_{j+1})),

      z^+ = z + \\tfrac h6 (k_1 + 2k_2 + 2k_3 + k_4).

  Local error O(h^5) per step for smooth ``f`` and a smooth input; with foh the input is
  piecewise linear, so RK4 integrates the interpolated input exactly to that order
  (with zoh every stage sees ``u_k``).

The noise enters as a single increment ``√T G w_k`` per sample in all cases (the
Euler–Maruyama diffusion term); integrator and hold only change the mean. The
transition is pure ``jax.numpy``: it can be jitted, vmapped and differentiated.

**Jacobian of the discrete map** (:meth:`Transition.jacobian`): ``(∂F/∂x, ∂F/∂p)``
composed from the continuous Jacobians ``f_x = ∂f/∂x``, ``f_p = ∂f/∂p`` (the generated
``drift_jac_x``/``drift_jac_p`` of a model from a spec) by the chain rule through the
same steps. With the tangent ``Z = [∂z/∂x, ∂z/∂p]`` (n × (n + n_p), ``Z_0 = [I, 0]``)
and ``D(z, u, Y) = f_x(z, u) Y + [0, f_p(z, u)]``, the derivative of ``f`` along a
tangent ``Y`` of its argument:

* Euler: ``Z_{j+1} = Z_j + h D(z_j, u(s_j), Z_j)``;
* RK4: ``K_1 = D(z, u_1, Z)``, ``K_2 = D(z + ½h k_1, u_m, Z + ½h K_1)``,
  ``K_3 = D(z + ½h k_2, u_m, Z + ½h K_2)``, ``K_4 = D(z + h k_3, u_4, Z + h K_3)``,
  ``Z^+ = Z + (h/6)(K_1 + 2K_2 + 2K_3 + K_4)``,

with the stage points and inputs of ``F`` itself, so the result is the exact derivative
of ``F`` (tests compare it with ``jax.jacfwd`` of ``F``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import jax.numpy as jnp
import numpy as np

from .. import precision  # noqa: F401  (float64, set once)
from ..errors import VsidgenError

INTEGRATORS = ("euler", "rk4")
#: input reconstruction between samples: zero-order hold, first-order hold (linear)
INPUT_HOLDS = ("zoh", "foh")


def check_settings(integrator: str, substeps: int, inputs: str = "zoh") -> tuple[str, int, str]:
    """(integrator, sub-steps, input hold) checked (VsidgenError with a hint otherwise)."""
    return _check(integrator, substeps, inputs)


def _check(integrator: str, substeps: int, inputs: str = "zoh") -> tuple[str, int, str]:
    if integrator not in INTEGRATORS:
        raise VsidgenError(
            f"unknown integrator '{integrator}'\n  hint: use one of {', '.join(INTEGRATORS)}")
    try:
        m = int(substeps)
    except (TypeError, ValueError):
        m = 0
    from ..limits import MAX_SUBSTEPS

    if m < 1 or m != substeps or m > MAX_SUBSTEPS:
        raise VsidgenError(f"substeps must be an integer from 1 to {MAX_SUBSTEPS}, got "
                           f"{substeps!r}\n  hint: sub-steps are unrolled into the compiled "
                           "code; for accuracy use the rk4 integrator with a few sub-steps")
    if inputs not in INPUT_HOLDS:
        raise VsidgenError(f"unknown input hold '{inputs}'\n  hint: use one of {', '.join(INPUT_HOLDS)}")
    return integrator, m, inputs


@dataclasses.dataclass(frozen=True, eq=False)
class Transition:
    """Mean transition ``F(x, v, p, dt)`` (callable) with its numerical setting.

    ``v`` is the step input of :meth:`step_inputs` (``u_k`` for zoh, ``(u_k, u_{k+1})``
    for foh); ``dt`` may be a Python float or a traced scalar.
    """

    fn: Callable
    integrator: str
    substeps: int
    inputs: str
    #: ``(x, v, p, dt) -> (∂F/∂x (n, n), ∂F/∂p (n, np))`` (module docstring)
    jac: Callable | None = None

    def __call__(self, x, v, p, dt):
        return self.fn(x, v, p, dt)

    def jacobian(self, x, v, p, dt):
        """``(∂F/∂x, ∂F/∂p)`` at ``(x, v, p, dt)``, shapes (n, n) and (n, np)."""
        if self.jac is None:
            import jax
            return jax.jacfwd(self.fn, argnums=(0, 2))(x, v, p, dt)
        return self.jac(x, v, p, dt)

    @property
    def key(self) -> tuple:
        """Hashable description of the numerical setting (caches of compiled code)."""
        return (self.integrator, self.substeps, self.inputs)

    def step_width(self, nu: int) -> int:
        """Length of one step input ``v_k`` for ``nu`` inputs."""
        return 2 * nu if self.inputs == "foh" else nu

    def step_inputs(self, u):
        """Step inputs ``v_k``, k = 0..N-2, of the (N, nu) input samples ``u`` (numpy or jax).

        zoh: ``u[:-1]``; foh: ``[u[:-1], u[1:]]`` side by side.
        """
        if self.inputs == "foh":
            xp = jnp if not isinstance(u, np.ndarray) else np
            return xp.concatenate([u[:-1], u[1:]], axis=1)
        return u[:-1]

    def scan_inputs(self, u):
        """One step input per sample, k = 0..N-1, for scans that also evaluate the output at
        ``u_k``: :meth:`step_inputs` with the last sample's own hold appended (its transition
        leaves the record and is never used)."""
        v = self.step_inputs(u)
        xp = jnp if not isinstance(u, np.ndarray) else np
        last = u[-1:] if self.inputs == "zoh" else xp.concatenate([u[-1:], u[-1:]], axis=1)
        return xp.concatenate([v, last], axis=0)


def _stage_inputs(v, inputs: str, m: int, j: int, rk4: bool):
    """Inputs of sub-step ``j``: ``(u(s_j),)`` (Euler) or ``(u(s_j), u(s_j + 1/(2m)), u(s_{j+1}))`` (RK4)."""
    if inputs == "zoh":
        return (v,) * (3 if rk4 else 1)
    nu = v.shape[-1] // 2
    u0, du = v[:nu], v[nu:] - v[:nu]
    if not rk4:
        return (u0 + (j / m) * du,)
    return u0 + (j / m) * du, u0 + (j / m + 0.5 / m) * du, u0 + ((j + 1) / m) * du


def transition_jacobian(drift: Callable, drift_jacobian: Callable, *, integrator: str = "euler",
                        substeps: int = 1, inputs: str = "zoh") -> Callable:
    """``J(x, v, p, dt) -> (∂F/∂x, ∂F/∂p)`` of the transition of :func:`transition_fn`, by the
    chain rule through its sub-steps from ``drift_jacobian(x, u, p) -> (f_x, f_u, f_p)``
    (formulas in the module docstring)."""
    integrator, m, inputs = _check(integrator, substeps, inputs)
    rk4 = integrator == "rk4"

    def J(x, v, p, dt):
        z = jnp.asarray(x)
        n = z.shape[0]
        Z = jnp.concatenate([jnp.eye(n, dtype=z.dtype), jnp.zeros((n, p.shape[0]), z.dtype)], axis=1)

        def D(zz, uu, Y):
            fx, _, fp = drift_jacobian(zz, uu, p)
            return fx @ Y + jnp.concatenate([jnp.zeros((n, n), fx.dtype), fp], axis=1)

        h = dt / m
        for j in range(m):
            if not rk4:
                (u1,) = _stage_inputs(v, inputs, m, j, False)
                Z = Z + h * D(z, u1, Z)
                z = z + h * drift(z, u1, p)
                continue
            u1, um, u4 = _stage_inputs(v, inputs, m, j, True)
            k1 = drift(z, u1, p)
            K1 = D(z, u1, Z)
            z2, Z2 = z + 0.5 * h * k1, Z + 0.5 * h * K1
            k2 = drift(z2, um, p)
            K2 = D(z2, um, Z2)
            z3, Z3 = z + 0.5 * h * k2, Z + 0.5 * h * K2
            k3 = drift(z3, um, p)
            K3 = D(z3, um, Z3)
            z4, Z4 = z + h * k3, Z + h * K3
            k4 = drift(z4, u4, p)
            K4 = D(z4, u4, Z4)
            z = z + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
            Z = Z + (h / 6.0) * (K1 + 2.0 * K2 + 2.0 * K3 + K4)
        return Z[:, :n], Z[:, n:]

    return J


def transition_fn(drift: Callable, *, integrator: str = "euler", substeps: int = 1,
                  inputs: str = "zoh", drift_jacobian: Callable | None = None) -> Transition:
    """Build the :class:`Transition` ``F(x, v, p, dt)`` from a bare drift ``f(x, u, p)``.

    ``drift_jacobian(x, u, p) -> (f_x, f_u, f_p)`` (e.g. :meth:`vsidgen.model.Model.drift_jacobian`)
    gives the transition its Jacobian by the chain rule (:func:`transition_jacobian`);
    without it :meth:`Transition.jacobian` differentiates ``F`` by forward-mode autodiff.
    See the module docstring for the formulas.
    """
    integrator, m, inputs = _check(integrator, substeps, inputs)

    if inputs == "zoh":
        if integrator == "euler":
            def one(z, u, p, h):
                return z + h * drift(z, u, p)
        else:
            def one(z, u, p, h):
                k1 = drift(z, u, p)
                k2 = drift(z + 0.5 * h * k1, u, p)
                k3 = drift(z + 0.5 * h * k2, u, p)
                k4 = drift(z + h * k3, u, p)
                return z + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)

        def F(x, u, p, dt):
            x = jnp.asarray(x)
            h = dt / m
            z = x
            # m is a small static integer: unroll (keeps the function simple to
            # differentiate and to vmap; no Python-side state).
            for _ in range(m):
                z = one(z, u, p, h)
            return z
    else:
        def F(x, v, p, dt):
            z = jnp.asarray(x)
            nu = v.shape[-1] // 2
            u0, du = v[:nu], v[nu:] - v[:nu]

            def u_at(s):  # s: fraction of the sample interval (static Python float)
                return u0 + s * du

            h = dt / m
            for j in range(m):
                s0 = j / m
                if integrator == "euler":
                    z = z + h * drift(z, u_at(s0), p)
                else:
                    um = u_at(s0 + 0.5 / m)
                    k1 = drift(z, u_at(s0), p)
                    k2 = drift(z + 0.5 * h * k1, um, p)
                    k3 = drift(z + 0.5 * h * k2, um, p)
                    k4 = drift(z + h * k3, u_at((j + 1) / m), p)
                    z = z + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
            return z

    F.__doc__ = (f"Mean transition F(x, v, p, dt): {integrator}, {m} substep(s), "
                 f"inputs {inputs} (see vsidgen.model.dynamics).")
    jac = None if drift_jacobian is None else transition_jacobian(
        drift, drift_jacobian, integrator=integrator, substeps=m, inputs=inputs)
    return Transition(F, integrator, m, inputs, jac)


def settings(model, *, integrator: str | None = None, substeps: int | None = None) -> tuple[str, int]:
    """Checked ``(integrator, substeps)`` for ``model``: an explicit value wins, ``None``
    (or an empty value) takes the model's own (``model.integrator``, ``model.substeps``;
    ``"euler"`` and ``1`` for a bare model that has none). The input hold: :func:`input_hold`.
    """
    integrator = integrator or getattr(model, "integrator", None) or "euler"
    substeps = substeps or getattr(model, "substeps", None) or 1
    integrator, substeps, _ = _check(integrator, substeps)
    return integrator, substeps


def input_hold(model, inputs: str | None = None) -> str:
    """Checked input hold for ``model``: ``inputs`` when given, else ``model.input_hold``
    (``"zoh"`` for a bare model that has none)."""
    inputs = inputs or getattr(model, "input_hold", None) or "zoh"
    return _check("euler", 1, inputs)[2]


def transition(model, *, integrator: str | None = "euler", substeps: int | None = 1,
               inputs: str | None = None) -> Transition:
    """Discrete mean transition ``F(x, v, p, dt)`` of ``model``.

    Args:
        model: a :class:`vsidgen.model.Model` (``model.drift``; with generated
            ``model.jacobians`` they give :meth:`Transition.jacobian` by the chain rule,
            else it is autodiff of ``F``; its ``integrator``,
            ``substeps`` and ``input_hold`` fill the arguments given as ``None``).
        integrator: ``"euler"`` (Euler–Maruyama mean ``x + dt f``) or ``"rk4"``.
        substeps: number ``m >= 1`` of equal sub-steps ``dt/m`` per sample.
        inputs: ``"zoh"`` or ``"foh"``, the input hold between samples
            (``None``: the model's, ``"zoh"`` for models without one).

    Returns:
        :class:`Transition`; pure, jit/vmap/grad friendly.
    """
    integrator, substeps = settings(model, integrator=integrator, substeps=substeps)
    return transition_fn(model.drift, integrator=integrator, substeps=substeps,
                         inputs=input_hold(model, inputs),
                         drift_jacobian=(model.drift_jacobian
                                         if getattr(model, "jacobians", None) is not None else None))


__all__ = ["INPUT_HOLDS", "INTEGRATORS", "Transition", "check_settings", "input_hold", "settings", "transition",
           "transition_fn", "transition_jacobian"]
