"""The package's dependency rules, read from the source with ``ast`` (docs/architecture.md).

* no import cycle among vsidgen modules (function-local imports count: they are still a
  dependency, only a later one);
* no private name (``_x``; dunders such as ``__version__`` are not private) imported from,
  or read as an attribute of, another vsidgen module;
* no import against the pipeline: a module imports only modules of its own stage or of an
  earlier one (``STAGES`` below, the order of docs/architecture.md); every module has a stage;
* ``jax_enable_x64`` is set only in ``vsidgen/precision.py``;
* the layout shows the pipeline: only the foundation modules and ``cli`` are flat, every other
  stage lives in one subpackage, and a subpackage's stages follow each other.

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
    ("foundation", ("vsidgen", "errors", "interrupts", "precision", "limits", "atomic", "suggest",
                    "metadata", "compilecache", "progress", "engine")),
    ("spec", ("spec.expr", "spec.units", "spec.dataunits", "spec.load", "spec.typed",
              "spec.symbolic", "spec.identifiability", "spec.overrides", "spec")),
    ("codegen", ("codegen.jaxmodule", "codegen")),
    ("model", ("model.runtime", "model.dynamics", "model")),
    ("data", ("data.formats", "data.records", "data.check", "data.simulate", "data")),
    ("estimator", ("estimator.linalg", "estimator.results", "estimator.core", "estimator.problem", "estimator.fit",
                   "estimator")),
    ("evaluation", ("evaluation.signals", "evaluation")),
    ("report", ("report.resultsdir", "report.html", "report")),
    ("fit job", ("fitjob.run", "fitjob.fleet", "fitjob")),
    ("diagnose: leaves", ("discrepancy.pvalues", "discrepancy.vuong", "discrepancy.base",
                          "discrepancy.specwrite")),
    ("diagnose: locate", ("discrepancy.locate",)),
    ("diagnose: catalogue", ("discrepancy.catalogue",)),
    ("diagnose: flight conditions", ("discrepancy.flightconst",)),
    ("diagnose: findings and refit", ("discrepancy.findings", "discrepancy.refit")),
    ("diagnose: fit states", ("discrepancy.fitstate",)),
    ("diagnose: numerics, noise model and delay profiles", ("discrepancy.numerics",
                                                             "discrepancy.noisemodel",
                                                             "discrepancy.delay")),
    ("diagnose: air-relative gust", ("discrepancy.gust",)),
    ("diagnose: score test", ("discrepancy.score",)),
    ("diagnose: gated round model, model families", ("discrepancy.gated", "discrepancy.family")),
    ("diagnose: search", ("discrepancy.search",)),
    ("diagnose: package", ("discrepancy",)),
    ("command line", ("cli", "_entry", "__main__")),
)


def _full(name: str) -> str:
    return "vsidgen" if name == "vsidgen" else f"vsidgen.{name}"


STAGE_OF = {_full(m): i for i, (_, mods) in enumerate(STAGES) for m in mods}

#: the flat modules of the package besides the foundation (and ``vsidgen/__init__.py``)
FLAT = ("cli", "_entry", "__main__")


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
    of the package at ``package`` (``extra``: {module name: source} added to it).

    ``from P import m`` with ``m`` a submodule of ``P`` is an edge to ``P.m`` alone: the
    package ``P`` itself runs for every import of one of its submodules, so, as for
    ``from P.m import x``, it is no edge of its own."""
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
                if not all(f"{target}.{alias.name}" in modules for alias in node.names):
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


def layout_problems(modules, stages=STAGES, flat=FLAT) -> list[str]:
    """Where the package layout does not read as the pipeline: a flat top-level module that is
    neither a foundation module nor in ``flat``; a stage after the foundation whose modules
    are not all in one top-level subpackage (``cli`` excepted); a subpackage whose stages are
    not consecutive."""
    allowed = {_full(m) for m in stages[0][1]} | {_full(m) for m in flat}
    packages = {m.rpartition(".")[0] for m in modules}
    problems = [f"{m} is a flat module outside the foundation" for m in sorted(modules)
                if m.count(".") == 1 and m not in allowed and m not in packages]
    seen: list[str] = []
    for name, mods in stages[1:]:
        if all(m in flat for m in mods):
            continue
        tops = {m.split(".")[0] for m in mods}
        if len(tops) != 1:
            problems.append(f"stage {name!r} spans the subpackages {sorted(tops)}")
            continue
        top = tops.pop()
        if top in seen and seen[-1] != top:
            problems.append(f"subpackage {top!r} holds stage {name!r} after another subpackage's")
        if not seen or seen[-1] != top:
            seen.append(top)
    return problems


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


def test_layout_reads_as_the_pipeline():
    assert layout_problems(set(_sources(PACKAGE))) == []


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
    "vsidgen.model.dynamics": "def f():\n    from ..estimator.fit import _Problem\n    return _Problem\n",
    # and the estimator importing dynamics: with the line above, a cycle
    "vsidgen.estimator.linalg": "from ..model import dynamics\n\ndef g():\n    return dynamics._check\n",
    "vsidgen.data.simulate": "import jax\njax.config.update('jax_enable_x64', True)\n",
}


def test_checks_fail_on_bad_imports():
    edges, private = analyse(PACKAGE, extra=BAD)
    comps = cycles(edges)
    assert any({"vsidgen.model.dynamics", "vsidgen.estimator.fit"} <= set(c) for c in comps), comps
    assert ("vsidgen.model.dynamics", 2, "from vsidgen.estimator.fit import _Problem") in private
    assert ("vsidgen.estimator.linalg", 4, "dynamics._check") in private
    bad = against_pipeline(edges)
    assert any(b.startswith("vsidgen.model.dynamics (stage 'model') imports vsidgen.estimator.fit")
               for b in bad), bad
    assert x64_outside_precision(PACKAGE, extra={
        "vsidgen/data/simulate.py": BAD["vsidgen.data.simulate"]}) == ["vsidgen/data/simulate.py"]
    assert x64_outside_precision(PACKAGE, extra={
        "vsidgen/data/formats.py": "import os\nos.environ['JAX_ENABLE_X64'] = '1'\n"}
        ) == ["vsidgen/data/formats.py"]


def test_layout_check_fails_on_a_flat_or_split_stage():
    modules = set(_sources(PACKAGE))
    assert layout_problems(modules | {"vsidgen.simulate"}) == [
        "vsidgen.simulate is a flat module outside the foundation"]
    split = tuple((n, ("data.formats", "records") if n == "data" else mods) for n, mods in STAGES)
    assert layout_problems(modules, split) == ["stage 'data' spans the subpackages ['data', 'records']"]
    back = STAGES[:3] + (("late spec", ("spec.late",)),) + STAGES[3:]
    assert layout_problems(modules, back) == [
        "subpackage 'spec' holds stage 'late spec' after another subpackage's"]


#: one bad module source per rule (it replaces the module's own source in the analysis)
ONE_RULE = {
    "cycle": {"vsidgen.errors": "from . import suggest\n"},          # suggest imports errors
    "private": {"vsidgen.cli": "from .data.records import _read_header\n"},
    "direction": {"vsidgen.codegen.jaxmodule": "from ..report import html\n"},  # html does not import codegen
}


@pytest.mark.parametrize("rule", sorted(ONE_RULE))
def test_each_rule_alone(rule):
    """One bad import per rule, caught by its own check and by no other one."""
    edges, private = analyse(PACKAGE, extra=ONE_RULE[rule])
    assert bool(cycles(edges)) == (rule == "cycle")
    assert bool(private) == (rule == "private")
    assert bool(against_pipeline(edges)) == (rule == "direction")
