"""Code generation: SymbolicModel -> readable JAX module ``generated/<name>.py``.

The module (template ``templates/model.py.j2``) defines ``drift(x, u, p)`` and
``output(x, u, p)`` that unpack x, u, p into named locals and compute the
spec's definitions in order, plus the Jacobians ``drift_jac_x/u/p`` and
``output_jac_x/u/p`` derived symbolically (sympy, on the definition-expanded
expressions, with common-subexpression elimination). Output is deterministic:
rebuilding an unchanged spec gives byte-identical files, and :func:`build`
skips writing when the embedded ``SPEC_HASH`` already matches.
"""

from __future__ import annotations

import dataclasses
import keyword
import os
import pathlib
import re

import jinja2
import sympy
from sympy.printing.numpy import JaxPrinter
from sympy.printing.precedence import precedence

from .atomic import write_text_atomic
from .errors import SpecError
from .symbolic import GENERATOR_VERSION, SymbolicModel, compile_spec

__all__ = ["GENERATOR_VERSION", "BuildResult", "generate", "build", "build_model",
           "embedded_hash", "template_dir", "safe_names"]

#: names the generated module uses itself (spec names equal to these get a `_` suffix)
RESERVED = frozenset({
    "x", "u", "p", "jnp", "jax", "np", "drift", "output", "drift_jac_x", "drift_jac_u",
    "drift_jac_p", "output_jac_x", "output_jac_u", "output_jac_p", "STATES", "INPUTS",
    "OUTPUTS", "PARAMETERS", "SPEC_PATH", "SPEC_HASH", "GENERATOR_VERSION",
})


def template_dir() -> pathlib.Path:
    """The repository's ``templates/`` folder."""
    import vsidgen
    return pathlib.Path(vsidgen.__file__).resolve().parent.parent / "templates"


class _Printer(JaxPrinter):
    """sympy's JAX printer, writing ``jnp.`` and readable literals."""

    def _module_format(self, fqn, register=True):
        out = super()._module_format(fqn, register)
        return out.replace("jax.numpy.", "jnp.")

    def _print_Float(self, expr):
        return repr(float(expr))

    def _print_Rational(self, expr):
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
    """Spec name -> Python identifier used in the generated module."""
    names = ([v.name for v in symbolic.states] + [v.name for v in symbolic.inputs]
             + [p.name for p in symbolic.parameters] + [c.name for c in symbolic.constants]
             + [n for n, _ in symbolic.definitions])
    taken = set(names) | RESERVED
    out = {}
    for n in names:
        if keyword.iskeyword(n) or n in RESERVED or n.startswith("_"):
            new = n + "_"
            while new in taken:
                new += "_"
            taken.add(new)
            out[n] = new
        else:
            out[n] = n
    return out


def _printer() -> _Printer:
    return _Printer({"fully_qualified_modules": True, "allow_unknown_functions": False})


def _clean(expr: sympy.Expr) -> sympy.Expr:
    """Drop DiracDelta terms (derivatives of sign/Heaviside: zero almost everywhere)."""
    if expr.has(sympy.DiracDelta):
        expr = expr.replace(lambda e: isinstance(e, sympy.DiracDelta), lambda e: sympy.S.Zero)
    return expr


def _print(printer: _Printer, expr) -> str:
    text = printer.doprint(expr)
    if "Not supported" in text or "\n" in text:
        raise SpecError(f"cannot generate JAX code for `{expr}`",
                        hint="this construct is not supported by the code generator")
    return text


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


def _jacobian_body(printer, exprs, variables, rename, shape) -> dict:
    rows = []
    for e in exprs:
        rows.append([_clean(sympy.diff(e, v)) for v in variables])
    flat = [entry for row in rows for entry in row]
    if not flat:
        return {"cse": [], "matrix": None, "shape": shape, "used": set()}
    gen = (sympy.Symbol(f"_c{i}", real=True) for i in range(10**9))
    replacements, reduced = sympy.cse(flat, symbols=gen, order="canonical")
    cse_lines = [(str(s), _print(printer, _clean(v).xreplace(rename))) for s, v in replacements]
    printed = [_print(printer, _clean(r).xreplace(rename)) for r in reduced]
    ncol = shape[1]
    matrix = [printed[i * ncol:(i + 1) * ncol] for i in range(shape[0])]
    used = _used_locals([v for _, v in replacements] + list(reduced), rename)
    return {"cse": cse_lines, "matrix": matrix, "shape": shape, "used": used}


def _fmt_equation(lhs: str, expr: sympy.Expr) -> str:
    return f"{lhs} = {sympy.sstr(expr)}"


def generate(symbolic: SymbolicModel, *, spec_path: str | None = None) -> str:
    """The source text of the generated module for ``symbolic``."""
    names = safe_names(symbolic)
    rename = {sympy.Symbol(n, real=True): sympy.Symbol(s, real=True) for n, s in names.items()}
    printer = _printer()
    pr = lambda e: _print(printer, _clean(e).xreplace(rename))  # noqa: E731
    if spec_path is None:
        spec_path = display_path(symbolic.source_path)

    def func_body(exprs, lhs_names):
        defs = _needed_definitions(symbolic, exprs)
        return {
            "used": _used_locals(list(exprs) + [e for _, e in defs], rename),
            "definitions": [(names[n], pr(e)) for n, e in defs],
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
        "drift_jac_x": _jacobian_body(printer, fx, xs, rename, (nx, nx)),
        "drift_jac_u": _jacobian_body(printer, fx, us, rename, (nx, nu)),
        "drift_jac_p": _jacobian_body(printer, fx, ps, rename, (nx, npar)),
        "output_jac_x": _jacobian_body(printer, hx, xs, rename, (ny, nx)),
        "output_jac_u": _jacobian_body(printer, hx, us, rename, (ny, nu)),
        "output_jac_p": _jacobian_body(printer, hx, ps, rename, (ny, npar)),
    }
    uses_slope = any("_interp_slope(" in line for j in jacs.values()
                     for line in [v for _, v in j["cse"]] + [c for row in (j["matrix"] or []) for c in row])
    env = jinja2.Environment(loader=jinja2.FileSystemLoader(str(template_dir())),
                             keep_trailing_newline=True, trim_blocks=True, lstrip_blocks=True,
                             undefined=jinja2.StrictUndefined, autoescape=False)
    template = env.get_template("model.py.j2")

    def doc(text: str) -> str:
        return str(text).replace("\\", "/").replace('"""', "'''")

    text = template.render(
        m=symbolic, spec_path=spec_path, version=GENERATOR_VERSION, names=names,
        description=doc(symbolic.description),
        constants=[(names[c.name], repr(float(c.value)), c.unit, doc(c.source)) for c in symbolic.constants],
        states=[(names[v.name], v) for v in symbolic.states],
        inputs=[(names[v.name], v) for v in symbolic.inputs],
        parameters=[(names[p.name], p) for p in symbolic.parameters],
        drift=drift, output=output, jacs=jacs, uses_slope=uses_slope, doc=doc,
        repr=repr,
    )
    return re.sub(r"[ \t]+\n", "\n", text)


def display_path(path) -> str:
    """``path`` relative to the current directory when possible, POSIX style."""
    path = pathlib.Path(path)
    try:
        return path.resolve().relative_to(pathlib.Path.cwd().resolve()).as_posix()
    except ValueError:
        return path.resolve().as_posix()


_HASH_RE = re.compile(r'^SPEC_HASH = "([0-9a-f]+)"$', re.M)


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
    written: bool          # False: the existing module already had this spec hash
    symbolic: SymbolicModel


def build_model(symbolic: SymbolicModel, *, out_dir="generated", force: bool = False) -> BuildResult:
    """Write ``out_dir/<name>.py`` for a compiled spec unless it is up to date."""
    module_path = pathlib.Path(out_dir) / f"{symbolic.name}.py"
    if not force and embedded_hash(module_path) == symbolic.source_hash:
        return BuildResult(symbolic.source_path, module_path, False, symbolic)
    write_text_atomic(module_path, generate(symbolic))
    return BuildResult(symbolic.source_path, module_path, True, symbolic)


def build(spec_paths, *, out_dir="generated", force: bool = False) -> list[BuildResult]:
    """Compile each spec and write its generated module (skipped when the hash matches).

    Raises:
        SpecError: for the first invalid spec (nothing is written for it).
    """
    if isinstance(spec_paths, (str, os.PathLike)):
        spec_paths = [spec_paths]
    return [build_model(compile_spec(p), out_dir=out_dir, force=force) for p in spec_paths]
