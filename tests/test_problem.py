"""The estimator's public problem object (vsidgen.estimator.Problem) against dense references.

The reference is ``jax.hessian``/``jax.grad`` of the flat negative ELBO (``Problem.flat_value``:
the plain sum of expected log densities, not the structured sigma-point assembly of
``Problem.blocks``), eliminated densely with numpy: S = H_bb + λ diag(d_b) − H_bμ A⁻¹ H_μb,
rhs = −g_b + H_bμ A⁻¹ g_μ, A = H_μμ + λ diag(d_μ).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from vsidgen.estimator import FitOptions, Problem, join_density, split_density
from vsidgen.estimator.linalg import btd_to_dense

from test_estimator import lin_model, make_record

jax.config.update("jax_enable_x64", True)


@pytest.fixture(scope="module")
def problem_point():
    P = Problem(lin_model(structure="full"), [make_record(6, seed=2, name="a"), make_record(5, seed=3, name="b")],
                FitOptions(bucket=False))
    s, recs = P.initial(FitOptions())
    rng = np.random.default_rng(1)
    s = s + 0.3 * rng.normal(size=s.shape)
    recs = [(m + 0.2 * rng.normal(size=m.shape), r + 0.2 * rng.normal(size=r.shape)) for m, r in recs]
    return P, s, recs


def test_layout_pack_unpack_round_trip(problem_point):
    P, s, recs = problem_point
    lay = P.layout
    v = lay.pack(s, recs)
    assert v.shape == (lay.size,) and lay.size == lay.n_mu + lay.nglob
    s2, recs2 = lay.unpack(v)
    np.testing.assert_array_equal(s2, s)
    for (m, r), (m2, r2) in zip(recs, recs2):
        np.testing.assert_array_equal(m2, m)
        np.testing.assert_array_equal(r2, r)
    np.testing.assert_array_equal(lay.pack(*lay.unpack(v)), v)
    # the border positions: every r_i, then z, then w, each exactly once
    parts = np.concatenate([lay.r_index(i) for i in range(lay.nrec)] + [lay.theta_index, lay.noise_index])
    np.testing.assert_array_equal(parts, np.arange(lay.nglob))
    assert lay.n_theta == 4 and lay.n_proc == 3 and lay.n_meas == 2  # full G on 2 states: 2 + 1 off-diagonal
    # the assumed-density parameters split and join
    d, L, C = split_density(recs[0][1], 2)
    assert L[0, 1] == 0.0 and L[0, 0] == L[1, 1] == 1.0
    np.testing.assert_array_equal(join_density(d, L, C), recs[0][1])


def test_noise_vector_inverts_the_noise_map(problem_point):
    P = problem_point[0]
    w = P.noise_vector(proc_std={"x1": 0.3, "x2": 0.05}, proc_G={("x2", "x1"): -0.02},
                       meas_std={"y1": 0.01, "y2": 0.2}, default_std=1.0)
    G = np.asarray(P.nm.G(jnp.asarray(w)))
    np.testing.assert_allclose(G, [[0.3, 0.0], [-0.02, 0.05]], rtol=1e-14)
    np.testing.assert_allclose(np.asarray(P.nm.sigma(jnp.asarray(w))), [0.01, 0.2], rtol=1e-14)
    assert P.process_noise_index("x2") == P.layout.noise_index[1]


@pytest.mark.slow
def test_reduced_system_equals_dense_elimination_of_the_flat_hessian(problem_point):
    P, s, recs = problem_point
    lay = P.layout
    v = jnp.asarray(lay.pack(s, recs))
    Hd = np.asarray(jax.jit(jax.hessian(P.flat_value))(v))
    gd = np.asarray(jax.jit(jax.grad(P.flat_value))(v))
    blks = P.blocks(s, recs)
    assert P.total(blks) == pytest.approx(float(P.flat_value(v)), rel=1e-12)
    # gradient split by parts
    grad = P.gradient(blks)
    gs, grecs = lay.unpack(gd)
    np.testing.assert_allclose(grad.shared, gs, rtol=1e-9, atol=1e-9 * np.abs(gd).max())
    for gm, gr, (gm_d, gr_d) in zip(grad.records_mu, grad.records_r, grecs):
        np.testing.assert_allclose(gm, gm_d, rtol=1e-9, atol=1e-9 * np.abs(gd).max())
        np.testing.assert_allclose(gr, gr_d, rtol=1e-9, atol=1e-9 * np.abs(gd).max())
    # block Hessian: the μ blocks are block tridiagonal
    nmu = lay.n_mu
    o = 0
    for b, n in zip(blks, lay.lengths):
        sz = n * lay.nx
        np.testing.assert_allclose(btd_to_dense(b["D"], b["B"]), Hd[o:o + sz, o:o + sz], rtol=1e-9,
                                   atol=1e-9 * np.abs(Hd).max())
        o += sz
    np.testing.assert_allclose(P.gather(blks)[1], Hd[nmu:, nmu:], rtol=1e-9, atol=1e-9 * np.abs(Hd).max())
    rng = np.random.default_rng(5)
    dmus = [rng.uniform(0.5, 2.0, size=(n, lay.nx)) for n in lay.lengths]
    dglob = rng.uniform(0.5, 2.0, size=lay.nglob)
    for lam in (30.0, 3.0):
        red = P.reduced_system(blks, lam=lam, dmus=dmus, dglob=dglob)
        A = Hd[:nmu, :nmu] + lam * np.diag(np.concatenate([d.ravel() for d in dmus]))
        if np.linalg.eigvalsh(A)[0] <= 0:
            assert red is None
            continue
        Wt = Hd[nmu:, :nmu]
        S_ref = Hd[nmu:, nmu:] + lam * np.diag(dglob) - Wt @ np.linalg.solve(A, Wt.T)
        rhs_ref = -gd[nmu:] + Wt @ np.linalg.solve(A, gd[:nmu])
        np.testing.assert_allclose(red.S, S_ref, rtol=1e-8, atol=1e-9 * np.abs(S_ref).max())
        np.testing.assert_allclose(red.rhs, rhs_ref, rtol=1e-8, atol=1e-9 * np.abs(rhs_ref).max())
        # back substitution: the full damped Newton step
        db = np.linalg.solve(red.S, red.rhs)
        ds, dmu, dr = P.back_substitute(red, db)
        step = lay.pack(ds, list(zip(dmu, dr)))
        Dfull = np.concatenate([d.ravel() for d in dmus] + [dglob])
        dense = np.linalg.solve(Hd + lam * np.diag(Dfull), -gd)
        np.testing.assert_allclose(step, dense, rtol=1e-7, atol=1e-9 * np.abs(dense).max())
