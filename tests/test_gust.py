"""The air-relative gust alternative of the noise-model stage (:mod:`vsidgen.discrepancy.gust`):
which models it applies to, what it writes, and its test's reference distribution."""

import math
import pathlib
import types

import numpy as np
import pytest
from scipy import stats

from vsidgen.discrepancy.base import model_info
from vsidgen.discrepancy.gust import gust_dof, gust_plans, write_gust_spec
from vsidgen.discrepancy.noisemodel import NoiseAlternative, NoiseModelTrial, decide
from vsidgen.spec import compile_spec

ROOT = pathlib.Path(__file__).resolve().parents[1]
BODY = ROOT / "benchmarks" / "independent" / "specs" / "hfb_body.yaml"


def _current(spec, mean):
    """The parts of a diagnose FitState that the gust plan reads (a fit at ``mean``)."""
    sym = compile_spec(spec)
    model = types.SimpleNamespace(
        name=sym.name, state_names=tuple(v.name for v in sym.states),
        parameter_names=tuple(p.name for p in sym.parameters), parameters=sym.parameters,
        process_noise=sym.process_noise)
    fit = types.SimpleNamespace(smoothers=[types.SimpleNamespace(mu=np.tile(mean, (8, 1)))],
                                theta=np.zeros(len(model.parameter_names)))
    return types.SimpleNamespace(spec_path=spec, fit=fit, model=model)


def test_body_axis_model_gets_a_gust_in_its_flow_angle_definitions(tmp_path):
    """A user's body-axis model (α = atan2(w, u), V = sqrt(u² + w²) as definitions): the gust
    perturbs w, the component α is most sensitive to, in both definitions, and nowhere else
    (the kinematic drift keeps the inertial w)."""
    cur = _current(BODY, [104.0, 8.0, 0.0, 0.08])
    (p,) = gust_plans(cur, model_info(BODY, dt=0.05))
    assert (p.role, p.velocity, p.unit) == ("alpha", "w", "m/s")
    assert set(p.definitions) == {"Vt", "a"}
    assert p.tau_start == pytest.approx(0.05) and p.tau_bounds[0] == pytest.approx(0.025)
    path = write_gust_spec(cur, [p], tmp_path / "gust.yaml", "hfb_body_gust")
    sym = compile_spec(path)
    assert [v.name for v in sym.states] == ["u", "w", "q", "theta", p.gust]
    assert sym.process_noise.states == ("u", "w", "q", "theta", p.gust)
    defs = dict(sym.definitions)
    W, w, u = (next(s for s in defs["a"].free_symbols if s.name == n) for n in (p.gust, "w", "u"))
    assert defs["a"].equals(__import__("sympy").atan2(w - W, u))
    drift = dict(zip((v.name for v in sym.states), sym.drift))
    assert W not in drift["w"].free_symbols and W not in drift["u"].free_symbols
    # noise std and correlation time (diagonal structure)
    assert gust_dof(cur, [p]) == 2


@pytest.mark.parametrize("spec", ["specs/hfb320.yaml", "specs/attas_lat.yaml",
                                  "benchmarks/independent/specs/lat_beta.yaml",
                                  "benchmarks/users/hfb_sp.yaml"])
def test_no_gust_where_the_flow_angles_are_states(spec):
    path = ROOT / spec
    n = len(compile_spec(path).states)
    assert gust_plans(_current(path, np.ones(n)), model_info(path, dt=0.05)) == []


def test_gust_multiplicity_counts_the_correlation_times_in_its_range():
    """The gust's p-value is multiplied by the number of √2-spaced correlation times between
    half an integration step and the upper bound: counted here on the grid itself (24 at
    20 Hz), and the threshold that gives is above χ²_k at α alone."""
    cur = _current(BODY, [104.0, 8.0, 0.0, 0.08])
    (p,) = gust_plans(cur, model_info(BODY, dt=0.05))
    lo, hi = p.tau_bounds
    grid = [lo * math.sqrt(2.0) ** k for k in range(200) if lo * math.sqrt(2.0) ** k <= hi]
    assert p.multiplicity == len(grid) == 24
    k, alpha = gust_dof(cur, [p]), 0.01
    lam = float(stats.chi2.isf(alpha, k)) + 1.0
    t = decide(NoiseModelTrial(NoiseAlternative.AIR_GUST, pathlib.Path("g.yaml"), k,
                               types.SimpleNamespace(elbo=lam / 2), converged=True),
               0.0, alpha / p.multiplicity)
    assert t.verdict.value == "not_significant"


def test_adopted_gust_is_reported_as_noise_model_not_physics():
    """The CLI lines and the conclusion sentence name an adopted gust as a noise-model finding,
    with its numbers (findings.json ``noise_gust``)."""
    from vsidgen.discrepancy.findings import noise_gust_text, summary_lines

    ng = {"gusts": [{"velocity": "w", "gust_state": "D_GUST_w", "definitions": {"a": "", "Vt": ""}}],
          "trials": [{}],
          "adopted": {"statistic": 361.4, "threshold": 15.2, "dof": 7,
                      "recommendation": "add the gust state(s) of r0_g01.yaml",
                      "explanation": "Noise model, not physics: the turbulence enters ..."}}
    text = noise_gust_text(ng)
    assert text.startswith("NOISE MODEL (not a physical effect)") and "w − D_GUST_w" in text
    assert "361.4 > 15.2" in text
    lines = summary_lines({"noise_gust": ng, "findings": [], "conclusion": "c."}, "findings.json")
    assert any(l.startswith("0. noise model (not physics): add the gust state") for l in lines)
    assert noise_gust_text({"trials": [{}], "adopted": None}) == ""
