"""The typed, located spec (vsidgen.spec.typed): read once, immutable, every value located;
the compiler (vsidgen.spec.symbolic) works on it alone."""

import ast
import dataclasses
import pathlib

import pytest

from vsidgen.spec import load as spec_module
from vsidgen.errors import SpecError
from vsidgen.spec.symbolic import GENERATOR_VERSION, compile_spec, compile_typed
from vsidgen.spec.typed import Located, read_spec

ROOT = pathlib.Path(__file__).resolve().parents[1]


def _line_of(path: pathlib.Path, start: str, after: str | None = None) -> int:
    """1-based number of the first line that starts (stripped) with ``start`` (after the line
    starting with ``after``), counted independently of the YAML reader."""
    lines = path.read_text().splitlines()
    begin = 0
    if after is not None:
        begin = next(i for i, ln in enumerate(lines) if ln.strip().startswith(after)) + 1
    return next(i for i, ln in enumerate(lines[begin:], begin) if ln.strip().startswith(start)) + 1


def test_declarations_and_equations_keep_their_text_and_place():
    path = ROOT / "specs" / "hfb320.yaml"
    s = read_spec(path, generator_version=GENERATOR_VERSION)
    assert [d.name.value for d in s.states] == ["V", "alpha", "theta", "q"]
    V = s.states[0]
    assert V.name.path == path and V.name.key_line == _line_of(path, "V:", after="states:")
    assert V.unit.value == "m/s" and V.unit.line == V.name.key_line
    drift_V = next(e for e in s.drift if e.name.value == "V")
    line = _line_of(path, "V:", after="drift:")
    assert drift_V.expression.line == line
    text = path.read_text().splitlines()[line - 1]
    assert drift_V.expression.value == text.split(":", 1)[1].strip()
    assert drift_V.expression.column == text.index(drift_V.expression.value) + 1
    assert {m.output.value for m in s.measurement_noise} <= {d.name.value for d in s.outputs}
    assert s.data is not None and [c.name.value for c in s.data.inputs] == ["de", "thrust"]


def test_spec_is_immutable():
    s = read_spec(ROOT / "specs" / "attas_sp.yaml", generator_version=GENERATOR_VERSION)
    with pytest.raises(dataclasses.FrozenInstanceError):
        s.name = s.name
    with pytest.raises(dataclasses.FrozenInstanceError):
        s.states[0].name.value = "beta"
    assert isinstance(s.states, tuple) and isinstance(s.drift, tuple)


@pytest.mark.parametrize("spec", sorted((ROOT / "specs").glob("*.yaml")), ids=lambda p: p.stem)
def test_compile_spec_is_compile_of_the_typed_spec_read_once(spec, monkeypatch):
    reads = []
    original = spec_module.load_yaml
    monkeypatch.setattr(spec_module, "load_yaml", lambda p: reads.append(p) or original(p))
    a = compile_spec(spec)
    assert len(reads) == len(a.files) == len(set(reads))  # each file of the spec read once
    b = compile_typed(read_spec(spec, generator_version=GENERATOR_VERSION))
    assert a == b and a.source_hash == b.source_hash and a.locations == b.locations


def test_compiler_reads_no_yaml():
    """symbolic compiles the typed spec: it imports neither the YAML reader nor yaml."""
    tree = ast.parse((ROOT / "vsidgen" / "spec" / "symbolic.py").read_text())
    imported = {(n.module or "") for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)}
    imported |= {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    assert "load" not in imported and "yaml" not in imported and "vsidgen.spec.load" not in imported


def test_compile_error_points_into_the_expression_text(tmp_path):
    """An error found by the compiler (not the reader) still points at the offending character."""
    p = tmp_path / "m.yaml"
    p.write_text("name: m\nstates:\n  x: {}\nparameters:\n  a: {}\ndrift:\n  x: a*x + alfa\n"
                 "observations: {}\noutputs: {}\n")
    with pytest.raises(SpecError) as info:
        compile_spec(p)
    err = info.value
    assert (err.line, err.column) == (7, "  x: a*x + alfa".index("alfa") + 1) and "alfa" in err.message


def test_located_relocates_offsets():
    at = Located("a + b", pathlib.Path("x.yaml"), 3, 7, 3, 3)
    moved = at.relocate(SpecError("bad", path="x.yaml", line=1, column=5, text="a + b"))
    assert (moved.line, moved.column) == (3, 11)
