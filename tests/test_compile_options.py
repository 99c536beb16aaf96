"""XLA compiler options of the objective's jitted functions (issue 16 item 3).

On the CPU backend the objective's functions are compiled with
``vsidgen.estimator.core.CPU_COMPILER_OPTIONS`` (XLA-CPU's elemental IR emitters instead of
its MLIR fusion emitters: the Hessian blocks compile 1.4–1.8x faster, docs/performance.md). The
tests check that the options reach every jitted function (an option XLA does not know must
make each of them fail to compile), that other backends keep XLA's defaults, and that the
blocks, value and factorisation equal those compiled with XLA's defaults to rounding, and
the exact Hessian of the flat objective (``jax.hessian``, an independent path).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_estimator import _pend_problem

from vsidgen.estimator import FitOptions
from vsidgen.estimator import core
from vsidgen.estimator import Problem


def _point(P, seed=0):
    s, recs = P.initial(FitOptions())
    rng = np.random.default_rng(seed)
    s = s + 0.3 * rng.normal(size=s.shape)
    return s, [(m + 0.2 * rng.normal(size=m.shape), r + 0.2 * rng.normal(size=r.shape)) for m, r in recs]


def test_other_backends_keep_xla_defaults(monkeypatch):
    assert jax.default_backend() != "cpu" or core.compiler_options() == core.CPU_COMPILER_OPTIONS
    monkeypatch.setattr(core.jax, "default_backend", lambda: "gpu")
    assert core.compiler_options() is None


@pytest.mark.skipif(jax.default_backend() != "cpu", reason="CPU compiler options")
def test_options_this_xla_does_not_know_are_dropped(monkeypatch):
    """jaxlib 0.11.2 refuses ``xla_cpu_use_fusion_emitters`` ("No such compile option"), which
    made every fit fail there: only the options XLA accepts are passed, and a fit runs."""
    monkeypatch.setattr(core, "CPU_COMPILER_OPTIONS",
                        {"xla_no_such_option_for_vsidgen": True, "xla_cpu_enable_fast_math": False})
    kept = core.compiler_options() or {}
    assert "xla_no_such_option_for_vsidgen" not in kept
    assert set(kept) <= {"xla_cpu_enable_fast_math"}  # kept where this XLA knows it
    monkeypatch.setattr(core, "CPU_COMPILER_OPTIONS", {"xla_no_such_option_for_vsidgen": True})
    assert core.compiler_options() is None
    model, rec = _pend_problem()
    P = Problem(model, [rec], FitOptions(bucket=False))
    s, recs = _point(P)
    assert np.isfinite(float(P.value(s, recs)))


@pytest.mark.skipif(jax.default_backend() != "cpu", reason="CPU compiler options")
def test_every_objective_jit_compiles_with_the_cpu_options(monkeypatch):
    model, rec = _pend_problem()
    # past the filter of unknown options: an option XLA refuses shows that it reached the jit
    monkeypatch.setattr(core, "compiler_options", lambda: {"xla_no_such_option_for_vsidgen": True})
    # the curvature structure is read off the jaxpr: building the objective compiles nothing
    Problem(model, [rec], FitOptions(bucket=False)).obj
    monkeypatch.setattr(core, "curvature_pairs", lambda *a, **k: None)  # no structure: general path
    P = Problem(model, [rec], FitOptions(bucket=False))
    s, recs = _point(P)
    (m, r), = recs
    args = (jnp.asarray(m), jnp.asarray(r), jnp.asarray(s), P.data[0], P.cfg)
    for call in (lambda: P.obj.value(*args), lambda: P.obj.blocks(*args)):
        with pytest.raises(Exception, match="xla_no_such_option_for_vsidgen"):
            call()
    N, n = m.shape
    nb = P.obj.nb
    blk = dict(D=jnp.broadcast_to(jnp.eye(n), (N, n, n)), B=jnp.zeros((N - 1, n, n)), W=jnp.zeros((N, n, nb)),
               gmu=jnp.zeros((N, n)), Hbb=jnp.eye(nb), gb=jnp.zeros(nb))
    with pytest.raises(Exception, match="xla_no_such_option_for_vsidgen"):
        P.obj.factor(blk, jnp.ones(m.shape), 1e-3)
    with pytest.raises(Exception, match="xla_no_such_option_for_vsidgen"):
        P.obj.back({"Xg": jnp.zeros(m.shape), "Y": jnp.zeros(m.shape + (2,))}, jnp.zeros(2))


@pytest.mark.slow
def test_cpu_options_equal_xla_defaults(monkeypatch):
    model, rec = _pend_problem()
    ours = dict(core.CPU_COMPILER_OPTIONS)
    out = {}
    for label, opts in (("vsidgen", ours), ("xla", {})):
        monkeypatch.setattr(core, "CPU_COMPILER_OPTIONS", dict(opts))
        P = Problem(model, [rec], FitOptions(bucket=False))  # the objective cache keys on the options
        s, recs = _point(P)
        b = P.blocks(s, recs)[0]
        fac = P.obj.factor(b, jnp.ones(recs[0][0].shape), 1e-3)
        out[label] = (P.obj, P.value(s, recs), b, fac)
    (o1, v1, b1, f1), (o0, v0, b0, f0) = out["vsidgen"], out["xla"]
    assert o1 is not o0
    np.testing.assert_allclose(v1, v0, rtol=1e-13)
    for k in b0:
        np.testing.assert_allclose(np.asarray(b1[k]), np.asarray(b0[k]), rtol=1e-12,
                                   atol=1e-13 * float(np.abs(np.asarray(b0[k])).max() or 1.0), err_msg=k)
    for k in ("S", "rhs", "Xg", "Y"):
        np.testing.assert_allclose(np.asarray(f1[k]), np.asarray(f0[k]), rtol=1e-11,
                                   atol=1e-12 * float(np.abs(np.asarray(f0[k])).max() or 1.0), err_msg=k)
