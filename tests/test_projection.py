"""The assumed density restricted to a subset of its states (the projected refit of a
candidate that added states, :func:`vsidgen.discrepancy.refit.restrict_density`), checked
against the moments computed here from the density's definition (estimator.core: Σ_cond =
L diag(eᵈ) Lᵀ, Σ_marg = Σ_cond + C Cᵀ = S_m S_mᵀ, cov(x_{k+1}, x_k) = C S_mᵀ)."""

import numpy as np
import pytest

from vsidgen.discrepancy.refit import _embed_r, restrict_decision, restrict_density
from vsidgen.estimator import join_density, split_density


def _moments(r, n):
    d, L, C = split_density(r, n)
    cond = L @ np.diag(np.exp(d)) @ L.T
    marg = cond + C @ C.T
    return cond, marg, C @ np.linalg.cholesky(marg).T


def _random_density(rng, n):
    d = rng.normal(-4.0, 1.0, n)
    L = np.eye(n)
    L[np.tril_indices(n, -1)] = rng.normal(0.0, 0.5, n * (n - 1) // 2)
    return join_density(d, L, rng.normal(0.0, 0.1, (n, n)))


@pytest.mark.parametrize("keep", [["a", "c"], ["c", "a"], ["b"], ["a", "b", "c", "d"]])
def test_restricted_moments_are_the_sub_blocks(keep):
    rng = np.random.default_rng(3)
    names = ["a", "b", "c", "d"]
    r = _random_density(rng, 4)
    _, marg, cross = _moments(r, 4)
    r1 = restrict_density(r, names, keep)
    cond1, marg1, cross1 = _moments(r1, len(keep))
    idx = [names.index(k) for k in keep]
    np.testing.assert_allclose(marg1, marg[np.ix_(idx, idx)], rtol=1e-10, atol=1e-14)
    np.testing.assert_allclose(cross1, cross[np.ix_(idx, idx)], rtol=1e-10, atol=1e-14)
    assert np.all(np.linalg.eigvalsh(cond1) > 0)


def test_restriction_undoes_the_stage0_embedding():
    """A density embedded with decoupled new states (stage 0 of a refit) restricted back to
    the original states is the original density."""
    rng = np.random.default_rng(5)
    r0 = _random_density(rng, 3)
    r1 = _embed_r(r0, 3, 5, [0, 2, 4], [1, 3], np.log([1e-6, 4e-6]), [3e-4, -1e-4])
    back = restrict_density(r1, ["x", "z1", "y", "z2", "w"], ["x", "y", "w"])
    np.testing.assert_allclose(back, r0, rtol=1e-9, atol=1e-12)


def test_restrict_decision_takes_the_mean_columns():
    rng = np.random.default_rng(7)
    mu = rng.normal(size=(6, 3))
    (out,) = restrict_decision([{"mu": mu, "r": _random_density(rng, 3)}],
                               ["p", "lag", "q"], ["p", "q"])
    np.testing.assert_array_equal(out["mu"], mu[:, [0, 2]])
    assert out["r"].shape == (2 + 1 + 4,)
