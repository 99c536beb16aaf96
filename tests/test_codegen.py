"""Generated code: Jacobians vs jax.jacfwd and finite differences, determinism, extends semantics."""

import pathlib
import shutil

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import sympy

from vsidgen.codegen.jaxmodule import build, embedded_hash, generate
from vsidgen.model import load_model
from vsidgen.spec import compile_spec

jax.config.update("jax_enable_x64", True)

SPECS = pathlib.Path(__file__).parent / "specs"

# points away from the kinks of sat/max/min/abs/sign and the interp knots; the last one
# lies beyond the saturation and outside the lookup table
POINTS = [
    ([0.3, 0.7, 0.5], [0.2, -0.1]),
    ([-1.2, -0.4, -0.6], [-0.5, 0.3]),
    ([2.0, -2.5, 1.5], [1.0, 0.05]),
]


@pytest.fixture(scope="module")
def nonlinear(tmp_path_factory):
    return load_model(SPECS / "nonlinear.yaml", generated_dir=tmp_path_factory.mktemp("gen"))


def _fd(fun, args, k, h=1e-6):
    """Central finite-difference Jacobian of fun w.r.t. args[k]."""
    base = [np.asarray(a, dtype=float) for a in args]
    cols = []
    for i in range(base[k].size):
        plus = [a.copy() for a in base]
        minus = [a.copy() for a in base]
        plus[k][i] += h
        minus[k][i] -= h
        cols.append((np.asarray(fun(*plus)) - np.asarray(fun(*minus))) / (2 * h))
    return np.stack(cols, axis=-1)


@pytest.mark.parametrize("x, u", POINTS)
def test_jacobians_match_jacfwd_and_finite_differences(nonlinear, x, u):
    mod = nonlinear.module
    p = np.array([sp.initial for sp in nonlinear.parameters]) + 0.1
    args = (jnp.array(x), jnp.array(u), jnp.array(p))
    for fname, fun in (("drift", mod.drift), ("output", mod.output)):
        for k, var in enumerate("xup"):
            sym = np.asarray(getattr(mod, f"{fname}_jac_{var}")(*args))
            ad = np.asarray(jax.jacfwd(fun, argnums=k)(*args))
            fd = _fd(fun, args, k)
            assert sym.shape == ad.shape == fd.shape
            np.testing.assert_allclose(sym, ad, rtol=1e-10, atol=1e-12, err_msg=f"{fname}_jac_{var}")
            np.testing.assert_allclose(sym, fd, rtol=1e-5, atol=1e-7, err_msg=f"{fname}_jac_{var}")


def test_generated_values_match_sympy(nonlinear):
    """drift/output vs direct numeric evaluation of the sympy expressions."""
    sm = nonlinear.symbolic
    x, u = POINTS[0]
    p = [q.initial for q in sm.parameters]
    subs = dict(zip(sm.state_symbols, x)) | dict(zip(sm.input_symbols, u))
    subs |= dict(zip(sm.parameter_symbols, p)) | sm.constant_values()
    want_f = [float(sympy.N(e.xreplace(subs))) for e in sm.drift_expanded()]
    want_h = [float(sympy.N(e.xreplace(subs))) for e in sm.observations_expanded()]
    args = (jnp.array(x), jnp.array(u), jnp.array(p))
    np.testing.assert_allclose(nonlinear.drift(*args), want_f, rtol=1e-12)
    np.testing.assert_allclose(nonlinear.output(*args), want_h, rtol=1e-12)


def test_jit_and_vmap(nonlinear):
    xs = jnp.array([pt[0] for pt in POINTS])
    us = jnp.array([pt[1] for pt in POINTS])
    p = jnp.array([q.initial for q in nonlinear.parameters])
    batched = jax.jit(jax.vmap(nonlinear.drift, in_axes=(0, 0, None)))(xs, us, p)
    assert batched.shape == (3, 3)
    np.testing.assert_allclose(batched[1], nonlinear.drift(xs[1], us[1], p), rtol=1e-12)


def test_module_api_and_renamed_locals(nonlinear):
    mod = nonlinear.module
    assert mod.STATES == ("x1", "x2", "lambda")
    assert mod.INPUTS == ("u1", "p")
    assert mod.PARAMETERS == ("k", "c", "a", "b", "x")
    assert mod.SPEC_HASH == nonlinear.symbolic.source_hash
    assert mod.G0 == 9.80665
    src = pathlib.Path(mod.__file__).read_text()
    # spec names stay as written (p, x are not taken by the module); a keyword gets `_kw_`
    assert "_kw_lambda = _x[2]" in src and "    p = _u[1]" in src and "    x = _p[4]" in src
    imports = [line for line in src.splitlines() if line.startswith(("import", "from"))]
    assert imports == ["import jax.numpy as jnp"]
    assert "spring = " in src  # definitions are readable named locals


def test_rebuild_byte_identical_and_skip(tmp_path):
    spec = SPECS / "child.yaml"
    first = build([spec], out_dir=tmp_path / "a")[0]
    second = build([spec], out_dir=tmp_path / "b")[0]
    assert first.written and second.written
    assert first.module_path.read_bytes() == second.module_path.read_bytes()
    assert generate(compile_spec(spec)) == first.module_path.read_text()
    mtime = first.module_path.stat().st_mtime_ns
    again = build([spec], out_dir=tmp_path / "a")[0]
    assert not again.written and first.module_path.stat().st_mtime_ns == mtime
    forced = build([spec], out_dir=tmp_path / "a", force=True)[0]
    assert forced.written
    assert embedded_hash(first.module_path) == compile_spec(spec).source_hash


def test_recorded_spec_path_does_not_depend_on_the_working_directory(tmp_path, monkeypatch):
    """SPEC_PATH is `specs/...` below a `specs` folder, else the file name, from any cwd."""
    import ast

    root = tmp_path / "repo"
    (root / "specs" / "sub").mkdir(parents=True)
    for f in ("base.yaml", "child.yaml"):
        shutil.copy(SPECS / f, root / "specs" / "sub" / f)
    texts = []
    for cwd in (tmp_path, root, root / "specs" / "sub"):
        monkeypatch.chdir(cwd)
        texts.append(generate(compile_spec(root / "specs" / "sub" / "child.yaml")))
    assert texts[0] == texts[1] == texts[2]
    tree = ast.parse(texts[0])
    path = [ast.literal_eval(n.value) for n in tree.body if isinstance(n, ast.Assign)
            and n.targets[0].id == "SPEC_PATH"]
    assert path == ["specs/sub/child.yaml"]
    assert "SPEC_PATH = 'specs/child.yaml'" in generate(compile_spec(SPECS / "child.yaml"))
    plain = tmp_path / "plain"
    plain.mkdir()
    for f in ("base.yaml", "child.yaml"):
        shutil.copy(SPECS / f, plain / f)
    assert "SPEC_PATH = 'child.yaml'" in generate(compile_spec(plain / "child.yaml"))


def test_build_rewrites_a_module_unless_its_text_is_exactly_the_new_one(tmp_path):
    """A module with the right SPEC_HASH but other text (edited, older template) is rebuilt."""
    spec = SPECS / "child.yaml"
    first = build([spec], out_dir=tmp_path)[0]
    text = first.module_path.read_text()
    first.module_path.write_text(text.replace("# ---- constants ----",
                                              "import os  # edited\n# ---- constants ----"))
    assert embedded_hash(first.module_path) == compile_spec(spec).source_hash
    again = build([spec], out_dir=tmp_path)[0]
    assert again.written and again.module_path.read_text() == text
    assert not build([spec], out_dir=tmp_path)[0].written


def test_hash_changes_with_spec_content(tmp_path):
    for f in ("base.yaml", "child.yaml"):
        shutil.copy(SPECS / f, tmp_path / f)
    h1 = compile_spec(tmp_path / "child.yaml").source_hash
    base = tmp_path / "base.yaml"
    base.write_text(base.read_text().replace("MQ: {unit: 1/s, initial: -1.0}",
                                             "MQ: {unit: 1/s, initial: -1.5}"))
    h2 = compile_spec(tmp_path / "child.yaml").source_hash
    assert h1 != h2  # a parent change invalidates the child's module
    out = build([tmp_path / "child.yaml"], out_dir=tmp_path / "gen")[0]
    assert out.written


def test_extends_and_add_terms_semantics():
    base = compile_spec(SPECS / "base.yaml")
    child = compile_spec(SPECS / "child.yaml")
    s = {n: sympy.Symbol(n, real=True) for n in
         ("V", "alpha", "q", "de", "CLAL", "CLQ", "CBAR", "V0", "MAL", "MQ", "MDE")}
    # replaced definition keeps its position, add_terms appended to the replacement
    assert [n for n, _ in child.definitions] == ["qbar", "CL"]
    cl = dict(child.definitions)["CL"]
    want = s["CLAL"] * s["alpha"] + sympy.Rational(1, 2) * s["alpha"] ** 2 \
        + s["CLQ"] * s["q"] * s["CBAR"] / s["V0"]
    assert sympy.simplify(cl - want) == 0
    # drift add_terms: base equation + the lookup-table term
    dq = child.drift[2] - (s["MAL"] * s["alpha"] + s["MQ"] * s["q"] + s["MDE"] * s["de"])
    assert dq.func.__name__ == "Interp"
    # parameters: new appended, overridden in place
    assert [p.name for p in child.parameters] == [p.name for p in base.parameters] + ["CLQ"]
    mde = {p.name: p for p in child.parameters}["MDE"]
    assert (mde.initial, mde.lower, mde.upper) == (-5.0, -20.0, 0.0)
    # noise merged key by key; name from child, integrator inherited
    assert child.name == "child" and (child.integrator, child.substeps) == ("rk4", 2)
    meas = {m.output: m for m in child.measurement_noise}
    assert meas["alpha"].estimate and meas["alpha"].floor == 0.0001
    assert meas["V"].floor == "auto"
    assert child.files[0].name == "base.yaml" and child.files[-1].name == "child.yaml"
    # the unused constant V0 of the base is used in the child
    assert not [w for w in child.warnings if "V0" in w.message]
    assert [w.message for w in base.warnings] == ["unused constant `V0`"]


def test_default_generated_dir(tmp_path, monkeypatch):
    specs = tmp_path / "proj" / "specs"
    specs.mkdir(parents=True)
    shutil.copy(SPECS / "base.yaml", specs / "base.yaml")
    monkeypatch.chdir(tmp_path)
    m = load_model(specs / "base.yaml")
    assert m.module_path == tmp_path / "proj" / "generated" / "base.py"
    assert m.nx == 3 and m.np == 5 and m.integrator == "rk4"
    out = m.drift(jnp.array([100.0, 0.05, 0.0]), jnp.array([0.01]),
                  jnp.array([p.initial for p in m.parameters]))
    assert out.shape == (3,) and bool(jnp.all(jnp.isfinite(out)))
