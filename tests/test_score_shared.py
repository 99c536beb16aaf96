"""The score screen's shared compilation of state-adding batches against the per-batch path.

:func:`vsidgen.discrepancy.score.screen_shared` evaluates every batch's Hessian blocks through
one :class:`~vsidgen.estimator.core.SwitchedObjective` per shape (models padded with inert
parameters, selected by a run-time index); the reference is
:func:`~vsidgen.discrepancy.score.screen_group`, each batch's own model and objective (the
path checked against a Kalman filter in test_score_states.py).
"""

from __future__ import annotations

import numpy as np
import pytest

from test_score_states import _simulate, fit_lin1

# one worker runs the whole module: its module-scoped fixtures are computed once
pytestmark = pytest.mark.xdist_group("test_score_shared")


@pytest.fixture(scope="module")
def lin1(tmp_path_factory):
    from vsidgen.discrepancy import propose

    tmp = tmp_path_factory.mktemp("lin1")
    st, info = fit_lin1(tmp, *_simulate(n=400))
    states = [c for c in propose(info) if c.screenable and c.states]
    return tmp, st, info, states


def test_shared_compilation_gives_the_per_batch_statistics(lin1, monkeypatch):
    from vsidgen.discrepancy.refit import REFIT_DETERMINISTIC_STD as DET
    from vsidgen.discrepancy.score import screen_group, screen_shared
    from vsidgen.estimator import core

    tmp, st, info, states = lin1
    # batches of one single-state candidate each: one shape, models with different parameters
    groups = [[c] for c in states if len(c.states) == 1]
    assert len(groups) >= 2
    made = []

    class Recorded(core.SwitchedObjective):
        def __init__(self, *a, **k):
            super().__init__(*a, **k)
            made.append(self)

    monkeypatch.setattr(core, "SwitchedObjective", Recorded)
    shared = screen_shared(groups, st, info, tmp / "shared", "s", "t_sh", generated_dir=tmp / "gen",
                           det_std=DET)
    ref = {}
    for i, g in enumerate(groups):
        ref.update(screen_group(g, st, info, tmp / "ref", f"b{i}", "t_ref",
                                generated_dir=tmp / "gen", det_std=DET))
    # one objective for the three batches, its Hessian blocks traced (compiled) once
    assert len(made) == 1 and len(made[0].models) == len(groups)
    assert made[0].traces["blocks"] == 1
    tested = 0
    for g in groups:
        k = g[0].key
        a, b = ref[k], shared[k]
        assert (a.tested, a.held, a.dof, a.note, a.ascent) == (b.tested, b.held, b.dof, b.note,
                                                             b.ascent), (a, b)
        if a.statistic is None:
            assert b.statistic is None
            continue
        tested += 1
        assert b.statistic == pytest.approx(a.statistic, rel=1e-8, abs=1e-10), (k, a, b)
        assert b.gain_rest == pytest.approx(a.gain_rest, rel=1e-6, abs=1e-9)
        for n in a.step:
            assert b.step[n] == pytest.approx(a.step[n], rel=1e-8, abs=1e-12)
    assert tested >= 1


def test_inert_padding_leaves_the_statistic_unchanged(lin1):
    """A batch model padded with inert free and fixed parameters (held in the test) gives its
    own statistics: the padded rows and columns of the gradient and Hessian are exact zeros."""
    from vsidgen.discrepancy.refit import REFIT_DETERMINISTIC_STD as DET
    from vsidgen.discrepancy.score import _batch_model, batch_statistics, padded_model
    from vsidgen.estimator import FitOptions, Problem
    from vsidgen.estimator.core import SwitchedObjective
    from vsidgen.model.dynamics import transition

    tmp, st, info, states = lin1
    g = [next(c for c in states if len(c.states) == 1)]
    m, bnames = _batch_model(g, st, info, tmp / "pad.yaml", "t_pad", generated_dir=tmp / "gen")
    recs = list(st.records)
    opts = FitOptions(deterministic_std=DET, bucket=False)
    own = batch_statistics(g, st, m, Problem(m, recs, opts), bnames, det_std=DET)
    nf = sum(not p.fixed for p in m.parameters)
    pm = padded_model(m, n_free=nf + 2, n_par=m.np + 5)
    assert pm.np == m.np + 5 and sum(not p.fixed for p in pm.parameters) == nf + 2
    P0 = Problem(pm, recs, opts)
    obj = SwitchedObjective([pm], P0.tm, P0.nm, [transition(pm, integrator=P0.integrator,
                                                            substeps=P0.substeps)])
    padded = batch_statistics(g, st, m, Problem(pm, recs, opts, objective=obj, branch=0), bnames,
                              det_std=DET)
    a, b = own[g[0].key], padded[g[0].key]
    assert a.statistic is not None and a.tested == b.tested and a.held == b.held
    assert b.statistic == pytest.approx(a.statistic, rel=1e-8)
    with pytest.raises(ValueError):
        padded_model(m, n_free=nf - 1, n_par=m.np)


def test_a_shape_without_shared_objective_is_screened_batch_by_batch(lin1, monkeypatch):
    """When the shared objective of a shape cannot be built, its batches fall back to their own
    objectives (:func:`screen_group`): every candidate still gets its statistic."""
    from vsidgen.discrepancy.refit import REFIT_DETERMINISTIC_STD as DET
    from vsidgen.discrepancy.score import screen_shared
    from vsidgen.errors import FitError
    from vsidgen.estimator import core

    tmp, st, info, states = lin1

    class Refused(core.SwitchedObjective):
        def __init__(self, *a, **k):
            raise FitError("refused for the test")

    monkeypatch.setattr(core, "SwitchedObjective", Refused)
    groups = [[c] for c in states if len(c.states) == 1]
    out = screen_shared(groups, st, info, tmp / "fallback", "f", "t_fb", generated_dir=tmp / "gen",
                        det_std=DET)
    assert set(out) == {g[0].key for g in groups}
    assert any(r.statistic is not None and np.isfinite(r.statistic) for r in out.values())
    assert not any(r.note.startswith("failed") for r in out.values()), out


@pytest.mark.parametrize("chunk", [16, 2])
def test_plain_batch_blocks_by_hessian_vector_products_equal_the_assembly(lin1, chunk, monkeypatch):
    """The plain batch's blocks from the current model's blocks and Hessian-vector products of
    the batch (:func:`~vsidgen.discrepancy.score.blocks_by_hvp`, no block assembly of the batch
    model) give the statistics of the batch's own assembled blocks, in one vmapped call or in
    chunks of 2 directions (memory-bounded chunks, :func:`~vsidgen.discrepancy.score.hvp_chunk`)."""
    from vsidgen.discrepancy import score

    monkeypatch.setattr(score, "HVP_CHUNK", chunk)
    from vsidgen.discrepancy import propose
    from vsidgen.discrepancy.refit import REFIT_DETERMINISTIC_STD as DET
    from vsidgen.discrepancy.score import _batch_model, batch_statistics, batches
    from vsidgen.estimator import FitOptions, Problem

    tmp, st, info, _ = lin1
    plain = [c for c in propose(info) if c.screenable and not c.states]
    g = batches(plain)[0]
    assert len(g) >= 3
    m, bnames = _batch_model(g, st, info, tmp / "plain.yaml", "t_plain", generated_dir=tmp / "gen")
    opts = FitOptions(deterministic_std=DET, bucket=False)
    recs = list(st.records)
    ref = batch_statistics(g, st, m, Problem(m, recs, opts), bnames, det_std=DET, hvp=False)
    Pb = Problem(m, recs, opts)

    def no_assembly(*a, **k):
        raise AssertionError("the batch model's blocks were assembled")
    Pb.blocks = no_assembly
    got = batch_statistics(g, st, m, Pb, bnames, det_std=DET, hvp=True)
    tested = 0
    for c in g:
        a, b = ref[c.key], got[c.key]
        assert (a.tested, a.held, a.dof, a.ascent) == (b.tested, b.held, b.dof, b.ascent), (a, b)
        if a.statistic is None:
            assert b.statistic is None
            continue
        tested += 1
        assert b.statistic == pytest.approx(a.statistic, rel=1e-6, abs=1e-8), (c.key, a, b)
        for n in a.step:
            assert b.step[n] == pytest.approx(a.step[n], rel=1e-6, abs=1e-10)
    assert tested >= 2, (tested, got)


def test_the_plain_batch_split_over_workers_gives_the_same_statistics(lin1, monkeypatch):
    """With several workers the batch without added states is screened in parts
    (:func:`~vsidgen.discrepancy.score.split_plain`); every new parameter is held in the null,
    so each candidate's statistic is the same in a part as in the whole batch."""
    from vsidgen.discrepancy import propose, score
    from vsidgen.discrepancy.refit import REFIT_DETERMINISTIC_STD as DET

    tmp, st, info, _ = lin1
    plain = [c for c in propose(info) if c.screenable and not c.states]
    (g,) = score.batches(plain)
    assert len(g) >= 4
    assert score.split_plain([g], 1) == [g]
    if len(g) < 2 * score.PLAIN_MIN_PART:         # too small to split at the default size
        assert score.split_plain([g], 8) == [g]
    monkeypatch.setattr(score, "PLAIN_MIN_PART", 2)
    parts = score.split_plain([g], 2)
    assert len(parts) == 2 and [c for p in parts for c in p] == g
    whole = score.screen_group(g, st, info, tmp / "whole", "w", "t_whole", generated_dir=tmp / "gen",
                               det_std=DET)
    split = {}
    for i, p in enumerate(parts):
        split.update(score.screen_group(p, st, info, tmp / "split", f"p{i}", "t_split",
                                        generated_dir=tmp / "gen", det_std=DET))
    tested = 0
    for c in g:
        a, b = whole[c.key], split[c.key]
        assert (a.tested, a.held, a.dof) == (b.tested, b.held, b.dof), (a, b)
        if a.statistic is None:
            assert b.statistic is None
            continue
        tested += 1
        assert b.statistic == pytest.approx(a.statistic, rel=1e-7, abs=1e-9), (c.key, a, b)
    assert tested >= 2


def test_hvp_chunk_keeps_the_vmapped_residuals_within_a_share_of_memory():
    """Directions per vmapped Hessian–vector-product call: never above HVP_CHUNK, k or the
    decision-vector budget, at least 1, and chunk × size × k × bytes-per-unit within the memory
    share (a new user's lateral model with 260 gated terms on 6,000 variables was killed at
    24 GB with 16 directions)."""
    from vsidgen.discrepancy.score import (HVP_BYTES_PER_UNIT, HVP_CHUNK, HVP_MEMORY_SHARE,
                                           hvp_chunk)

    gib = 2 ** 30
    assert hvp_chunk(3, 500, memory=64 * gib) == 3
    assert hvp_chunk(170, 500, memory=64 * gib) == HVP_CHUNK
    for k, size, mem in [(260, 6100, 24 * gib), (260, 6100, 16 * gib), (170, 4100, 24 * gib),
                         (500, 20000, 8 * gib)]:
        kc = hvp_chunk(k, size, memory=mem)
        assert 1 <= kc <= HVP_CHUNK
        assert kc == 1 or kc * size * k * HVP_BYTES_PER_UNIT <= HVP_MEMORY_SHARE * mem
        assert kc < HVP_CHUNK        # these batches no longer take 16 directions at once
    assert hvp_chunk(260, 6100, memory=16 * gib) <= hvp_chunk(260, 6100, memory=24 * gib)
    assert hvp_chunk(10 ** 4, 10 ** 6, memory=gib) == 1
