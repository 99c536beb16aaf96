"""Standard-error reliability flags: raised only with a cause, each naming what to act on.

* A well-posed linear model (the Kalman-checked test model of test_estimator) fitted to its
  own kind of data carries no flag: ``std_errors_reliable`` is True.
* The same model with the elevator term written as a sum of two parameters (b2a + b2b: only
  the sum is identifiable) is flagged, and the flag names both parameters.
* The rules of :func:`std_error_flags` on hand-made inputs: a pair correlated beyond the
  stated limit, a tiny eigenvalue of the correlation matrix, a 95 % interval crossing a
  bound, a stop short of an optimum.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from tests.test_estimator import C_OUT, lin_model, make_record
from vsidgen.estimator import FitOptions, StdErrorIssue, StopReason, fit
from vsidgen.estimator.fit import CORRELATION_LIMIT, EIGENVALUE_LIMIT, std_error_flags
from vsidgen.metadata import Parameter
from vsidgen.model import Model


def _sum_model():
    """The linear test model with b2 written as b2a + b2b (only the sum enters)."""
    base = lin_model()

    def drift(x, u, p):
        A = jnp.array([[p[0], 1.0], [p[1], p[2]]])
        return A @ x + jnp.array([0.0, p[3] + p[4]]) * u[0]

    def output(x, u, p):
        return jnp.asarray(C_OUT) @ x

    pars = base.parameters[:3] + (Parameter("b2a"), Parameter("b2b"))
    return Model(name="lin_sum", drift=drift, output=output, states=base.states, inputs=base.inputs,
                 outputs=base.outputs, parameters=pars, process_noise=base.process_noise,
                 measurement_noise=base.measurement_noise)


@pytest.fixture(scope="module")
def rec():
    return make_record(300, seed=4)


def test_identifiable_converged_fit_has_no_flag(rec):
    res = fit(lin_model(), [rec], options=FitOptions(noise_start="data"))
    assert res.converged, res.status
    assert res.std_error_flags == () and res.std_errors_reliable
    assert not [w for w in res.warnings if not w.get("reliable", True)]


def test_parameters_entering_only_as_a_sum_are_flagged_and_named(rec):
    res = fit(_sum_model(), [rec], options=FitOptions(noise_start="data", max_iter=60))
    assert not res.std_errors_reliable
    issues = {f.issue for f in res.std_error_flags}
    assert issues & {StdErrorIssue.HESSIAN_NOT_PD, StdErrorIssue.NEAR_SINGULAR}, res.std_error_flags
    named = {p for f in res.std_error_flags
             if f.issue in (StdErrorIssue.HESSIAN_NOT_PD, StdErrorIssue.NEAR_SINGULAR) for p in f.parameters}
    assert {"b2a", "b2b"} <= named, res.std_error_flags
    assert any("b2a" in w["message"] and "fix one" in w["message"] for w in res.warnings)


NAMES = ["a", "b", "c"]
FREE = dict(kind=np.zeros(3, int), lo=np.zeros(3), hi=np.ones(3), positive_definite=True)


def test_rules_correlated_pair():
    R = np.eye(3)
    R[0, 1] = R[1, 0] = -(1 + CORRELATION_LIMIT) / 2
    (f,) = std_error_flags(NAMES, np.ones(3), np.ones(3), R, **FREE)
    assert f.issue is StdErrorIssue.NEAR_SINGULAR and f.parameters == ("a", "b")
    R[0, 1] = R[1, 0] = -0.99  # strong but below the limit: valid, large s.e.
    assert std_error_flags(NAMES, np.ones(3), np.ones(3), R, **FREE) == ()


def test_rules_three_way_collinearity_without_a_strong_pair():
    # c ≈ (a + b)/√2 direction: pairwise correlations ≈ 0.707, smallest eigenvalue ≈ 0
    v = np.array([1.0, 1.0, -np.sqrt(2.0)]) / 2.0
    R = np.eye(3) - (1 - EIGENVALUE_LIMIT / 10) * np.outer(v, v)
    d = np.sqrt(np.diag(R))
    R = R / np.outer(d, d)
    assert np.max(np.abs(R - np.eye(3))) < CORRELATION_LIMIT
    (f,) = std_error_flags(NAMES, np.ones(3), np.ones(3), R, **FREE)
    assert f.issue is StdErrorIssue.NEAR_SINGULAR and set(f.parameters) == {"a", "b", "c"}


def test_rules_bound_and_not_converged():
    kw = dict(FREE, kind=np.array([1, 3, 0]), lo=np.array([0.0, -1.0, 0.0]), hi=np.array([1.0, 1.0, 1.0]))
    theta, se = np.array([0.5, 0.9, 5.0]), np.array([0.2, 0.06, 10.0])
    # a: 0.5 from its lower bound with s.e. 0.2 (2.5 s.e.): fine; b: 0.1 from 1 with s.e. 0.06: flagged
    (f,) = std_error_flags(NAMES, theta, se, np.eye(3), **kw)
    assert f.issue is StdErrorIssue.AT_BOUND and f.parameters == ("b",)
    flags = std_error_flags(NAMES, theta, se, np.eye(3), **dict(kw, kind=np.zeros(3, int)),
                            stop_reason=StopReason.ITERATION_LIMIT)
    assert [f.issue for f in flags] == [StdErrorIssue.NOT_CONVERGED]
    assert std_error_flags(NAMES, theta, se, np.eye(3), **dict(kw, kind=np.zeros(3, int)),
                           stop_reason=StopReason.NEWTON_DECREMENT) == ()


def test_rules_deterministic_limit_not_reached():
    kw = dict(FREE, stop_reason=StopReason.NEWTON_DECREMENT)
    (f,) = std_error_flags(NAMES, np.ones(3), np.ones(3), np.eye(3), **kw,
                           limit={"reached": False, "states": ["phi"]})
    assert f.issue is StdErrorIssue.DETERMINISTIC_LIMIT and "phi" in f.detail
    assert std_error_flags(NAMES, np.ones(3), np.ones(3), np.eye(3), **kw,
                           limit={"reached": True, "states": ["phi"]}) == ()


# ----------------------------------------------------------------- parameters at a bound
def _bounded(lo, hi, *, alone=False):
    """The linear test model with a22 (true −0.8) bounded to [lo, hi]; ``alone``: the other
    parameters and the noise fixed at their true values (a22 the only free θ)."""
    import dataclasses

    from tests.test_estimator import A_TRUE, B_TRUE

    true = {"a11": A_TRUE[0, 0], "a21": A_TRUE[1, 0], "b2": B_TRUE[1]}
    base = lin_model(est_noise=not alone)
    pars = tuple(dataclasses.replace(p, lower=lo, upper=hi) if p.name == "a22"
                 else dataclasses.replace(p, fixed=True, initial=float(true[p.name])) if alone
                 else p for p in base.parameters)
    return dataclasses.replace(base, parameters=pars)


def _saturated_start(model, rec, res, name, z):
    """A warm start at ``res`` with the free parameter ``name`` moved to z (its transform
    saturated at a bound)."""
    from vsidgen.estimator import WarmStart

    s = np.array(res.decision["s"], float)
    free = [p.name for p in model.parameters if not p.fixed]
    s[free.index(name)] = z
    return WarmStart.from_decision({"s": s, "records": res.decision["records"]})


def test_a_parameter_stuck_at_a_saturated_bound_is_released_to_the_interior_optimum(rec):
    """a22 bounded to [−60, 0] (the other θ and the noise fixed at their true values) and
    started saturated at −60 (the sigmoid's derivative e^{−40}: the gradient in z vanishes
    whichever way the ELBO slopes). Before: a stop there with the s.e. NaN and an
    identifiability warning. Now the bound is probed, the ELBO rises inwards, the fit
    continues and reaches the optimum of the same model without bounds (the reference), and
    says so. (With everything free the others adapt to a22 = −60 while it is stuck — the
    y1 measurement noise collapsed to 4e-6 — and the release then ends in that poorer
    basin: the bound is released, but what adapted to it is not restarted.)"""
    import dataclasses

    m = _bounded(-60.0, 0.0, alone=True)
    free = fit(dataclasses.replace(m, parameters=tuple(
        dataclasses.replace(p, lower=None, upper=None) for p in m.parameters)), [rec],
        options=FitOptions(noise_start="data"))
    start = fit(m, [rec], options=FitOptions(noise_start="data"))
    assert start.converged
    res = fit(m, [rec], options=FitOptions(warm_start=_saturated_start(m, rec, start, "a22", -40.0)))
    assert res.converged, res.status
    i = list(res.parameter_names).index("a22")
    # both converged (Newton decrement < 1e-3 nats): the same optimum up to that tolerance
    assert abs(res.theta[i] - free.theta[i]) < 0.2 * free.std_errors[i]
    assert abs(res.elbo - free.elbo) < 0.01
    assert any(w["code"] == "left_bound" and w["parameters"] == ["a22"] for w in res.warnings)
    assert res.std_error_flags == () and np.isfinite(res.std_errors[i])


def test_an_active_bound_holds_and_only_that_parameter_loses_its_standard_error(rec):
    """a22 bounded to [−60, −3] (the data want −0.8): the bound is active — probing inwards
    lowers the ELBO — so the parameter stays at −3; it is flagged AT_BOUND by name (not an
    identifiability problem) and the other parameters keep finite standard errors."""
    m = _bounded(-60.0, -3.0)
    start = fit(m, [rec], options=FitOptions(noise_start="data"))
    res = fit(m, [rec], options=FitOptions(warm_start=_saturated_start(m, rec, start, "a22", 40.0)))
    i = list(res.parameter_names).index("a22")
    assert abs(res.theta[i] + 3.0) < 1e-6
    assert not any(w["code"] == "left_bound" for w in res.warnings)
    issues = {f.issue: f for f in res.std_error_flags}
    assert StdErrorIssue.AT_BOUND in issues and issues[StdErrorIssue.AT_BOUND].parameters == ("a22",)
    assert StdErrorIssue.HESSIAN_NOT_PD not in issues
    others = [j for j in range(len(res.theta)) if j != i]
    assert np.all(np.isfinite(res.std_errors[others])) and np.isnan(res.std_errors[i])


def test_limit_warning_says_what_happened_without_nan():
    """When no continuation stage after the first converged the warning says so (it printed
    'changed the ELBO by nan nats' and 'std 1 × the first stage's')."""
    from vsidgen.estimator.fit import _limit_message

    nan = float("nan")
    text = _limit_message({"states": ["phi"], "std": {"phi": 0.0065}, "stages": [{}] * 5,
                           "elbo_change": nan, "theta_change_se": nan, "scale": 1.0})
    assert "nan" not in text and "4 tried" in text and "phi 0.0065" in text
    text = _limit_message({"states": ["phi"], "std": {"phi": 1e-4}, "stages": [{}] * 3,
                           "elbo_change": 0.3, "theta_change_se": 0.2, "scale": 0.01})
    assert "0.3 nats" in text and "0.01 ×" in text
