"""A saddle whose directions of descent couple to the state means is left, not reported as
converged (estimator.fit._curvature_step, FitOptions.negative_curvature).

The model is a linear two-state system with a third, unmeasured state z (a first-order lag)
fed back into x2: ``ẋ2 = … + c1 z``, ``ż = −z + c2 x2``; the record is a numpy Euler
simulation with c1 = 2, c2 = −1. Both couplings start at 0: there z reaches no output and is
driven by nothing, the ELBO is symmetric under (z, c1, c2) → (−z, −c1, −c2) and its gradient
in c1, c2 vanishes — a saddle at which the relative-gradient test is met. The references
are independent of the structured elimination: the dense Hessian of the flat −ELBO by
``jax.hessian`` and its Schur complement over the border.
"""

from __future__ import annotations

import importlib
import math
import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

from vsidgen.estimator import FitOptions, Problem, fit
from vsidgen.estimator.problem import SCORE_DAMPING
from vsidgen.metadata import MeasurementNoiseSpec, Parameter, ProcessNoiseSpec, Variable
from vsidgen.model import Model

jax.config.update("jax_enable_x64", True)
F = importlib.import_module("vsidgen.estimator.fit")

T = 0.05
A = np.array([[-0.5, 1.0], [-2.0, -0.8]])
B2, C1, C2 = 1.5, 2.0, -1.0
G = np.array([0.1, 0.2, 0.3])
R = np.array([0.05, 0.08])
C_OUT = np.array([[1.0, 0.0], [0.5, 1.0]])


def _record(N, seed=3):
    rng = np.random.default_rng(seed)
    k = np.arange(N)
    u = (np.sign(np.sin(k * T * 1.3)) + 0.3 * np.sin(k * T * 4.1))[:, None]
    x = np.array([0.3, -0.2, 0.0])
    X = np.empty((N, 3))
    for i in range(N):
        X[i] = x
        dx = np.array([A[0] @ x[:2], A[1] @ x[:2] + B2 * u[i, 0] + C1 * x[2], -x[2] + C2 * x[1]])
        x = x + T * dx + math.sqrt(T) * G * rng.normal(size=3)
    y = X[:, :2] @ C_OUT.T + R * rng.normal(size=(N, 2))
    return types.SimpleNamespace(name="r", path=None, t=k * T, dt=T, u=u, y=y,
                                 input_names=("u",), output_names=("y1", "y2"))


def _drift(x, u, p):
    return jnp.array([p[0] * x[0] + x[1],
                      p[1] * x[0] + p[2] * x[1] + p[3] * u[0] + p[4] * x[2],
                      -x[2] + p[5] * x[1]])


def _output(x, u, p):
    return jnp.asarray(C_OUT) @ x[:2]


def _model(estimate_process_noise=False):
    return Model(name="lin_lag", drift=_drift, output=_output,
                 states=(Variable("x1"), Variable("x2"), Variable("z")), inputs=(Variable("u"),),
                 outputs=(Variable("y1"), Variable("y2")),
                 parameters=tuple(Parameter(n) for n in ("a11", "a21", "a22", "b2", "c1", "c2")),
                 process_noise=ProcessNoiseSpec(states=("x1", "x2", "z"),
                                                estimate=estimate_process_noise,
                                                std={"x1": G[0], "x2": G[1], "z": G[2]}),
                 measurement_noise=tuple(MeasurementNoiseSpec(o, std=float(s))
                                         for o, s in zip(("y1", "y2"), R)))


def _dense(P, m, s, recs):
    """(H, d, e) at the measured iterate: the dense Hessian of −ELBO and the structured
    direction with its eigenvalue."""
    e, ds, dmu, dr = F._curvature_direction(P, m)
    d = P.layout.pack(ds, list(zip(dmu, dr)))
    H = np.asarray(jax.jit(jax.hessian(P.flat_value))(jnp.asarray(P.layout.pack(s, recs))))
    return H, d, e


def _start(model, N):
    opts = FitOptions(noise_start="data")
    P = Problem(model, [_record(N)], opts)
    s, recs = P.initial(opts, "data")
    return P, s, recs, F._lm_measure(P, s, recs)


def test_the_direction_is_the_most_negative_curvature_of_the_dense_hessian():
    """At the saddle z's initial value is free (the state-mean block A is singular, the
    undamped elimination fails); the direction is the eigenvector of the most negative
    eigenvalue e of the damped Schur complement S_λ = H_bb − H_bμ (A + λD)⁻¹ H_μb built from
    the dense Hessian, and its curvature is dᵀHd = e − λ Δμᵀ D Δμ < 0 exactly."""
    P, s, recs, m = _start(_model(), 40)
    assert not math.isfinite(m.decrement)                      # indefinite at the start
    assert np.all(m.grad.shared[4:6] == 0.0)                   # the saddle's zero gradient
    assert P.reduced_system(m.blks) is None                    # A singular
    H, d, e = _dense(P, m, s, recs)
    nmu = sum(P.lengths) * P.layout.nx
    mu, b = np.arange(nmu), np.arange(nmu, H.shape[0])
    Dmu = np.maximum(np.abs(np.diag(H)[mu]), 1e-300)
    Al = H[np.ix_(mu, mu)] + SCORE_DAMPING * np.diag(Dmu)
    S = H[np.ix_(b, b)] - H[np.ix_(b, mu)] @ np.linalg.solve(Al, H[np.ix_(mu, b)])
    _, dglob = F._marquardt_diagonal(P, m)
    w = scipy.linalg.eigh(S, np.diag(dglob), eigvals_only=True)
    assert e < 0
    # λ = 1e-10 makes the elimination ill-conditioned (≈ 1e10): agreement to 1e-5
    assert e == pytest.approx(w[0], rel=1e-5)
    dmu = d[:nmu]
    assert d @ H @ d == pytest.approx(e - SCORE_DAMPING * dmu @ (Dmu * dmu), rel=1e-5)
    assert d @ H @ d < 0


def test_a_saddle_that_couples_to_the_state_means_is_left():
    rec = _record(400)
    stuck = fit(_model(), [rec], options=FitOptions(noise_start="data", max_iter=60,
                                                    negative_curvature=False))
    # without the step: "converged" by the relative gradient at the saddle, z unused
    assert stuck.converged and abs(float(stuck.theta[4] * stuck.theta[5])) < 1e-6
    res = fit(_model(), [rec], options=FitOptions(noise_start="data", max_iter=60))
    assert any(h.get("curvature_step") for h in res.history)
    assert float(res.theta[4] * res.theta[5]) < -0.5           # the feedback found (truth −2)
    assert res.elbo > stuck.elbo + 10.0
