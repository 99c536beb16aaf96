"""Stored traced programs (``vsidgen.compilecache.StoredJit``): a later process loads the
estimator's lowered programs instead of tracing them, and computes exactly what the process
that stored them computed; anything the trace depends on changes the key."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from vsidgen import compilecache, load_model
from vsidgen.compilecache import StoredJit
from vsidgen.data import Record
from vsidgen.estimator import FitOptions, fit
from vsidgen.estimator import core

pytest.importorskip("flatbuffers")   # jax.export's serialization


def _f(x, c):
    return {"y": jnp.sin(x) * c["a"] + c["b"].sum(), "n": x.shape[0]}


def test_a_stored_program_is_loaded_and_computes_the_same(tmp_path):
    x, c = jnp.linspace(0.0, 1.0, 7), {"a": jnp.float64(2.0), "b": jnp.ones(3)}
    first = StoredJit(_f, key="f", directory=tmp_path)
    out1 = first(x, c)
    assert (first.stored, first.loaded) == (1, 0)
    assert len(list(tmp_path.glob("*.jaxexp"))) == 1

    calls = []

    def traced(x, c):           # the same function; a Python side effect counts its traces
        calls.append(1)
        return _f(x, c)

    second = StoredJit(traced, key="f", directory=tmp_path)
    out2 = second(x, c)
    assert (second.stored, second.loaded) == (0, 1) and calls == []    # not traced
    np.testing.assert_array_equal(out1["y"], out2["y"])
    np.testing.assert_array_equal(out2["y"], np.sin(np.asarray(x)) * 2.0 + 3.0)

    # another shape is another program; another key another file
    second(jnp.zeros(5), c)
    assert second.stored == 1 and len(list(tmp_path.glob("*.jaxexp"))) == 2
    StoredJit(_f, key="g", directory=tmp_path)(x, c)
    assert len(list(tmp_path.glob("*.jaxexp"))) == 3


def test_a_corrupt_file_is_exported_again_and_tracers_use_the_plain_jit(tmp_path):
    x, c = jnp.linspace(0.0, 1.0, 7), {"a": jnp.float64(2.0), "b": jnp.ones(3)}
    StoredJit(_f, key="f", directory=tmp_path)(x, c)
    (path,) = tmp_path.glob("*.jaxexp")
    path.write_bytes(b"not a program")
    again = StoredJit(_f, key="f", directory=tmp_path)
    np.testing.assert_allclose(again(x, c)["y"], np.sin(np.asarray(x)) * 2.0 + 3.0)
    assert (again.stored, again.loaded) == (1, 0)
    valid = StoredJit(_f, key="f", directory=tmp_path)
    valid(x, c)
    assert (valid.stored, valid.loaded) == (0, 1)               # the rewritten file loads
    # inside a transformation the arguments are tracers: the plain jit (differentiable)
    g = jax.grad(lambda a: again(x, {"a": a, "b": c["b"]})["y"].sum())(jnp.float64(2.0))
    assert float(g) == pytest.approx(float(np.sin(np.asarray(x)).sum()), rel=1e-12)


SPEC = """\
name: stored_sp
states:
  alpha: {unit: rad}
  q: {unit: rad/s}
inputs:
  de: {unit: rad}
outputs:
  alpha: {unit: rad}
  q: {unit: rad/s}
parameters:
  Za: {initial: 0, unit: 1/s}
  Ma: {initial: 0, unit: 1/s^2}
  Mq: {initial: 0, unit: 1/s}
  Mde: {initial: 0, unit: 1/s^2}
drift:
  alpha: Za*alpha + q
  q: Ma*alpha + Mq*q + Mde*de
observations:
  alpha: alpha
  q: q
data:
  time: t
  inputs: {de: de}
  outputs: {alpha: alpha, q: q}
"""


def _record() -> Record:
    """A short period simulated by hand (exact discretisation of the linear model, sensor
    noise), not by vsidgen."""
    from scipy.linalg import expm

    rng = np.random.default_rng(5)
    n, dt = 240, 0.05
    t = np.arange(n) * dt
    de = 0.03 * np.sign(np.sin(0.7 * t))
    A = np.array([[-1.2, 1.0], [-6.0, -1.5]])
    B = np.array([0.0, -9.0])
    Ad = expm(A * dt)
    Bd = np.linalg.solve(A, (Ad - np.eye(2)) @ B)
    x = np.zeros((n, 2))
    for k in range(n - 1):
        x[k + 1] = Ad @ x[k] + Bd * de[k] + rng.normal(0.0, [0.0005, 0.002])
    y = x + rng.normal(0.0, [0.001, 0.002], size=x.shape)
    return Record(name="sp", path=None, t=t, dt=dt, u=de[:, None], y=y,
                  input_names=("de",), output_names=("alpha", "q"), t_raw=t)


@pytest.mark.slow
def test_a_fit_loads_its_stored_programs_and_gives_the_same_result(tmp_path, monkeypatch):
    spec = tmp_path / "sp.yaml"
    spec.write_text(SPEC)
    model = load_model(spec, generated_dir=tmp_path / "gen")
    rec = _record()
    opts = FitOptions(noise_start="unit")
    plain = fit(model, [rec], options=opts)          # no store (the suite's default)

    monkeypatch.setattr(compilecache, "_EXPORTED_DIR", tmp_path / "store")
    monkeypatch.setattr(core, "_OBJECTIVES", {})
    first = fit(model, [rec], options=opts)
    obj1 = next(iter(core._OBJECTIVES.values()))
    assert isinstance(obj1._blocks, StoredJit) and obj1._blocks.stored == 1

    monkeypatch.setattr(core, "_OBJECTIVES", {})      # as a new process: nothing in memory
    second = fit(model, [rec], options=opts)
    obj2 = next(iter(core._OBJECTIVES.values()))
    assert obj2 is not obj1
    assert obj2._blocks.loaded == 1 and obj2.traces["blocks"] == 0     # loaded, not traced
    np.testing.assert_array_equal(second.theta, first.theta)
    assert second.elbo == first.elbo and second.iterations == first.iterations
    # the plain jit compiles another program of the same function: equal to rounding
    np.testing.assert_allclose(first.theta, plain.theta, rtol=1e-7, atol=1e-9)

    # a setting the trace reads (a module constant) is part of the key: traced again
    monkeypatch.setattr(core, "ASSEMBLY_CHUNK", 64)
    monkeypatch.setattr(core, "_OBJECTIVES", {})
    fit(model, [rec], options=opts)
    obj3 = next(iter(core._OBJECTIVES.values()))
    assert obj3._blocks.loaded == 0 and obj3._blocks.stored == 1


def test_only_a_generated_model_is_stored(tmp_path):
    """A model whose functions are not exactly its generated module's has no key."""
    import dataclasses

    spec = tmp_path / "sp.yaml"
    spec.write_text(SPEC)
    model = load_model(spec, generated_dir=tmp_path / "gen")
    from vsidgen.model.dynamics import transition

    F = transition(model)
    assert core.generated_model_key(model, F) is not None
    wrapped = dataclasses.replace(model, drift=lambda x, u, p: model.drift(x, u, p))
    assert core.generated_model_key(wrapped, transition(wrapped)) is None
    # the key follows the text the loader executed (session 47: the module is run from the
    # generated text, not read again from the file): editing the file after loading changes
    # nothing that runs, and so not the key; another spec's text does
    k0 = core.generated_model_key(model, F)
    model.module_path.write_text(model.module_path.read_text() + "\n# edited\n")
    assert core.generated_model_key(model, F) == k0
    spec.write_text(SPEC.replace("stored_sp", "stored_sp2"))
    other = load_model(spec, generated_dir=tmp_path / "gen")
    assert core.generated_model_key(other, transition(other)) not in (None, k0)
