"""Starting state means of states no output measures directly (:func:`invert_outputs`).

A new user's body-axis model (states u, w, q, θ; outputs V = √(u² + w²), α = atan2(w, u))
started at u = w = 0, where its airspeed vanishes and the pitching moment's q·c/(2V) is not
finite: the fit stopped before its first iteration. The reference here is the kinematic
inversion written out by hand (u = V cos α, w = V sin α), on a record made with numpy.
"""

from __future__ import annotations

import textwrap

import numpy as np

from vsidgen.data import load_record
from vsidgen.estimator import FitOptions, Problem
from vsidgen.model import load_model

BODY_AXES = textwrap.dedent("""
    name: body_axes
    states:
      u: {unit: m/s}
      w: {unit: m/s}
      q: {unit: rad/s}
      theta: {unit: rad}
      lag: {unit: rad, description: a state no output sees}
    inputs:
      de: {unit: rad}
    outputs:
      V: {unit: m/s}
      alpha: {unit: rad}
      q: {unit: rad/s}
      theta: {unit: rad}
    constants:
      c: {value: 2.0, unit: m}
    parameters:
      Za: {unit: 1/s}
      Ma: {unit: 1/s^2}
      Mq: {unit: 1/rad}
      Mde: {unit: 1/s^2}
    definitions:
      Vt: sqrt(u**2 + w**2)
      a: atan2(w, u)
    drift:
      u: -q*w - 9.81*sin(theta)
      w: q*u + 9.81*cos(theta) + Za*a*Vt
      q: Ma*a + Mq*q*c/(2*Vt) + Mde*lag
      theta: q
      lag: 10*(de - lag)
    observations:
      V: Vt
      alpha: a
      q: q
      theta: theta
    noise:
      process: {states: [u, w, q, theta]}
    data:
      time: t_s
      inputs: {de: de_rad}
      outputs: {V: v_mps, alpha: alpha_rad, q: q_radps, theta: theta_rad}
    """)


def _record(tmp_path, n=120):
    rng = np.random.default_rng(3)
    t = np.arange(n) * 0.02
    V = 70.0 + 0.5 * np.sin(0.7 * t) + 0.01 * rng.normal(size=n)
    alpha = 0.05 + 0.02 * np.sin(2.1 * t) + 1e-4 * rng.normal(size=n)
    alpha[17] = np.nan                       # a missing sample keeps its start
    cols = {"t_s": t, "de_rad": 0.01 * np.sign(np.sin(t)), "v_mps": V, "alpha_rad": alpha,
            "q_radps": 0.04 * np.cos(2.1 * t), "theta_rad": 0.05 + 0.01 * np.sin(t)}
    path = tmp_path / "rec.csv"
    np.savetxt(path, np.column_stack(list(cols.values())), delimiter=",",
               header=",".join(cols), comments="", fmt="%.15g")
    return path, V, alpha


def _problem(tmp_path, text, name="body"):
    """(model, Problem on the record of :func:`_record`, V, α) of the spec ``text``."""
    spec = tmp_path / f"{name}.yaml"
    spec.write_text(text)
    model = load_model(spec, generated_dir=tmp_path / f"gen_{name}")
    path, V, alpha = _record(tmp_path)
    return model, Problem(model, [load_record(model, path)], FitOptions(bucket=False)), V, alpha


def test_body_axis_velocities_start_at_the_kinematic_inversion(tmp_path):
    model, P, V, alpha = _problem(tmp_path, BODY_AXES)
    rec = P.records[0]
    s, [(mu, _)] = P.initial(FitOptions())
    names = list(model.state_names)
    ok = np.isfinite(alpha)
    np.testing.assert_allclose(mu[ok, names.index("u")], (V * np.cos(alpha))[ok], rtol=1e-9)
    np.testing.assert_allclose(mu[ok, names.index("w")], (V * np.sin(alpha))[ok], rtol=1e-7,
                               atol=1e-9)
    # α missing at sample 17: V alone does not determine u and w (they would go to 45°):
    # interpolated between samples 16 and 18
    for i, ref in ((names.index("u"), V * np.cos(alpha)), (names.index("w"), V * np.sin(alpha))):
        assert mu[17, i] == 0.5 * (mu[16, i] + mu[18, i])
        assert abs(mu[17, i] - 0.5 * (ref[16] + ref[18])) < 1e-6
    # measured states at their measurements, the state no output sees at 0
    np.testing.assert_allclose(mu[:, names.index("q")], np.asarray(rec.y)[:, 2])
    assert np.all(mu[:, names.index("lag")] == 0.0)
    # the objective is finite at the start (it was not: V = 0 in q·c/(2V))
    assert np.isfinite(P.value(s, [(mu, _)]))
    # the zero start is still there on request
    _, [(mu0, _)] = P.initial(FitOptions(init_states="zero"))
    assert np.all(mu0 == 0.0)


def test_states_the_outputs_determine_are_not_held_by_the_release_start(tmp_path):
    """u and w, solved from V and α at every sample but one, count as measured through the
    outputs (:attr:`Problem.output_solved`): the release start, which holds unmeasured states
    with process noise deterministic first (they have no data scale of their own), has
    nothing to hold and is not run; a state no output sees (``lag``) is not solved. Without α
    the outputs do not determine u and w: they are not solved (the release start holds them)."""
    import importlib
    import time

    fit_module = importlib.import_module("vsidgen.estimator.fit")

    model, P, _, _ = _problem(tmp_path, BODY_AXES)
    names = list(model.state_names)
    assert {names[i] for i in P.output_solved} == {"u", "w"}
    assert fit_module._release_start(P, FitOptions(max_iter=5), time.perf_counter()) is None
    # V only: u and w are not determined at any sample
    no_alpha = (BODY_AXES.replace("  alpha: {unit: rad}\n", "")
                .replace("  alpha: a\n", "").replace(" alpha: alpha_rad,", ""))
    assert "alpha" not in no_alpha
    _, P2, _, _ = _problem(tmp_path, no_alpha, "body_v")
    assert P2.output_solved == frozenset()


def test_a_gust_beside_the_body_velocity_leaves_u_solved(tmp_path):
    """A user's gust state W in the air-relative velocity (α = atan2(w − W, u)): the outputs
    see w − W only, so w and W are not determined, but u still is — it starts at V cos α
    (the inversion written by hand), not at 0, where the airspeed vanishes and the
    fit stopped before its first iteration ("gradient is not finite"). w and W keep their
    start, and only u counts as solved."""
    gust = (BODY_AXES.replace("name: body_axes", "name: body_gust")
            .replace("  lag: {unit: rad, description: a state no output sees}\n",
                     "  lag: {unit: rad, description: a state no output sees}\n"
                     "  W: {unit: m/s, description: vertical gust}\n")
            .replace("  Vt: sqrt(u**2 + w**2)\n  a: atan2(w, u)\n",
                     "  Vt: sqrt(u**2 + (w - W)**2)\n  a: atan2(w - W, u)\n")
            .replace("  lag: 10*(de - lag)\n", "  lag: 10*(de - lag)\n  W: -W/0.5\n")
            .replace("process: {states: [u, w, q, theta]}", "process: {states: [u, w, q, theta, W]}"))
    assert "atan2(w - W, u)" in gust and "  W: -W/0.5" in gust
    model, P, V, alpha = _problem(tmp_path, gust, "gust")
    s, [(mu, r)] = P.initial(FitOptions())
    names = list(model.state_names)
    ok = np.isfinite(alpha)
    np.testing.assert_allclose(mu[ok, names.index("u")], (V * np.cos(alpha))[ok], rtol=1e-7)
    assert np.all(mu[:, names.index("w")] == 0.0) and np.all(mu[:, names.index("W")] == 0.0)
    assert {names[i] for i in P.output_solved} == {"u"}
    assert np.isfinite(P.value(s, [(mu, r)]))


def test_determined_columns_reads_the_null_space():
    from vsidgen.estimator.problem import _determined_columns

    J = np.array([[[1.0, 0.0, 0.0], [0.0, 1.0, -1.0]],       # u; w − W
                  [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]])       # u; w (W unseen)
    d = _determined_columns(J)
    assert d.tolist() == [[True, False, False], [True, True, False]]
    full = _determined_columns(np.eye(3)[None])
    assert full.tolist() == [[True, True, True]]
