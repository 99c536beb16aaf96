"""The deterministic-limit statistic of an input-carrying candidate compares like with like
(session 46; ``search.limit_correction``).

A new user's Twin Otter lateral model (φ̇ = p + tan θ₀ r without process noise, the rate
gyros' noise at its floor) under ``vsidgen diagnose --time-limit``: a rudder lag and a Padé
rudder delay ended at their nesting point (2e-5 s), 0.26 (2ΔELBO) below their nested
reference, yet were reported at 2ΔELBO 1.323e7, p = 0, and the lag led the unfinished
round. The limit continuation took *every* deterministic state to zero process noise — the
user's φ as well as the added lag state. The candidate's side is a fit (its noise refitted at
each std); the nested reference is a smoothing at the current model's fixed noise, which
cannot follow φ's constraint when the rates are pinned by their measurements: the reference
fell to ELBO −6.59e6 (booked as an "x₀ entropy" of −6.61e6). Now only the added states go to
the limit; the model's own states stay at the quasi-deterministic std at which the round's
reference holds them. And a refit that ends below its nesting point is flagged
(``below_nesting_point``) whatever statistic a correction gives it.

The record is simulated here with numpy (Euler at the sample rate: a rate ``x`` measured
almost exactly and its integral ``phi`` with a small process noise the model does not have);
no lag in the data, so the lag candidate must stay at its nesting point and not be significant.
"""

from __future__ import annotations

import dataclasses
import math
import types

import numpy as np
import pytest

DT = 0.05

SPEC = """
name: lin2phi
description: a rate and its integral; the integral has no process noise (like a bank angle)
states:
  x: {unit: "1", description: rate}
  phi: {unit: "1", description: integral of the rate}
inputs:
  u: {unit: "1", description: input}
outputs:
  y: {unit: "1", description: measured rate}
  phi_m: {unit: "1", description: measured integral}
parameters:
  A: {unit: 1/s, description: pole}
  B: {unit: 1/s, description: input gain}
drift:
  x: A*x + B*u
  phi: x
observations:
  y: x
  phi_m: phi
noise:
  process:
    states: [x]
  measurement:
    y: {floor: auto}
    phi_m: {floor: auto}
data:
  time: t
  inputs:
    u: u
  outputs:
    y: y
    phi_m: phi_m
"""


def _simulate(n=400, seed=5):
    """(t, u, y, phi_m): x' = −1.2 x + 2 u with process noise 0.08/√s, φ' = x with a small
    process noise 0.0015/√s (which the model lacks), Euler at DT; y to 1e-4, φ to 1e-4."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * DT
    u = np.zeros(n)
    for t0, w, a in ((1, 2, 1.0), (4, 1.5, -1.0), (7, 1, 1.0), (9, 1, -1.0), (13, 2, 0.8),
                     (17, 1.5, -0.8)):
        u += a * ((t >= t0) & (t < t0 + w))
    x = phi = 0.0
    xs, ps = np.empty(n), np.empty(n)
    for i in range(n):
        xs[i], ps[i] = x, phi
        x, phi = (x + DT * (-1.2 * x + 2.0 * u[i]) + 0.08 * math.sqrt(DT) * rng.standard_normal(),
                  phi + DT * x + 0.0015 * math.sqrt(DT) * rng.standard_normal())
    return t, u, xs + 1e-4 * rng.standard_normal(n), ps + 1e-4 * rng.standard_normal(n)


@pytest.fixture(scope="module")
def null_lag(tmp_path_factory):
    """(candidate, RefitOutcome, current FitState): the actuator-lag candidate of ``u`` refitted
    (staged, with the limit statistic) against the current model fitted as the diagnose
    refits hold it (φ quasi-deterministic, :func:`search._held_reference`)."""
    from vsidgen.data import load_records
    from vsidgen.discrepancy import propose
    from vsidgen.discrepancy.fitstate import diag_options, evaluated
    from vsidgen.discrepancy.search import model_info_of, staged_refit
    from vsidgen.estimator import fit
    from vsidgen.model import load_model

    tmp = tmp_path_factory.mktemp("limit_ref46")
    t, u, y, pm = _simulate()
    csv = tmp / "lin2phi.csv"
    np.savetxt(csv, np.column_stack([t, u, y, pm]), delimiter=",", header="t,u,y,phi_m",
               comments="")
    spec = tmp / "lin2phi.yaml"
    spec.write_text(SPEC)
    model = load_model(spec, generated_dir=tmp / "gen")
    records, _ = load_records(model, [csv], ())
    res = fit(model, list(records), options=diag_options(200))
    assert res.converged and res.deterministic_states == ("phi",)
    current = evaluated(spec, model, tuple(records), res, (), max_iter=200)
    info = model_info_of(current)
    cand = next(c for c in propose(info) if c.effect == "actuator_lag")
    out = staged_refit(cand, current, info, tmp / "lag.yaml", "lin2phi_lag",
                       generated_dir=tmp / "gen", max_iter=200)
    return cand, out, current


def test_the_limit_of_the_added_state_leaves_the_models_own_deterministic_state_held(null_lag):
    """Old code: φ taken to 1e-7 on both sides, the reference (fixed noise) lost 86 nats more
    than the candidate: a lag of 6e-5 s (no lag in the data) at 2ΔELBO 134 (quasi: 4.30)."""
    from vsidgen.discrepancy.refit import REFIT_DETERMINISTIC_STD, quasi_stds
    from vsidgen.discrepancy.search import lr_test

    cand, out, current = null_lag
    assert out.state.fit.converged
    d = out.limit_detail
    assert d is not None and out.limit_correction is not None, out.notes
    m2 = out.state.model
    q = quasi_stds(m2, out.state.records, REFIT_DETERMINISTIC_STD)
    added = [n for n in m2.state_names if n not in current.model.state_names]
    assert added and set(d["std"]) == {"phi", *added}
    # the user's φ stays where the current model (the round's reference) holds it ...
    assert d["std"]["phi"] == pytest.approx(q[m2.state_names.index("phi")])
    # ... and only the added state goes to its limit
    (a,) = added
    assert d["std"][a] < 0.1 * q[m2.state_names.index(a)]
    # like with like: the limit changes the statistic of a lag at its nesting point by ~nothing
    # (measured: quasi 4.2969, limit 4.2969; old code: limit 138.4)
    assert abs(out.limit_correction) < 0.5, d
    assert abs(d["statistic_limit"] - d["statistic_quasi"]) < 0.5, d
    # the reference in the limit is an ELBO of the same order as the candidate's, not a collapse
    assert abs(d["elbo_candidate"] - d["elbo_reference"]) < 10.0, d
    # the x0 entropy booked for the round's comparison is not inflated by the correction
    assert abs(out.x0_entropy) < 50.0, out.x0_entropy
    lam, p = lr_test(out.elbo_ref, out.state.elbo, cand.n_free)
    assert lam < 3.84 and p > 0.05, (lam, p, out.notes)     # measured: −0.012


def test_a_refit_below_its_nesting_point_is_flagged_whatever_its_corrected_statistic(null_lag):
    """A statistic corrected to another noise must not turn an optimiser failure into evidence
    (the Twin Otter rudder lag: 0.26 below its nesting point, reported at 1.3e7 and leading the
    unfinished round)."""
    from vsidgen.discrepancy.findings import leading_refit
    from vsidgen.discrepancy.refit import RefitVerdict
    from vsidgen.discrepancy.search import Trial, lr_test, trial_verdict

    cand, out, current = null_lag
    st = out.state
    corr = 1.3e7
    # the nested reference 0.13 nats above the refit at its own noise, a huge limit correction
    ro = dataclasses.replace(out, elbo_ref=st.elbo + 0.13 - 0.5 * corr, limit_correction=corr)
    assert ro.elbo_nesting == pytest.approx(st.elbo + 0.13)
    lam, p = lr_test(ro.elbo_ref, st.elbo, cand.n_free)
    assert lam > 1e6 and p < 1e-10
    verdict = trial_verdict(cand, st, lam, ro)
    assert verdict is RefitVerdict.BELOW_NESTING_POINT
    trial = Trial(cand, 1.0, st.spec_path, st, lam, cand.n_free, p, refit=ro,
                  statistic_vs_base=2.0 * (st.elbo - current.elbo), converged=True,
                  verdict=verdict)
    row = trial.to_json()
    assert row["verdict"] == "below_nesting_point"
    assert leading_refit({"refitted": [row]}, 0.01) is None
    # at its nesting point (within the tolerance) the same correction stays a statistic
    ok = dataclasses.replace(out, elbo_ref=st.elbo - 0.5 * corr, limit_correction=corr)
    assert trial_verdict(cand, st, lam, ok) is RefitVerdict.ORDINARY


def test_the_limit_is_not_taken_for_a_refit_below_its_nesting_point(null_lag):
    """``limit_correction`` leaves a refit that ended below its nesting point at its quasi
    statistic (flagged by its verdict), with a note, and spends no continuation on it."""
    from vsidgen.discrepancy.refit import RefitOutcome
    from vsidgen.discrepancy.search import limit_correction

    cand, out, current = null_lag
    st = out.state
    new_states = [n for n in st.model.state_names if n not in current.model.state_names]
    fresh = RefitOutcome(elbo_ref=st.elbo + 0.5)
    r0 = types.SimpleNamespace(elbo=st.elbo + 0.5, converged=True, decision=None)
    limit_correction(fresh, st.model, list(st.records), st.fit, (None, None, r0, None),
                     new_states, new_params=tuple(q.name for q in cand.parameters),
                     max_iter=200)
    assert fresh.limit_correction is None and fresh.limit_detail is None
    assert fresh.elbo_ref == st.elbo + 0.5
    assert any("below its nesting point" in n for n in fresh.notes), fresh.notes
