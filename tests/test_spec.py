"""Spec loading and validation: one test per class of spec error (message, location, hint)."""

import textwrap

import pytest

from vsidgen.errors import SpecError
from vsidgen.spec import compile_spec

GOOD = """\
name: mini
states:
  V: {unit: m/s}
  alpha: {unit: rad}
inputs:
  de: {unit: rad}
outputs:
  V: {unit: m/s}
constants:
  G0: {value: 9.80665, unit: m/s^2}
parameters:
  CD0: {initial: 0.1, bounds: [0, 1]}
  MDE: {unit: 1/s}
definitions:
  drag: CD0*V**2
drift:
  V: -drag + G0*sin(alpha)
  alpha: MDE*de
observations:
  V: V
data:
  time: t_s
  inputs: {de: de_rad}
  outputs: {V: v_mps}
"""


def write(tmp_path, text, name="spec.yaml"):
    path = tmp_path / name
    path.write_text(textwrap.dedent(text))
    return path


def error(tmp_path, text, name="spec.yaml") -> SpecError:
    path = write(tmp_path, text, name)
    with pytest.raises(SpecError) as ei:
        compile_spec(path)
    return ei.value


def replace(old, new, text=GOOD):
    assert old in text, old
    return text.replace(old, new, 1)


def test_good_spec_compiles(tmp_path):
    m = compile_spec(write(tmp_path, GOOD))
    assert [s.name for s in m.states] == ["V", "alpha"]
    assert m.parameters[0].lower == 0 and m.parameters[0].initial == 0.1
    assert [w.code for w in m.warnings] == []


def test_unknown_symbol_points_to_token(tmp_path):
    err = error(tmp_path, replace("  alpha: MDE*de", "  alpha: MDE*dee"))
    assert err.message == "unknown symbol `dee`"
    assert (err.line, err.column) == (18, 14)
    assert err.hint == "did you mean `de`?"
    assert str(err).startswith(f"{tmp_path / 'spec.yaml'}:18:14: error:")


def test_unknown_symbol_in_quoted_scalar(tmp_path):
    err = error(tmp_path, replace("  alpha: MDE*de", '  alpha: "MDE*alfa"'))
    assert (err.line, err.column) == (18, 15)
    assert err.hint == "did you mean `alpha`?"


def test_unknown_symbol_in_block_scalar(tmp_path):
    err = error(tmp_path, replace("  alpha: MDE*de", "  alpha: |\n    MDE*de\n      + G0*alfa"))
    assert (err.line, err.column) == (20, 12)


def test_unknown_symbol_in_multiline_plain_scalar(tmp_path):
    err = error(tmp_path, replace("  alpha: MDE*de", "  alpha: MDE*de\n    + G0*alfa"))
    assert (err.line, err.column) == (19, 10)


def test_duplicate_equation(tmp_path):
    err = error(tmp_path, replace("  alpha: MDE*de", "  alpha: MDE*de\n  V: 0"))
    assert err.message == "duplicate equation for state `V`"
    assert (err.line, err.column) == (19, 3)
    assert "line 17" in err.hint


def test_duplicate_parameter(tmp_path):
    err = error(tmp_path, replace("  MDE: {unit: 1/s}", "  MDE: {unit: 1/s}\n  CD0: 1"))
    assert err.message == "duplicate parameter `CD0`"
    assert err.line == 14


def test_unknown_top_level_key(tmp_path):
    err = error(tmp_path, replace("definitions:", "definitons:"))
    assert err.message == "unknown key `definitons` in the spec (top level)"
    assert (err.line, err.column) == (14, 1)
    assert err.hint == "did you mean `definitions`?"


def test_unknown_entry_key(tmp_path):
    err = error(tmp_path, replace("CD0: {initial: 0.1, bounds: [0, 1]}", "CD0: {inital: 0.1}"))
    assert err.message == "unknown key `inital` in parameter `CD0`"
    assert (err.line, err.column) == (12, 9)
    assert err.hint == "did you mean `initial`?"


@pytest.mark.parametrize("key", ["min", "upper", "lb"])
def test_limits_written_as_other_tools_write_them(tmp_path, key):
    """`min:`/`max:`, `lower:`/`upper:`, `lb:`/`ub:` point to the one key vsidgen has."""
    err = error(tmp_path, replace("CD0: {initial: 0.1, bounds: [0, 1]}", f"CD0: {{initial: 0.1, {key}: 0}}"))
    assert err.message == f"unknown key `{key}` in parameter `CD0`"
    assert err.hint == "a parameter's limits are one key: `bounds: [lower, upper]`"


def test_type_error(tmp_path):
    err = error(tmp_path, replace("value: 9.80665", "value: fast"))
    assert err.message == "value of constant `G0` must be a number, got str `fast`"
    assert (err.line, err.column) == (10, 15)
    assert "number" in err.hint


def test_yaml_syntax_error(tmp_path):
    err = error(tmp_path, replace("  V: {unit: m/s}\n  alpha", "  V: {unit: m/s\n  alpha"))
    assert err.message.startswith("YAML syntax error")
    assert err.line == 4 and err.column is not None
    assert err.hint


def test_missing_file(tmp_path):
    with pytest.raises(SpecError) as ei:
        compile_spec(tmp_path / "nope.yaml")
    assert ei.value.message == "spec file not found"
    assert ei.value.hint


def test_missing_equation(tmp_path):
    err = error(tmp_path, replace("  alpha: MDE*de\n", ""))
    assert err.message == "missing drift equation for state `alpha`"
    assert err.line == 16
    assert "exactly one equation" in err.hint


def test_equation_for_undeclared_state(tmp_path):
    err = error(tmp_path, replace("  alpha: MDE*de", "  alpha: MDE*de\n  alfa: 0"))
    assert err.message == "drift equation for undeclared state `alfa`"
    assert (err.line, err.column) == (19, 3)
    assert err.hint == "did you mean `alpha`?"


def test_unmapped_output(tmp_path):
    err = error(tmp_path, replace("  outputs: {V: v_mps}", "  outputs: {}"))
    assert err.message == "output `V` is not mapped to a data column"
    assert err.line == 24
    assert "data.outputs" in err.hint


def test_mapping_for_unknown_channel(tmp_path):
    err = error(tmp_path, replace("  inputs: {de: de_rad}", "  inputs: {de: de_rad, dee: dr_rad}"))
    assert err.message == "data mapping for unknown input `dee`"
    assert (err.line, err.column) == (23, 24)
    assert err.hint == "did you mean `de`?"


def test_definition_cycle_is_reported(tmp_path):
    err = error(tmp_path, replace("  drag: CD0*V**2", "  drag: CD0*V**2*lift\n  lift: 2*drag"))
    assert err.message == "definition cycle: drag -> lift -> drag"
    assert (err.line, err.column) == (15, 3)
    assert err.hint


def test_name_clash(tmp_path):
    err = error(tmp_path, replace("  MDE: {unit: 1/s}", "  MDE: {unit: 1/s}\n  G0: 1"))
    assert "name `G0` is declared twice: as a constant" in err.message
    assert "and as a parameter" in err.message
    assert (err.line, err.column) == (14, 3)
    assert err.hint


def test_bounds_lo_ge_hi(tmp_path):
    err = error(tmp_path, replace("bounds: [0, 1]", "bounds: [1, 0]"))
    assert err.message == "bounds of parameter `CD0`: lower 1 >= upper 0"
    assert (err.line, err.column) == (12, 31)
    assert err.hint


def test_initial_outside_bounds(tmp_path):
    err = error(tmp_path, replace("initial: 0.1", "initial: 2"))
    assert "initial value 2 of parameter `CD0` is outside its bounds [0, 1]" == err.message
    assert (err.line, err.column) == (12, 18)
    assert "inside the bounds" in err.hint


def test_unknown_unit(tmp_path):
    err = error(tmp_path, replace("  V: {unit: m/s}", "  V: {unit: m/sec}", ))
    assert err.message == "unknown unit `sec`"
    assert (err.line, err.column) == (3, 15)
    assert "did you mean `s`?" in err.hint           # (had only the list; session 44)
    err = error(tmp_path, replace("  V: {unit: m/s}", "  V: {unit: furlong}", ))
    assert "known units" in err.hint and "`1` for a dimensionless" in err.hint
    err = error(tmp_path, replace("  V: {unit: m/s}", "  V: {unit: dimensionless}", ))
    assert "did you mean `1`?" in err.hint
    err = error(tmp_path, replace("  V: {unit: m/s}", "  V: {unit: \"\"}", ))
    assert err.message == "empty unit"


def test_extends_cycle(tmp_path):
    write(tmp_path, "name: a\nextends: b.yaml\n", "a.yaml")
    write(tmp_path, "name: b\nextends: a.yaml\n", "b.yaml")
    with pytest.raises(SpecError) as ei:
        compile_spec(tmp_path / "a.yaml")
    assert ei.value.message == "`extends` cycle: a.yaml -> b.yaml -> a.yaml"
    assert ei.value.line == 2 and ei.value.hint


def test_add_terms_unknown_target(tmp_path):
    err = error(tmp_path, GOOD + "add_terms:\n  drift:\n    alfa: 1\n")
    assert err.message == "add_terms: there is no drift equation for `alfa` to add to"
    assert (err.line, err.column) == (27, 5)
    assert err.hint == "did you mean `alpha`?"


def test_bad_noise(tmp_path):
    err = error(tmp_path, GOOD + "noise:\n  measurement:\n    V: {estimate: false}\n")
    assert "fixed (estimate: false) but has no `std`" in err.message
    assert err.line == 27 and "std" in err.hint
    err = error(tmp_path, GOOD + "noise:\n  process: {states: [V, alfa]}\n")
    assert err.message == "noise.process.states: `alfa` is not a state"
    assert (err.line, err.column) == (26, 25)


def test_expression_error_inside_extending_file_points_to_child(tmp_path):
    write(tmp_path, GOOD, "base.yaml")
    err = error(tmp_path, "name: kid\nextends: base.yaml\ndefinitions:\n  drag: CD0*V**2 + CDX\n",
                "kid.yaml")
    assert err.message == "unknown symbol `CDX`"
    assert err.path.name == "kid.yaml" and (err.line, err.column) == (4, 20)


def test_warnings_unused_and_units(tmp_path):
    text = replace("  MDE: {unit: 1/s}", "  MDE: {unit: 1/s}\n  CX: 0")
    text = replace("  V: -drag + G0*sin(alpha)", "  V: -drag + G0*sin(alpha) + V", text)
    m = compile_spec(write(tmp_path, text))
    msgs = [w.message for w in m.warnings]
    assert "unused parameter `CX`" in msgs
    units = [w for w in m.warnings if w.code == "units"]
    assert any("`V` has dimension length/time " in w.message and "length/time**2" in w.message
               and "drift of `V`" in w.message for w in units), msgs
    assert units and all(w.line == 18 for w in units)


def test_integrator_input_hold(tmp_path):
    m = compile_spec(write(tmp_path, replace("states:\n", "integrator: {method: rk4, inputs: foh}\nstates:\n")))
    assert (m.integrator, m.substeps, m.input_hold) == ("rk4", 1, "foh")
    assert compile_spec(write(tmp_path, GOOD, "plain.yaml")).input_hold == "zoh"
    err = error(tmp_path, replace("states:\n", "integrator: {method: euler, inputs: fho}\nstates:\n"))
    assert err.message == "unknown input hold `fho`"
    assert (err.line, err.text) == (2, "integrator: {method: euler, inputs: fho}")
    assert err.hint == "did you mean `foh`?"
    err = error(tmp_path, replace("states:\n", "integrator: {method: euler, input: foh}\nstates:\n"))
    assert "input" in err.message and err.line == 2


@pytest.mark.parametrize("text,hint", [
    ("(1 + ZQ)q", "`)q` → `)*q`"),                 # a product written as on paper
    ("2alpha + q", "`2alpha` → `2*alpha`"),
    ("ZQ q", "`ZQ q` → `ZQ*q`"),
])
def test_product_without_star_is_named_with_the_fix(text, hint):
    from vsidgen.spec.expr import parse_expression
    import sympy

    ns = {n: sympy.Symbol(n) for n in ("ZQ", "q", "alpha")}
    with pytest.raises(SpecError) as e:
        parse_expression(text, ns, path="m.yaml", line=3, column=10)
    assert "syntax error" in str(e.value) and hint in str(e.value)


def test_valid_exponents_and_calls_get_no_product_hint():
    from vsidgen.spec.expr import _implicit_product_hint

    for text in ("1e-3*a", "2.5E+4 + b", "sin(a)", "a*(b)", "x if y else z", "a or b"):
        assert _implicit_product_hint(text) is None, text


def test_greek_letter_is_spelt_out_in_the_hint(tmp_path):
    p = tmp_path / "g.yaml"
    p.write_text(textwrap.dedent("""\
        name: g
        states: {alpha: {unit: rad}}
        parameters: {Za: {unit: 1/s}}
        drift:
          alpha: Za*α
        """))
    with pytest.raises(SpecError) as e:
        compile_spec(p)
    msg = str(e.value)
    assert "unknown symbol `α`" in msg and "did you mean `alpha`?" in msg and ":5:" in msg


def test_constants_in_non_coherent_units_are_warned_with_their_coherent_value(tmp_path):
    """The equations use every number as it stands: `{value: 3, unit: deg}` inside cos() is 3
    rad, a span in ft beside a speed in m/s is not metres — a new user's spec had both with 0
    warnings. Each is warned at its line with the coherent value to write; a conversion
    factor (`R2D: {value: 57.2958, unit: deg/rad}`, written to produce an output in deg) is
    not, and no number is changed behind the user's back."""
    text = replace("  G0: {value: 9.80665, unit: m/s^2}\n",
                   "  G0: {value: 9.80665, unit: m/s^2}\n  SIG: {value: 3, unit: deg}\n"
                   "  B: {value: 10, unit: ft}\n  R2D: {value: 57.29577951308232, unit: deg/rad}\n")
    text = replace("  alpha: MDE*de\n", "  alpha: MDE*de + cos(alpha + SIG)*V/B + 0*R2D\n", text)
    m = compile_spec(write(tmp_path, text))
    consts = {c.name: c for c in m.constants}
    assert consts["SIG"].value == 3.0 and consts["B"].value == 10.0
    w = [x for x in m.warnings if x.code == "noncoherent_unit"]
    assert sorted(x.line for x in w) == [11, 12]
    assert "0.0523599, unit: rad" in w[0].hint and "3.048, unit: m" in w[1].hint


def test_non_coherent_units_of_parameters_and_variables_are_warned(tmp_path):
    """A parameter in 1/deg beside α in rad is estimated per rad; a state in deg must not meet
    sin/cos: both are said with the coherent unit to declare, at the declaration's line."""
    text = replace("  MDE: {unit: 1/s}\n", "  MDE: {unit: 1/s}\n  CMA: {unit: 1/deg}\n")
    text = replace("  alpha: {unit: rad}\n", "  alpha: {unit: deg}\n", text)
    text = replace("  alpha: MDE*de\n", "  alpha: MDE*de + CMA*alpha\n", text)
    m = compile_spec(write(tmp_path, text))
    w = {x.message.split("`")[1]: x for x in m.warnings if x.code == "noncoherent_unit"}
    assert set(w) == {"CMA", "alpha"}
    assert "1/rad" in w["CMA"].hint and "57.2958" in w["CMA"].hint and w["CMA"].line == 14
    assert "declare `unit: rad`" in w["alpha"].hint and w["alpha"].line == 4


def test_numbers_with_an_exponent_and_no_dot_are_numbers(tmp_path):
    """PyYAML (YAML 1.1) reads `1e-3` as text; the hint of a refused number suggested writing
    exactly that. Initial values, bounds and floors accept it."""
    text = replace("  CD0: {initial: 0.1, bounds: [0, 1]}\n",
                   "  CD0: {initial: 1e-3, bounds: [-1e2, 1E+1]}\n")
    m = compile_spec(write(tmp_path, text))
    p = m.parameters[0]
    assert (p.initial, p.lower, p.upper) == (1e-3, -100.0, 10.0)
    err = error(tmp_path, replace("  CD0: {initial: 0.1, bounds: [0, 1]}\n",
                                  "  CD0: {initial: 1e-3x, bounds: [0, 1]}\n"), "bad.yaml")
    assert "must be a number" in str(err)


def test_substeps_are_bounded(tmp_path):
    """Sub-steps are unrolled into the compiled transition: 10^8 compiled for ever."""
    err = error(tmp_path, GOOD + "integrator: {method: rk4, substeps: 100000000}\n")
    assert "from 1 to 64" in str(err) and err.line == 25 and "rk4" in err.hint
    from vsidgen.errors import VsidgenError
    from vsidgen.model.dynamics import transition_fn

    with pytest.raises(VsidgenError, match="from 1 to 64"):
        transition_fn(lambda x, u, p: x, substeps=10 ** 8)


def test_hints_a_new_user_needs(tmp_path):
    """Case-only typos suggest the case variant; `unit: knot` suggests `kt`, `unit: mph` points
    to the data map;
    a comma inside an unquoted {...} value says to quote it."""
    from vsidgen.suggest import closest

    assert closest("Cl_P", ["Cl_b", "Cl_p", "Cl_r"]) == ["Cl_p"]
    err = error(tmp_path, replace("outputs:\n  V: {unit: m/s}\n", "outputs:\n  V: {unit: knot}\n"))
    assert "unknown unit `knot`" in str(err) and err.hint == "did you mean `kt`?"
    err = error(tmp_path, replace("outputs:\n  V: {unit: m/s}\n", "outputs:\n  V: {unit: mph}\n"))
    assert "unknown unit `mph`" in str(err) and "data column" in err.hint and "kt" in err.hint
    err = error(tmp_path, replace("  MDE: {unit: 1/s}\n",
                                  "  MDE: {unit: 1/s, description: M_de (per rad, nose down)}\n"),
                "comma.yaml")
    assert "unknown key" in str(err) and "quotes" in err.hint
    err = error(tmp_path, replace("  MDE: {unit: 1/s}\n",
                                  "  MDE: {unit: 1/s, description: elevator, measured}\n"),
                "comma2.yaml")
    assert "unknown key `measured`" in str(err) and "quotes" in err.hint


def test_a_constant_that_makes_an_equation_infinite_is_refused_at_the_equation(tmp_path):
    """`1/K` with `K: {value: 0}`: refused by check at the equation, naming the constant (it
    passed check and ended in an internal error, ZeroDivisionError, in the generated code)."""
    text = replace("  G0: {value: 9.80665, unit: m/s^2}\n",
                   "  G0: {value: 9.80665, unit: m/s^2}\n  K: {value: 0, unit: \"1\"}\n")
    text = replace("  alpha: MDE*de\n", "  alpha: MDE*de + 1/(K + 0*alpha)\n", text)
    err = error(tmp_path, text)
    assert "drift equation of `alpha`" in str(err) and "K = 0" in str(err) and err.line == 19


def test_roots_of_squared_dimensions_simplify(tmp_path):
    """√(u² + w²) of two speeds is a speed (dimensions are positive: (length²/time²)^½ =
    length/time); k times a cube root of a speed, length^(1/3)/time^(4/3), is still warned."""
    p = tmp_path / "b.yaml"
    p.write_text(textwrap.dedent("""\
        name: b
        states: {u: {unit: m/s}, w: {unit: m/s}}
        outputs: {V: {unit: m/s}, R: {unit: m/s}}
        parameters: {k: {unit: 1/s}}
        definitions:
          Vt: sqrt(u**2 + w**2)
        drift:
          u: -k*u*Vt/Vt
          w: -k*w + k*(u**2 + w**2)**0.5
        observations:
          V: Vt
          R: (u**3)**(1/3) + Vt*(u/w)**(1/3) + k*u**(1/3)
        data:
          time: t
          outputs: {V: V, R: R}
        """))
    m = compile_spec(p)
    units = [w.message for w in m.warnings if w.code == "units"]
    assert len(units) == 1 and "observation of `R`" in units[0] and "length**(1/3)/time**(4/3)" in units[0], units


@pytest.mark.parametrize("written, said", [("9" * 400, "finite number"),
                                           ("1:30", "not a plain decimal"),
                                           ("010", "not a plain decimal"),
                                           ("0x1F", "not a plain decimal")],
                         ids=["400 digits", "base 60", "octal", "hex"])
def test_numbers_yaml_11_reads_oddly_are_refused_at_their_line(tmp_path, written, said):
    """A 400-digit integer as an initial value ended in `internal error: OverflowError`
    (exit 3); YAML 1.1 reads `1:30` as 90, `010` as 8 and `0x1F` as 31 without a word
    (session 44, red team). Each is refused at its line with a hint."""
    err = error(tmp_path, replace("CD0: {initial: 0.1, bounds: [0, 1]}",
                                  f"CD0: {{initial: {written}, bounds: [0, 1]}}"))
    assert said in str(err) and ":12:" in str(err), str(err)
    ok = compile_spec(write(tmp_path, replace("CD0: {initial: 0.1, bounds: [0, 1]}",
                                              "CD0: {initial: 1_000.5, bounds: [-1e4, 1E+4]}")))
    assert ok.parameters[0].initial == 1000.5


@pytest.mark.parametrize("char, hint", [("\u2028", "line break"), ("\x85", "line break"),
                                        ("\x1b", "plain text"), ("\x0c", "plain text")])
def test_characters_yaml_refuses_or_counts_as_lines_are_located_by_the_files_lines(
        tmp_path, char, hint):
    """An ESC byte gave "YAML error: … position 1415" (no line, a literal `\\n`); U+2028 or
    NEL in a description moved every later error's line number (YAML counts them as line
    breaks, editors do not) (session 44, red team). Refused at the file's own line and
    column, whatever its line ends."""
    for end in ("\n", "\r\n"):
        text = replace("  alpha: MDE*de\n", f"  alpha: MDE*de  # a{char}b\n").replace("\n", end)
        err = error(tmp_path, text)
        line = next(i for i, ln in enumerate(GOOD.splitlines(), 1) if "alpha: MDE*de" in ln)
        assert f":{line}:" in str(err) and f"U+{ord(char):04X}" in str(err), str(err)
        assert hint in str(err)


def test_a_data_map_scale_of_zero_is_refused(tmp_path):
    """`scale: 0` read every sample as the offset (`check` showed `de: 0 .. 0`; session 44,
    red team)."""
    text = GOOD.replace("de: de_rad", "de: {column: de_rad, scale: 0}")
    assert text != GOOD
    err = error(tmp_path, text)
    assert "scale of `de` is 0" in str(err)
