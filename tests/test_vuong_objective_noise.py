"""The one-step predictive likelihoods of a refit (Vuong's test of alternatives) use the noise
the refit's ELBO was computed with: a state the candidate adds is quasi-deterministic there
(a small fixed process noise), which the reported G sets to zero.

Reference: for a linear model the steady-state Kalman filter's Σ_k ℓ_k is (up to its first
samples' transient) the log-likelihood of the records, which the ELBO bounds from below; the
filter is checked against that bound, and against a filter written out here."""

from __future__ import annotations

import math

import numpy as np
import pytest

from vsidgen import load_model
from vsidgen.data import Record
from vsidgen.discrepancy.fitstate import evaluated
from vsidgen.discrepancy.search import Trial, trial_loglik
from vsidgen.estimator import FitOptions, fit
from vsidgen.evaluation import predictive_loglik

# a user's pitch model with an elevator actuator lag written as a state
SPEC = """\
name: pitch_lag
states:
  q: {unit: rad/s}
  de_act: {unit: rad}
inputs:
  de: {unit: rad}
outputs:
  q: {unit: rad/s}
parameters:
  Mq: {initial: 0, unit: 1/s}
  Mde: {initial: 0, unit: 1/s^2}
  tau: {initial: 0.2, unit: s, bounds: [0.01, 2]}
drift:
  q: Mq*q + Mde*de_act
  de_act: (de - de_act)/tau
observations:
  q: q
noise:
  process:
    states: [q]
data:
  time: t
  inputs: {de: de}
  outputs: {q: q}
"""


def _record() -> Record:
    """Simulated by hand: the actuator's position wanders about its command (actuator noise),
    which the fitted model can only explain through the lag state's process noise."""
    rng = np.random.default_rng(2)
    n, dt, tau = 400, 0.05, 0.15
    t = np.arange(n) * dt
    de = 0.05 * np.sign(np.sin(0.9 * t))
    q, a = 0.0, 0.0
    y = np.zeros(n)
    for k in range(n):
        y[k] = q + rng.normal(0.0, 0.002)
        for _ in range(10):                       # fine Euler sub-steps
            h = dt / 10
            q += h * (-1.5 * q - 8.0 * a) + math.sqrt(h) * 0.01 * rng.normal()
            a += h * (de[k] - a) / tau + math.sqrt(h) * 0.05 * rng.normal()
    return Record(name="r", path=None, t=t, dt=dt, u=de[:, None], y=y[:, None],
                  input_names=("de",), output_names=("q",), t_raw=t)


@pytest.fixture(scope="module")
def refit(tmp_path_factory):
    d = tmp_path_factory.mktemp("vuong_noise")
    spec = d / "pitch_lag.yaml"
    spec.write_text(SPEC)
    model = load_model(spec, generated_dir=d / "gen")
    rec = _record()
    # the lag state quasi-deterministic with a std of 30 % of the elevator's spread per √s
    res = fit(model, [rec], options=FitOptions(deterministic="quasi", deterministic_input_scale=0.3,
                                               noise_start="unit"))
    return evaluated(spec, model, (rec,), res, (), max_iter=200)


def test_the_objective_noise_is_kept_beside_the_reported_one(refit):
    i = refit.model.state_names.index("de_act")
    assert refit.fit.G[i, i] == 0.0                       # reported: no process noise
    spread = float(np.std(refit.records[0].u[:, 0]))
    assert refit.fit.G_objective[i, i] == pytest.approx(0.3 * spread, rel=1e-9)


def _kalman_loglik(model, rec, theta, mu0, G, R) -> float:
    """A time-varying Kalman filter of the (linear) model, written out here (exact
    discretisation of the Euler step the model uses: x_{k+1} = (I + T A) x_k + T B u_k)."""
    Mq, Mde, tau = (float(theta[model.parameter_names.index(n)]) for n in ("Mq", "Mde", "tau"))
    T = float(rec.dt)
    A = np.eye(2) + T * np.array([[Mq, Mde], [0.0, -1.0 / tau]])
    B = T * np.array([0.0, 1.0 / tau])
    H = np.array([[1.0, 0.0]])
    Q = T * G @ G.T
    x, P = np.asarray(mu0, float), np.eye(2) * 1e-4
    ll = 0.0
    for k in range(rec.u.shape[0]):
        S = H @ P @ H.T + R
        e = rec.y[k] - H @ x
        ll += -0.5 * float(e @ np.linalg.solve(S, e) + np.log(np.linalg.det(2 * np.pi * S)))
        K = P @ H.T @ np.linalg.inv(S)
        x, P = x + K @ e, P - K @ H @ P
        x, P = A @ x + B * rec.u[k, 0], A @ P @ A.T + Q
    return ll


def test_trial_likelihoods_use_the_objective_noise(refit):
    t = Trial(candidate=None, score=0.0, spec_path=refit.spec_path, state=refit, statistic=0.0,
              dof=1, p_value=1.0)
    (ll,) = trial_loglik(t)
    (ll_reported,) = [predictive_loglik(s) for s in refit.signals]
    elbo = refit.fit.elbo
    # the ELBO bounds the log-likelihood of the model it was computed for (a few nats of
    # the filter's start-up transient aside)
    assert ll.sum() > elbo - 5.0
    ref = _kalman_loglik(refit.model, refit.records[0], refit.fit.theta, refit.fit.smoothers[0].mu[0],
                         refit.fit.G_objective, refit.fit.R)
    assert ll.sum() == pytest.approx(ref, abs=5.0)
    # with the reported (zero) noise on the lag state the same θ predicts far worse: the
    # likelihood of another model, below the refit's own ELBO
    assert ll_reported.sum() < elbo - 20.0
