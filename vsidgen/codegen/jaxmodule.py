"""Code generation: SymbolicModel -> readable JAX module ``generated/<name>.py``.

The module (template ``vsidgen/codegen/templates/model.py.j2``) defines ``drift(x, u, p)`` and
``output(x, u, p)`` that unpack x, u, p into named locals and compute the
spec's definitions in order, plus the Jacobians ``drift_jac_x/u/p`` and
``output_jac_x/u/p`` derived symbolically (sympy, on the definition-expanded
expressions, with common-subexpression elimination). Output is deterministic:
rebuilding an unchanged spec gives byte-identical files, and :func:`build`
skips writing only when the existing file already holds exactly the text it
would write.

Spec text never becomes code. Every value the template interpolates must be a
:class:`Code` (the jinja ``finalize`` hook refuses anything else), and a
:class:`Code` is made only by

* :func:`py_literal` -- ``repr`` of a ``str``, a Python string literal for any text;
* :func:`comment_text` -- one line for a ``#`` comment: every character that is
  not printable (line breaks ``\\n \\r \\x0b \\x0c \\x1c-\\x1e \\x85 \\u2028 \\u2029``,
  tabs, NUL, lone surrogates) is written as its escape sequence;
* :func:`docstring_text` -- text inside ``\"\"\"...\"\"\"``: backslashes and double quotes
  escaped, non-printable characters other than ``\\n`` escaped;
* :func:`identifier` -- a name that ``str.isidentifier`` accepts and that is not a keyword;
* the expression printer, whose output is parsed back with :mod:`ast` and may
  only read the generated locals and ``jnp``.

Names inside the generated functions: the arguments are ``_x, _u, _p`` and every
other internal name starts with ``_`` (spec names cannot), so states, inputs,
parameters, constants and definitions keep their spec names; a spec name that is
a Python keyword is written ``_kw_<name>``.
"""

from __future__ import annotations

import ast
import dataclasses
import keyword
import math
import os
import pathlib
import re

import jinja2
import sympy
from sympy.printing.numpy import JaxPrinter
from sympy.printing.precedence import precedence

from ..atomic import write_text_atomic
from ..errors import SpecError
from ..spec import GENERATED_MODULE_NAMES, GENERATOR_VERSION, SymbolicModel, compile_spec

__all__ = ["GENERATOR_VERSION", "BuildResult", "Code", "generate", "build", "build_model",
           "embedded_hash", "is_up_to_date", "template_dir", "safe_names", "py_literal",
           "comment_text", "docstring_text", "identifier", "recorded_spec_path"]

#: names the generated module defines or imports without a leading ``_``; a spec name
#: may not be one of these (:func:`vsidgen.spec.symbolic.compile_spec` says so with its location)
RESERVED = GENERATED_MODULE_NAMES


class Code(str):
    """Text that is valid Python where the template puts it (see the module docstring)."""


def py_literal(value: str) -> Code:
    """A Python string literal for any text: ``repr`` of the ``str``, unchanged.

    ``ast.literal_eval(py_literal(s)) == s`` for every ``str`` s (lone surrogates and
    every non-printable character come out as escape sequences, so the literal is
    one line of encodable text).
    """
    if not isinstance(value, str):
        raise TypeError(f"py_literal needs a str, got {type(value).__name__}")
    return Code(repr(value))


def _escape_char(ch: str) -> str:
    return repr(ch)[1:-1] if ch not in "'\"" else ch


def comment_text(value: str) -> Code:
    """``value`` as one line of a ``#`` comment.

    Every character ``c`` with ``not c.isprintable()`` (which covers every line break
    ``str.splitlines`` knows, tabs, NUL and lone surrogates) is replaced by its escape
    sequence (``\\n``, ``\\u2028``...), so the comment can never end early.
    """
    return Code("".join(ch if ch.isprintable() else _escape_char(ch) for ch in str(value)))


def docstring_text(value: str) -> Code:
    """``value`` for the inside of a ``\"\"\"`` docstring, read back exactly.

    ``\\`` and ``"`` are escaped (no escape sequence and no closing quote can come from
    the text), ``\\n`` stays a line break, every other non-printable character becomes
    its escape sequence, and trailing spaces of each line are dropped.
    """
    out = []
    for ch in str(value):
        if ch == "\\":
            out.append("\\\\")
        elif ch == '"':
            out.append('\\"')
        elif ch == "\n" or ch.isprintable():
            out.append(ch)
        else:
            out.append(_escape_char(ch))
    return Code("\n".join(line.rstrip(" ") for line in "".join(out).split("\n")))


def identifier(name: str) -> Code:
    """``name`` when it is a Python identifier and not a keyword (else ValueError: a bug)."""
    if not (isinstance(name, str) and name.isidentifier() and not keyword.iskeyword(name)):
        raise ValueError(f"not a usable identifier: {name!r}")
    return Code(name)


def _finalize(value):
    """jinja ``finalize``: only :class:`Code` and integers reach the generated text."""
    if isinstance(value, Code):
        return value
    if isinstance(value, bool) or value is None:
        raise TypeError(f"template interpolates {value!r}")
    if isinstance(value, int):
        return value
    if isinstance(value, tuple) and all(isinstance(v, int) and not isinstance(v, bool)
                                        for v in value):
        return value
    raise TypeError(f"template interpolates unescaped {type(value).__name__} {value!r}")


def template_dir() -> pathlib.Path:
    """The templates shipped inside the package (``vsidgen/codegen/templates``), so an
    installed wheel can generate code."""
    return pathlib.Path(__file__).resolve().parent / "templates"


class _Printer(JaxPrinter):
    """sympy's JAX printer, writing ``jnp.`` and readable literals."""

    def _module_format(self, fqn, register=True):
        out = super()._module_format(fqn, register)
        return out.replace("jax.numpy.", "jnp.")

    def _print_Float(self, expr):
        return repr(float(expr))

    def _print_Integer(self, expr):
        # a Python int beyond 2**53 would overflow JAX's integer conversion
        return str(int(expr)) if abs(int(expr)) <= 2**53 else repr(float(expr))

    def _print_Rational(self, expr):
        if max(abs(expr.p), expr.q) > 2**53:
            return repr(float(expr))
        return f"{expr.p}/{expr.q}"

    def _print_Half(self, expr):
        return "0.5"

    def _print_Pow(self, expr, rational=False):
        base, exp = expr.args
        b = self.parenthesize(base, precedence(expr))
        if exp == sympy.S.Half:
            return f"jnp.sqrt({self._print(base)})"
        if exp == -sympy.S.Half:
            return f"(1/jnp.sqrt({self._print(base)}))"
        if exp == -1:
            return f"(1/{b})"
        if exp.is_Integer and exp < 0:
            return f"(1/{b}**{-int(exp)})"
        if exp.is_Integer:
            return f"{b}**{int(exp)}"
        return f"{b}**{self.parenthesize(exp, precedence(expr))}"

    def _nested(self, fn, args):
        args = [self._print(a) for a in args]
        out = args[-1]
        for a in reversed(args[:-1]):
            out = f"{fn}({a}, {out})"
        return out

    def _print_Min(self, expr):
        return self._nested("jnp.minimum", expr.args)

    def _print_Max(self, expr):
        return self._nested("jnp.maximum", expr.args)

    def _print_Heaviside(self, expr):
        h0 = expr.args[1] if len(expr.args) > 1 else sympy.S.Half
        return f"jnp.heaviside({self._print(expr.args[0])}, {self._print(sympy.Float(h0))})"

    def _print_Abs(self, expr):
        return f"jnp.abs({self._print(expr.args[0])})"

    def _print_sign(self, expr):
        return f"jnp.sign({self._print(expr.args[0])})"

    def _print_DiracDelta(self, expr):
        return "0.0"

    def _print_Tuple(self, expr):
        return "(" + ", ".join(self._print(a) for a in expr.args) + ("," if len(expr.args) == 1 else "") + ")"

    def _print_Interp(self, expr):
        x, xs, ys = (self._print(a) for a in expr.args)
        return f"jnp.interp({x}, jnp.asarray({xs}), jnp.asarray({ys}))"

    def _print_InterpSlope(self, expr):
        x, xs, ys = (self._print(a) for a in expr.args)
        return f"_interp_slope({x}, jnp.asarray({xs}), jnp.asarray({ys}))"

    def _print_Exp1(self, expr):
        return "jnp.e"

    def _print_Pi(self, expr):
        return "jnp.pi"


def safe_names(symbolic: SymbolicModel) -> dict[str, str]:
    """Spec name -> Python identifier used in the generated module.

    Spec names are kept; a Python keyword (a state ``lambda``) becomes ``_kw_lambda``
    (spec names never start with ``_``, so this cannot meet another name).
    """
    names = ([v.name for v in symbolic.states] + [v.name for v in symbolic.inputs]
             + [p.name for p in symbolic.parameters] + [c.name for c in symbolic.constants]
             + [n for n, _ in symbolic.definitions])
    out = {}
    for n in names:
        if n in RESERVED or n.startswith("_"):
            raise SpecError(f"name `{n}` is reserved by the generated module",
                            path=symbolic.source_path,
                            hint="choose another name")
        out[n] = str(identifier("_kw_" + n if keyword.iskeyword(n) else n))
    return out


def _printer() -> _Printer:
    return _Printer({"fully_qualified_modules": True, "allow_unknown_functions": False})


def _clean(expr: sympy.Expr) -> sympy.Expr:
    """Drop DiracDelta terms (derivatives of sign/Heaviside: zero almost everywhere)."""
    if expr.has(sympy.DiracDelta):
        expr = expr.replace(lambda e: isinstance(e, sympy.DiracDelta), lambda e: sympy.S.Zero)
    return expr


_CSE_NAME = re.compile(r"_c[0-9]+")


def _print(printer: _Printer, expr, allowed: frozenset) -> Code:
    """``expr`` as one line of Python that reads only ``allowed`` names, ``jnp`` and CSE locals.

    The printed text is parsed back (:func:`ast.parse`); a name the generated function
    does not define (``inf``, ``nan``, ``zoo``...) or a literal that is not a finite
    number raises SpecError instead of reaching the module.
    """
    text = printer.doprint(expr)
    bad = "Not supported" in text or any(not c.isprintable() for c in text)
    if not bad:
        try:
            tree = ast.parse(text, mode="eval")
        except (SyntaxError, ValueError, RecursionError, MemoryError):
            bad = True
        else:
            for node in ast.walk(tree):
                if isinstance(node, ast.Name) and not (
                        node.id in allowed or _CSE_NAME.fullmatch(node.id)):
                    bad = True
                elif isinstance(node, ast.Constant) and (
                        isinstance(node.value, bool) or not isinstance(node.value, (int, float))
                        or not math.isfinite(node.value)):
                    bad = True
    if bad:
        raise SpecError(f"cannot generate JAX code for `{str(expr)[:200]}`",
                        hint="this construct (or a value that is not a finite number) is not "
                             "supported by the code generator")
    return Code(text)


def _needed_definitions(symbolic: SymbolicModel, exprs) -> list[tuple[str, sympy.Expr]]:
    syms = {sympy.Symbol(n, real=True): (n, e) for n, e in symbolic.definitions}
    needed: set[str] = set()
    stack = [s for e in exprs for s in e.free_symbols if s in syms]
    while stack:
        s = stack.pop()
        n, e = syms[s]
        if n not in needed:
            needed.add(n)
            stack.extend(t for t in e.free_symbols if t in syms)
    return [(n, e) for n, e in symbolic.definitions if n in needed]


def _used_locals(exprs, rename) -> set[str]:
    """Names of the generated locals that ``exprs`` read (so each function unpacks only those)."""
    return {str(rename.get(s, s)) for e in exprs for s in sympy.sympify(e).free_symbols}


def _jacobian_body(printer, exprs, variables, rename, shape, allowed) -> dict:
    rows = []
    for e in exprs:
        # an entry whose variable does not occur is zero without differentiating (a model of
        # n states has n² + n·n_p entries, most of them zero in a large sparse model)
        occurs = e.free_symbols
        rows.append([_clean(sympy.diff(e, v)) if v in occurs else sympy.S.Zero for v in variables])
    flat = [entry for row in rows for entry in row]
    if not flat:
        return {"cse": [], "matrix": None, "shape": shape, "used": set(), "unpack": []}
    gen = (sympy.Symbol(f"_c{i}", real=True) for i in range(10**9))
    replacements, reduced = sympy.cse(flat, symbols=gen, order="canonical")
    cse_lines = [(identifier(str(s)), _print(printer, _clean(v).xreplace(rename), allowed))
                 for s, v in replacements]
    memo: dict = {}      # equal entries (zeros above all) printed and checked once

    def printed_entry(r):
        if r not in memo:
            memo[r] = _print(printer, _clean(r).xreplace(rename), allowed)
        return memo[r]

    printed = [printed_entry(r) for r in reduced]
    ncol = shape[1]
    matrix = [Code(", ".join(printed[i * ncol:(i + 1) * ncol])) for i in range(shape[0])]
    used = _used_locals([v for _, v in replacements] + list(reduced), rename)
    return {"cse": cse_lines, "matrix": matrix, "shape": shape, "used": used}


def _fmt_equation(lhs: str, expr: sympy.Expr) -> Code:
    return docstring_text(f"{lhs} = {sympy.sstr(expr)}")


def _names_line(names) -> Code:
    return docstring_text(", ".join(names))


def _tuple_literal(names) -> Code:
    return Code("(" + "".join(py_literal(n) + ", " for n in names) + ")")


def generate(symbolic: SymbolicModel, *, spec_path: str | None = None) -> str:
    """The source text of the generated module for ``symbolic``.

    ``spec_path`` is recorded as ``SPEC_PATH`` (default: :func:`recorded_spec_path`).
    """
    names = safe_names(symbolic)
    rename = {sympy.Symbol(n, real=True): sympy.Symbol(s, real=True) for n, s in names.items()}
    allowed = frozenset(names.values()) | {"jnp", "_interp_slope"}
    printer = _printer()
    pr = lambda e: _print(printer, _clean(e).xreplace(rename), allowed)  # noqa: E731
    if spec_path is None:
        spec_path = recorded_spec_path(symbolic.source_path)

    slots = []
    for vec, kind, items in (("_x", "state", symbolic.states), ("_u", "input", symbolic.inputs),
                             ("_p", "parameter", symbolic.parameters)):
        for i, v in enumerate(items):
            note = f"{kind} {v.name}" + (f" [{v.unit}]" if v.unit else "")
            if getattr(v, "fixed", False):
                note += " (fixed)"
            slots.append((identifier(names[v.name]), Code(vec), i, comment_text(note)))

    def unpack(used) -> list:
        return [slot for slot in slots if slot[0] in used]

    def func_body(exprs, lhs_names):
        defs = _needed_definitions(symbolic, exprs)
        used = _used_locals(list(exprs) + [e for _, e in defs], rename)
        return {
            "used": used, "unpack": unpack(used),
            "definitions": [(identifier(names[n]), pr(e)) for n, e in defs],
            "results": [pr(e) for e in exprs],
            "doc": [_fmt_equation(n, e) for n, e in defs]
                   + [_fmt_equation(l, e) for l, e in zip(lhs_names, exprs)],
        }

    drift = func_body(symbolic.drift, [f"d{v.name}/dt" for v in symbolic.states])
    output = func_body(symbolic.observations, [o.name for o in symbolic.outputs])
    fx = symbolic.drift_expanded()
    hx = symbolic.observations_expanded()
    xs, us, ps = symbolic.state_symbols, symbolic.input_symbols, symbolic.parameter_symbols
    nx, nu, ny, npar = len(xs), len(us), len(hx), len(ps)
    jacs = {
        "drift_jac_x": _jacobian_body(printer, fx, xs, rename, (nx, nx), allowed),
        "drift_jac_u": _jacobian_body(printer, fx, us, rename, (nx, nu), allowed),
        "drift_jac_p": _jacobian_body(printer, fx, ps, rename, (nx, npar), allowed),
        "output_jac_x": _jacobian_body(printer, hx, xs, rename, (ny, nx), allowed),
        "output_jac_u": _jacobian_body(printer, hx, us, rename, (ny, nu), allowed),
        "output_jac_p": _jacobian_body(printer, hx, ps, rename, (ny, npar), allowed),
    }
    for jac in jacs.values():
        jac["unpack"] = unpack(jac["used"])
    uses_slope = any("_interp_slope(" in line for j in jacs.values()
                     for line in [v for _, v in j["cse"]] + list(j["matrix"] or []))
    env = jinja2.Environment(loader=jinja2.FileSystemLoader(str(template_dir())),
                             keep_trailing_newline=True, trim_blocks=True, lstrip_blocks=True,
                             undefined=jinja2.StrictUndefined, autoescape=False,
                             finalize=_finalize)
    env.filters.update(lit=py_literal, comment=comment_text, doc=docstring_text, ident=identifier)
    template = env.get_template("model.py.j2")


    def fmt_value(value: float) -> Code:
        if not math.isfinite(value):
            raise SpecError(f"constant value {value!r} is not finite", path=symbolic.source_path)
        return Code(repr(float(value)))

    text = template.render(
        name=identifier(symbolic.name), spec_path=py_literal(str(spec_path)),
        spec_hash=py_literal(symbolic.source_hash), version=py_literal(GENERATOR_VERSION),
        version_text=docstring_text(GENERATOR_VERSION),
        spec_path_text=docstring_text(str(spec_path)),
        description=docstring_text(symbolic.description),
        state_names=_names_line(v.name for v in symbolic.states),
        input_names=_names_line(v.name for v in symbolic.inputs),
        output_names=_names_line(v.name for v in symbolic.outputs),
        parameter_names=_names_line(v.name for v in symbolic.parameters),
        states_tuple=_tuple_literal(v.name for v in symbolic.states),
        inputs_tuple=_tuple_literal(v.name for v in symbolic.inputs),
        outputs_tuple=_tuple_literal(v.name for v in symbolic.outputs),
        parameters_tuple=_tuple_literal(v.name for v in symbolic.parameters),
        constants=[(identifier(names[c.name]), fmt_value(c.value),
                    comment_text(f"[{c.unit or '-'}]" + (f" {c.source}" if c.source else "")))
                   for c in symbolic.constants],
        state_labels=[comment_text(f"d{v.name}/dt") for v in symbolic.states],
        output_labels=[comment_text(v.name) for v in symbolic.outputs],
        drift=drift, output=output, jacs=jacs, uses_slope=uses_slope,
    )
    return re.sub(r"[ \t]+\n", "\n", text)


def recorded_spec_path(path) -> str:
    """The spec path written into the module: independent of the working directory.

    ``specs/<path below the nearest enclosing folder named specs>`` when the spec lies
    in such a folder (the repository layout), else the file name alone. POSIX style.
    """
    path = pathlib.Path(path).resolve()
    for parent in path.parents:
        if parent.name == "specs":
            return (pathlib.PurePosixPath("specs") / path.relative_to(parent).as_posix()).as_posix()
    return path.name


def display_path(path) -> str:
    """``path`` relative to the current directory when possible, POSIX style (for messages)."""
    path = pathlib.Path(path)
    try:
        return path.resolve().relative_to(pathlib.Path.cwd().resolve()).as_posix()
    except ValueError:
        return path.resolve().as_posix()


_HASH_RE = re.compile(r"""^SPEC_HASH = ['"]([0-9a-f]+)['"]$""", re.M)


def embedded_hash(module_path) -> str | None:
    """The SPEC_HASH written in an existing generated module (None if absent/unreadable)."""
    try:
        head = pathlib.Path(module_path).read_text(encoding="utf-8")[:20000]
    except (OSError, UnicodeDecodeError):
        return None
    m = _HASH_RE.search(head)
    return m.group(1) if m else None


@dataclasses.dataclass(frozen=True)
class BuildResult:
    """Outcome of building one spec."""

    spec_path: pathlib.Path
    module_path: pathlib.Path
    written: bool          # False: the existing module already held exactly this text
    symbolic: SymbolicModel


def build_model(symbolic: SymbolicModel, *, out_dir="generated", force: bool = False,
                text: str | None = None) -> BuildResult:
    """Write ``out_dir/<name>.py`` for a compiled spec unless it is up to date.

    Up to date means: the file exists and holds exactly the text :func:`generate` gives
    now (so a changed recorded path, template or generator is always rewritten).
    ``text``: that text when the caller has it already (``generate(symbolic)``).
    """
    module_path = pathlib.Path(out_dir) / f"{symbolic.name}.py"
    text = generate(symbolic) if text is None else text
    current = _current_text(module_path)
    if not force and current == text:
        return BuildResult(symbolic.source_path, module_path, False, symbolic)
    if module_path.exists():
        _refuse_foreign_module(symbolic, module_path, current)
    write_text_atomic(module_path, text)
    return BuildResult(symbolic.source_path, module_path, True, symbolic)


_SPEC_PATH_RE = re.compile(r"""^SPEC_PATH = ('[^'\n]*'|"[^"\n]*")$""", re.M)


def generated_from(text: str | None) -> str | None:
    """The SPEC_PATH recorded in a generated module's text (None: not a vsidgen module)."""
    if not text or "generated by vsidgen" not in text[:2000]:
        return None
    m = _SPEC_PATH_RE.search(text[:20000])
    if m is None:
        return None
    try:
        v = ast.literal_eval(m.group(1))
    except (ValueError, SyntaxError):
        return None
    return v if isinstance(v, str) else None


def _refuse_foreign_module(symbolic: SymbolicModel, module_path: pathlib.Path, current: str | None) -> None:
    """Raise SpecError when ``module_path`` exists but is not this spec's module: a file
    vsidgen did not generate, or the module of another spec with the same model name (a
    user's spec named like a shipped one, built from the repository's folder, would replace
    the repository's module). The module of this spec (same recorded SPEC_PATH) is rebuilt."""
    from ..errors import SpecError

    mine = recorded_spec_path(symbolic.source_path)
    theirs = generated_from(current)
    if theirs == mine:
        return
    line = None
    try:
        for i, ln in enumerate(pathlib.Path(symbolic.source_path).read_text(encoding="utf-8").splitlines(), 1):
            if ln.startswith("name:"):
                line = (i, ln)
                break
    except (OSError, UnicodeDecodeError, TypeError):
        pass
    what = (f"{display_path(module_path)} was generated from another spec ({theirs!r}), not from "
            f"{mine!r}" if theirs is not None else
            f"{display_path(module_path)} exists and is not a module vsidgen generated")
    raise SpecError(f"model `{symbolic.name}`: {what}; it is left as it is",
                    path=symbolic.source_path, line=line[0] if line else None,
                    column=1 if line else None, text=line[1] if line else None,
                    hint=f"give this model another `name:` in the spec, run from another folder "
                         f"(a spec outside a `specs` folder writes to ./generated), or delete "
                         f"{display_path(module_path)} if nothing needs it")


def _current_text(module_path: pathlib.Path) -> str | None:
    try:
        if not module_path.is_file():
            return None
        return module_path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError):
        return None


def is_up_to_date(symbolic: SymbolicModel, module_path, *, text: str | None = None) -> bool:
    """True when ``module_path`` holds exactly the text :func:`generate` gives for ``symbolic``
    (``text``: that text, when the caller has it)."""
    return _current_text(pathlib.Path(module_path)) == (generate(symbolic) if text is None else text)


def build(spec_paths, *, out_dir="generated", force: bool = False) -> list[BuildResult]:
    """Compile each spec and write its generated module (skipped when the hash matches).

    Raises:
        SpecError: for the first invalid spec (nothing is written for it).
    """
    if isinstance(spec_paths, (str, os.PathLike)):
        spec_paths = [spec_paths]
    return [build_model(compile_spec(p), out_dir=out_dir, force=force) for p in spec_paths]
