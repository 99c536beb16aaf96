"""Safe expression parser: spec text -> sympy expression.

The text is parsed with ``ast.parse(text, mode="eval")`` and the syntax tree is
walked against a strict whitelist; sympy objects are built directly from the
nodes. Nothing from the text is ever evaluated, imported or looked up as a
Python attribute (no ``eval``/``exec``/``sympify``).

Accepted syntax:

* numbers (int and float literals; no complex), declared names, ``pi``,
* ``+ - * / **`` and unary ``+``/``-``, parentheses,
* calls of the whitelisted functions with positional arguments::

      sin cos tan asin acos atan atan2 exp log sqrt abs tanh sign min max
      sat(x, lo, hi)        = Min(Max(x, lo), hi)                (hard saturation)
      smoothsat(x, lo, hi)  = lo + (hi - lo) * (tanh(2 (x - m)/(hi - lo)) + 1)/2,
                              m = (lo + hi)/2                   (smooth saturation:
                              value m and unit slope at x = m, tends to lo / hi)
      interp(x, [x0, x1, ...], [y0, y1, ...])  linear lookup table (clamped at the ends,
                              like ``numpy.interp``); list literals only here.

Anything else (attributes, subscripts, lambdas, comprehensions, keyword
arguments, strings, dunder names, unknown names or functions) raises
:class:`~vsidgen.errors.SpecError` with the column of the offending token.
"""

from __future__ import annotations

import ast
import keyword
import re
import warnings
import math
from collections.abc import Mapping

import sympy

from ..errors import SpecError

MAX_LENGTH = 2000
MAX_DEPTH = 64
MAX_EXPONENT = 100
MAX_CONSTANT = 1e300
_KW_MARK = "\u0436"  # a non-ASCII identifier letter (never in a valid spec name)
_IDENT = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")

#: whitelisted function names -> number of positional arguments (None: >= 2)
FUNCTIONS: dict[str, int | None] = {
    "sin": 1, "cos": 1, "tan": 1, "asin": 1, "acos": 1, "atan": 1, "atan2": 2,
    "exp": 1, "log": 1, "sqrt": 1, "abs": 1, "tanh": 1, "sign": 1,
    "min": None, "max": None, "sat": 3, "smoothsat": 3, "interp": 3,
}

_DELAY_DECLARATION = ("declared on the input, in seconds: "
                      "`inputs: {de: {unit: rad, delay: 0.1}}`")
_DELAY_HINT = "a pure transport delay of an input is " + _DELAY_DECLARATION
_PIECEWISE_HINT = ("piecewise terms are written with max/min (a break: `max(alpha - 0.2, 0)`), "
                   "sign, sat(x, lo, hi) or interp(x, [x0, x1, ...], [y0, y1, ...])")
#: functions of other languages a new user writes, and what to write in a spec instead
FUNCTION_EQUIVALENTS: dict[str, str] = {
    "ln": "the natural logarithm is `log(x)`",
    "log10": "write `log(x)/log(10)`",
    "log2": "write `log(x)/log(2)`",
    **dict.fromkeys(("pow", "power"), "write `x**y` for a power"),
    **dict.fromkeys(("sq", "square", "sqr"), "write `x**2`"),
    "fabs": "write `abs(x)`",
    **dict.fromkeys(("arcsin", "arccos", "arctan", "arctan2"),
                    "inverse trigonometric functions are asin, acos, atan and atan2"),
    **dict.fromkeys(("sinh", "cosh"), "write it with exp: sinh(x) = (exp(x) - exp(-x))/2"),
    **dict.fromkeys(("deg2rad", "radians", "deg", "d2r"),
                    "multiply by `pi/180` (`pi` is built in), or convert the data column to "
                    "radians in the data map (`scale:`)"),
    **dict.fromkeys(("rad2deg", "degrees", "r2d"), "multiply by `180/pi` (`pi` is built in)"),
    **dict.fromkeys(("clip", "clamp", "saturate", "saturation", "limit", "sat2"),
                    "hard limits are `sat(x, lo, hi)`, smooth ones `smoothsat(x, lo, hi)`"),
    **dict.fromkeys(("heaviside", "step", "Heaviside"),
                    "a unit step is `(sign(x) + 1)/2`; " + _PIECEWISE_HINT),
    **dict.fromkeys(("if", "ifelse", "where", "piecewise", "Piecewise", "switch"), _PIECEWISE_HINT),
    **dict.fromkeys(("delay", "Delay", "timedelay", "transport_delay", "lag"), _DELAY_HINT),
    **dict.fromkeys(("der", "diff", "d", "derivative", "dot", "ddt"),
                    "the left side of a `drift:` entry is the state's derivative; the right side "
                    "uses values only (a derivative of another state: write its equation, or "
                    "name it under `definitions:`)"),
}

#: names available in every expression unless the spec declares them
BUILTIN_NAMES: dict[str, sympy.Basic] = {"pi": sympy.pi}

_UNARY = {
    "sin": sympy.sin, "cos": sympy.cos, "tan": sympy.tan, "asin": sympy.asin,
    "acos": sympy.acos, "atan": sympy.atan, "exp": sympy.exp, "log": sympy.log,
    "sqrt": sympy.sqrt, "abs": sympy.Abs, "tanh": sympy.tanh, "sign": sympy.sign,
}


# ---------------------------------------------------------------------------
# lookup tables
# ---------------------------------------------------------------------------

def _table_values(xs, ys):
    return [float(v) for v in xs], [float(v) for v in ys]


def _interp_numeric(x: float, xs, ys) -> float:
    xs, ys = _table_values(xs, ys)
    if x <= xs[0]:
        return ys[0]
    if x >= xs[-1]:
        return ys[-1]
    for i in range(len(xs) - 1):
        if xs[i] <= x <= xs[i + 1]:
            w = (x - xs[i]) / (xs[i + 1] - xs[i])
            return ys[i] + w * (ys[i + 1] - ys[i])
    return ys[-1]  # pragma: no cover


def _slope_numeric(x: float, xs, ys) -> float:
    xs, ys = _table_values(xs, ys)
    if x < xs[0] or x > xs[-1]:
        return 0.0
    for i in range(len(xs) - 1):
        if xs[i] <= x < xs[i + 1] or (i == len(xs) - 2 and x == xs[-1]):
            return (ys[i + 1] - ys[i]) / (xs[i + 1] - xs[i])
    return 0.0  # pragma: no cover


class Interp(sympy.Function):
    """Linear interpolation ``Interp(x, (x0, x1, ...), (y0, y1, ...))``.

    The table is held in the arguments as sympy Tuples of numbers (strictly
    increasing x). Clamped outside the table (like ``numpy.interp``). The
    derivative with respect to x is the piecewise-constant slope
    :class:`InterpSlope`; generated code prints ``jnp.interp(x, xp, fp)``.
    """

    nargs = 3

    @classmethod
    def eval(cls, x, xs, ys):
        if x.is_Number and x.is_finite:
            return sympy.Float(_interp_numeric(float(x), xs, ys))
        return None

    def fdiff(self, argindex=1):
        if argindex != 1:
            return sympy.S.Zero
        return InterpSlope(*self.args)

    def _eval_derivative(self, s):
        # the tables are constants: only the first argument depends on s
        return self.fdiff(1) * self.args[0].diff(s)

    def _eval_is_real(self):
        return True


class InterpSlope(sympy.Function):
    """Slope of :class:`Interp`: (y[i+1]-y[i])/(x[i+1]-x[i]) on segment i, 0 outside."""

    nargs = 3

    @classmethod
    def eval(cls, x, xs, ys):
        if x.is_Number and x.is_finite:
            return sympy.Float(_slope_numeric(float(x), xs, ys))
        return None

    def fdiff(self, argindex=1):
        return sympy.S.Zero

    def _eval_derivative(self, s):
        return sympy.S.Zero

    def _eval_is_real(self):
        return True


def smoothsat(x, lo, hi):
    """Smooth saturation lo + (hi-lo)*(tanh(2*(x-mid)/(hi-lo)) + 1)/2, mid=(lo+hi)/2."""
    mid = (lo + hi) / 2
    return lo + (hi - lo) * (sympy.tanh(2 * (x - mid) / (hi - lo)) + 1) / 2


# ---------------------------------------------------------------------------
# parser
# ---------------------------------------------------------------------------

class _Ctx:
    def __init__(self, text, namespace, path, line, column, free_names, units):
        self.text = text
        self.namespace = namespace
        self.path = path
        self.line = line
        self.column = column
        self.free_names = free_names
        self.units = units
        self.free: dict[str, sympy.Symbol] = {}
        self.aliases: dict[str, str] = {}
        self.flat = text   # the text ast parsed (its byte offsets are the nodes')


def _source(ctx: _Ctx, node: ast.AST) -> str | None:
    """The text of ``node`` as written (ast normalises names to NFKC and numbers to values)."""
    end = getattr(node, "end_col_offset", None)
    if end is None or getattr(node, "end_lineno", 1) != getattr(node, "lineno", 1):
        return None
    return ctx.flat.encode("utf-8")[node.col_offset:end].decode("utf-8", "replace")


def _error(ctx: _Ctx, message: str, node: ast.AST | None = None, *, hint: str | None = None,
           offset: int | None = None, length: int | None = None):
    if node is not None and hasattr(node, "col_offset"):
        offset = _char_offset(ctx.text, node.col_offset)
        end = getattr(node, "end_col_offset", None)
        if getattr(node, "end_lineno", 1) != getattr(node, "lineno", 1):
            end = None
        length = (_char_offset(ctx.text, end) - offset) if end is not None else 1
    return _make_error(ctx.text, message, path=ctx.path, line=ctx.line, column=ctx.column,
                       offset=offset, length=length, hint=hint)


def _char_offset(text: str, byte_offset: int) -> int:
    """The character offset in ``text`` of the UTF-8 byte offset ``ast`` reports (they
    differ after a non-ASCII character, e.g. a Greek or a look-alike Cyrillic letter)."""
    return len(text.encode("utf-8")[:byte_offset].decode("utf-8", "ignore"))


def non_ascii_note(name: str) -> str | None:
    """Names the non-ASCII characters of ``name`` (a look-alike letter pasted from a
    document is invisible in the message otherwise)."""
    import unicodedata

    odd = [ch for ch in dict.fromkeys(name) if not ch.isascii()]
    if not odd:
        return None
    return "`{}` contains {}".format(name, ", ".join(
        f"U+{ord(ch):04X} {unicodedata.name(ch, 'unnamed character')}" for ch in odd))


def _make_error(text, message, *, path, line, column, offset, length, hint=None):
    shown = text.replace("\n", " ")
    if len(shown) > 200:
        lo = max(0, (offset or 0) - 60)
        shown_part = shown[lo:lo + 160]
        span = (((offset or 0) - lo) + 1, max(1, min(length or 1, 160))) if offset is not None else None
        shown = shown_part
    else:
        span = ((offset + 1), max(1, length or 1)) if offset is not None else None
    col = column
    if column is not None and offset is not None:
        col = column + offset
    return SpecError(message, path=path, line=line, column=col, text=shown, hint=hint, span=span)


#: a factor written directly against the next one, as on paper: ``(1 + Zq)q``, ``2x``, ``a b``
_IMPLICIT_PRODUCT = re.compile(
    r"(\)|(?<![\w.])\d+\.?\d*(?:[eE][-+]?\d+)?(?![eE][-+]?\d)(?=[A-Za-z_(])"
    r"|(?<![\w.])[A-Za-z_]\w*(?=\s+[A-Za-z_]))"
    r"(\s*)([A-Za-z_]\w*|\()")


def _statement_hint(text: str) -> str | None:
    """A hint for a statement written where one expression belongs (``x;``, ``qdot = …``)."""
    t = text.strip()
    if t.endswith(";"):
        return "remove the trailing `;`: an entry holds one expression"
    if "=" in t.replace("==", "").replace("<=", "").replace(">=", "").replace("!=", ""):
        return ("an entry holds the right-hand side only: the key names what it defines "
                "(`q: MQ*q + MDE*de`, not `q: qdot = MQ*q + MDE*de`)")
    return None


def _implicit_product_hint(text: str) -> str | None:
    """A hint for a product written without ``*``, showing the first one found."""
    for m in _IMPLICIT_PRODUCT.finditer(text):
        left, right = m.group(1), m.group(3)
        if keyword.iskeyword(left) or keyword.iskeyword(right):
            continue
        return f"write `*` for a product: `{left}{m.group(2)}{right}` → `{left}*{right}`"
    return None


#: typographic characters pasted from documents, and what to write instead
_TYPOGRAPHY = {"\u2212": "-", "\u2013": "-", "\u2014": "-", "\u00d7": "*", "\u00b7": "*",
               "\u22c5": "*", "\u2219": "*", "\u00f7": "/", "\u2044": "/", "\u2215": "/"}
_SUPERSCRIPT = dict(zip("\u2070\u00b9\u00b2\u00b3\u2074\u2075\u2076\u2077\u2078\u2079\u207b",
                        "0123456789-"))


def _typography_hint(text: str, units: bool) -> str | None:
    """A hint for a typographic or invisible character in an expression (U+2212 minus,
    × and · for products, superscript powers, no-break and zero-width spaces)."""
    import unicodedata

    power = "^" if units else "**"
    for ch in text:
        if ch in _TYPOGRAPHY:
            return f"write the ASCII `{_TYPOGRAPHY[ch]}` instead of `{ch}` ({unicodedata.name(ch, '')})"
        if ch in _SUPERSCRIPT:
            return f"write powers as `{power}2`, not as superscripts (`{ch}`)"
        if unicodedata.category(ch) in ("Zs", "Cf", "Cc") and ch != " ":
            return (f"remove the invisible character U+{ord(ch):04X} "
                    f"({unicodedata.name(ch, 'control character')}) or replace it with a space")
        plain = unicodedata.normalize("NFKC", ch)
        if not ch.isascii() and plain.isascii() and plain.strip():
            return f"write the ASCII `{plain}` instead of `{ch}` ({unicodedata.name(ch, '')})"
    return None


def _ascii_greek(name: str) -> str:
    """``α`` → ``alpha``, ``δe`` → ``deltae``: Greek letters spelt as their ASCII names."""
    import unicodedata

    out = []
    for ch in name:
        uname = unicodedata.name(ch, "")
        if uname.startswith("GREEK SMALL LETTER ") or uname.startswith("GREEK CAPITAL LETTER "):
            word = uname.rsplit(" ", 1)[-1].lower()
            out.append(word if uname.startswith("GREEK SMALL") else word.capitalize())
        else:
            out.append(ch)
    return "".join(out)


def did_you_mean(name: str, candidates) -> str | None:
    """A 'did you mean `x`?' hint for ``name`` among ``candidates`` (or None)."""
    from ..suggest import closest

    close = closest(name, sorted(candidates))
    if close:
        return f"did you mean `{close[0]}`?"
    return None


def _check_number(ctx, value, node):
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise _error(ctx, "only int and float number literals are allowed", node)
    written = _source(ctx, node) or ""
    if written[:2].lower() in ("0x", "0o", "0b"):
        # `0x10` was read as 16 (session 46): numbers in a spec are plain decimal
        raise _error(ctx, f"number literal `{written}` is not decimal", node,
                     hint="write numbers in plain decimal, e.g. 16 or 1e-3")
    if value == 0 and re.search(r"[1-9]", re.split(r"[eE]", written, maxsplit=1)[0]):
        # `1e-999` silently became 0 and its term vanished (session 46)
        raise _error(ctx, f"number literal `{written}` is too small: it becomes 0 in double "
                          "precision", node,
                     hint=f"literals must be 0 or at least {1 / MAX_CONSTANT:g} in magnitude")
    if isinstance(value, float) and not math.isfinite(value):
        raise _error(ctx, "number literal is not finite", node, hint="use a finite number")
    if abs(value) > MAX_CONSTANT:
        raise _error(ctx, "number literal is too large", node,
                     hint=f"literals must be at most {MAX_CONSTANT:g} in magnitude")
    if isinstance(value, int):
        return sympy.Integer(value)
    return sympy.Float(repr(value), 15)


def _usable_constant(value) -> bool:
    """True when the constant ``value`` is real, finite and 0 or of magnitude in [1e-300, 1e300].

    Compared in sympy's arbitrary-exponent floats, so 1e-600 and 1e600 are seen as such
    (in IEEE doubles they would silently become 0 and inf).
    """
    try:
        v = value if value.is_Number else value.evalf(15)
        if not (v.is_Number and v.is_finite and v.is_extended_real):
            return False
        mag = abs(v)
        return bool(mag == 0 or (sympy.Float(1 / MAX_CONSTANT) <= mag <= sympy.Float(MAX_CONSTANT)))
    except (OverflowError, ValueError, TypeError, ZeroDivisionError, AttributeError):
        return False


def _folded(ctx: _Ctx, result, node: ast.AST):
    """``result`` of the operation at ``node``, refused when folding made it unusable.

    sympy folds numbers and merges powers as it builds (``1e300*1e300`` is one Float
    1e600, ``(a**100)**100`` is ``a**10000``, ``a**100*a**100`` is ``a**200``). The new
    node and its direct arguments -- where folding puts its results -- must hold only
    numbers of magnitude at most :data:`MAX_CONSTANT` and numeric exponents of magnitude
    at most :data:`MAX_EXPONENT`.
    """
    if not isinstance(result, sympy.Basic):
        return result
    for part in (result, *result.args):
        if part in (sympy.zoo, sympy.oo, -sympy.oo, sympy.nan):
            raise _error(ctx, "this part of the expression is not finite "
                              "(division by zero or an infinite value)", node)
        if part.is_number and not isinstance(part, (sympy.Tuple, sympy.logic.boolalg.Boolean)):
            if not _usable_constant(part):
                raise _error(ctx, "the constant part of this expression is not a real number of "
                                  f"magnitude between {1 / MAX_CONSTANT:g} and {MAX_CONSTANT:g} "
                                  "(or 0)", node,
                             hint="write the value as a number literal; check the constant factors")
        if part.is_Pow and part.exp.is_Number and abs(part.exp) > MAX_EXPONENT:
            raise _error(ctx, f"the total exponent of this power exceeds {MAX_EXPONENT}", node,
                         hint=f"powers (also nested ones such as (a**10)**20) must have exponents "
                              f"of magnitude at most {MAX_EXPONENT}")
    return result


def _convert(ctx: _Ctx, node: ast.AST, depth: int):
    if depth > MAX_DEPTH:
        raise _error(ctx, "expression is nested too deeply", node,
                     hint=f"at most {MAX_DEPTH} levels of nesting; use definitions")
    if isinstance(node, ast.Expression):
        return _convert(ctx, node.body, depth + 1)
    if isinstance(node, ast.Constant):
        return _check_number(ctx, node.value, node)
    if isinstance(node, ast.Name):
        return _name(ctx, node)
    if isinstance(node, ast.UnaryOp):
        operand = _convert(ctx, node.operand, depth + 1)
        if isinstance(node.op, ast.USub):
            return _folded(ctx, -operand, node)
        if isinstance(node.op, ast.UAdd):
            return operand
        raise _error(ctx, f"operator `{_op_text(node.op)}` is not allowed", node,
                     hint="allowed: + - * / ** and unary minus")
    if isinstance(node, ast.BinOp):
        if ctx.units and isinstance(node.op, ast.BitXor):
            op = ast.Pow()
        else:
            op = node.op
        if not isinstance(op, (ast.Add, ast.Sub, ast.Mult, ast.Div, ast.Pow)):
            hint = "allowed: + - * / **"
            if isinstance(op, ast.BitXor):
                hint = ("use ** for powers: `" + ctx.text.strip().replace("^", "**") + "`")
            # point at the operator itself, not at the whole operation (`^` binds last, so
            # the operation of `k*a + k*a^2` was the whole line; session 44)
            gap_start = _char_offset(ctx.text, getattr(node.left, "end_col_offset", 0) or 0)
            gap_end = _char_offset(ctx.text, getattr(node.right, "col_offset", 0) or 0)
            sym = _op_text(node.op)
            at = ctx.text.find(sym, gap_start, max(gap_end, gap_start))
            if at < 0 or getattr(node, "end_lineno", 1) != getattr(node, "lineno", 1):
                raise _error(ctx, f"operator `{sym}` is not allowed", node, hint=hint)
            raise _error(ctx, f"operator `{sym}` is not allowed", None, hint=hint, offset=at,
                         length=len(sym))
        if isinstance(op, (ast.Add, ast.Sub, ast.Mult, ast.Div)):
            return _chain(ctx, node, depth)
        left = _convert(ctx, node.left, depth + 1)
        right = _convert(ctx, node.right, depth + 1)
        if isinstance(op, ast.Pow):
            if right.is_Number and (not right.is_finite or abs(right) > MAX_EXPONENT):
                raise _error(ctx, "exponent is too large", node.right,
                             hint=f"exponents must be at most {MAX_EXPONENT} in magnitude")
            if left.is_Number and right.is_Number and abs(right) > 1 and (
                    abs(left) >= 1e6 or (left != 0 and abs(left) <= 1e-6)):
                raise _error(ctx, "power of a large constant", node,
                             hint="write the value as a number literal")
            return _folded(ctx, left ** right, node)
        if isinstance(op, ast.Add):
            return _folded(ctx, left + right, node)
        if isinstance(op, ast.Sub):
            return _folded(ctx, left - right, node)
        if isinstance(op, ast.Mult):
            return _folded(ctx, left * right, node)
        return _folded(ctx, left / right, node)
    if isinstance(node, ast.Call):
        return _folded(ctx, _call(ctx, node, depth), node)
    if isinstance(node, ast.Tuple) and re.search(r"\d,\d", ast.unparse(node).replace(", ", ",")):
        raise _error(ctx, "a tuple is not allowed in an expression", node,
                     hint="a decimal comma? write numbers with a point (`1.5`, not `1,5`)")
    raise _error(ctx, _describe(node) + " is not allowed in an expression", node,
                 hint=(_PIECEWISE_HINT if isinstance(node, (ast.IfExp, ast.Compare, ast.BoolOp))
                       else "expressions may use numbers, declared names, + - * / **, and the "
                            "functions " + ", ".join(FUNCTIONS)))


_SAME_LEVEL = ((ast.Add, ast.Sub), (ast.Mult, ast.Div))


def _chain(ctx: _Ctx, node: ast.BinOp, depth: int):
    """A chain of operators of one precedence level (``a + b - c + ...``, ``a*b/c*...``), which
    Python parses as a left-leaning tree, converted term by term at one depth: a long sum is
    long, not deep (a flat 65-term polynomial was refused as "nested too deeply": red team,
    session 47). Its length is bounded by the spec's size and the equation-size checks."""
    level = next(c for c in _SAME_LEVEL if isinstance(node.op, c))
    chain = []
    cur = node
    while isinstance(cur, ast.BinOp) and isinstance(cur.op, level):
        chain.append(cur)
        cur = cur.left
    acc = _convert(ctx, cur, depth + 1)
    for n in reversed(chain):
        right = _convert(ctx, n.right, depth + 1)
        if isinstance(n.op, ast.Add):
            acc = _folded(ctx, acc + right, n)
        elif isinstance(n.op, ast.Sub):
            acc = _folded(ctx, acc - right, n)
        elif isinstance(n.op, ast.Mult):
            acc = _folded(ctx, acc * right, n)
        else:
            acc = _folded(ctx, acc / right, n)
    return acc


def _op_text(op) -> str:
    return {ast.BitXor: "^", ast.BitAnd: "&", ast.BitOr: "|", ast.Mod: "%", ast.FloorDiv: "//",
            ast.LShift: "<<", ast.RShift: ">>", ast.MatMult: "@", ast.Invert: "~",
            ast.Not: "not", ast.Pow: "**"}.get(type(op), type(op).__name__)


def _describe(node) -> str:
    names = {
        ast.Attribute: "attribute access", ast.Subscript: "subscript", ast.Lambda: "lambda",
        ast.ListComp: "comprehension", ast.SetComp: "comprehension", ast.DictComp: "comprehension",
        ast.GeneratorExp: "comprehension", ast.List: "a list", ast.Tuple: "a tuple",
        ast.Dict: "a dict", ast.Set: "a set", ast.Compare: "comparison", ast.BoolOp: "boolean operator",
        ast.IfExp: "conditional expression", ast.NamedExpr: "assignment", ast.JoinedStr: "a string",
        ast.Starred: "starred argument", ast.Await: "await", ast.Yield: "yield",
        ast.YieldFrom: "yield", ast.Slice: "slice", ast.FormattedValue: "a string",
    }
    return names.get(type(node), type(node).__name__)


def _name(ctx: _Ctx, node: ast.Name):
    written = _source(ctx, node)
    if written is not None and written != node.id and node.id.isascii():
        # Python reads `ＭＱ` (full-width) or `ﬁ` (a ligature) as `MQ`, `fi` (NFKC): a name
        # that is not the declared one was taken silently (session 46)
        note = non_ascii_note(written)
        raise _error(ctx, f"name `{written}` is not ASCII (Python would read it as "
                          f"`{node.id}`)", node,
                     hint=(f"{note}; " if note else "") + f"write the ASCII `{node.id}`")
    name = ctx.aliases.get(node.id, node.id)
    if name.startswith("__") or name.startswith("_"):
        raise _error(ctx, f"name `{name}` is not allowed (leading underscore)", node)
    if name in ctx.namespace:
        return ctx.namespace[name]
    if not ctx.units and name in BUILTIN_NAMES:
        return BUILTIN_NAMES[name]
    if ctx.free_names:
        if not name.isascii():
            raise _error(ctx, f"name `{name}` must be ASCII", node)
        sym = ctx.free.get(name)
        if sym is None:
            sym = ctx.free[name] = sympy.Symbol(name, real=True)
        return sym
    what = "unit" if ctx.units else "symbol"
    if name in FUNCTIONS and not ctx.units:
        raise _error(ctx, f"`{name}` is a function; call it with arguments", node)
    known = list(ctx.namespace) + ([] if ctx.units else list(BUILTIN_NAMES))
    spelt = _ascii_greek(name)
    hint = (f"did you mean `{spelt}`? (names are ASCII: spell Greek letters out)"
            if spelt != name and spelt in known else did_you_mean(name, known))
    if ctx.units and name in ("knot", "knots", "kts"):
        hint = "did you mean `kt`?"
    elif ctx.units and name in ("mph", "kph", "fps"):
        # units the data map converts (pint) but the spec's equations do not use
        hint = (f"`{name}` is a unit for a data column (the data map converts it: "
                f"`{{column: NAME, unit: {name}}}`); for speeds the spec takes m/s, ft/s or kt")
    if ctx.units and name.lower() in _UNIT_SPELLINGS:
        hint = f"did you mean `{_UNIT_SPELLINGS[name.lower()]}`?"
    if ctx.units:
        m = re.fullmatch(r"([A-Za-z]+)(\d+)", name)
        if m and m.group(1) in ctx.namespace:   # `m/s2`: a power written without ^
            hint = f"did you mean `{m.group(1)}^{m.group(2)}`? (powers are written with ^)"
    if not ctx.units and name == "e":
        hint = "for Euler's number write `exp(x)` (not `e**x`); " + (hint or
                "else declare `e` under states, inputs, constants, parameters or definitions")
    if hint is None:
        hint = ("declare it under states, inputs, constants, parameters or definitions"
                if not ctx.units else "known units: " + ", ".join(sorted(ctx.namespace))
                + "; `1` for a dimensionless quantity")
    note = non_ascii_note(name) if spelt == name else None
    if note:
        hint = f"{note} (names are ASCII); {hint}"
    raise _error(ctx, f"unknown {what} `{name}`", node, hint=hint)


#: unit names as people write them -> the spec's spelling (`rad/sec` had no hint)
_UNIT_SPELLINGS = {"sec": "s", "secs": "s", "second": "s", "seconds": "s", "meter": "m",
                   "meters": "m", "metre": "m", "metres": "m", "radian": "rad", "radians": "rad",
                   "degree": "deg", "degrees": "deg", "hz": "Hz", "newton": "N", "newtons": "N",
                   "kilogram": "kg", "kilograms": "kg", "feet": "ft", "foot": "ft",
                   "hour": "h", "hours": "h", "hr": "h", "minute": "min", "minutes": "min",
                   "pascal": "Pa", "kelvin": "K", "dimensionless": "1", "none": "1",
                   "unitless": "1", "nondim": "1", "nd": "1",
                   "dps": "deg/s", "mps": "m/s"}


def _table(ctx: _Ctx, node, depth: int, what: str):
    if not isinstance(node, (ast.List, ast.Tuple)):
        raise _error(ctx, f"interp: the {what} must be a list of numbers like [0, 1, 2]", node)
    if len(node.elts) < 2:
        raise _error(ctx, f"interp: the {what} needs at least 2 values", node)
    values = []
    for elt in node.elts:
        v = _convert(ctx, elt, depth + 1)
        if not v.is_Number or not v.is_finite:
            raise _error(ctx, f"interp: the {what} must contain numbers only", elt)
        values.append(sympy.Float(float(v), 15))
    return values


def _call(ctx: _Ctx, node: ast.Call, depth: int):
    func = node.func
    if not isinstance(func, ast.Name):
        raise _error(ctx, "only calls of the whitelisted function names are allowed", func,
                     hint="allowed functions: " + ", ".join(FUNCTIONS))
    name = func.id
    if ctx.units or name not in FUNCTIONS:
        hint = None
        if not ctx.units:
            hint = FUNCTION_EQUIVALENTS.get(name)
            if hint is None and name in ctx.namespace:
                # a declared variable called like a function: `de(t - 0.1)`, `alpha(t)`
                hint = (f"`{name}` is a variable, not a function: write `{name}` (the delay "
                        f"of an input read late is {_DELAY_DECLARATION})")
            hint = hint or did_you_mean(name, FUNCTIONS)
        raise _error(ctx, f"unknown function `{name}`", func,
                     hint=hint or "allowed functions: " + ", ".join(FUNCTIONS))
    if node.keywords:
        raise _error(ctx, f"keyword arguments are not allowed in `{name}(...)`", node.keywords[0].value
                     if not hasattr(node.keywords[0], "col_offset") else node.keywords[0],
                     hint="pass the arguments by position")
    nargs = FUNCTIONS[name]
    if nargs is None:
        if len(node.args) < 2:
            raise _error(ctx, f"`{name}` needs at least 2 arguments", node)
    elif len(node.args) != nargs:
        raise _error(ctx, f"`{name}` takes {nargs} argument{'s' if nargs > 1 else ''}, "
                          f"got {len(node.args)}", node)
    for a in node.args:
        if isinstance(a, ast.Starred):
            raise _error(ctx, "starred arguments are not allowed", a)
    if name == "interp":
        x = _convert(ctx, node.args[0], depth + 1)
        xs = _table(ctx, node.args[1], depth, "x table")
        ys = _table(ctx, node.args[2], depth, "y table")
        if len(xs) != len(ys):
            raise _error(ctx, f"interp: x table has {len(xs)} values but y table has {len(ys)}", node)
        if any(not (b > a) for a, b in zip(xs, xs[1:])):
            raise _error(ctx, "interp: x table must be strictly increasing", node.args[1])
        return Interp(x, sympy.Tuple(*xs), sympy.Tuple(*ys))
    args = [_convert(ctx, a, depth + 1) for a in node.args]
    if name in _UNARY:
        return _UNARY[name](args[0])
    if name == "atan2":
        return sympy.atan2(args[0], args[1])
    if name == "min":
        return sympy.Min(*args)
    if name == "max":
        return sympy.Max(*args)
    if name == "sat":
        lo, hi = args[1], args[2]
        if lo.is_number and hi.is_number and lo.is_real and hi.is_real and bool(lo > hi):
            # sat(x, 0.1, -0.1) is the constant -0.1 (red team, session 47)
            raise _error(ctx, f"sat: the lower limit {float(lo):g} is above the upper limit "
                              f"{float(hi):g}", node,
                         hint="write sat(x, lo, hi) with lo <= hi")
        return sympy.Min(sympy.Max(args[0], args[1]), args[2])
    if name == "smoothsat":
        return smoothsat(*args)
    raise _error(ctx, f"unknown function `{name}`", func)  # pragma: no cover


def _bad_result(expr) -> bool:
    try:
        return bool(expr.has(sympy.zoo, sympy.oo, -sympy.oo, sympy.nan, sympy.I))
    except Exception:  # pragma: no cover
        return True


def parse_expression(text, namespace: Mapping[str, sympy.Basic], *, path=None, line=None,
                     column=None, free_names: bool = False, units: bool = False):
    """Parse ``text`` into a sympy expression over the symbols of ``namespace``.

    Args:
        text: the expression (a number is accepted too).
        namespace: name -> sympy object for every name the expression may use.
        path, line, column: location of the first character of ``text`` in the
            spec file (for error messages; the column of the offending token is
            ``column + offset``).
        free_names: every unknown identifier becomes a real ``sympy.Symbol``
            (used for data-column expressions); read them with
            :func:`parse_expression_free`.
        units: unit-string mode: ``^`` means power, no functions, no ``pi``.

    Raises:
        SpecError: for anything outside the whitelist (never another exception).
    """
    return _parse(text, namespace, path=path, line=line, column=column,
                  free_names=free_names, units=units)[0]


def parse_expression_free(text, namespace: Mapping[str, sympy.Basic] | None = None, *, path=None,
                          line=None, column=None):
    """Like :func:`parse_expression` with unknown names as free symbols.

    Returns ``(expr, names)`` where ``names`` lists the free identifiers in order
    of first appearance (e.g. the data columns a channel expression reads).
    """
    expr, ctx = _parse(text, namespace or {}, path=path, line=line, column=column,
                       free_names=True, units=False)
    return expr, tuple(ctx.free)


def _parse(text, namespace, *, path, line, column, free_names, units):
    if isinstance(text, bool):
        raise SpecError("expected an expression, got a boolean", path=path, line=line, column=column)
    if isinstance(text, (int, float)):
        text = repr(text)
    if not isinstance(text, str):
        raise SpecError(f"expected an expression (text), got {type(text).__name__}",
                        path=path, line=line, column=column)
    ctx = _Ctx(text, namespace, path, line, column, free_names, units)
    if len(text) > MAX_LENGTH:
        raise _make_error(text, f"expression is too long ({len(text)} characters)", path=path,
                          line=line, column=column, offset=None, length=None,
                          hint=f"at most {MAX_LENGTH} characters; split it into definitions")
    if not text.strip():
        if units:
            raise SpecError("empty unit", path=path, line=line, column=column,
                            hint="write a unit such as `m/s` or `1` for a dimensionless "
                                 "quantity, or leave `unit:` out")
        raise SpecError("empty expression", path=path, line=line, column=column,
                        hint="write an expression such as `0` or `a*b`")
    if "\x00" in text:
        raise SpecError("expression contains a NUL character", path=path, line=line, column=column)
    flat = text.replace("\r", " ").replace("\n", " ").replace("\t", " ")
    # declared names that are Python keywords (e.g. a state `lambda`): swap them for a
    # same-length placeholder identifier so offsets stay exact
    kw = [k for k in namespace if keyword.iskeyword(k)]
    if kw:
        def swap(m):
            word = m.group(0)
            if word in kw:
                ph = word[:-1] + _KW_MARK
                ctx.aliases[ph] = word
                return ph
            return word
        flat = _IDENT.sub(swap, flat)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            tree = ast.parse(flat, mode="eval")
        ctx.flat = flat
    except SyntaxError as exc:
        off = (exc.offset - 1) if exc.offset and (exc.lineno in (None, 1)) else None
        if off is not None and (off < 0 or off > len(flat)):
            off = None
        raise _make_error(text, f"syntax error: {exc.msg}", path=path, line=line, column=column,
                          offset=off, length=1,
                          hint=(_typography_hint(flat, units) or _implicit_product_hint(flat)
                                or _statement_hint(flat))) from None
    except (RecursionError, MemoryError):
        raise _make_error(text, "expression is nested too deeply", path=path, line=line,
                          column=column, offset=None, length=None) from None
    except (ValueError, TypeError, OverflowError) as exc:
        raise _make_error(text, f"invalid expression: {exc}", path=path, line=line,
                          column=column, offset=None, length=None) from None
    try:
        expr = _convert(ctx, tree, 0)
    except SpecError:
        raise
    except (RecursionError, MemoryError):
        raise _make_error(text, "expression is nested too deeply or too large", path=path,
                          line=line, column=column, offset=None, length=None) from None
    except Exception as exc:  # sympy raising on odd input: still a user error
        raise _make_error(text, f"invalid expression ({type(exc).__name__})", path=path,
                          line=line, column=column, offset=None, length=None) from None
    if not isinstance(expr, sympy.Basic) or isinstance(expr, sympy.Tuple):
        raise _make_error(text, "not a scalar expression", path=path, line=line, column=column,
                          offset=None, length=None)
    if not units and _bad_result(expr):
        raise _make_error(text, "expression is not finite or not real (division by zero, "
                                "log(0), sqrt of a negative number...)", path=path, line=line,
                          column=column, offset=None, length=None)
    return expr, ctx
