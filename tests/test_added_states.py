"""States a diagnose candidate adds (a lag, a Padé delay) carry no process noise of their own,
whatever the user's spec says about noise, and the Padé delay nests the current model.

A new user's spec usually has no ``noise`` section, which gives *every* state process noise.
Candidate specs extend it; before, their added lag state inherited free (with
``structure: full``, correlated) process noise and became a coloured-noise channel: on the
real HFB-320 record an elevator "lag" was accepted with 2ΔELBO 151.7 and its time constant
at the lower bound (no lag at all), and the same model in degrees did not converge."""

import math
import pathlib
import textwrap

import numpy as np
import pytest

from vsidgen.discrepancy import propose
from vsidgen.discrepancy.base import model_info
from vsidgen.spec import compile_spec

DT = 0.1
SPEC = """\
name: sp_user
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


def _write(tmp_path: pathlib.Path, noise: str = "") -> pathlib.Path:
    base = tmp_path / "base.yaml"
    base.write_text(SPEC + textwrap.dedent(noise))
    return base


def _candidates(tmp_path: pathlib.Path, noise: str, effects=("actuator_lag", "control_delay")):
    base = _write(tmp_path, noise)
    info = model_info(base, dt=DT)
    out = []
    for c in propose(info):
        if c.effect in effects:
            path = tmp_path / f"{c.effect}.yaml"
            path.write_text(c.spec_yaml(base, name=f"cand_{c.effect}", candidate_path=path,
                                        info=info))
            out.append((c, path))
    assert {c.effect for c, _ in out} == set(effects)
    return out


@pytest.mark.parametrize("noise", ["", "noise:\n  process:\n    structure: full\n"],
                         ids=["no_noise_section", "structure_full"])
def test_added_input_states_have_no_process_noise(tmp_path, noise):
    for c, path in _candidates(tmp_path, noise):
        sym = compile_spec(path)
        assert [s.name for s in sym.states][-1] == c.states[0].name
        assert tuple(sym.process_noise.states) == ("alpha", "q"), (c.key, sym.process_noise)
        if noise:
            assert sym.process_noise.structure == "full"


def test_pade_delay_state_is_the_exact_held_step_response(tmp_path):
    """Under a held unit step an Euler step of the Padé state's drift is the exact solution of
    (τ/2) ż = u − z, z = 1 − e^{−2t/τ}, and the delayed input the model sees, 2·mean − u over
    the step, is the Padé delay's exact mean over that step; as τ → 0 the model sees u
    itself (the current model: the refit starts at its nesting point)."""
    from vsidgen.model import load_model

    (c, path), = _candidates(tmp_path, "", effects=("control_delay",))
    m = load_model(path, generated_dir=tmp_path / "gen")
    names = list(m.parameter_names)
    theta = np.zeros(len(names))
    tau_name = c.parameters[0].name
    assert c.parameters[0].lower < 0.05 * DT           # nests the current model
    theta[names.index("Zde")] = 1.0                    # α̇ sees the delayed elevator only
    for tau in (0.05, 0.3, 1.0):
        theta[names.index(tau_name)] = tau
        z = 0.0
        for k in range(1, 6):
            x = np.array([0.0, 0.0, z])
            f = np.asarray(m.drift(x, np.array([1.0]), theta), float)
            # α̇ = the delayed input the model sees over the step: 2·(mean of z) − u
            tc = tau / 2
            mean_z = 1.0 + (z - 1.0) * tc / DT * (1.0 - math.exp(-DT / tc))
            assert f[0] == pytest.approx(2.0 * mean_z - 1.0, abs=1e-6)
            z = z + DT * f[2]
            assert z == pytest.approx(1.0 - math.exp(-k * DT / tc), abs=1e-6)
    theta[names.index(tau_name)] = c.parameters[0].lower
    f = np.asarray(m.drift(np.array([0.0, 0.0, 0.3]), np.array([1.0]), theta), float)
    assert f[0] == pytest.approx(1.0, abs=0.02)        # 1 % of z − u at the bound


def test_continuous_pade_delay_bounds(tmp_path):
    """The continuous Padé form refitted after acceptance (:func:`lag_hold`): ż = 2(u − z)/τ,
    stable under RK4 for 2h/τ ≤ 2.785 and under Euler for 2h/τ ≤ 2 (its bound: 0.8 and 2
    steps)."""
    import dataclasses

    from vsidgen.discrepancy.catalogue import ContinuousControlDelay

    info = model_info(_write(tmp_path), dt=DT)
    for integrator, steps in (("rk4", 0.8), ("euler", 2.0)):
        i2 = dataclasses.replace(info, integrator=integrator)
        (c,) = ContinuousControlDelay().applies_to(i2)
        assert c.parameters[0].lower == pytest.approx(steps * DT)
        assert 2.0 * DT / c.parameters[0].lower <= (2.785 if integrator == "rk4" else 2.0)
        assert c.states[0].drift.replace(" ", "") == f"2*(de-{c.states[0].name})/{c.parameters[0].name}"
