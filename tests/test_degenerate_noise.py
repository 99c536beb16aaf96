"""Rank-deficient process noise (one gust driving two equations) against an exact Kalman reference.

Linear model with two states, a damped oscillator driven by u: a single white-noise gust w
enters both equations through the loadings l = (l1, l2), so Q = T l lᵀ is singular — the
structure of a vertical gust acting on the α and q equations through Z_α/V and M_α/V. In
the lower-triangular factor of the spec (``structure: full``) that is G_22 = 0:
``degenerate: [x2]``. The discrete model (Euler) has an exact likelihood from a Kalman
filter, which handles a singular Q without approximation, and exact smoothed means from the
Rauch–Tung–Striebel smoother; both are written here in numpy and share nothing with
vsidgen. With a flat prior on x_0 the filter starts from N(0, P0 I) and
log p(y) ≈ log p_KF(y) + (n/2) log(2π P0).
"""

from __future__ import annotations

import math
import types

import jax.numpy as jnp
import numpy as np
import pytest
from kalman_ref import kalman_loglik_jax, kalman_rts, maximum_likelihood   # tests/ is on sys.path

from vsidgen.errors import SpecError
from vsidgen.estimator import FitOptions, fit, smooth
from vsidgen.metadata import MeasurementNoiseSpec, Parameter, ProcessNoiseSpec, Variable
from vsidgen.model import Model, load_model

pytestmark = pytest.mark.xdist_group("test_degenerate_noise")

T = 0.05
THETA_TRUE = np.array([-0.5, -2.0, -0.8, 1.5])  # a11, a21, a22, b2
L_TRUE = np.array([0.1, 0.3])                     # gust loadings of the two equations
R_STD = np.array([0.02, 0.04])
P0 = 1e6


def _A(p):
    return np.array([[p[0], 1.0], [p[1], p[2]]])


def drift(x, u, p):
    return jnp.stack([p[0] * x[0] + x[1], p[1] * x[0] + p[2] * x[1] + p[3] * u[0]])


def output(x, u, p):
    return x


def model(*, estimate=True, degenerate=("x2",)):
    return Model(
        name="gust2", drift=drift, output=output,
        states=(Variable("x1"), Variable("x2")), inputs=(Variable("u"),),
        outputs=(Variable("y1"), Variable("y2")),
        parameters=tuple(Parameter(n) for n in ("a11", "a21", "a22", "b2")),
        process_noise=ProcessNoiseSpec(states=("x1", "x2"), structure="full", estimate=estimate,
                                       degenerate=degenerate),
        measurement_noise=tuple(MeasurementNoiseSpec(o, estimate=estimate, std=float(s), floor=0.0)
                                for o, s in zip(("y1", "y2"), R_STD)))


def record(N, seed, *, independent=0.0):
    """``independent``: std of a second, independent noise source on x2 (0: one gust only)."""
    rng = np.random.default_rng(seed)
    k = np.arange(N)
    u = (np.sign(np.sin(k * T * 1.3)) + 0.3 * np.sin(k * T * 4.1))[:, None]
    x = np.array([0.3, -0.2])
    X = np.empty((N, 2))
    for i in range(N):
        X[i] = x
        x = x + T * (_A(THETA_TRUE) @ x + np.array([0.0, THETA_TRUE[3]]) * u[i, 0]) \
            + math.sqrt(T) * (L_TRUE * rng.normal() + np.array([0.0, independent]) * rng.normal())
    y = X + R_STD * rng.normal(size=(N, 2))
    return types.SimpleNamespace(name="r", path=None, t=k * T, dt=T, u=u, y=y,
                                 input_names=("u",), output_names=("y1", "y2"))


def kalman(theta, lv, r, rec, *, smooth=False):
    """Exact log-likelihood (flat prior on x_0) with the rank-one Q = T l lᵀ; RTS means."""
    lv = np.asarray(lv, float)
    return kalman_rts(np.eye(2) + T * _A(theta), T * np.array([[0.0], [theta[3]]]), np.eye(2),
                      T * np.outer(lv, lv), np.diag(np.asarray(r, float) ** 2), rec.u, rec.y,
                      P0=P0, smooth=smooth)


@pytest.fixture(scope="module")
def rec():
    return record(400, seed=5)


@pytest.fixture(scope="module")
def fitted(rec):
    return fit(model(), [rec], options=FitOptions(noise_start="data"))


def test_smoothing_with_a_rank_deficient_given_noise_matches_the_exact_smoother(rec):
    """A given G whose Q is singular (one gust): its zero Cholesky pivot is taken in the limit."""
    G = np.array([[L_TRUE[0], 0.0], [L_TRUE[1], 0.0]])
    res = smooth(model(estimate=False, degenerate=()), [rec], THETA_TRUE,
                 {"G": G, "R": np.diag(R_STD ** 2)})
    assert res.converged, res.status
    lim = res.deterministic_limit
    assert lim is not None and lim["reached"] and lim["states"] == ["x2"], lim
    ll, ms, Ps = kalman(THETA_TRUE, L_TRUE, R_STD, rec, smooth=True)
    gap = ll - res.elbo
    assert gap > -1e-3, gap                 # a lower bound on the exact likelihood
    assert gap < 1.0, gap                   # and tight: only the stationary covariance at the ends is slack
    mid = slice(40, -40)
    err = np.abs(res.smoothers[0].mu[mid] - ms[mid]) / np.sqrt(np.diagonal(Ps[mid], axis1=1, axis2=2))
    assert err.max() < 0.05, err.max()


def test_fit_with_a_degenerate_state_matches_the_exact_rank_one_mle(fitted, rec):
    res = fitted
    assert res.converged, res.status
    lim = res.deterministic_limit
    assert lim is not None and lim["reached"] and lim["states"] == ["x2"], lim
    assert res.deterministic_states == ()
    assert res.G[1, 1] == 0.0 and res.G[1, 0] != 0.0          # reported with the exact zero pivot
    Q = res.G @ res.G.T
    assert abs(np.linalg.det(Q)) < 1e-12 * np.prod(np.diag(Q))
    se = res.std_errors
    assert np.all(np.isfinite(se)) and np.all(se > 0)
    assert np.all(np.abs(res.theta - THETA_TRUE) < 3 * se), (res.theta, se)

    def loglik(v):    # the rank-one model in jax.numpy, for exact gradients
        A = jnp.array([[v[0], 1.0], [v[1], v[2]]])
        return kalman_loglik_jax(jnp.eye(2) + T * A, T * jnp.array([[0.0], [v[3]]]), jnp.eye(2),
                                 T * jnp.outer(v[4:6], v[4:6]), jnp.diag(jnp.exp(v[6:8]) ** 2),
                                 rec.u, rec.y, P0=P0)

    v0 = np.concatenate([THETA_TRUE, L_TRUE, np.log(R_STD)])
    assert abs(float(loglik(v0)) - kalman(v0[:4], L_TRUE, R_STD, rec)) < 1e-6
    opt = maximum_likelihood(loglik, v0)
    assert np.all(np.abs(res.theta - opt.x[:4]) < 0.5 * se), (res.theta, opt.x[:4], se)
    lv = np.sign(opt.x[4]) * opt.x[4:6]
    assert np.allclose(res.G[:, 0], lv, rtol=0.1), (res.G[:, 0], lv)   # the gust's loadings
    assert res.elbo <= -opt.fun + 1e-3          # the ELBO cannot exceed the maximised likelihood
    assert -opt.fun - res.elbo < 2.0, -opt.fun - res.elbo
    assert "degenerate_noise_rejected" not in [w["code"] for w in res.warnings]


def test_a_degenerate_constraint_the_data_contradict_is_warned():
    """x2 with an independent noise source as strong as the gust's: `degenerate: [x2]` is
    rejected by the likelihood ratio of the relaxed stage against the limit."""
    res = fit(model(), [record(400, seed=6, independent=0.3)], options=FitOptions(noise_start="data"))
    (w,) = [w for w in res.warnings if w["code"] == "degenerate_noise_rejected"]
    assert w["states"] == ["x2"] and w["statistic"] > w["threshold"], w


def test_the_degenerate_model_beats_independent_noise_by_the_likelihood_ratio(fitted, rec):
    """The same record under diagonal (independent) noise: the exact rank-one likelihood is higher,
    and the variational fits rank the two models in the same order."""
    m = Model(name="gust2d", drift=drift, output=output,
              states=(Variable("x1"), Variable("x2")), inputs=(Variable("u"),),
              outputs=(Variable("y1"), Variable("y2")),
              parameters=tuple(Parameter(n) for n in ("a11", "a21", "a22", "b2")),
              process_noise=ProcessNoiseSpec(states=("x1", "x2")),
              measurement_noise=tuple(MeasurementNoiseSpec(o, floor=0.0) for o in ("y1", "y2")))
    res_d = fit(m, [rec], options=FitOptions(noise_start="data"))
    assert res_d.converged, res_d.status
    assert fitted.elbo > res_d.elbo + 3.0, (fitted.elbo, res_d.elbo)


SPEC = """\
name: gust
states:
  alpha: {unit: rad}
  q: {unit: rad/s}
inputs:
  de: {unit: rad}
outputs:
  alpha: {unit: rad}
  q: {unit: rad/s}
parameters:
  ZA: {}
  MA: {}
  MQ: {}
  MDE: {}
drift:
  alpha: ZA*alpha + q
  q: MA*alpha + MQ*q + MDE*de
observations:
  alpha: alpha
  q: q
data:
  time: t
  inputs: {de: de}
  outputs: {alpha: alpha, q: q}
noise:
  process:
    states: [alpha, q]
{noise}
"""


@pytest.mark.parametrize("noise,needle", [
    ("    structure: diagonal\n    degenerate: [q]", "needs `structure: full`"),
    ("    structure: full\n    degenerate: [alpha]", "first state with process noise"),
    ("    structure: full\n    degenerate: [qq]", "not a state with process noise"),
    ("    structure: full\n    degenerate: q", "must be a list"),
])
def test_degenerate_spec_errors_name_the_line(tmp_path, noise, needle):
    p = tmp_path / "gust.yaml"
    p.write_text(SPEC.replace("{noise}", noise))
    with pytest.raises(SpecError) as ei:
        load_model(p, generated_dir=tmp_path / "gen")
    msg = str(ei.value)
    text = p.read_text().splitlines()
    line = next(i for i, t in enumerate(text, 1) if "degenerate" in t)   # the offending line
    assert needle in msg and f"gust.yaml:{line}:" in msg, msg


def test_degenerate_spec_loads(tmp_path):
    p = tmp_path / "gust.yaml"
    p.write_text(SPEC.replace("{noise}", "    structure: full\n    degenerate: [q]"))
    m = load_model(p, generated_dir=tmp_path / "gen")
    assert m.process_noise.degenerate == ("q",) and m.process_noise.structure == "full"


def test_cli_fit_of_a_degenerate_spec_reports_it(tmp_path, capsys, rec):
    """End to end through the command line: the spec's `degenerate: [q]`, the line that says so,
    and results.json's G with the exact zero pivot (the record of the tests above, where the
    spec's model is the simulated one: ZA = a11, MA = a21, MQ = a22, MDE = b2)."""
    import json

    from vsidgen.cli import main

    (tmp_path / "specs").mkdir()
    p = tmp_path / "specs" / "gust.yaml"   # generated code goes to tmp_path/generated
    p.write_text(SPEC.replace("{noise}", "    structure: full\n    degenerate: [q]"))
    csv = tmp_path / "r.csv"
    np.savetxt(csv, np.column_stack([rec.t, rec.u[:, 0], rec.y]), delimiter=",",
               header="t,de,alpha,q", comments="")
    out = tmp_path / "out"
    rc = main(["fit", str(p), str(csv), "--out", str(out), "--quiet"])
    text = capsys.readouterr().out
    assert rc == 0, text
    assert "degenerate process noise: q" in text and "exact limit" in text, text
    G = np.asarray(json.loads((out / "results.json").read_text())["noise"]["G"])
    assert G[1, 1] == 0.0 and G[1, 0] != 0.0
    assert np.allclose(G[:, 0], L_TRUE, rtol=0.15), G
    assert (tmp_path / "generated" / "gust.py").exists()
