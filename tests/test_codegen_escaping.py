"""No spec text can escape its literal, comment or docstring in the generated module.

Property-based (hypothesis): arbitrary text -- line breaks of every kind, quotes, backslashes,
NUL, lone surrogates, code -- goes into every text field that reaches the generated module
(description, state/input/output/parameter descriptions, units, constant sources, the
recorded spec path). The module must parse to exactly the statements of the same model with
harmless text (the abstract syntax trees are compared with every string literal blanked),
hold the text exactly where it is meant to be, be encodable as UTF-8, and importing it must
run nothing but definitions. Names are identifiers by construction: arbitrary text as a name
is either a valid name that appears unchanged in the module, or a located SpecError.
"""

from __future__ import annotations

import ast
import copy
import dataclasses
import keyword

import pytest
import yaml
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from vsidgen.codegen.jaxmodule import comment_text, docstring_text, generate, py_literal
from vsidgen.errors import SpecError
from vsidgen.spec.symbolic import GENERATED_MODULE_NAMES, compile_spec, valid_name

SPEC = """\
name: esc
description: harmless
states:
  q: {unit: rad/s, description: pitch rate}
inputs:
  de: {unit: rad, description: elevator}
outputs:
  q: {unit: rad/s, description: measured q}
constants:
  K: {value: 1.5, unit: "1", source: a book}
parameters:
  Mq: {unit: 1/s, description: damping}
  Mde: {unit: 1/s^2, description: control, fixed: true, initial: 1}
definitions:
  qdot: K*(Mq*q + Mde*de)
drift:
  q: qdot
observations:
  q: q
data:
  time: t
  inputs: {de: de_rad}
  outputs: {q: q_radps}
"""

PAYLOAD = "x\nimport os; os.system('touch SENTINEL')\n#"
BREAKS = "\n\r\x0b\x0c\x1c\x1d\x1e\x85\u2028\u2029"
hostile_text = st.lists(st.one_of(
    st.characters(blacklist_categories=()),            # everything, lone surrogates included
    st.sampled_from(list(BREAKS + "\"'\\#\x00\t{}%") + ['"""', "'''", "\\N", "\\x", PAYLOAD]),
), max_size=25).map("".join)


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    path = tmp_path_factory.mktemp("esc") / "esc.yaml"
    path.write_text(SPEC)
    return compile_spec(path)


def _skeleton(tree: ast.AST) -> str:
    """ast.dump with every string constant blanked (docstrings and literals)."""
    class Blank(ast.NodeTransformer):
        def visit_Constant(self, node):
            if isinstance(node.value, str):
                return ast.copy_location(ast.Constant(value=""), node)
            return node
    return ast.dump(Blank().visit(copy.deepcopy(tree)))


def _assigned(tree) -> dict:
    return {t.id: ast.literal_eval(n.value) for n in tree.body if isinstance(n, ast.Assign)
            for t in n.targets if isinstance(t, ast.Name) and t.id.isupper()}


def _with_texts(sym, desc, sdesc, unit, src, pdesc):
    states = tuple(dataclasses.replace(v, description=sdesc, unit=unit) for v in sym.states)
    inputs = tuple(dataclasses.replace(v, description=sdesc) for v in sym.inputs)
    outputs = tuple(dataclasses.replace(v, description=sdesc, unit=unit) for v in sym.outputs)
    constants = tuple(dataclasses.replace(c, source=src, unit=unit) for c in sym.constants)
    params = tuple(dataclasses.replace(p, description=pdesc, unit=unit) for p in sym.parameters)
    return dataclasses.replace(sym, description=desc, states=states, inputs=inputs,
                               outputs=outputs, constants=constants, parameters=params)


@settings(max_examples=60, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(desc=hostile_text, sdesc=hostile_text, unit=hostile_text, src=hostile_text,
       pdesc=hostile_text, path=hostile_text)
@example(desc=PAYLOAD, sdesc=PAYLOAD, unit=PAYLOAD, src=PAYLOAD, pdesc=PAYLOAD,
         path='x"; import os; os.system("touch SENTINEL"); y="')
@example(desc='"""\nimport os\n"""', sdesc="\\", unit="\u2028import os", src="\r\nimport os",
         pdesc='\\"""', path="a'b\"c\nd")
@example(desc="\ud800 \x00 \\N{x}", sdesc="\x85", unit="\x0c", src="\x1c", pdesc="\u2029",
         path="\ud800")
def test_arbitrary_text_never_escapes(base, tmp_path, monkeypatch, desc, sdesc, unit, src,
                                      pdesc, path):
    expected = ast.parse(generate(base, spec_path="esc.yaml"))
    text = generate(_with_texts(base, desc, sdesc, unit, src, pdesc), spec_path=path)
    text.encode("utf-8")  # lone surrogates escaped: the file can be written
    tree = ast.parse(text)
    assert _skeleton(tree) == _skeleton(expected)
    consts = _assigned(tree)
    assert consts["SPEC_PATH"] == path
    assert consts["STATES"] == ("q",) and consts["PARAMETERS"] == ("Mq", "Mde")
    doc = ast.get_docstring(tree, clean=False)
    shown = "\n".join(line.rstrip(" ") for line in desc.split("\n"))
    if desc:
        assert shown in doc
    monkeypatch.chdir(tmp_path)
    namespace: dict = {"__name__": "esc_generated"}
    exec(compile(tree, "esc_generated.py", "exec"), namespace)  # noqa: S102
    assert not (tmp_path / "SENTINEL").exists()
    assert {k for k in namespace if not k.startswith("__")} == {
        k for k in _defined(expected)}


def _defined(tree) -> set:
    out = set()
    for node in tree.body:
        if isinstance(node, ast.Assign):
            out |= {t.id for t in node.targets if isinstance(t, ast.Name)}
        elif isinstance(node, ast.FunctionDef):
            out.add(node.name)
        elif isinstance(node, ast.Import):
            out |= {(a.asname or a.name) for a in node.names}
    return out


@settings(max_examples=60, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(st.text(max_size=80))
@example("q\n")
@example("p")
@example("lambda")
@example("jnp")
@example("x" * 65)
def test_names_are_identifiers_or_refused(tmp_path_factory, name):
    doc = yaml.safe_load(SPEC)
    doc["states"] = {name: {"unit": "rad/s"}}
    doc["drift"] = {name: "-Mq"}
    doc["observations"] = {"q": "Mq"}
    doc["definitions"] = {}
    text = yaml.safe_dump(doc, allow_unicode=False)
    if yaml.safe_load(text)["states"] != {name: {"unit": "rad/s"}}:
        return  # YAML cannot carry this key unchanged
    path = tmp_path_factory.mktemp("names") / "names.yaml"
    path.write_text(text)
    ok = valid_name(name) and name not in GENERATED_MODULE_NAMES and name not in (
        "sin cos tan asin acos atan atan2 exp log sqrt abs tanh sign min max sat smoothsat "
        "interp pi K Mq Mde de".split())
    try:
        sym = compile_spec(path)
    except SpecError as err:
        assert not ok, str(err)
        assert err.line is not None and str(path) in err.render()
        return
    assert ok
    tree = ast.parse(generate(sym))
    assert _assigned(tree)["STATES"] == (name,)
    local = "_kw_" + name if keyword.iskeyword(name) else name
    assert local.isidentifier() and not keyword.iskeyword(local)


@settings(deadline=None)
@given(hostile_text)
def test_escapers_round_trip(s):
    assert ast.literal_eval(py_literal(s)) == s
    c = comment_text(s)
    assert len(c.splitlines()) <= 1 and c.isprintable()
    d = docstring_text(s)
    assert ast.literal_eval('"""' + d + ' """')[:-1] == "\n".join(
        line.rstrip(" ") for line in s.split("\n"))
