"""The score screen batches candidates in a canonical order (by key), so that a spec's batch
models — their parameter order and generated code — do not depend on the record's ranking and
the persistent compilation cache serves diagnose runs on other records (issue 16)."""

import random

from vsidgen.discrepancy import score
from vsidgen.discrepancy.base import model_info, registered_effects


def _candidates():
    info = model_info("specs/hfb320.yaml", dt=0.1)
    out = []
    for eff in registered_effects():
        out.extend(eff.applies_to(info))
    return [c for c in out if c.screenable]


def test_screen_batches_do_not_depend_on_the_candidates_order(monkeypatch, tmp_path):
    seen = []

    def fake_task(kind, payload, *args):
        cands = [c for g in payload for c in g] if kind == "shared" else payload
        seen[-1].append((kind, tuple(c.key for c in cands)))
        return {}

    monkeypatch.setattr(score, "_screen_task", fake_task)
    cands = _candidates()
    assert len(cands) > 50 and any(c.states for c in cands)
    for order in (list(cands), list(reversed(cands)), random.Random(3).sample(cands, len(cands))):
        seen.append([])
        score.screen(order, None, None, tmp_path, "t", generated_dir=tmp_path, det_std=1e-3)
    assert seen[0] == seen[1] == seen[2]
    plain = next(keys for kind, keys in seen[0] if kind == "batch")
    assert list(plain) == sorted(plain)
