"""Maneuvers, input-spec parsing, stochastic simulation and the CSV round trip."""

from __future__ import annotations

import time

import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg
import sympy

from vsidgen.data import load_record
from vsidgen.errors import VsidgenError
from vsidgen.metadata import ChannelMap, DataSpec, Parameter, ProcessNoiseSpec, Variable
from vsidgen.model import Model
from vsidgen.data.simulate import (MANEUVERS, doublet, multisine, parse_input_spec, simulate,
                              simulate_to_csv, step, three_two_one_one)


def linear_model(data=None):
    """Short-period-like linear model: x = (alpha, q), u = (de, da), y = (alpha, q, nz)."""
    def drift(x, u, p):
        A = jnp.array([[p[0], 1.0], [p[1], p[2]]])
        B = jnp.array([[0.0, 0.01], [p[3], 0.0]])
        return A @ x + B @ u

    def output(x, u, p):
        return jnp.array([x[0], x[1], 5.0 * x[0] + 0.2 * u[0]])

    data = data or DataSpec(
        time="t_s",
        inputs=(ChannelMap("de", "de_rad"),
                ChannelMap("da", expr=(sympy.Symbol("r") - sympy.Symbol("l")) / 2, columns=("r", "l"))),
        outputs=(ChannelMap("alpha", "alpha_rad"), ChannelMap("q", "q_radps"),
                 ChannelMap("nz", "az_mps2", scale=-1 / 9.80665, offset=0.0)))
    return Model(name="lin", drift=drift, output=output,
                 states=(Variable("alpha"), Variable("q")), inputs=(Variable("de"), Variable("da")),
                 outputs=(Variable("alpha"), Variable("q"), Variable("nz")),
                 parameters=(Parameter("Za", initial=-0.7), Parameter("Ma", initial=-4.0),
                             Parameter("Mq", initial=-1.5), Parameter("Mde", initial=-6.0)),
                 process_noise=ProcessNoiseSpec(states=("alpha", "q")), measurement_noise=(), data=data)


THETA = {"Za": -0.8, "Ma": -5.0, "Mq": -2.0, "Mde": -8.0}


# ---------------------------------------------------------------- maneuvers

def test_doublet_and_3211_shapes():
    t = np.arange(0, 10, 0.01)
    d = doublet(t, amplitude=2.0, start=1.0, width=0.5)
    assert np.all(d[(t < 1.0)] == 0) and np.all(d[(t >= 2.0)] == 0)
    assert np.all(d[(t >= 1.0) & (t < 1.5 - 1e-9)] == 2.0)
    assert np.all(d[(t >= 1.5 + 1e-9) & (t < 2.0 - 1e-9)] == -2.0)
    assert d.sum() * 0.01 == pytest.approx(0.0, abs=0.05)
    s = three_two_one_one(t, amplitude=1.0, start=2.0, unit=1.0)
    # +1 on [2,5), -1 on [5,7), +1 on [7,8), -1 on [8,9), 0 after
    for a, b, v in ((0, 2, 0), (2, 5, 1), (5, 7, -1), (7, 8, 1), (8, 9, -1), (9, 10, 0)):
        sel = (t > a + 1e-6) & (t < b - 1e-6)
        assert np.all(s[sel] == v), (a, b)
    assert np.sum(s == 1) * 0.01 == pytest.approx(4.0, abs=0.02)
    st = step(t, amplitude=-3.0, start=4.0)
    assert np.all(st[t < 4.0] == 0) and np.all(st[t >= 4.0] == -3.0)
    assert set(MANEUVERS) == {"doublet", "3211", "multisine", "step"}


def test_multisine():
    t = np.arange(0, 20, 0.01)
    u = multisine(t, amplitude=0.1, f_min=0.2, f_max=1.0, n=5)
    assert np.max(np.abs(u)) == pytest.approx(0.1)
    # spectrum: energy at the 5 frequencies 0.2, 0.4, ..., 1.0 Hz (integer cycles in 20 s)
    spec = np.abs(np.fft.rfft(u))
    freqs = np.fft.rfftfreq(t.size, 0.01)
    peaks = np.sort(freqs[np.argsort(spec)[-5:]])
    np.testing.assert_allclose(peaks, [0.2, 0.4, 0.6, 0.8, 1.0], atol=1e-9)
    amps = spec[np.isin(np.round(freqs, 6), [0.2, 0.4, 0.6, 0.8, 1.0])]
    np.testing.assert_allclose(amps, amps[0], rtol=1e-6)   # equal power
    # Schroeder phases give a lower peak factor than zero phases
    zero_phase = sum(np.cos(2 * np.pi * f * t) for f in (0.2, 0.4, 0.6, 0.8, 1.0))
    rms = np.sqrt(np.mean(u ** 2))
    assert np.max(np.abs(u)) / rms < np.max(np.abs(zero_phase)) / np.sqrt(np.mean(zero_phase ** 2))


def test_parse_input_spec():
    spec = parse_input_spec("de=3211:amplitude=0.02,start=1,unit=0.5")
    t = np.arange(0, 6, 0.1)
    assert spec.name == "de"
    np.testing.assert_array_equal(spec.evaluate(t), three_two_one_one(t, amplitude=0.02, start=1, unit=0.5))
    c = parse_input_spec("thrust=const:value=11600")
    assert np.all(c(t) == 11600.0)
    s = parse_input_spec("de = const:value=-5e-2 + doublet:amplitude=1e+0,start=2")
    np.testing.assert_allclose(s(t), -0.05 + doublet(t, amplitude=1.0, start=2.0))
    m = parse_input_spec("de=multisine:amplitude=0.1,n=4")
    assert dict(m.terms[0][1])["n"] == 4


@pytest.mark.parametrize("text, frag", [
    ("de", "NAME=MANEUVER"), ("de=wiggle:amplitude=1", "unknown maneuver 'wiggle'"),
    ("de=doublet:amp=1", "unknown option 'amp'"), ("de=doublet:start=1", "needs option(s) amplitude"),
    ("de=step:amplitude=x", "not a number"), ("de=multisine:amplitude=1,n=2.5", "an integer from 1 to 1000"),
])
def test_parse_input_spec_errors(text, frag):
    with pytest.raises(VsidgenError) as info:
        parse_input_spec(text)
    msg = str(info.value)
    assert frag in msg
    assert "3211:amplitude,start=1.0,unit=0.5" in msg and "const:value" in msg   # the hint


# ---------------------------------------------------------------- simulation

def _inputs(t):
    return {"de": three_two_one_one(t, amplitude=0.05, start=1, unit=0.5), "da": 0.01}


def test_deterministic_matches_euler_recursion():
    model = linear_model()
    t = np.arange(0, 5, 0.02)
    res = simulate(model, theta=THETA, t=t, u=_inputs(t), x0={"alpha": 0.01, "q": 0.0})
    A = np.array([[-0.8, 1.0], [-5.0, -2.0]])
    B = np.array([[0.0, 0.01], [-8.0, 0.0]])
    x = np.array([0.01, 0.0])
    xs = [x]
    for k in range(t.size - 1):
        x = x + 0.02 * (A @ x + B @ res.u[k])
        xs.append(x)
    np.testing.assert_allclose(res.x, np.array(xs), rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(res.y[:, 2], 5 * res.x[:, 0] + 0.2 * res.u[:, 0], atol=1e-15)


def test_noise_statistics_and_seed():
    """Process noise: stationary covariance of the discrete system; measurement noise std."""
    model = linear_model()
    T, n = 0.01, 100_000
    t = np.arange(n) * T
    t0 = time.perf_counter()
    kw = dict(theta=THETA, t=t, u={"de": 0.0, "da": 0.0}, x0=[0.0, 0.0],
              process_std={"alpha": 0.05, "q": 0.2}, measurement_std={"nz": 0.3}, seed=3)
    res = simulate(model, **kw)
    assert time.perf_counter() - t0 < 20.0
    A = np.array([[-0.8, 1.0], [-5.0, -2.0]])
    Ad = np.eye(2) + T * A
    Qd = T * np.diag([0.05, 0.2]) ** 2
    P = scipy.linalg.solve_discrete_lyapunov(Ad, Qd)
    emp = np.cov(res.x[1000:].T)
    np.testing.assert_allclose(emp, P, rtol=0.15, atol=0.15 * np.sqrt(np.outer(np.diag(P), np.diag(P))).max())
    e = res.y[:, 2] - 5 * res.x[:, 0]
    assert np.std(e) == pytest.approx(0.3, rel=0.02)
    np.testing.assert_array_equal(res.y[:, 0], res.x[:, 0])   # no noise on alpha
    again = simulate(model, **kw)
    np.testing.assert_array_equal(again.y, res.y)
    other = simulate(model, **{**kw, "seed": 4})
    assert not np.array_equal(other.y, res.y)


def test_quantize_and_theta_array():
    model = linear_model()
    t = np.arange(0, 3, 0.05)
    th = np.array([THETA[k] for k in ("Za", "Ma", "Mq", "Mde")])
    res = simulate(model, theta=th, t=t, u=_inputs(t), x0=[0.02, 0.0], quantize={"alpha": 1e-3},
                   integrator="rk4", substeps=2)
    np.testing.assert_allclose(res.y[:, 0] / 1e-3, np.round(res.y[:, 0] / 1e-3), atol=1e-9)
    assert np.max(np.abs(res.y[:, 0] - res.x[:, 0])) <= 0.5e-3 + 1e-15


@pytest.mark.parametrize("kw, frag", [
    (dict(theta={"Zq": 1.0}), "unknown parameter"), (dict(theta=[1.0]), "theta has 1"),
    (dict(u={"de": 0.0}), "missing ['da']"), (dict(x0=[0.0]), "x0"),
    (dict(process_std={"V": 1.0}), "unknown name 'V'"), (dict(t=[0.0, 0.1, 0.3]), "uniformly"),
    (dict(integrator="heun"), "unknown integrator"),
])
def test_simulate_errors(kw, frag):
    t = np.arange(0, 1, 0.1)
    args = dict(theta=THETA, t=t, u={"de": 0.0, "da": 0.0}, x0=[0.0, 0.0])
    args.update(kw)
    with pytest.raises(VsidgenError, match=None) as info:
        simulate(linear_model(), **args)
    assert frag in str(info.value)


def test_divergence_is_reported():
    t = np.arange(0, 200, 0.5)
    with pytest.raises(VsidgenError, match="simulation diverged: state `(alpha|q)` .* at sample"):
        simulate(linear_model(), theta={"Za": 3.0, "Ma": 50.0, "Mq": 3.0, "Mde": 0.0}, t=t,
                 u={"de": 0.0, "da": 0.0}, x0=[1.0, 0.0])


@pytest.mark.parametrize("kw, frag", [
    (dict(u={"de": 1e300, "da": 0.0}), "input `de` reaches 1e+300 at sample 0"),
    (dict(measurement_std={"alpha": 1e300}), "output `alpha` reaches"),
    (dict(quantize={"alpha": -1.0}), "must be finite and > 0"),
    (dict(quantize={"alpha": float("nan")}), "must be finite and > 0"),
])
def test_absurd_amplitudes_and_steps_are_refused(kw, frag):
    """Values whose squares overflow float64 cannot be fitted: refused with the channel and
    sample, like a divergence (they were written to the record); a quantisation step must be
    positive (a negative one was ignored silently)."""
    t = np.arange(0, 1, 0.1)
    args = dict(theta=THETA, t=t, u={"de": 0.01, "da": 0.0}, x0=[0.0, 0.0])
    args.update(kw)
    with pytest.raises(VsidgenError) as info:
        simulate(linear_model(), **args)
    assert frag in str(info.value)


def test_quantising_an_output_to_one_level_is_warned():
    t = np.arange(0, 3, 0.05)
    res = simulate(linear_model(), theta=THETA, t=t, u=_inputs(t), x0=[0.02, 0.0],
                   quantize={"alpha": 1e3})
    assert len(res.warnings) == 1 and "`alpha` quantised to a single level" in res.warnings[0]
    assert simulate(linear_model(), theta=THETA, t=t, u=_inputs(t), x0=[0.02, 0.0],
                    quantize={"alpha": 1e-3}).warnings == ()


# ---------------------------------------------------------------- CSV round trip

def test_simulate_to_csv_roundtrip(tmp_path):
    model = linear_model()
    t = np.arange(0, 4, 0.02)
    out = tmp_path / "syn.csv"
    res = simulate_to_csv(model, out, theta=THETA, t=t, u=_inputs(t), x0=[0.01, 0.0],
                          process_std={"q": 0.05}, measurement_std={"alpha": 1e-3, "nz": 0.05},
                          seed=7)
    rec = load_record(model, out)
    np.testing.assert_array_equal(rec.t, res.t)
    assert rec.dt == pytest.approx(0.02, rel=1e-12)
    np.testing.assert_array_equal(rec.u[:, 0], res.u[:, 0])     # column map: exact
    np.testing.assert_array_equal(rec.u[:, 1], res.u[:, 1])     # expr (r - l)/2 inverted: r = 2 da, l = 0
    np.testing.assert_array_equal(rec.y[:, :2], res.y[:, :2])
    np.testing.assert_allclose(rec.y[:, 2], res.y[:, 2], rtol=4e-16, atol=0)   # scaled: 1 ulp
    header = out.read_text().splitlines()[0].split(",")
    assert header == ["t_s", "de_rad", "da", "r", "l", "alpha_rad", "q_radps", "az_mps2"]
    assert [p.name for p in tmp_path.iterdir()] == ["syn.csv"]


def test_simulate_writes_the_time_column_in_its_declared_unit(tmp_path):
    """A spec whose time column is in milliseconds (``time: {column: t_ms, unit: ms}``) gets
    its stamps written in ms, and reads them back as the simulated seconds."""
    import dataclasses

    base = linear_model()
    model = dataclasses.replace(base, data=dataclasses.replace(
        base.data, time="t_ms", time_scale=1e-3, time_unit="ms"))
    t = np.arange(0, 2, 0.02)
    out = tmp_path / "ms.csv"
    res = simulate_to_csv(model, out, theta=THETA, t=t, u=_inputs(t), x0=[0.01, 0.0], seed=1)
    second = out.read_text().splitlines()[2].split(",")
    assert float(second[0]) == pytest.approx(20.0)
    rec = load_record(model, out)
    np.testing.assert_allclose(rec.t, res.t, rtol=1e-12, atol=1e-12)
    assert rec.dt == pytest.approx(0.02, rel=1e-12)
    assert not [w for w in rec.warnings if w.code.value == "slow_sampling"]
