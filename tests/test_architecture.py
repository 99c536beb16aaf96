"""The package's dependency rules, read from the source with ``ast`` (docs/architecture.md).

* no import cycle among vsidgen modules (function-local imports count: they are still a
  dependency, only a later one);
* no private name (``_x``; dunders such as ``__version__`` are not private) imported from,
  or read as an attribute of, another vsidgen module;
* no import against the pipeline: a module imports only modules of its own stage or of an
  earlier one (``STAGES`` below, the order of docs/architecture.md); every module has a stage;
* ``jax_enable_x64`` is set only in ``vsidgen/precision.py``.

Each rule is also checked against a deliberately bad module, so that none of them passes
vacuously.
"""

from __future__ import annotations

import ast
import functools
import pathlib
import re

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "vsidgen"

#: The pipeline, first stage first (docs/architecture.md, "Dependency direction").
STAGES: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("foundation", ("vsidgen", "errors", "precision", "limits", "atomic", "suggest", "metadata",
                    "compilecache", "progress", "engine")),
    ("spec", ("expr", "units", "dataunits", "spec", "typedspec", "symbolic", "overrides")),
    ("codegen", ("codegen",)),
    ("model", ("model", "dynamics")),
    ("data", ("formats", "data", "datacheck", "simulate")),
    ("estimator", ("estimator.linalg", "estimator.results", "estimator.core", "estimator.problem", "estimator.fit",
                   "estimator")),
    ("evaluation", ("evaluation",)),
    ("results", ("resultsdir", "report")),
    ("fit job", ("pipeline", "fleet")),
    ("diagnose: leaves", ("discrepancy.base", "discrepancy.specwrite")),
    ("diagnose: locate", ("discrepancy.locate",)),
    ("diagnose: catalogue", ("discrepancy.catalogue",)),
    ("diagnose: flight conditions", ("discrepancy.flightconst",)),
    ("diagnose: findings and refit", ("discrepancy.findings", "discrepancy.refit")),
    ("diagnose: fit states", ("discrepancy.fitstate",)),
    ("diagnose: numerics and delay profiles", ("discrepancy.numerics", "discrepancy.delay")),
    ("diagnose: score test", ("discrepancy.score",)),
    ("diagnose: gated round model", ("discrepancy.gated",)),
    ("diagnose: search", ("discrepancy.search",)),
    ("diagnose: package", ("discrepancy",)),
    ("command line", ("cli",)),
)


def _full(name: str) -> str:
    return "vsidgen" if name == "vsidgen" else f"vsidgen.{name}"


STAGE_OF = {_full(m): i for i, (_, mods) in enumerate(STAGES) for m in mods}


def _module_name(path: pathlib.Path, package: pathlib.Path) -> str:
    parts = list(path.with_suffix("").relative_to(package.parent).parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _sources(package: pathlib.Path) -> dict[str, tuple[pathlib.Path, str]]:
    return {_module_name(p, package): (p, p.read_text(encoding="utf-8"))
            for p in sorted(package.rglob("*.py"))}


@functools.lru_cache(maxsize=None)
def _parsed(text: str) -> ast.Module:
    """The syntax tree of a source text (parsed once per text; the checks only read it)."""
    return ast.parse(text)


def _private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def analyse(package: pathlib.Path, top: str = "vsidgen", extra: dict | None = None):
    """Import edges {module: {module: first line}} and private-name uses [(module, line, text)]
    of the package at ``package`` (``extra``: {module name: source} added to it)."""
    sources = {m: t for m, (_, t) in _sources(package).items()}
    sources.update(extra or {})
    modules = set(sources)
    edges: dict[str, dict[str, int]] = {m: {} for m in modules}
    private: list[tuple[str, int, str]] = []
    for mod, text in sources.items():
        is_pkg = (package.parent / mod.replace(".", "/") / "__init__.py").exists()
        here = mod if is_pkg else mod.rpartition(".")[0]
        tree = _parsed(text)
        module_aliases: set[str] = set()

        def add(target: str, line: int) -> None:
            if target != mod and target in modules:
                edges[mod].setdefault(target, line)

        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom):
                if node.level:
                    base = here.split(".")[:len(here.split(".")) - node.level + 1]
                    target = ".".join(base + ([node.module] if node.module else []))
                else:
                    target = node.module or ""
                if target.split(".")[0] != top:
                    continue
                add(target, node.lineno)
                for alias in node.names:
                    sub = f"{target}.{alias.name}"
                    if sub in modules:
                        add(sub, node.lineno)
                        module_aliases.add(alias.asname or alias.name)
                    elif _private(alias.name) and target != mod:
                        private.append((mod, node.lineno, f"from {target} import {alias.name}"))
            elif isinstance(node, ast.Import):
                for alias in node.names:
                    if alias.name.split(".")[0] == top:
                        add(alias.name, node.lineno)
                        if alias.asname:
                            module_aliases.add(alias.asname)
        for node in ast.walk(tree):
            if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name)
                    and node.value.id in module_aliases and _private(node.attr)):
                private.append((mod, node.lineno, f"{node.value.id}.{node.attr}"))
    return edges, private


def cycles(edges: dict[str, dict[str, int]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in edges.get(v, {}):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(edges):
        if v not in index:
            visit(v)
    return out


def against_pipeline(edges: dict[str, dict[str, int]]) -> list[str]:
    return [f"{m} (stage {STAGES[STAGE_OF[m]][0]!r}) imports {t} (stage "
            f"{STAGES[STAGE_OF[t]][0]!r}, later) at line {line}"
            for m, targets in sorted(edges.items()) for t, line in sorted(targets.items())
            if m in STAGE_OF and t in STAGE_OF and STAGE_OF[t] > STAGE_OF[m]]


def _sets_x64(text: str) -> bool:
    """Whether the source switches x64 on: a call whose first argument is the option name
    (``jax.config.update("jax_enable_x64", ...)``, ``os.environ.setdefault("JAX_ENABLE_X64",
    ...)``) or an assignment to ``...["JAX_ENABLE_X64"]``; reading or forwarding it is not."""
    def is_name(node) -> bool:
        return (isinstance(node, ast.Constant) and isinstance(node.value, str)
                and node.value.lower() == "jax_enable_x64")

    for node in ast.walk(_parsed(text)):
        if isinstance(node, ast.Call) and node.args and is_name(node.args[0]):
            if not (isinstance(node.func, ast.Attribute) and node.func.attr in ("get", "getenv")):
                return True
        if isinstance(node, (ast.Assign, ast.AugAssign)):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            if any(isinstance(t, ast.Subscript) and is_name(t.slice) for t in targets):
                return True
    return False


def x64_outside_precision(package: pathlib.Path, extra: dict | None = None) -> list[str]:
    texts = {str(p.relative_to(package.parent)): t for _, (p, t) in _sources(package).items()}
    texts.update(extra or {})
    return [name for name, t in sorted(texts.items())
            if _sets_x64(t) and name != str(pathlib.Path("vsidgen", "precision.py"))]


# ----------------------------------------------------------------------------- the package


def test_every_module_has_a_stage():
    modules = set(_sources(PACKAGE))
    assert sorted(modules - set(STAGE_OF)) == [], "add the module to STAGES and docs/architecture.md"
    assert sorted(set(STAGE_OF) - modules) == [], "STAGES names a module that does not exist"


def test_no_import_cycles():
    edges, _ = analyse(PACKAGE)
    assert cycles(edges) == []


def test_no_private_names_across_modules():
    _, private = analyse(PACKAGE)
    assert private == []


def test_imports_follow_the_pipeline():
    edges, _ = analyse(PACKAGE)
    assert against_pipeline(edges) == []


def test_x64_switched_on_only_in_precision():
    assert x64_outside_precision(PACKAGE) == []
    assert _sets_x64((PACKAGE / "precision.py").read_text(encoding="utf-8"))


def test_architecture_doc_lists_every_module():
    doc = (ROOT / "docs" / "architecture.md").read_text(encoding="utf-8")
    missing = [m for m in sorted(STAGE_OF) if m != "vsidgen" and m not in doc]
    assert missing == []


# ----------------------------------------------------------------------------- the checks can fail

BAD = {
    # dynamics (model stage) reaching into the estimator (later) through a private name,
    # inside a function (a function-local import is still a dependency)
    "vsidgen.dynamics": "def f():\n    from .estimator.fit import _Problem\n    return _Problem\n",
    # and the estimator importing dynamics: with the line above, a cycle
    "vsidgen.estimator.linalg": "from .. import dynamics\n\ndef g():\n    return dynamics._check\n",
    "vsidgen.simulate": "import jax\njax.config.update('jax_enable_x64', True)\n",
}


def test_checks_fail_on_bad_imports():
    edges, private = analyse(PACKAGE, extra=BAD)
    comps = cycles(edges)
    assert any({"vsidgen.dynamics", "vsidgen.estimator.fit"} <= set(c) for c in comps), comps
    assert ("vsidgen.dynamics", 2, "from vsidgen.estimator.fit import _Problem") in private
    assert ("vsidgen.estimator.linalg", 4, "dynamics._check") in private
    bad = against_pipeline(edges)
    assert any(b.startswith("vsidgen.dynamics (stage 'model') imports vsidgen.estimator.fit")
               for b in bad), bad
    assert x64_outside_precision(PACKAGE, extra={"vsidgen/simulate.py": BAD["vsidgen.simulate"]}
                                 ) == ["vsidgen/simulate.py"]
    assert x64_outside_precision(PACKAGE, extra={
        "vsidgen/formats.py": "import os\nos.environ['JAX_ENABLE_X64'] = '1'\n"}) == ["vsidgen/formats.py"]


#: one bad module source per rule (it replaces the module's own source in the analysis)
ONE_RULE = {
    "cycle": {"vsidgen.errors": "from . import suggest\n"},          # suggest imports errors
    "private": {"vsidgen.cli": "from .data import _read_header\n"},
    "direction": {"vsidgen.codegen": "from . import report\n"},      # report does not import codegen
}


@pytest.mark.parametrize("rule", sorted(ONE_RULE))
def test_each_rule_alone(rule):
    """One bad import per rule, caught by its own check and by no other one."""
    edges, private = analyse(PACKAGE, extra=ONE_RULE[rule])
    assert bool(cycles(edges)) == (rule == "cycle")
    assert bool(private) == (rule == "private")
    assert bool(against_pipeline(edges)) == (rule == "direction")
