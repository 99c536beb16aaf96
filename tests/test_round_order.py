"""A round examines its candidates in rank order: the refits ranked above a transport delay
run before the delay's profile, those ranked below it after (before, every refit ran first and
the profiles last, so under a time limit a delay ranked third waited behind weaker refits:
hfb_de_lag_0.15_s1 stopped at its limit with the delay pending after four C_m hinge refits
whose score statistics were 20–40 times smaller). The trials come back in the order the
decision expects: refits in rank order, then the profiled delays; with the keys of the
candidates the round's refit deadline left unrefitted (none starts after the first is cut)."""

from __future__ import annotations

import types

from vsidgen.discrepancy import search
from vsidgen.engine import TaskOutcome, TaskStatus


class _Engine:
    def __init__(self, log, cancel_at=None):
        self.log, self.cancel_at = log, cancel_at

    def run(self, fn, tasks, *, deadline=None, on_done=None):
        out = []
        for key, _ in tasks:
            self.log.append(("refit", key))
            status = TaskStatus.CANCELLED if key == self.cancel_at else TaskStatus.DONE
            out.append(TaskOutcome(key, status, value=key))
        return out


def _plan(keys, profiled):
    cands = [types.SimpleNamespace(key=k, info={}) for k in keys]
    ranked = [(10.0 - i, None, c, None) for i, c in enumerate(cands)]
    by_key = {c.key: (i, None, c, None) for i, c in enumerate(cands)}
    tasks = [(c.key, ("one",)) for i, c in enumerate(cands) if i not in profiled]
    # the engine receives them in any order: the plan's rank decides
    return search._RoundPlan(ranked, [f"{k}.yaml" for k in keys], profiled, {}, tasks[::-1],
                             by_key)


def _run(monkeypatch, keys, profiled, cancel_at=None):
    log = []

    def delay_trial(c, score, current, path, name, **kw):
        log.append(("profile", c.key))
        return types.SimpleNamespace(key=c.key, state=None, refit=None,
                                     to_json=lambda: {"key": c.key})

    monkeypatch.setattr(search, "delay_trial", delay_trial)
    monkeypatch.setattr(search, "_trial_of", lambda o, c, score, sr, path, current: o.key)
    monkeypatch.setattr(search, "_refit_done", lambda *a, **k: None)
    run = types.SimpleNamespace(progress=None, engine=_Engine(log, cancel_at), deadline=None,
                                say=lambda *a: None, gen=None, max_iter=10, alpha=0.01)
    st = types.SimpleNamespace(unfinished={"pending": list(keys), "refitted": []})
    current = types.SimpleNamespace(model=types.SimpleNamespace(name="m"))
    trials, cut = search._refit_round(run, st, 1, _plan(keys, profiled), current)
    return log, trials, cut


def test_refits_and_delay_profiles_run_in_rank_order(monkeypatch):
    keys = ["lag", "skew", "delay_de", "hinge1", "hinge2", "delay_th", "sq"]
    log, trials, cut = _run(monkeypatch, keys, [2, 5])
    assert log == [("refit", "lag"), ("refit", "skew"), ("profile", "delay_de"),
                   ("refit", "hinge1"), ("refit", "hinge2"), ("profile", "delay_th"),
                   ("refit", "sq")]
    assert trials[:5] == ["lag", "skew", "hinge1", "hinge2", "sq"]
    assert [t.key for t in trials[5:]] == ["delay_de", "delay_th"] and cut == []


def test_a_delay_ranked_first_is_profiled_first_and_a_cancelled_refit_cuts_the_rest(monkeypatch):
    log, _, _ = _run(monkeypatch, ["delay_de", "lag", "hinge"], [0])
    assert log[0] == ("profile", "delay_de")
    log, trials, cut = _run(monkeypatch, ["skew", "lag", "delay_de", "hinge"], [2],
                            cancel_at="lag")
    # the delay was never profiled, the hinge never started; the skew's trial is kept
    assert log == [("refit", "skew"), ("refit", "lag")]
    assert trials == ["skew"] and cut == ["lag", "delay_de", "hinge"]
