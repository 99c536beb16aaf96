"""The report's "where" table shows, beside the residual tests of locate, the exact score test
of the round-1 screen per target, so that a sensor error the smoother absorbs (residual tests
clean, score test strong) is not shown as "no mismatch" next to a candidate ranked first.
(Session 47: a new user's lateral model had "bias p=1, scale p=0.33" on p_m while
sensor_scale:p_m scored −log10 p 80.5 in the screen.)"""

import re

from vsidgen.discrepancy.findings import _screen_leads, report_section


def _ev(flagged=False):
    return {"flagged": flagged, "systematic_share": 0.0, "windows": [],
            "bias": {"p": 1.0}, "scale": {"p": 0.33}, "lag_s": 0.0}


def _cand(key, target, mlp):
    return {"key": key, "target": target,
            "score_test": {"statistic": 1.0, "dof": 1, "minus_log10_p": mlp}}


def _doc():
    screen = [_cand("sensor_bias:p_m", "output:p_m", 2.0),
              _cand("sensor_scale:p_m", "output:p_m", 80.5),
              _cand("missing_derivative:p:r", "drift:p", 4.0),
              _cand("coefficient_derivative:side:r", "definition:side", 157.0),
              {"key": "locate_only:q", "target": "output:q_m", "score_test": None},
              _cand("nan:x", "output:r_m", float("nan"))]
    loc = {"states": {"p": {"flagged": True, "systematic_share": 0.29, "windows": [],
                            "top_regressors": [{"name": "udot:da", "p": 1e-19}]}},
           "outputs": {"p_m": _ev(), "r_m": _ev()}}
    return {"conclusion": "x", "findings": [], "locate": loc,
            "rounds": [{"round": 1, "screen": screen, "trials": []}]}


def _rows(html):
    table = html[html.index("Where the base"):html.index("</table>")]
    return [re.sub(r"<[^>]+>", "|", r) for r in table.split("<tr>")[2:]]


def test_each_target_gets_its_strongest_score_test():
    leads = _screen_leads(_doc())
    assert leads == {"definition:side": "coefficient_derivative:side:r, −log₁₀ p 157",
                     "output:p_m": "sensor_scale:p_m, −log₁₀ p 80.5",
                     "drift:p": "missing_derivative:p:r, −log₁₀ p 4"}
    assert list(leads)[0] == "definition:side"     # strongest first


def test_report_table_puts_the_score_test_beside_the_residual_tests():
    rows = _rows(report_section(_doc()))
    p_m = next(r for r in rows if "output p_m" in r)
    assert "scale p=0.33" in p_m and "sensor_scale:p_m, −log₁₀ p 80.5" in p_m
    assert "missing_derivative:p:r" in next(r for r in rows if "equation p" in r)
    assert "—" in next(r for r in rows if "output r_m" in r)     # NaN statistic not shown
    # targets without a residual test (definitions, inputs) get their own row
    assert any("definition side" in r and "157" in r for r in rows)


def test_no_screen_no_score_column_values():
    doc = _doc()
    doc["rounds"] = []
    assert _screen_leads(doc) == {}
    rows = _rows(report_section(doc))
    assert all("−log₁₀" not in r for r in rows)


# ---------------------------------------------------------------------------
# exact-geometry equations get no aerodynamic regressors (session 47: the bank-angle
# equation of a new user's lateral model was offered β·δa)
# ---------------------------------------------------------------------------

def _lateral_records():
    import numpy as np
    from vsidgen.discrepancy.locate import LocateRecord

    rng = np.random.default_rng(3)
    n, dt = 1200, 0.02
    t = np.arange(n) * dt
    da = np.sign(np.sin(0.7 * t)) * 0.05
    beta = 0.05 * np.sin(0.9 * t) + 0.002 * rng.standard_normal(n)
    p = 0.2 * np.sin(1.3 * t + 0.4)
    phi = np.cumsum(p) * dt
    X = np.column_stack([beta, p, phi])
    # the bank-angle equation error: a p-gyro scale error (0.05 p) plus a β·δa-shaped part
    err = 0.05 * p[:-1] + 4.0 * beta[:-1] * da[:-1] + 0.002 * rng.standard_normal(n - 1)
    f = np.zeros((n - 1, 3))
    f[:, 2] = p[:-1]
    xdot = f.copy()
    xdot[:, 2] += err
    rec = LocateRecord(name="r", t=t, u=da[:, None], y_meas=X, y_smooth=X, y_pred=X, y_sim=X,
                       x_smooth=X, xdot_fd=xdot, f_smooth=f)
    return [rec]


def test_kinematic_equation_is_tested_only_against_its_rates():
    from vsidgen.discrepancy.locate import locate

    kw = dict(state_names=["beta", "p", "phi"], input_names=["da"],
              output_names=["beta", "p", "phi"], roles={"beta": "beta", "p": "p"})
    free = locate(_lateral_records(), **kw)
    names = {r.name for r in free.states["phi"].regressors[:5]}
    assert any(n.startswith("prod:") or n.startswith("u:") for n in names)   # the old offer
    geo = locate(_lateral_records(), kinematics={"phi": frozenset({"p"})}, **kw)
    ev = geo.states["phi"]
    assert {r.name for r in ev.regressors} <= {"x:p", "1"}
    assert ev.regressors[0].name == "x:p" and ev.flagged
    # the other equations keep every regressor
    assert len(geo.states["beta"].regressors) == len(free.states["beta"].regressors)


def test_search_names_the_kinematic_equations_of_a_spec(tmp_path):
    from vsidgen.discrepancy.search import _kinematic_equations
    from vsidgen.model import load_model

    spec = tmp_path / "lat.yaml"
    spec.write_text("""
name: lat_k
states:
  beta: {unit: rad}
  p: {unit: rad/s}
  r: {unit: rad/s}
  phi: {unit: rad}
inputs:
  da: {unit: rad}
parameters:
  Lb: {unit: 1/s^2}
  Lp: {unit: 1/s}
  Nr: {unit: 1/s}
  Yb: {unit: 1/s}
  Lda: {unit: 1/s^2}
drift:
  beta: Yb*beta - r + 0.15*phi
  p: Lb*beta + Lp*p + Lda*da
  r: Nr*r
  phi: p + 0.1*r
outputs:
  beta_m: {unit: rad}
  p_m: {unit: rad/s}
  phi_m: {unit: rad}
observations:
  beta_m: beta
  p_m: p
  phi_m: phi
data:
  time: t
  inputs: {da: da}
  outputs: {beta_m: b, p_m: p, phi_m: f}
""")
    m = load_model(spec, generated_dir=tmp_path / "gen")
    kin = _kinematic_equations(m)
    assert kin == {"phi": frozenset({"p", "r"})}


# ---------------------------------------------------------------------------
# break points are placed where the variable moves, not where it rests (session 47)
# ---------------------------------------------------------------------------

def test_break_points_leave_out_a_rest_value():
    import numpy as np
    from vsidgen.discrepancy.locate import break_points

    t = np.arange(1500) * 0.02
    rudder = np.where((t > 5) & (t < 9), 0.08 * np.sin(2.1 * (t - 5)), 0.0)   # at rest: 0
    pts = break_points(rudder)
    assert len(pts) == 4 and all(b != 0.0 for _, b in pts)
    moving = rudder[rudder != 0.0]
    assert all(moving.min() < b < moving.max() for _, b in pts)
    # a variable without a rest value keeps its percentiles
    alpha = 0.1 + 0.05 * np.sin(0.7 * t)
    assert break_points(alpha) == [(k, float(f"{np.percentile(alpha, q):.6g}"))
                                   for k, q in (("hinge", 70), ("hinge", 85),
                                                ("hingelo", 15), ("hingelo", 30))]
    # a control that hardly moves gets no break
    assert break_points(np.where(t < 0.2, 0.01 * t, 0.0)) == []


# ---------------------------------------------------------------------------
# two refits that tie exactly are one model (session 47: a β vane 6 m ahead and a lateral
# accelerometer 5.5 m behind the CG reached the same ELBO to 1e-4 nats, and the finding said
# "another airspeed" would separate them)
# ---------------------------------------------------------------------------

def _trial(elbo, dof=1, converged=True):
    import types

    fit = types.SimpleNamespace(converged=converged)
    return types.SimpleNamespace(state=types.SimpleNamespace(elbo=elbo, fit=fit), dof=dof)


def test_an_exact_tie_is_one_model_in_two_parameterisations():
    from vsidgen.discrepancy.findings import TIE_NATS, exact_tie

    best = _trial(20218.20597)
    assert exact_tie(best, _trial(20218.20587))                    # the lateral record's pair
    assert not exact_tie(best, _trial(20218.20597 - 3 * TIE_NATS))
    assert not exact_tie(best, _trial(20218.20587, dof=2))
    assert not exact_tie(best, _trial(20218.20587, converged=False))


def test_an_exact_tie_reads_as_such_in_the_summary():
    from vsidgen.discrepancy.findings import EQUIVALENT_TEXT, summary_lines

    alt = {"key": "sensor_position:ay:r", "effect": "sensor_position", "target": "output:ay",
           "statistic": 42.41174, "equivalent": True, "separated_by": EQUIVALENT_TEXT}
    f = {"rank": 1, "key": "sensor_position:beta:r", "effect": "sensor_position",
         "target": "output:beta", "ambiguous": True, "parameters": {}, "explanation": "x",
         "evidence": {"statistic": 42.41193, "threshold": 15.37}, "alternatives": [alt]}
    lines = summary_lines({"findings": [f], "conclusion": "c"}, "f.json")
    text = "\n".join(lines)
    assert "exactly as well, the same model in another parameterisation" in text
    assert "another airspeed" not in text and "installed position" in text


def test_a_projected_refit_is_named_after_the_spec_it_extends(tmp_path):
    import types

    from vsidgen.discrepancy.search import projected_path

    cand = types.SimpleNamespace(key="coefficient_nonlinear:side_force:sq:dr")
    spec = tmp_path / "candidates" / "r1_04_coefficient_nonlinear_side_force_sq_dr.yaml"
    t = types.SimpleNamespace(candidate=cand, spec_path=spec)
    got = projected_path(tmp_path, 1, 2, t)       # third in the round's list, fourth by rank
    assert got == spec.with_name("r1_04_coefficient_nonlinear_side_force_sq_dr.projected.yaml")
    t = types.SimpleNamespace(candidate=cand, spec_path=None)
    assert projected_path(tmp_path, 1, 2, t).name.startswith("r1_03_")
