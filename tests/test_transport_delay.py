"""Pure transport delay of an input (vsidgen.data.delay_input, spec `inputs: {u: {delay: s}}`,
the diagnose delay profile of vsidgen.discrepancy.delay) against exact references; the
end-to-end case uses the independent simulator of benchmarks/independent."""

from __future__ import annotations

import math
import pathlib
import sys
import textwrap

import numpy as np
import pytest

from vsidgen.data import delay_input, load_record
from vsidgen.discrepancy.delay import delay_grid, delay_p_value, hold_lag, parabola_vertex
from vsidgen.errors import SpecError
from vsidgen.spec import compile_spec

ROOT = pathlib.Path(__file__).resolve().parents[1]


def test_delay_input_is_exact_for_piecewise_linear_signals_and_holds_the_start():
    t = np.arange(0, 2.0 + 1e-12, 0.05)
    u = np.where(t < 1.0, 2.0 * t, 2.0) - 0.3  # ramp then constant
    for tau in (0.05, 0.0125, 0.137, 0.5):
        ref = np.where(t - tau < 1.0, 2.0 * np.maximum(t - tau, 0.0), 2.0) - 0.3
        # exact wherever t − τ does not straddle the kink at t = 1 within one sample
        ok = np.abs(t - tau - 1.0) >= 0.05
        np.testing.assert_allclose(delay_input(u, t, tau)[ok], ref[ok], rtol=0, atol=1e-12)
    np.testing.assert_array_equal(delay_input(u, t, 0.0), u)


def test_spec_delay_is_applied_at_loading_and_validated(tmp_path):
    spec = ROOT / "specs" / "attas_sp.yaml"
    data = ROOT / "data" / "attas_sp_synthetic.csv"
    child = tmp_path / "d.yaml"
    child.write_text(f"extends: {spec}\nname: attas_delayed\ninputs:\n  de: {{delay: 0.1}}\n")
    m = compile_spec(child)
    assert [(v.name, v.delay) for v in m.inputs] == [("de", 0.1)]
    r0, r1 = load_record(compile_spec(spec), data), load_record(m, data)
    np.testing.assert_allclose(r1.u[:, 0], np.interp(r0.t - 0.1, r0.t, r0.u[:, 0]), atol=1e-15)
    assert not np.array_equal(r0.u, r1.u) and np.array_equal(r0.y, r1.y)
    bad = tmp_path / "b.yaml"
    bad.write_text(textwrap.dedent(f"""\
        extends: {spec}
        name: attas_bad
        inputs:
          de: {{delay: -0.2}}
        """))
    with pytest.raises(SpecError) as ei:
        compile_spec(bad)
    assert ei.value.line == 4 and "between 0 and" in ei.value.message


def test_grid_parabola_hold_lag_and_p_value():
    g = delay_grid(0.04)
    assert g[0] == pytest.approx(0.02) and max(g) <= 1.0 and len(g) == 12 - 1  # 32 T > 1 s
    assert delay_grid(0.5)[:2] == [0.25, 0.5]
    x = np.array([0.08, 0.12, 0.16])
    v, c = parabola_vertex(x, 10.0 - 0.5 * 400.0 * (x - 0.11) ** 2)
    assert v == pytest.approx(0.11) and c == pytest.approx(400.0)
    assert math.isnan(parabola_vertex(x, x ** 2)[0])  # a minimum, not a maximum
    model = type("M", (), {"input_hold": "zoh", "integrator": "euler", "substeps": 1})
    assert hold_lag(model, 0.04) == pytest.approx(0.02)
    model.input_hold, model.substeps = "foh", 4
    assert hold_lag(model, 0.04) == pytest.approx(0.005)
    model.integrator = "rk4"
    assert hold_lag(model, 0.04) == 0.0
    from scipy import stats
    assert delay_p_value(20.0, 10) == pytest.approx(10 * stats.chi2.sf(20.0, 1))
    assert delay_p_value(1.0, 10) == 1.0 and delay_p_value(-3.0, 10) == 1.0


@pytest.mark.slow
def test_diagnose_names_an_independent_delay_in_seconds(tmp_path):
    """An elevator transport delay of 0.12 s concealed by the independent simulator (continuous
    time, inputs moving between samples) on the ATTAS short-period model: named first as a
    transport delay, in seconds, within 3 standard errors (measured 0.121 ± 0.0024 s)."""
    sys.path.insert(0, str(ROOT / "benchmarks" / "independent"))
    import sim

    from vsidgen.discrepancy import run_diagnose

    cols, _ = sim.simulate_sp(effect="de_delay", magnitude=0.12, seed=0)
    csv = tmp_path / "rec.csv"
    sim.write_csv(csv, cols)
    res = run_diagnose(ROOT / "specs" / "attas_sp.yaml", [csv], out=tmp_path / "o", max_rounds=1,
                       effects=["transport_delay"], numerics=False)
    f = res.findings[0]
    assert (f["effect"], f["target"]) == ("transport_delay", "input:de")
    (name, p), = f["parameters"].items()
    assert name == "D_DELAY_de" and p["unit"] == "s"
    assert abs(p["estimate"] - 0.12) < 3 * p["std_error"]
    assert f["added_terms"]["inputs"]["de"]["delay"] == pytest.approx(p["estimate"] - 0.02)


def test_profile_highest_at_zero_is_no_delay_not_an_optimizer_failure(monkeypatch):
    """On a record without a delay every delayed fit is below the current model: the profile
    reports τ = 0 with no refit (not a refit 'below its nesting point')."""
    import types

    from vsidgen.discrepancy import delay as D, search
    from vsidgen.discrepancy.base import Candidate
    from vsidgen.engine import Engine

    rec = types.SimpleNamespace(dt=0.04)
    model = types.SimpleNamespace(input_names=("de",), inputs=(types.SimpleNamespace(delay=0.0),))
    current = types.SimpleNamespace(records=(rec,), elbo=100.0, model=model)
    monkeypatch.setattr(D, "_grid_task", lambda cur, j, tau, it: (100.0 - 50.0 * tau, True))
    prof = D.profile_delay(current, "de", pathlib.Path("x.yaml"), "x", engine=Engine(workers=1),
                           generated_dir=None, max_iter=10)
    assert prof.at_zero and prof.state is None and prof.estimate == 0.0
    c = Candidate("transport_delay", "transport_delay:de", "input:de", "e",
                  info={"input": "de", "profile": "delay"}, screenable=False)
    monkeypatch.setattr(D, "profile_delay", lambda *a, **k: prof)
    t = search.delay_trial(c, 3.0, current, pathlib.Path("x.yaml"), "x", engine=None,
                            generated_dir=None, max_iter=10, deadline=None)
    assert t.state is None and t.statistic == 0.0 and t.p_value == 1.0 and t.verdict is None
    assert "τ = 0" in t.refit.notes[0] and t.to_json()["verdict"] is None
