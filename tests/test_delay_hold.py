"""What a transport delay means depends on how the inputs move between samples.

A model with a zero-order hold uses ``u_k`` over the whole step: an input that moves
continuously is thereby delayed by half a sample, one that steps at the samples is not. A fit
without the delay cannot tell the two apart (the hold's half sample absorbs part of a delay),
so diagnose profiles the delay under both holds and lets the better fit decide
(``search.delay_trial``). Checked on records from an independent numpy simulation (a 20×
finer grid, the input delayed exactly) of a one-state linear model written as a user would:
the delay comes out within 3 standard errors of the truth, in seconds, and with the right
hold in the spec, for a continuously moving input and for one that steps at the samples.
"""

from __future__ import annotations

import csv
import math

import numpy as np
import pytest

from vsidgen.discrepancy import run_diagnose

DT = 0.05
DELAY = 0.2   # four samples

SPEC = """
name: lin1_rk4
description: one-state linear model, RK4 with the inputs held over each sample
states:
  x: {unit: "1", description: state}
inputs:
  u: {unit: "1", description: input}
outputs:
  y: {unit: "1", description: measured state}
parameters:
  A: {unit: 1/s, description: pole}
  B: {unit: 1/s, description: input gain}
drift:
  x: A*x + B*u
observations:
  y: x
integrator: {method: rk4, substeps: 1, inputs: zoh}
noise:
  process:
    states: [x]
    structure: diagonal
    estimate: true
  measurement:
    y: {floor: auto}
data:
  time: t
  inputs:
    u: u
  outputs:
    y: y
"""


def _input(t, stepped: bool):
    """A multistep with ramps of 0.3 s (moving between samples) or steps at the samples."""
    levels = ((1.0, 1.0), (2.5, -1.0), (3.5, 1.0), (4.0, -1.0), (6.0, 0.0), (9.0, 0.8),
              (11.0, -0.8), (13.0, 0.0), (16.0, 1.0), (17.5, -0.6), (19.0, 0.0))
    t = np.asarray(t, float)
    if stepped:
        t = np.floor(t / DT + 1e-9) * DT   # held from each sample
    u = np.zeros_like(t)
    prev = 0.0
    for t0, lv in levels:
        u = u + (lv - prev) * ((t >= t0) if stepped else np.clip((t - t0) / 0.3, 0.0, 1.0))
        prev = lv
    return u


def _record(path, stepped: bool, seed: int = 3, n: int = 440):
    rng = np.random.default_rng(seed)
    a, b, gw, sv = -1.5, 2.0, 0.03, 0.01
    sub = 20
    h = DT / sub
    x = 0.0
    t = np.arange(n) * DT
    ys = np.empty(n)
    for i in range(n):
        ys[i] = x + sv * rng.standard_normal()
        for s in range(sub):
            tt = t[i] + s * h
            # RK2 (midpoint) on the fine grid with the exactly delayed input
            u1 = _input(np.array([tt - DELAY]), stepped)[0]
            um = _input(np.array([tt + 0.5 * h - DELAY]), stepped)[0]
            xm = x + 0.5 * h * (a * x + b * u1)
            x = x + h * (a * xm + b * um) + gw * math.sqrt(h) * rng.standard_normal()
    u = _input(t, stepped)
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["t", "u", "y"])
        for row in zip(t, u, ys):
            w.writerow([f"{v:.10g}" for v in row])


@pytest.mark.parametrize("stepped, method", [
    (False, "rk4"),
    pytest.param(True, "rk4", marks=pytest.mark.slow),
    pytest.param(False, "euler", marks=pytest.mark.slow)],
    ids=["moving", "stepped", "moving-euler"])
def test_delay_and_hold_decided_together(tmp_path, stepped, method):
    """``moving-euler``: the same spec stepping by Euler, whose one step per sample has a phase
    error of the order of the hold's half sample: the delay is profiled again under RK4 with
    a first-order hold, and that setting goes into the spec."""
    spec = tmp_path / "lin1.yaml"
    spec.write_text(SPEC if method == "rk4" else SPEC.replace(
        "integrator: {method: rk4, substeps: 1, inputs: zoh}",
        "integrator: {method: euler, substeps: 1, inputs: zoh}").replace("name: lin1_rk4",
                                                                         "name: lin1_euler"))
    data = tmp_path / "rec.csv"
    _record(data, stepped)
    res = run_diagnose(spec, [data], out=tmp_path / "o", max_rounds=1,
                       effects=["transport_delay"], numerics=False, noise_model=False)
    f = res.findings[0]
    assert (f["effect"], f["target"]) == ("transport_delay", "input:u")
    (name, p), = f["parameters"].items()
    assert name == "D_DELAY_u" and p["unit"] == "s"
    assert abs(p["estimate"] - DELAY) < 3 * p["std_error"], (p, f["explanation"])
    trial = next(t for r in res.document["rounds"] for t in r["trials"]
                 if t["key"] == "transport_delay:u")
    print(f["explanation"])
    if stepped:   # the zero-order hold is right and adds nothing
        assert "integrator" not in f["added_terms"]
        assert "move in steps at the samples" in f["explanation"]
    elif method == "rk4":   # the inputs move: a first-order hold, whose RK4 stages add no lag
        assert f["added_terms"]["integrator"] == {"inputs": "foh"}
        assert "first-order hold" in f["explanation"]
        assert "integrator: {inputs: foh}" in res.document["conclusion"]   # the CLI line too
    else:
        assert f["added_terms"]["integrator"] == {"method": "rk4", "inputs": "foh"}
        assert p["hold_lag"] == 0.0 and p["estimate"] == p["spec_value"]
        assert "integrator: {method: rk4, inputs: foh}" in res.document["conclusion"]
    assert trial["statistic"] > 0
