"""Discrete-time transition of the continuous model.

The model is the Itô SDE ``dx = f(x, u, θ) dt + G dW`` with the input held
constant over one sample interval (zero-order hold, ``u(t) = u_k`` for
``t_k <= t < t_{k+1}``). The estimator, the simulator and the evaluation all
use the same *mean* transition

.. math::

    x_{k+1} = F(x_k, u_k, θ, T) + \\sqrt{T}\\, G\\, w_k,\\qquad w_k \\sim N(0, I),

where ``F`` is one of

* ``"euler"`` (Euler–Maruyama, the paper's choice) with ``m = substeps``
  sub-steps of ``h = T/m``:

  .. math:: z_0 = x_k,\\quad z_{j+1} = z_j + h\\, f(z_j, u_k, θ),\\quad F = z_m

  (``m = 1`` gives ``F = x + T f(x, u, θ)``).
* ``"rk4"``: the classic fourth-order Runge–Kutta step over ``h = T/m`` (again
  ``m`` sub-steps, ``u`` held at ``u_k``):

  .. math::

      k_1 = f(z),\\ k_2 = f(z + \\tfrac h2 k_1),\\ k_3 = f(z + \\tfrac h2 k_2),\\
      k_4 = f(z + h k_3),\\quad z^+ = z + \\tfrac h6 (k_1 + 2k_2 + 2k_3 + k_4).

  Local error O(h^5) per step for smooth ``f``.

The noise enters as a single increment ``√T G w_k`` per sample in both cases
(the Euler–Maruyama diffusion term); the integrator only changes the mean.
The returned function is pure ``jax.numpy``: it can be jitted, vmapped and
differentiated.
"""

from __future__ import annotations

from collections.abc import Callable

import jax.numpy as jnp

from . import precision  # noqa: F401  (float64, set once)
from .errors import VsidgenError

INTEGRATORS = ("euler", "rk4")


def _check(integrator: str, substeps: int) -> tuple[str, int]:
    if integrator not in INTEGRATORS:
        raise VsidgenError(
            f"unknown integrator '{integrator}'\n  hint: use one of {', '.join(INTEGRATORS)}")
    try:
        m = int(substeps)
    except (TypeError, ValueError):
        m = 0
    if m < 1 or m != substeps:
        raise VsidgenError(f"substeps must be an integer >= 1, got {substeps!r}")
    return integrator, m


def transition_fn(drift: Callable, *, integrator: str = "euler", substeps: int = 1) -> Callable:
    """Build ``F(x, u, p, dt)`` from a bare drift function ``f(x, u, p)``.

    See the module docstring for the formulas. ``dt`` may be a Python float or
    a traced scalar.
    """
    integrator, m = _check(integrator, substeps)

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

    F.__doc__ = (f"Mean transition F(x, u, p, dt): {integrator}, {m} substep(s), "
                 "u held at u_k (see vsidgen.dynamics).")
    return F


def settings(model, *, integrator: str | None = None, substeps: int | None = None) -> tuple[str, int]:
    """Checked ``(integrator, substeps)`` for ``model``: an explicit value wins, ``None``
    (or an empty value) takes the model's own (``model.integrator``, ``model.substeps``;
    ``"euler"`` and ``1`` for a bare model that has none).
    """
    integrator = integrator or getattr(model, "integrator", None) or "euler"
    substeps = substeps or getattr(model, "substeps", None) or 1
    return _check(integrator, substeps)


def transition(model, *, integrator: str | None = "euler", substeps: int | None = 1) -> Callable:
    """Discrete mean transition ``F(x, u, p, dt)`` of ``model``.

    Args:
        model: a :class:`vsidgen.model.Model` (only ``model.drift`` is used).
        integrator: ``"euler"`` (Euler–Maruyama mean ``x + dt f``) or ``"rk4"``;
            ``None`` takes ``model.integrator``.
        substeps: number ``m >= 1`` of equal sub-steps ``dt/m`` per sample
            (``None`` takes ``model.substeps``).

    Returns:
        ``F(x, u, p, dt) -> (nx,)`` jnp array; pure, jit/vmap/grad friendly.
    """
    integrator, substeps = settings(model, integrator=integrator, substeps=substeps)
    return transition_fn(model.drift, integrator=integrator, substeps=substeps)


__all__ = ["INTEGRATORS", "settings", "transition", "transition_fn"]
