"""generated/ in the repository is up to date with specs/ (CI fails otherwise)."""

import os
import pathlib

import pytest

from vsidgen.codegen import build

ROOT = pathlib.Path(__file__).resolve().parents[1]
SPECS = sorted((ROOT / "specs").glob("*.yaml"))


@pytest.mark.parametrize("spec", SPECS, ids=[s.stem for s in SPECS])
def test_generated_module_matches_spec(spec, tmp_path, monkeypatch):
    monkeypatch.chdir(ROOT)  # paths in generated headers are relative to the repository root
    results = build([spec.relative_to(ROOT)], out_dir=tmp_path, force=True)
    assert len(results) == 1
    fresh = pathlib.Path(results[0].module_path)
    committed = ROOT / "generated" / fresh.name
    assert committed.exists(), f"{committed} missing: run `vsidgen build specs/*.yaml`"
    assert fresh.read_bytes() == committed.read_bytes(), (
        f"{committed.relative_to(ROOT)} is stale: run `vsidgen build specs/*.yaml` and commit")


def test_every_generated_module_has_a_spec():
    names = {s.stem for s in SPECS}
    for mod in (ROOT / "generated").glob("*.py"):
        if mod.name == "__init__.py":
            continue
        assert mod.stem in names, f"generated/{mod.name} has no spec in specs/"
    assert os.path.isdir(ROOT / "generated")


@pytest.mark.parametrize("module", sorted((ROOT / "generated").glob("*.py")),
                         ids=lambda p: p.stem)
def test_generated_code_imports_only_jax_and_numpy(module):
    import ast

    tree = ast.parse(module.read_text())
    roots = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            roots |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            roots.add((node.module or "").split(".")[0] if node.level == 0 else ".")
    assert roots and roots <= {"jax", "numpy"}, roots
