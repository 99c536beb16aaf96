"""The initial value of a state that carries an input (an actuator lag, a Padé delay) has a
proper prior, N(u₀, std(u)²) (``FitOptions.input_state_prior``), not the flat prior of the
aircraft's states.

Found on a new user's ATTAS pitch model (degrees, no noise section): diagnose accepted an
"elevator lag" of 9.3e-5 s (2ΔELBO 38.9, validation ELBO 1212 → 1881). Under the flat
prior the lag state's initial value was a free impulse on the first step: it started at
−4478 deg (the elevator's first sample 2.3 deg), acting on the pitch rate through a
coupling of 10⁻³, and removed the first step's residual — an initial-value artefact, not a
lag. Here the record is simulated by hand (numpy, no vsidgen code) with a disturbance in
its first step.
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from vsidgen import FitOptions, fit, load_model, load_record, smooth
from vsidgen.discrepancy import propose
from vsidgen.discrepancy.base import model_info
from vsidgen.discrepancy.fitstate import diag_options
from vsidgen.discrepancy.refit import REFIT_DETERMINISTIC_STD, parameter_start, stage0_start
from vsidgen.estimator import Problem, WarmStart
from vsidgen.estimator.linalg import btd_to_dense
from vsidgen.estimator.problem import initial_prior_term, input_state_prior_scales

DT = 0.05
SPEC = """\
name: sp_prior_user
states:
  alpha: {unit: rad}
  q: {unit: rad/s}
inputs:
  de: {unit: rad}
outputs:
  alpha: {unit: rad}
  q: {unit: rad/s}
parameters:
  Za: {unit: 1/s}
  Zde: {unit: 1/s}
  Ma: {unit: 1/s^2}
  Mq: {unit: 1/s}
  Mde: {unit: 1/s^2}
drift:
  alpha: Za*alpha + q + Zde*de
  q: Ma*alpha + Mq*q + Mde*de
observations:
  alpha: alpha
  q: q
data:
  time: t
  inputs: {de: de}
  outputs: {alpha: alpha, q: q}
"""


def _simulate(path, n=240, kick=0.25, seed=3):
    """Short period by RK4 at 1/20 of the sample period, inputs interpolated linearly, small
    process and measurement noise, and a pitch-rate disturbance of ``kick`` rad/s over the
    first sample (a record that starts in a gust)."""
    rng = np.random.default_rng(seed)
    Za, Zde, Ma, Mq, Mde = -1.2, -0.15, -8.0, -2.0, -12.0
    t = np.arange(n) * DT
    de = 0.03 * np.sin(2 * np.pi * 0.4 * t) * (t < 6) - 0.02 * ((t > 7) & (t < 8))
    x = np.array([0.01, 0.0])
    sub = 20
    h = DT / sub
    ys = []
    for k in range(n):
        ys.append(x.copy())
        if k == n - 1:
            break
        for j in range(sub):
            def f(xx, s):
                u = de[k] + (de[k + 1] - de[k]) * s
                return np.array([Za * xx[0] + xx[1] + Zde * u, Ma * xx[0] + Mq * xx[1] + Mde * u])
            s0 = j / sub
            k1 = f(x, s0)
            k2 = f(x + h / 2 * k1, s0 + 0.5 / sub)
            k3 = f(x + h / 2 * k2, s0 + 0.5 / sub)
            k4 = f(x + h * k3, s0 + 1.0 / sub)
            x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        x = x + np.sqrt(DT) * np.array([0.002, 0.01]) * rng.normal(size=2)
        if k == 0:
            x[1] += kick
    y = np.asarray(ys) + np.array([2e-4, 5e-4]) * rng.normal(size=(n, 2))
    with open(path, "w") as fh:
        fh.write("t,de,alpha,q\n")
        for k in range(n):
            fh.write(f"{t[k]:.4f},{de[k]:.8f},{y[k, 0]:.8f},{y[k, 1]:.8f}\n")


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("prior")
    base = tmp / "base.yaml"
    base.write_text(SPEC)
    csv = tmp / "rec.csv"
    _simulate(csv)
    info = model_info(base, dt=DT)
    (c,) = [c for c in propose(info) if c.effect == "actuator_lag"]
    path = tmp / "lag.yaml"
    path.write_text(c.spec_yaml(base, name="sp_prior_lag", candidate_path=path, info=info))
    mb = load_model(base, generated_dir=tmp / "gen")
    m2 = load_model(path, generated_dir=tmp / "gen")
    return dict(c=c, mb=mb, m2=m2, rb=load_record(mb, csv), r2=load_record(m2, csv))


def test_prior_scale_and_mean_are_the_carried_input_s(case):
    m2, r2 = case["m2"], case["r2"]
    sc = input_state_prior_scales(m2, [r2])
    j = m2.state_names.index(case["c"].states[0].name)
    assert list(sc) == [j]                       # only the lag state carries an input
    u = np.asarray(r2.u, float)[:, 0]
    assert sc[j][0] == pytest.approx(float(np.std(u)))
    assert sc[j][1] == [pytest.approx(u[0])]
    assert input_state_prior_scales(m2, [r2], "none") == {}
    with pytest.raises(Exception, match="does not carry an input"):
        input_state_prior_scales(m2, [r2], ("q",))


@pytest.mark.slow
def test_structured_derivatives_include_the_prior(case):
    """Value, gradient and Hessian of the structured assembly with the prior equal those of
    jax on the flat objective (an independent path), and the prior adds exactly
    −E_q log N(x₀; u₀, std²) to the value."""
    m2, r2 = case["m2"], case["r2"]
    opts = FitOptions(noise_start="data", deterministic="quasi", deterministic_std=1e-3,
                      deterministic_input_scale=0.07, bucket=False)
    P = Problem(m2, [r2], opts)
    P0 = Problem(m2, [r2], FitOptions(noise_start="data", deterministic="quasi", deterministic_std=1e-3,
                                      deterministic_input_scale=0.07, bucket=False,
                                      input_state_prior="none"))
    s, recs = P.initial(opts, "data")
    rng = np.random.default_rng(1)
    s = s + 0.1 * rng.normal(size=s.shape)
    recs = [(m + 0.05 * rng.normal(size=m.shape), r + 0.2 * rng.normal(size=r.shape)) for m, r in recs]
    j = m2.state_names.index(case["c"].states[0].name)
    recs[0][0][0, j] += 0.3                      # far from u₀: the mean term counts
    # the prior's value, from its definition
    sd, (mean,) = input_state_prior_scales(m2, [r2])[j]
    Sm = np.asarray(P.obj.cov_factors(jnp.asarray(recs[0][1]))[2])
    var = float(Sm[j] @ Sm[j])
    want = 0.5 * math.log(2 * math.pi * sd ** 2) + 0.5 * ((recs[0][0][0, j] - mean) ** 2 + var) / sd ** 2
    assert P.value(s, recs) - P0.value(s, recs) == pytest.approx(want, rel=1e-10)
    v = jnp.asarray(P.layout.pack(s, recs))
    Hd = np.asarray(jax.jit(jax.hessian(P.flat_value))(v))
    gd = np.asarray(jax.jit(jax.grad(P.flat_value))(v))
    assert float(P.flat_value(v)) == pytest.approx(P.value(s, recs), rel=1e-12)
    (b,) = P.blocks(s, recs)
    gg, Hg = P.gather([b])
    sz = recs[0][0].size
    Hs = np.zeros_like(Hd)
    gs = np.zeros_like(gd)
    Hs[:sz, :sz] = btd_to_dense(b["D"], b["B"])
    Wd = np.asarray(b["W"]).reshape(sz, -1)
    Hs[:sz, sz + P.idx[0]] = Wd
    Hs[sz + P.idx[0], :sz] = Wd.T
    Hs[sz:, sz:] = Hg
    gs[:sz] = np.asarray(b["gmu"]).ravel()
    gs[sz:] = gg
    assert float(b["f"]) == pytest.approx(P.value(s, recs), rel=1e-12)
    np.testing.assert_allclose(Hs, Hd, rtol=1e-9, atol=1e-9 * np.abs(Hd).max())
    np.testing.assert_allclose(gs, gd, rtol=1e-9, atol=1e-9 * np.abs(gd).max())


@pytest.mark.slow
def test_a_fast_lag_at_its_nesting_point_gains_nothing_from_its_initial_value(case):
    """The candidate at its nesting point (smallest time constant), the current model's
    estimates and noise, only the assumed density fitted (diagnose's stage 0): with the
    prior its ELBO is the current model's plus the new state's initial-value term H₀ (the
    nested reference); under the flat prior the lag state's initial value absorbs the first
    step's disturbance as an impulse, ending many nats above that reference."""
    mb, m2, rb, r2, c = case["mb"], case["m2"], case["rb"], case["r2"], case["c"]
    base = fit(mb, [rb])
    assert base.converged
    z2, th2 = parameter_start(m2)
    th2 = np.asarray(th2, float).copy()
    names = list(m2.parameter_names)
    for n, v in zip(mb.parameter_names, np.asarray(base.theta, float)):
        th2[names.index(n)] = v                  # the current estimates (diagnose writes them)
    tau = c.parameters[0]
    th2[names.index(tau.name)] = tau.lower
    dec0, G1, R1, H0, _ = stage0_start(m2, [r2], base, mb, th2, REFIT_DETERMINISTIC_STD)
    j = m2.state_names.index(c.states[0].name)
    sd = input_state_prior_scales(m2, [r2])[j][0]

    def stage0(prior):
        return smooth(m2, [r2], th2, {"G": G1, "R": R1},
                      options=diag_options(200, warm_start=WarmStart.from_decision(dec0),
                                           input_state_prior=prior))
    with_prior = stage0("all")
    assert with_prior.converged
    assert with_prior.elbo - (base.elbo + H0) == pytest.approx(0.0, abs=0.05)
    mu0 = float(np.asarray(with_prior.smoothers[0].mu)[0, j])
    assert abs(mu0 - float(np.asarray(r2.u)[0, 0])) < sd
    # the flat prior: the same reference with the entropy alone as the state's term
    P = math.exp(2 * H0 + math.log(2 * math.pi * sd ** 2))  # solve H₀ = term(P) approximately
    for _ in range(50):
        P = math.exp(2 * (H0 - initial_prior_term(P, sd) + 0.5 * math.log(2 * math.pi * math.e * P))) \
            / (2 * math.pi * math.e)
    h_flat = 0.5 * math.log(2 * math.pi * math.e * P)
    flat = stage0("none")
    assert flat.elbo - (base.elbo + h_flat) > 3.0, "the flat prior's impulse should be visible here"
    assert abs(float(np.asarray(flat.smoothers[0].mu)[0, j])) > 10 * sd
