"""Refits of state-adding candidates as one model family (one compilation per shape).

The reference is each candidate's own refit (:func:`vsidgen.discrepancy.search._refit_task`
with its own compiled model); the family path (:func:`~vsidgen.discrepancy.search._family_task`)
fits the same problems through one :class:`~vsidgen.estimator.ModelFamily`, whose objective
switches between the members at run time. Same optimum, a different compiled function: the
statistics agree to the optimiser's tolerance, and the family's functions are traced once.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from test_score_states import _simulate, fit_lin1

pytestmark = pytest.mark.xdist_group("test_family")


@pytest.fixture(scope="module")
def lin1(tmp_path_factory):
    from vsidgen.discrepancy import propose

    tmp = tmp_path_factory.mktemp("lin1f")
    st, info = fit_lin1(tmp, *_simulate(n=400))
    return tmp, st, info, propose(info)


def test_family_chunks_group_by_shape_and_spread_over_workers():
    from vsidgen.discrepancy.base import Candidate, NewParameter, NewState
    from vsidgen.discrepancy.family import family_chunks, family_shape

    def cand(key, n_states, n_par, fixed=()):
        pars = tuple(NewParameter(name=f"P_{key}_{j}", fixed=j in fixed) for j in range(n_par))
        sts = tuple(NewState(name=f"S_{key}_{j}", drift="0") for j in range(n_states))
        return Candidate(effect="e", key=key, target="t", explanation="", parameters=pars,
                         states=sts)

    a, b, c, d, e = (cand("a", 1, 2), cand("b", 1, 2), cand("c", 1, 2), cand("d", 2, 2),
                     cand("e", 0, 1))
    f = cand("f", 1, 2, fixed=(1,))
    assert family_shape(e) is None and family_shape(a) == (1, 2, 2) and family_shape(f) == (1, 2, 1)
    keys = lambda chunks: [[x.key for x in ch] for ch in chunks]  # noqa: E731
    assert keys(family_chunks([a, e, b, d, c, f], 1)) == [["a", "b", "c"], ["d"], ["f"]]
    assert keys(family_chunks([a, e, b, d, c, f], 2)) == [["a", "c"], ["b"], ["d"], ["f"]]
    assert keys(family_chunks([a, b, c], 8)) == [["a"], ["b"], ["c"]]


def test_member_outcomes_of_a_failed_family_task_are_per_candidate():
    from vsidgen.discrepancy.family import member_outcomes
    from vsidgen.engine import TaskOutcome, TaskStatus

    lost = TaskOutcome("family:a+b", TaskStatus.LOST, error="worker died", wall_s=3.0)
    out = member_outcomes(lost, ["a", "b"])
    assert [(o.key, o.status, o.error) for o in out] == [("a", TaskStatus.LOST, "worker died"),
                                                         ("b", TaskStatus.LOST, "worker died")]
    inner = [TaskOutcome("a", TaskStatus.DONE, value=1), TaskOutcome("b", TaskStatus.FAILED,
                                                                     error="E: x")]
    done = TaskOutcome("family:a+b", TaskStatus.DONE, value=inner)
    assert member_outcomes(done, ["a", "b"]) == inner
    single = TaskOutcome("a", TaskStatus.DONE, value=1)
    assert member_outcomes(single, ()) == [single]


@pytest.mark.slow
def test_a_family_refit_equals_each_candidates_own_refit(lin1, monkeypatch):
    from vsidgen.discrepancy.search import _family_task, _refit_task
    from vsidgen.engine import TaskStatus
    from vsidgen.estimator import StopReason, core, problem

    tmp, st, info, cands = lin1
    modes = [c for c in cands if c.effect == "missing_dynamics"]
    assert len(modes) >= 2
    members = modes[:2]
    made = []

    class Recorded(core.SwitchedObjective):
        def __init__(self, *a, **k):
            super().__init__(*a, **k)
            made.append(self)

    monkeypatch.setattr(problem, "SwitchedObjective", Recorded)
    own = []                     # models that compiled an objective of their own
    real_get = problem.get_objective

    def recorded_get(model, *a, **k):
        own.append(model.name)
        return real_get(model, *a, **k)

    monkeypatch.setattr(problem, "get_objective", recorded_get)
    fam = _family_task([(c, tmp / f"fam_{i}.yaml", f"t_fam_{i}") for i, c in enumerate(members)],
                       st, info, tmp / "gen", 200)
    assert [o.key for o in fam] == [c.key for c in members]
    assert all(o.status is TaskStatus.DONE for o in fam), [o.error for o in fam]
    # stage 0 (θ fixed), stages 1-2 and the validation-free evaluation: one switched
    # objective per problem structure, each traced once for both members
    assert made and all(len(o.models) == 2 for o in made)
    assert not [n for n in own if n.startswith("t_fam_")], own
    assert all(v <= 1 for o in made for v in o.traces.values()), [o.traces for o in made]
    for i, (c, o) in enumerate(zip(members, fam)):
        ro_f, _ = o.value
        ro_r, _ = _refit_task(c, st, info, tmp / f"own_{i}.yaml", f"t_own_{i}", tmp / "gen", 200)
        assert ro_f.state.model.drift is not ro_r.state.model.drift
        assert ro_f.elbo_ref == pytest.approx(ro_r.elbo_ref, rel=1e-9, abs=1e-7)
        # both stop when the Newton decrement λ²/2 < 1e-3 nats: each ELBO is within about
        # that of the common optimum (the rounding of the two compiled functions differs, so
        # the iterations may stop one step apart)
        fa, fr = ro_f.state.fit, ro_r.state.fit
        # a refit may also stop at its iteration limit crawling along a flat valley (the
        # mode's time constant; seen for the own refit of missing_dynamics:x:x on one
        # machine, λ²/2 = 0.0098 nats left after 400 iterations, while the family's converged):
        # it is then λ²/2 from the optimum by the quadratic model, and the tolerances grow by
        # that distance (ELBO) and by √(2·λ²/2) standard errors (θ)
        left = []
        for f in (fa, fr):
            if f.converged:
                left.append(1e-3)
            else:
                assert f.stop_reason is StopReason.ITERATION_LIMIT, (c.key, f.status)
                assert np.isfinite(f.newton_decrement) and f.newton_decrement < 0.05, f.status
                left.append(float(f.newton_decrement))
        assert fa.converged or fr.converged, c.key
        assert ro_f.state.elbo == pytest.approx(ro_r.state.elbo, abs=2e-3 + sum(left)), c.key
        assert fa.parameter_names == fr.parameter_names
        # a point whose Newton decrement is λ²/2 < 1e-3 lies within √(2·1e-3) ≈ 0.045
        # standard errors of the optimum (in the Hessian's metric): two such points within 0.09
        se = np.where(np.isfinite(fr.std_errors), fr.std_errors, np.inf)
        reach = sum(np.sqrt(2 * x) for x in left)
        assert np.all(np.abs(fa.theta - fr.theta) <= reach * se + 1e-9), (c.key, fa.theta, fr.theta, se)


def test_a_family_refit_that_raises_is_that_candidates_failure(lin1, monkeypatch):
    from vsidgen.discrepancy import search
    from vsidgen.engine import TaskStatus

    from vsidgen.discrepancy.refit import RefitOutcome

    tmp, st, info, cands = lin1
    members = [c for c in cands if c.effect == "missing_dynamics"][:2]

    def second_fails(c, *a, **k):
        if c.key == members[1].key:
            raise ValueError("boom\nsecond line")
        return RefitOutcome(notes=["first"])

    monkeypatch.setattr(search, "staged_refit", second_fails)
    out = search._family_task([(c, tmp / f"ff_{i}.yaml", f"t_ff_{i}")
                               for i, c in enumerate(members)], st, info, tmp / "gen", 200,
                              deadline=None)
    assert out[0].status is TaskStatus.DONE and out[0].value[0].notes == ["first"]
    assert (out[1].status, out[1].error) == (TaskStatus.FAILED, "ValueError: boom")


def test_a_member_whose_spec_cannot_be_built_fails_alone(lin1, monkeypatch):
    from vsidgen.discrepancy import search
    from vsidgen.discrepancy.refit import RefitOutcome
    from vsidgen.engine import TaskStatus

    tmp, st, info, cands = lin1
    members = [c for c in cands if c.effect == "missing_dynamics"][:2]
    real_write = search.write_candidate

    def first_unwritable(c, *a, **k):
        if c.key == members[0].key:
            raise OSError("disk full")
        return real_write(c, *a, **k)

    monkeypatch.setattr(search, "write_candidate", first_unwritable)
    monkeypatch.setattr(search, "staged_refit", lambda c, *a, **k: RefitOutcome(notes=[c.key]))
    out = search._family_task([(c, tmp / f"fw_{i}.yaml", f"t_fw_{i}")
                               for i, c in enumerate(members)], st, info, tmp / "gen", 200)
    assert (out[0].status, out[0].error) == (TaskStatus.FAILED, "OSError: disk full")
    assert out[1].status is TaskStatus.DONE and out[1].value[0].notes == [members[1].key]


def test_a_family_refit_past_its_deadline_is_cancelled_per_candidate(lin1):
    import time

    import dataclasses

    from vsidgen.discrepancy.family import TaskDeadline
    from vsidgen.discrepancy.search import _family_task
    from vsidgen.engine import TaskStatus

    tmp, st, info, cands = lin1
    members = [c for c in cands if c.effect == "missing_dynamics"][:2]
    past = TaskDeadline.of(time.monotonic() - 1.0)
    assert past.passed() and not TaskDeadline.of(time.monotonic() + 60.0).passed()
    # in another process the wall-clock time decides
    assert dataclasses.replace(past, pid=-1, monotonic=math.inf).passed()
    assert not dataclasses.replace(past, pid=-1, wall=time.time() + 60.0).passed()
    out = _family_task([(c, tmp / f"fc_{i}.yaml", f"t_fc_{i}") for i, c in enumerate(members)],
                       st, info, tmp / "gen", 200, deadline=past)
    assert [o.status for o in out] == [TaskStatus.CANCELLED, TaskStatus.CANCELLED]


@pytest.mark.slow
def test_a_round_with_a_family_gives_the_per_candidate_findings(lin1):
    """The whole diagnose round (serial engine): the state-adding candidates of one shape
    refitted as one family give the trials of the per-candidate path (``gated=False``)."""
    import json

    from vsidgen.discrepancy import search

    tmp, st, info, cands = lin1
    data = tmp / "lin1.csv"
    docs, logs = {}, {}
    for fam in (True, False):
        out = tmp / f"diag_{fam}"
        msgs: list[str] = []
        search.run_diagnose(tmp / "lin1.yaml", [data], out=out, max_rounds=1, max_candidates=3,
                            effects=["missing_dynamics"], numerics=False, noise_model=False,
                            workers=1, gated=fam, progress=msgs.append)
        docs[fam] = json.loads((out / "findings.json").read_text())
        logs[fam] = "\n".join(msgs)
    assert "one compilation" in logs[True] and "one compilation" not in logs[False]
    g, s = docs[True], docs[False]
    assert [f["key"] for f in g["findings"]] == [f["key"] for f in s["findings"]]
    tg = {t["key"]: t for t in g["rounds"][0]["trials"]}
    ts = {t["key"]: t for t in s["rounds"][0]["trials"]}
    assert list(tg) == list(ts) and len(tg) >= 2
    for k in tg:
        assert tg[k]["statistic"] == pytest.approx(ts[k]["statistic"], abs=1e-2), k
