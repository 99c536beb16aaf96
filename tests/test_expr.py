"""Safe expression parser: whitelist, hostile input, error locations."""

import builtins
import contextlib
import os
from unittest import mock

import pytest
import sympy
from hypothesis import HealthCheck, given, settings, strategies as st

from vsidgen.spec import expr as expr_module
from vsidgen.errors import SpecError
from vsidgen.spec.expr import Interp, InterpSlope, parse_expression, parse_expression_free

NS = {n: sympy.Symbol(n, real=True) for n in ("alpha", "V", "q", "de", "y", "lambda")}
a, V, q = NS["alpha"], NS["V"], NS["q"]


def test_arithmetic_and_functions():
    e = parse_expression("-V**2/2 + 3*sin(alpha) - atan2(q, V) + max(alpha, q, 1)", NS)
    ref = -V**2 / 2 + 3 * sympy.sin(a) - sympy.atan2(q, V) + sympy.Max(a, q, 1)
    assert sympy.simplify(e - ref) == 0


def test_sat_and_smoothsat():
    assert parse_expression("sat(alpha, -1, 2)", NS) == sympy.Min(sympy.Max(a, -1), 2)
    s = parse_expression("smoothsat(alpha, -1, 3)", NS)
    f = sympy.lambdify(a, s)
    assert f(1.0) == pytest.approx(1.0)  # midpoint value
    assert float(sympy.diff(s, a).subs(a, 1)) == pytest.approx(1.0)  # unit slope at mid
    assert f(100.0) == pytest.approx(3.0) and f(-100.0) == pytest.approx(-1.0)


def test_interp_value_and_slope():
    e = parse_expression("interp(alpha, [0, 1, 3], [0, 2, 3])", NS)
    assert isinstance(e, Interp)
    assert float(e.subs(a, 0.5)) == pytest.approx(1.0)
    assert float(e.subs(a, 2.0)) == pytest.approx(2.5)
    assert float(e.subs(a, 9.0)) == pytest.approx(3.0)
    d = sympy.diff(e, a)
    assert isinstance(d, InterpSlope)
    assert float(d.subs(a, 0.5)) == pytest.approx(2.0)
    assert float(d.subs(a, 2.0)) == pytest.approx(0.5)
    assert float(d.subs(a, -1.0)) == 0.0


def test_keyword_named_symbol():
    assert parse_expression("2*lambda + y", NS) == 2 * NS["lambda"] + NS["y"]


def test_free_names_for_data_columns():
    e, cols = parse_expression_free("(da_right_rad - da_left_rad)/2")
    assert cols == ("da_right_rad", "da_left_rad")
    assert e.subs({sympy.Symbol(c, real=True): v for c, v in zip(cols, (3.0, 1.0))}) == pytest.approx(1.0)


def test_unknown_name_location_and_hint():
    with pytest.raises(SpecError) as ei:
        parse_expression("V + 2*alfa", NS, path="m.yaml", line=12, column=9)
    err = ei.value
    assert err.message == "unknown symbol `alfa`"
    assert (err.line, err.column) == (12, 9 + 6)
    assert err.hint == "did you mean `alpha`?"
    assert err.span == (7, 4)
    assert "m.yaml:12:15: error: unknown symbol `alfa`" in str(err)
    assert "\n          ^^^^" in str(err)


def test_non_ascii_names_are_located_by_character_and_named():
    """ast reports UTF-8 byte offsets; the caret and column count characters, and a
    look-alike letter pasted from a document is named."""
    with pytest.raises(SpecError) as ei:
        parse_expression("q + V\u0430 + V", NS, path="m.yaml", line=2, column=5)
    err = ei.value
    assert err.span == (5, 2) and err.column == 5 + 4
    assert "U+0430 CYRILLIC SMALL LETTER A" in err.hint
    with pytest.raises(SpecError) as ei:
        parse_expression("q*\u03b1\u03b1 + V", NS, path="m.yaml", line=2, column=5)
    assert ei.value.span == (3, 2)


@pytest.mark.parametrize("text, hint", [
    ("V \u2212 q", "ASCII `-` instead of `\u2212`"),
    ("V \u00d7 q", "ASCII `*`"),
    ("V\u00b2", "`**2`, not as superscripts"),
    ("V +\u00a0q", "invisible character U+00A0"),
    ("V + q\u200b", "invisible character U+200B"),
    ("V * \uff12", "ASCII `2` instead of"),
])
def test_typographic_characters_get_a_hint(text, hint):
    with pytest.raises(SpecError) as ei:
        parse_expression(text, NS, path="s.yaml", line=3, column=1)
    assert hint in (ei.value.hint or "")


@pytest.mark.parametrize("text, hint", [
    ("log(V) + ln(q)", "the natural logarithm is `log(x)`"),
    ("V * deg2rad(q)", "multiply by `pi/180`"),
    ("arctan(V)", "asin, acos, atan and atan2"),
    ("clip(V, 0, 1)", "`sat(x, lo, hi)`"),
    ("delay(q, 0.1)", "declared on the input, in seconds"),
    ("V + q(t - 0.1)", "`q` is a variable, not a function: write `q`"),
    ("V if q > 0 else 0", "max/min (a break"),
    ("V * (q > 0)", "max/min (a break"),
    ("V + q;", "remove the trailing `;`"),
    ("qdot = V + q", "right-hand side only"),
    ("sinn(V)", "did you mean `sin`?"),
    ("V * e**q", "write `exp(x)` (not `e**x`)"),
    ("V * 1,5", "a decimal comma?"),
])
def test_what_other_languages_write_gets_the_spec_equivalent(text, hint):
    """Functions and statements a new user brings from MATLAB, numpy or Modelica are refused
    with what to write in a spec (before: the list of allowed functions, or no hint)."""
    with pytest.raises(SpecError) as ei:
        parse_expression(text, NS, path="s.yaml", line=3, column=1)
    assert hint in (ei.value.hint or ""), ei.value


@pytest.mark.parametrize("text, fragment, col", [
    ("V.real", "attribute access", 1),
    ("V[0]", "subscript", 1),
    ("lambda: 1", None, None),
    ("[x for x in y]", "comprehension", 1),
    ("sin(x=1)", "keyword arguments", None),
    ("'abc'", "number literals", 1),
    ("__import__('os')", "unknown function `__import__`", 1),
    ("foo(V)", "unknown function `foo`", 1),
    ("V ^ 2", "operator `^`", 3),
    ("2**1000", "exponent is too large", 4),
    ("9**9**9", "exponent is too large", 4),
    ("1e999999", "not finite", 1),
    ("1j", "number literals", 1),
    ("V < 2", "comparison", 1),
    ("True", "number literals", 1),
    ("sin(V, q)", "takes 1 argument", 1),
    ("interp(V, [0, 1], [1, 2, 3])", "y table has 3", 1),
    ("interp(V, [0, 1], [1])", "at least 2 values", 19),
    ("interp(V, [1, 0], [1, 2])", "strictly increasing", 11),
    ("1/0", "not finite", None),
    ("", "empty", None),
    ("V +", "syntax error", None),
])
def test_rejections(text, fragment, col):
    with pytest.raises(SpecError) as ei:
        parse_expression(text, NS, path="s.yaml", line=3, column=1)
    if fragment:
        assert fragment in ei.value.message
    if col is not None:
        assert ei.value.column == col


def test_too_long_and_too_deep():
    with pytest.raises(SpecError, match="too long"):
        parse_expression("+".join(["V"] * 1500), NS)
    assert parse_expression("(" * 150 + "V" + ")" * 150, NS) == V  # parentheses alone are fine
    with pytest.raises(SpecError, match="nested too deeply"):
        parse_expression("sin(" * 100 + "V" + ")" * 100, NS)
    with pytest.raises(SpecError, match="nested too deeply"):
        parse_expression("-" * 500 + "V", NS)


HOSTILE = [
    "__import__('os').system('x')", "().__class__.__bases__", "lambda: 1", "[x for x in y]",
    "__builtins__", "V.__dict__", "9**9**9", "1e999999", "a.b", "a[0]", "f(x=1)",
    "(" * 1000 + ")" * 1000, "V" * 5000, "sin(" * 300 + "V" + ")" * 300, "exec('1')",
    "eval('1')", "open('/etc/passwd')", "getattr(V, 'x')", "{1: 2}", "{V}", "(V, q)",
    "*V", "V if q else de", "(y := 3)", "f'{V}'", "b'x'", "...", "None", "not V",
    "V @ q", "~V", "V // q", "V % q", "\x00", "V\n+\nq\n)", "\\", "sin", "interp(V, V, V)",
    "interp(V, [0, 1], [0, 1], 3)", "max(V)", "99999999**99", "10**300*10**300",
]


def _boom(*args, **kwargs):  # pragma: no cover - must never run
    raise AssertionError("expression text was executed")


@contextlib.contextmanager
def _guarded():
    """During parsing: os.system, eval/exec in vsidgen.spec.expr and imports of os/subprocess fail."""
    real_import = builtins.__import__

    def guarded_import(name, *args, **kwargs):
        if name.split(".")[0] in ("os", "subprocess", "shutil", "posix"):
            raise AssertionError(f"import of {name} during parsing")
        return real_import(name, *args, **kwargs)
    with mock.patch.object(os, "system", _boom), \
            mock.patch.object(builtins, "__import__", guarded_import), \
            mock.patch.dict(expr_module.__dict__, {"eval": _boom, "exec": _boom}):
        yield


@pytest.fixture
def no_side_effects():
    yield


def _parse_only_spec_errors(text):
    try:
        with _guarded():
            e = parse_expression(text, NS)
    except SpecError:
        return None
    assert isinstance(e, sympy.Basic)
    return e


@pytest.mark.parametrize("text", HOSTILE)
def test_hostile_strings(text, no_side_effects):
    if text in ("99999999**99", "10**300*10**300"):
        _parse_only_spec_errors(text)  # a big exact number is allowed, nothing else may happen
        return
    with pytest.raises(SpecError):
        with _guarded():
            parse_expression(text, NS)


_atoms = st.sampled_from(["V", "alpha", "q", "1", "2.5", "1e308", "0", "__x", "os", "sin",
                          "interp", "[0, 1]", "'s'", "lambda", "x"])
_ops = st.sampled_from(["+", "-", "*", "/", "**", "^", ".", "(", ")", ",", "[", "]", " ",
                        "=", ":", "!", "%", "@", "if", "for", "\n"])


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.one_of(st.text(max_size=200),
                 st.lists(st.one_of(_atoms, _ops), max_size=40).map("".join)))
def test_fuzz_never_other_exception(no_side_effects, text):
    _parse_only_spec_errors(text)
