"""The quasi-deterministic std of a state that carries an input is relative to the input's
size (scale-free in its unit): an engine lag state in N must not get the absolute std
calibrated for an elevator in rad (hfb_thrust_lag_0.5_s0: the thrust lag's refit stopped at
its iteration limit with 1e-3 N/√s; with the relative std it converged in 140 s)."""

from __future__ import annotations

import numpy as np
import pytest

from vsidgen import load_model
from vsidgen.data import Record
from vsidgen.discrepancy.refit import REFIT_DETERMINISTIC_REL, REFIT_DETERMINISTIC_STD, quasi_stds
from vsidgen.estimator import FitOptions
from vsidgen.estimator.core import input_filter_scales
from vsidgen.estimator.problem import Problem

# a pitch model whose thrust acts through an engine lag state (the form diagnose adds),
# written by hand; the unit of thrust is a parameter of the test
SPEC = """\
name: lagged_{tag}
states:
  q: {{unit: rad/s}}
  theta: {{unit: rad}}
  T_lag: {{unit: {unit}, description: engine lag state}}
inputs:
  de: {{unit: rad}}
  thrust: {{unit: {unit}}}
outputs:
  q: {{unit: rad/s}}
  theta: {{unit: rad}}
parameters:
  Mq: {{initial: -1.0, unit: 1/s}}
  Mde: {{initial: -5.0, unit: 1/s^2}}
  MT: {{initial: {mt}, unit: 1/(s^2*{unit})}}
  tau: {{initial: 0.5, unit: s, bounds: [0.05, 5]}}
drift:
  q: Mq*q + Mde*de + MT*T_lag
  theta: q
  T_lag: (thrust - T_lag)/tau
observations:
  q: q
  theta: theta
noise:
  process:
    states: [q, theta]
data:
  time: t
  inputs: {{de: de, thrust: thrust}}
  outputs: {{q: q, theta: theta}}
"""


def _model(tmp_path, unit: str, mt: float, tag: str = "a"):
    p = tmp_path / f"lag_{tag}.yaml"
    p.write_text(SPEC.format(tag=tag, unit=unit, mt=mt))
    return load_model(p, generated_dir=tmp_path / "gen")


def _record(thrust_scale: float) -> Record:
    rng = np.random.default_rng(3)
    n = 200
    t = np.arange(n) * 0.05
    de = 0.02 * np.sign(np.sin(t))
    thrust = thrust_scale * (12000.0 + 1500.0 * (t > 4.0) - 1500.0 * (t > 7.0))
    y = 0.01 * rng.standard_normal((n, 2))
    return Record(name="r", path=None, t=t, dt=0.05, u=np.column_stack([de, thrust]), y=y,
                  input_names=("de", "thrust"), output_names=("q", "theta"), t_raw=t)


def test_input_filter_scale_is_the_carried_input_std(tmp_path):
    m = _model(tmp_path, "N", 1e-5)
    rec = _record(1.0)
    sc = input_filter_scales(m, [rec])
    thrust = rec.u[:, 1]
    assert sc[:2] == pytest.approx([0.0, 0.0])        # q, θ carry no input
    assert sc[2] == pytest.approx(float(np.std(thrust)), rel=1e-12)
    q = quasi_stds(m, [rec], REFIT_DETERMINISTIC_STD)
    assert q[2] == pytest.approx(REFIT_DETERMINISTIC_REL * np.std(thrust), rel=1e-12)
    assert q[0] == REFIT_DETERMINISTIC_STD


def test_refit_problem_std_is_scale_free(tmp_path):
    """The same lag with thrust recorded in N and in kN (numbers ×1000 apart): the lag
    state's fixed std is the same fraction of the input, the states without an input keep
    the absolute one."""
    dets = []
    for tag, scale, mt in (("N", 1.0, 1e-5), ("kN", 1e-3, 1e-2)):
        m = _model(tmp_path, "N", mt, tag=tag)
        rec = _record(scale)
        P = Problem(m, [rec], FitOptions(deterministic="quasi",
                                         deterministic_std=REFIT_DETERMINISTIC_STD,
                                         deterministic_input_scale=REFIT_DETERMINISTIC_REL))
        det = np.asarray(P.nm.det)
        assert bool(P.nm.deterministic[2])
        dets.append(det[2])
        # without the option the absolute std (the estimator's default behaviour) is kept
        P0 = Problem(m, [rec], FitOptions(deterministic="quasi",
                                          deterministic_std=REFIT_DETERMINISTIC_STD))
        assert np.asarray(P0.nm.det)[2] == REFIT_DETERMINISTIC_STD
    assert dets[0] == pytest.approx(1000.0 * dets[1], rel=1e-9)
    assert dets[0] > 1.0           # ~0.007 × 700 N, not 1e-3 N


def test_a_state_driven_by_a_control_is_not_an_input_filter(tmp_path):
    """α̇ = Z_α α + Z_δe δe has δe's unit and depends on it, but is not a filter of δe (its
    drift is not driven by δe − α): it keeps the absolute std; the lag state is tagged."""
    spec = tmp_path / "sp.yaml"
    spec.write_text(SPEC.format(tag="sp", unit="N", mt=1e-5)
                    .replace("  q: {unit: rad/s}\n", "  q: {unit: rad/s}\n  alpha: {unit: rad}\n", 1)
                    .replace("  theta: q\n", "  theta: q\n  alpha: q - 0.8*alpha - 0.1*de\n"))
    m = load_model(spec, generated_dir=tmp_path / "gen_sp")
    assert "alpha" in m.state_names
    sc = input_filter_scales(m, [_record(1.0)])
    names = list(m.state_names)
    assert sc[names.index("alpha")] == 0.0
    assert sc[names.index("T_lag")] > 0.0


# -- which state carries an input: ∂f/∂u + ∂f/∂z ≡ 0, decided at random points, checked
# against sympy.simplify (the reference) on expressions small enough for it

def _carries_by_simplify(f, u, z) -> bool:
    import sympy

    du = sympy.diff(f, u)
    return du != 0 and sympy.simplify(du + sympy.diff(f, z)) == 0


def _forms():
    import sympy

    u, z, tau, a, b, V = sympy.symbols("u z tau a b V", real=True)
    return (u, z), [
        (u - z) / tau,                                    # lag
        2 * (u - z) / tau,                                # Padé state
        sympy.sin(u - z) * V + a,                         # nonlinear in the difference
        sympy.tanh((u - z) / tau) * a ** 2 - b * V,       # a rate-limited actuator's smooth form
        sympy.Piecewise((u - z, a > 1), (2 * (u - z), True)),
        (sympy.exp(u) - sympy.exp(z)) * a,                # depends on both, not on the difference
        a * z + b * u,                                    # a flow angle driven by a control
        (u - z) ** 2 / tau + a * z,
        (u - z) / tau + 1e-12 * u,                        # a difference plus a tiny extra term
        u * z,
        a + b,                                            # neither
    ]


@pytest.mark.parametrize("k", range(11))
def test_carried_input_identity_matches_simplify(k):
    from vsidgen.estimator.core import _driven_by_difference

    (u, z), forms = _forms()
    f = forms[k]
    assert _driven_by_difference(f, u, z) == _carries_by_simplify(f, u, z)


def test_carried_input_identity_on_a_gated_screen_drift():
    """A diagnose screen's gated drift (≈150 gate terms in one equation; ``sympy.simplify`` on
    it took more than a minute): not a carried input, and the lag form with the same gate
    terms added on the difference alone still is."""
    import sympy

    from vsidgen.estimator.core import _driven_by_difference

    u, z, tau, V, q = sympy.symbols("u z tau V q", real=True)
    gates = sympy.symbols("g0:150", real=True)
    terms = [g * (V ** (i % 3) * sympy.sin(z) ** (i % 2) * u ** (i % 4) * q ** (i % 5))
             for i, g in enumerate(gates)]
    drift = -z / tau + 3 * u + q + sum(terms)
    assert not _driven_by_difference(drift, u, z)
    lag = (u - z) / tau + sum(g * (u - z) ** (i % 3 + 1) * V for i, g in enumerate(gates))
    assert _driven_by_difference(lag, u, z)
