"""MATLAB .mat records and data-map units: same record, same estimates as the CSV in SI units."""

from __future__ import annotations

import math
import pathlib

import numpy as np
import pytest

from vsidgen.cli import main
from vsidgen.data import load_record
from vsidgen.errors import DataError, SpecError
from vsidgen.spec import compile_spec

# one worker runs the whole module: its module-scoped fixtures are computed once
pytestmark = pytest.mark.xdist_group("test_formats_units")

ROOT = pathlib.Path(__file__).resolve().parent.parent
SPEC = ROOT / "specs" / "attas_sp.yaml"
CSV = ROOT / "data" / "attas_sp_synthetic.csv"


def _csv_columns(path):
    """Independent reader: header + numpy block."""
    head = path.read_text().splitlines()[0].split(",")
    block = np.loadtxt(path, delimiter=",", skiprows=1)
    return head, block


def _write_mat73(path, variables):
    """A MATLAB v7.3 file as MATLAB writes it: 512-byte text header, HDF5, arrays transposed,
    `MATLAB_class` attributes, cell arrays as object references into `#refs#`."""
    import h5py

    with h5py.File(path, "w", userblock_size=512) as f:
        refs = f.create_group("#refs#")
        for name, value in variables.items():
            if isinstance(value, list):  # cell array of char
                dt = h5py.special_dtype(ref=h5py.Reference)
                cell = np.empty((1, len(value)), dtype=dt)
                for j, text in enumerate(value):
                    d = refs.create_dataset(f"{name}_{j}", data=np.array(
                        [[ord(c)] for c in text], dtype=np.uint16))
                    d.attrs["MATLAB_class"] = np.bytes_("char")
                    cell[0, j] = d.ref
                ds = f.create_dataset(name, data=cell.T)
                ds.attrs["MATLAB_class"] = np.bytes_("cell")
            else:
                arr = np.atleast_2d(np.asarray(value, dtype=np.float64))
                if arr.shape[0] == 1:
                    arr = arr.T  # a MATLAB column vector N x 1
                ds = f.create_dataset(name, data=arr.T)  # column-major on disk
                ds.attrs["MATLAB_class"] = np.bytes_("double")
    with open(path, "r+b") as fh:
        fh.write(b"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: test HDF5 schema 1.00 .")


@pytest.fixture(scope="module")
def mat_files(tmp_path_factory):
    import scipy.io

    d = tmp_path_factory.mktemp("mat")
    head, block = _csv_columns(CSV)
    per_var = {h: block[:, j] for j, h in enumerate(head)}
    scipy.io.savemat(d / "vars.mat", per_var)
    scipy.io.savemat(d / "named.mat", {"X": block, "X_names": np.array(head, dtype=object)})
    scipy.io.savemat(d / "fdata.mat", {"fdata": block})
    _write_mat73(d / "v73.mat", per_var)
    _write_mat73(d / "v73named.mat", {"X": block, "X_names": head})
    return d


def _selected_spec(tmp_path, head):
    """attas_sp with the data map written as SIDPAC-style column selections fdata(:,k)."""
    k = {h: j + 1 for j, h in enumerate(head)}
    text = (f"extends: {SPEC}\nname: attas_sp_fdata\ndata:\n  time: 'fdata(:,{k['t_s']})'\n"
            f"  inputs: {{de: 'fdata(:,{k['de_rad']})'}}\n"
            f"  outputs: {{alpha: 'fdata(:,{k['alpha_rad']})', q: 'fdata(:,{k['q_radps']})'}}\n")
    path = tmp_path / "fdata.yaml"
    path.write_text(text)
    return path


def test_mat_records_equal_the_csv(mat_files, tmp_path):
    sym = compile_spec(SPEC)
    ref = load_record(sym, CSV)
    for name in ("vars.mat", "named.mat", "v73.mat", "v73named.mat"):
        rec = load_record(sym, mat_files / name)
        for a in ("t_raw", "u", "y"):
            assert np.array_equal(getattr(rec, a), getattr(ref, a)), (name, a)
        assert rec.dt == ref.dt and rec.name == pathlib.Path(name).stem
    head, _ = _csv_columns(CSV)
    rec = load_record(compile_spec(_selected_spec(tmp_path, head)), mat_files / "fdata.mat")
    assert np.array_equal(rec.y, ref.y) and np.array_equal(rec.u, ref.u)


def test_mat_errors_are_located(mat_files, tmp_path):
    sym = compile_spec(SPEC)
    with pytest.raises(DataError) as ei:  # no variable fdata in this file
        load_record(compile_spec(_selected_spec(tmp_path, _csv_columns(CSV)[0])),
                    mat_files / "vars.mat")
    assert "'fdata(:,1)' not found" in str(ei.value)
    bad = tmp_path / "bad.yaml"
    bad.write_text(f"extends: {SPEC}\nname: bad\ndata: {{time: fdata, inputs: {{de: de_rad}}, "
                   "outputs: {alpha: alpha_rad, q: q_radps}}\n")
    with pytest.raises(DataError) as ei:
        load_record(compile_spec(bad), mat_files / "fdata.mat")
    assert "626x4 matrix" in str(ei.value) and "fdata(:,1)" in ei.value.hint
    misspelt = tmp_path / "typo.yaml"
    misspelt.write_text(f"extends: {SPEC}\nname: typo\ndata: {{time: t_s, inputs: {{de: de_rd}}, "
                        "outputs: {alpha: alpha_rad, q: q_radps}}\n")
    with pytest.raises(DataError) as ei:
        load_record(compile_spec(misspelt), mat_files / "vars.mat")
    assert ei.value.column == "de_rd" and "de_rad" in ei.value.hint
    with pytest.raises(DataError) as ei:
        load_record(sym, _binary(tmp_path))
    assert "not a supported data file" in str(ei.value) and "MATLAB .mat" in ei.value.hint


def _binary(tmp_path):
    p = tmp_path / "rec.xlsx"
    p.write_bytes(b"PK\x03\x04" + bytes(range(256)) * 4)
    return p


def test_check_data_on_binary_file_names_formats(tmp_path, capsys):
    p = tmp_path / "rec.dat"
    p.write_bytes(b"\xdd\xfe\x00\x01" * 100)
    assert main(["check", str(SPEC), "--data", str(p)]) == 2
    err = capsys.readouterr().err
    assert "utf-8" not in err and "supported formats" in err and "Traceback" not in err


@pytest.fixture(scope="module")
def reference_fit():
    """The attas_sp model and its fit to the CSV record (SI units)."""
    from vsidgen.estimator import FitOptions, fit
    from vsidgen.model import load_model

    model = load_model(SPEC)
    options = FitOptions(max_iter=60)
    return model, options, fit(model, [load_record(model, CSV)], options=options)


def test_mat_fit_equals_csv_fit(mat_files, reference_fit):
    from vsidgen.estimator import fit

    model, options, ref = reference_fit
    res = fit(model, [load_record(model, mat_files / "v73named.mat")], options=options)
    assert ref.converged and res.converged
    assert res.elbo == ref.elbo
    assert np.array_equal(res.theta, ref.theta) and np.array_equal(res.std_errors, ref.std_errors)


# ---------------------------------------------------------------- units in the data map

DEG = math.pi / 180.0


def _degree_record(tmp_path):
    head, block = _csv_columns(CSV)
    scale = {"t_s": 1.0, "de_rad": 1 / DEG, "alpha_rad": 1 / DEG, "q_radps": 1 / DEG}
    names = {"t_s": "t_s", "de_rad": "de_deg", "alpha_rad": "alpha_deg", "q_radps": "q_degps"}
    path = tmp_path / "deg.csv"
    with open(path, "w") as fh:
        fh.write(",".join(names[h] for h in head) + "\n")
        np.savetxt(fh, block * np.array([scale[h] for h in head]), fmt="%.17g", delimiter=",")
    return path


def _unit_spec(tmp_path, alpha_unit="deg", name="attas_sp_deg"):
    path = tmp_path / f"{name}.yaml"
    path.write_text(f"extends: {SPEC}\nname: {name}\ndata:\n  time: t_s\n"
                    "  inputs: {de: {column: de_deg, unit: deg}}\n"
                    f"  outputs:\n    alpha: {{column: alpha_deg, unit: {alpha_unit}}}\n"
                    "    q: {column: q_degps, unit: deg/s}\n")
    return path


def test_degree_columns_declared_in_degrees_give_the_radian_estimates(tmp_path, reference_fit):
    from vsidgen.estimator import fit

    model, options, ref = reference_fit
    deg = _degree_record(tmp_path)
    spec = _unit_spec(tmp_path)  # attas_sp with {column: .._deg, unit: deg} (deg/s for q)
    rec, rad = load_record(compile_spec(spec), deg), load_record(model, CSV)
    np.testing.assert_allclose(rec.y, rad.y, rtol=1e-14, atol=1e-17)
    np.testing.assert_allclose(rec.u, rad.u, rtol=1e-14, atol=1e-17)
    assert rec.warnings == ()
    res = fit(model, [rec], options=options)  # the same equations: only the data map differs
    assert ref.converged and res.converged
    assert res.elbo == pytest.approx(ref.elbo, rel=1e-9)
    np.testing.assert_allclose(res.theta, ref.theta, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(res.std_errors, ref.std_errors, rtol=1e-5)


def test_unit_conversions_against_textbook_factors(tmp_path):
    from vsidgen.spec.dataunits import conversion

    assert conversion("deg", "rad") == pytest.approx((DEG, 0.0), rel=1e-15)
    assert conversion("ft", "m")[0] == pytest.approx(0.3048, rel=1e-15)
    assert conversion("kt", "m/s")[0] == pytest.approx(1852 / 3600, rel=1e-15)
    assert conversion("ft/s", "m/s")[0] == pytest.approx(0.3048, rel=1e-15)
    assert conversion("g", "m/s^2")[0] == pytest.approx(9.80665, rel=1e-15)
    assert conversion("deg/s", "rad/s")[0] == pytest.approx(DEG, rel=1e-15)
    assert conversion("degC", "K") == pytest.approx((1.0, 273.15), rel=1e-15)
    assert conversion("lbf", "N")[0] == pytest.approx(4.4482216152605, rel=1e-12)


def test_incompatible_unit_is_a_located_spec_error(tmp_path, capsys):
    spec = _unit_spec(tmp_path, alpha_unit="ft", name="bad_unit")
    with pytest.raises(SpecError) as ei:
        compile_spec(spec)
    err = ei.value
    assert err.path == spec and err.line == 7 and "alpha" in err.message
    assert "[length]" in err.message and "rad" in err.message
    spec2 = _unit_spec(tmp_path, alpha_unit="furlongs_per_blink", name="unknown_unit")
    assert main(["check", str(spec2)]) == 2
    assert "unknown unit" in capsys.readouterr().err


def test_degrees_read_as_radians_warn(tmp_path, capsys):
    """The 2π rule: an angle beyond one revolution (rate beyond one per second) read as rad."""
    t = np.arange(200) * 0.04
    de_deg = 8.0 * np.sin(t)                   # |de| <= 8 deg: read as rad, beyond 2π
    alpha_deg = 3.0 + 2.0 * np.sin(2 * t)      # <= 5 deg: below 2π even as rad (not flagged)
    q_degps = 20.0 * np.cos(2 * t)             # 20 deg/s: read as rad/s, beyond 2π rad/s
    path = tmp_path / "deg.csv"
    with open(path, "w") as fh:
        fh.write("t_s,de_deg,alpha_deg,q_degps\n")
        np.savetxt(fh, np.column_stack([t, de_deg, alpha_deg, q_degps]), fmt="%.17g", delimiter=",")
    spec = tmp_path / "wrong.yaml"
    spec.write_text(f"extends: {SPEC}\nname: wrong\ndata:\n  time: t_s\n  inputs: {{de: de_deg}}\n"
                    "  outputs: {alpha: alpha_deg, q: q_degps}\n")
    rec = load_record(compile_spec(spec), path)
    assert {w.channel for w in rec.warnings} == {"de", "q"}
    assert load_record(compile_spec(_unit_spec(tmp_path)), path.rename(tmp_path / "d2.csv")
                       ).warnings == ()
    assert main(["check", str(spec), "--data", str(tmp_path / "d2.csv")]) == 0
    err = capsys.readouterr().err
    assert "{column: de_deg, unit: deg}" in err and "{column: q_degps, unit: deg/s}" in err
    # the 2π rule misses α (5 deg read as rad is within one revolution); its column's name does not
    assert "input `alpha`" not in err and "output `alpha` (column" not in err
    assert "column `alpha_deg` of output `alpha` is named in `deg`" in err


def test_a_column_named_in_other_units_than_the_spec_warns(tmp_path, capsys):
    """`alpha: alpha_deg` for an angle in rad (and `q (deg/s)`, `az_g`-style suffixes) with no
    conversion in the data map: the spec check warns at the entry and names the fix (the 2π
    rule above misses an α of a few degrees read as radians); declared units, a `scale`, or a
    suffix in the spec's own unit give no warning."""
    from vsidgen.spec.dataunits import column_suffix_unit, suffix_mismatch

    assert column_suffix_unit("alpha_deg") == "deg" and column_suffix_unit("q_deg_s") == "deg/s"
    assert column_suffix_unit("q (deg/s)") == "deg/s" and column_suffix_unit("az_g") == "g"
    assert column_suffix_unit("delta_e") is None and column_suffix_unit("alpha") is None
    assert suffix_mismatch("V_kts", "m/s") == "knot" and suffix_mismatch("alpha_rad", "rad") is None
    assert suffix_mismatch("h_m", "rad") is None               # another dimension: not a scale
    path = tmp_path / "suffix.yaml"
    path.write_text(f"extends: {SPEC}\nname: suffix\ndata:\n  time: t_s\n"
                    "  inputs: {de: {column: \"de (deg)\"}}\n"
                    "  outputs:\n    alpha: alpha_deg\n"
                    "    q: {column: q_degps, scale: 0.017453292519943295}\n")
    sym = compile_spec(path)
    got = [w for w in sym.warnings if w.code == "column_unit_suffix"]
    assert [(w.line, w.message.split("`")[1]) for w in got] == [(5, "de (deg)"), (7, "alpha_deg")]
    assert "`alpha: {column: alpha_deg, unit: deg}`" in got[1].hint
    assert '`de: {column: "de (deg)", unit: deg}`' in got[0].hint
    assert main(["check", str(path)]) == 0
    assert "column `alpha_deg` of output `alpha` is named in `deg`" in capsys.readouterr().err
    assert not [w for w in compile_spec(_unit_spec(tmp_path)).warnings
                if w.code == "column_unit_suffix"]


def test_a_column_named_in_another_dimension_is_a_wrong_column(tmp_path):
    """`alpha: v_mps` (a speed column mapped to an angle; a slip of the data map): the spec
    check says the column's name states another dimension, and the 2π plausibility warning no
    longer suggests declaring the column in degrees but asks whether it is the right column."""
    import numpy as np

    from vsidgen.data import load_record
    from vsidgen.spec.dataunits import DataWarningCode, suffix_other_dimension

    assert suffix_other_dimension("v_mps", "rad") == "m/s"
    assert suffix_other_dimension("alpha_deg", "rad") is None      # same dimension: a scale
    assert suffix_other_dimension("alpha", "rad") is None          # no unit in the name
    path = tmp_path / "wrong.yaml"
    path.write_text(f"extends: {SPEC}\nname: wrongcol\ndata:\n  time: t_s\n"
                    "  inputs: {de: de_rad}\n"
                    "  outputs:\n    alpha: v_mps\n    q: q_radps\n")
    sym = compile_spec(path)
    got = [w for w in sym.warnings if w.code == "column_other_dimension"]
    assert len(got) == 1 and got[0].line == 7 and "a wrong column?" in got[0].message
    t = 0.1 * np.arange(40)
    csv = tmp_path / "d.csv"
    csv.write_text("t_s,de_rad,v_mps,q_radps\n" + "".join(
        f"{a},{0.01 * np.sin(a)},{70 + np.sin(a)},{0.01 * np.cos(a)}\n" for a in t))
    rec = load_record(sym, csv)
    plaus = [w for w in rec.warnings if w.code is DataWarningCode.IMPLAUSIBLE_RANGE]
    assert len(plaus) == 1 and "is `v_mps` the right column for `alpha`?" in plaus[0].hint
    assert "unit: deg" not in plaus[0].hint


def test_fit_shows_and_records_a_column_read_in_another_unit(tmp_path, capsys, monkeypatch):
    """`fit` (not only `check`) says that `alpha: alpha_rad` feeds a state declared in degrees
    without conversion, before the fit, and results.json keeps the warning."""
    import json

    root = pathlib.Path(__file__).resolve().parents[1]
    text = (root / "specs" / "attas_sp.yaml").read_text()
    text = text.replace("name: attas_sp", "name: attas_sp_deg_user").replace(
        "alpha: {unit: rad,", "alpha: {unit: deg,")
    spec = tmp_path / "deg.yaml"
    spec.write_text(text)
    out = tmp_path / "out"
    monkeypatch.chdir(tmp_path)  # the generated module goes to ./generated
    main(["fit", str(spec), str(root / "data" / "attas_sp_synthetic.csv"), "--out", str(out),
          "--max-iter", "2", "--quiet", "--noise-start", "data"])
    err = capsys.readouterr().err
    assert "column `alpha_rad` of output `alpha` is named in `rad`" in err
    res = json.loads((out / "results.json").read_text())
    assert [w["code"] for w in res["warnings"]].count("column_unit_suffix") == 1


def test_a_conversion_factor_that_underflows_or_overflows_is_refused():
    """`deg*deg*...` (400 factors) / deg is dimensionless like rad, and (π/180)^399 underflowed
    to 0: every sample read as 0 without a word (session 43). Refused with the factor."""
    from vsidgen.spec import dataunits

    with pytest.raises(dataunits.UnitConversionError, match="not a usable factor"):
        dataunits.conversion("*".join(["deg**9"] * 7) + "/deg", "rad")
    with pytest.raises(dataunits.UnitConversionError, match="longer than"):
        dataunits.conversion("*".join(["deg"] * 400) + "/deg", "rad")
    assert dataunits.conversion("deg", "rad")[0] == pytest.approx(math.pi / 180)


def test_a_scale_that_converts_the_dimension_is_no_wrong_column(tmp_path):
    """`nz: {column: az_mps2, scale: -0.10197162}` (−1/g: a load factor read from an
    acceleration, the documented pattern) drew "a wrong column?" with no way to silence it
    (session 43); a bare sign flip converts nothing and still does."""
    for scale, expected in (("-0.10197162", 0), ("-1", 1)):
        path = tmp_path / f"nz{len(scale)}.yaml"
        path.write_text(f"extends: {SPEC}\nname: nzscale\ndata:\n  time: t_s\n"
                        "  inputs: {de: de_rad}\n"
                        f"  outputs:\n    alpha: {{column: az_mps2, scale: {scale}}}\n    q: q_radps\n")
        sym = compile_spec(path)
        got = [w for w in sym.warnings if w.code == "column_other_dimension"]
        assert len(got) == expected, (scale, [w.message for w in sym.warnings])


@pytest.mark.parametrize("expr, warned", [("(alpha_rad + alpha2_rad)/2", True),
                                          ("alpha_rad*57.29578", False),
                                          ("(alpha_rad + alpha2_rad)*28.64789", False),
                                          ("sin(alpha_rad)", False)])
def test_an_expression_of_columns_in_another_unit_scale_warns(tmp_path, expr, warned):
    """An `expr` entry reading only `*_rad` columns into an input declared in deg, converting
    nothing, was read unconverted without a word (session 43; the same slip with `column:`
    warns). A coefficient equal to the conversion factor (57.3, or 28.6 on each of two
    columns) converts; a nonlinear expression is left alone."""
    path = tmp_path / "e.yaml"
    path.write_text(f"extends: {SPEC}\nname: exprdeg\noutputs:\n  alpha: {{unit: deg}}\n"
                    "data:\n  time: t_s\n  inputs: {de: de_rad}\n"
                    f"  outputs:\n    alpha: {{expr: \"{expr}\"}}\n    q: q_radps\n")
    sym = compile_spec(path)
    got = [w for w in sym.warnings if w.code == "column_unit_suffix" and "expression of" in w.message]
    assert bool(got) is warned, [w.message for w in sym.warnings]
    if warned:
        assert "add `unit: rad`" in got[0].hint and got[0].line == 9


def test_a_bias_in_the_units_of_its_equation_is_not_warned_as_noncoherent(tmp_path):
    """A model written in degrees: a bias `c1` in deg/s² added (through a definition) to the
    drift of a rate in deg/s is in the unit it is declared in; the warning told the user to
    declare it in rad/s² (session 43). Added to an equation in rad/s it is still warned."""
    def spec(rate_unit):
        return (f"name: degbias\nstates:\n  p: {{unit: {rate_unit}}}\ninputs:\n  da: {{unit: deg}}\n"
                "outputs:\n  p: {unit: deg/s}\nparameters:\n  Lp: {unit: 1/s}\n  Lda: {unit: 1/s^2}\n"
                "  c1: {unit: deg/s^2}\ndefinitions:\n  pd: Lp*p + Lda*da + c1\ndrift:\n  p: pd\n"
                "observations:\n  p: p\ndata:\n  time: t_s\n  inputs: {da: da_deg}\n"
                "  outputs: {p: p_degps}\n")
    for rate_unit, warned in (("deg/s", False), ("rad/s", True)):
        path = tmp_path / f"b{warned}.yaml"
        path.write_text(spec(rate_unit))
        sym = compile_spec(path)
        got = [w for w in sym.warnings if w.code == "noncoherent_unit" and "`c1`" in w.message]
        assert bool(got) is warned, (rate_unit, [w.message for w in sym.warnings])


def test_newcomers_unit_slips_get_the_right_hint(tmp_path):
    """Session 43, a new user's slips: `rad/s2` was answered "did you mean `s`?"; a data-map
    `unit: deg` on a column named `*_rad` was accepted silently; pint's exception class
    name leaked into the unknown-unit message."""
    from vsidgen.spec import dataunits

    text = SPEC.read_text().replace("M0:  {unit: rad/s^2", "M0:  {unit: rad/s2")
    bad = tmp_path / "s2.yaml"
    bad.write_text(text)
    with pytest.raises(SpecError) as err:
        compile_spec(bad)
    assert "did you mean `s^2`?" in str(err.value)
    path = tmp_path / "u.yaml"
    path.write_text(f"extends: {SPEC}\nname: unitslip\ndata:\n  time: t_s\n  inputs: {{de: de_rad}}\n"
                    "  outputs:\n    alpha: {column: alpha_rad, unit: deg}\n    q: q_radps\n")
    got = [w for w in compile_spec(path).warnings if w.code == "column_unit_suffix"]
    assert len(got) == 1 and "declares it in `deg`" in got[0].message and "`unit: rad`" in got[0].hint
    with pytest.raises(dataunits.UnitConversionError) as err:
        dataunits.conversion("furlong_per_fortnight", "m/s")
    assert "Error" not in str(err.value)


def test_scale_of_agrees_with_evaluating_in_both_unit_systems():
    """`units.scale_of(e)` claims e(x_coherent) = s·e(x_declared) for every value: checked by
    evaluating each expression at random points in both systems (the reference shares no
    code with the walker). Where it says None, no single factor relates the two."""
    import math as _m
    import random

    import sympy
    from vsidgen.spec import units

    p, q, a, y, c, k, V = sympy.symbols("p q a y c k V")
    declared = {p: "deg/s", q: "rad/s", a: "deg", y: "m/(s*deg)", c: "deg/s^2", k: "1/deg",
                V: "m/s"}
    scales = {s: units.coherent(u)[0] for s, u in declared.items()}
    cases = [y*p + V/10, y*p + 3, p/a, sympy.sin(a), sympy.sin(a*sympy.pi/180), k*a + 1,
             p + q, p + c*y/y*2, sympy.Abs(p) * a, sympy.Max(p, 2*p), sympy.atan2(p, q),
             sympy.atan2(p, 2*p), sympy.sign(p - 3) * V, (y*p)**2 + V**2/100, sympy.sqrt(a)]
    rng = random.Random(0)
    for e in cases:
        s = units.scale_of(e, scales)
        ratios = []
        for _ in range(5):
            decl = {sym: rng.uniform(0.2, 2.0) for sym in declared}
            coh = {sym: v * scales[sym] for sym, v in decl.items()}
            d, h = float(e.xreplace(decl)), float(e.xreplace(coh))
            ratios.append(h / d if d != 0 else _m.nan)
        constant = all(_m.isclose(r, ratios[0], rel_tol=1e-9) for r in ratios)
        if s is None:
            assert not constant or e.has(sympy.Max, sympy.atan2, sympy.sign), (e, ratios)
        else:
            assert constant and _m.isclose(ratios[0], s, rel_tol=1e-9), (e, s, ratios)


def test_a_model_written_in_degrees_is_not_warned_but_sin_of_degrees_is(tmp_path):
    """Session 44: a derivative in m/(s·deg) times a rate in deg/s was warned as non-coherent
    (the check read names, not the algebra); the whole of a lateral model consistent in
    degrees got 14 warnings. Now only what is wrong as written is warned: sin() of a bank
    angle in deg, and a rate in rad/s added to one in deg/s."""
    def spec(bank_term, rate_unit):
        return ("name: degmodel\nconstants:\n  g: {value: 9.80665, unit: m/s^2}\n"
                "  V: {value: 70, unit: m/s}\nstates:\n  beta: {unit: deg}\n"
                f"  p: {{unit: {rate_unit}}}\n  r: {{unit: deg/s}}\n  phi: {{unit: deg}}\n"
                "inputs:\n  da: {unit: deg}\noutputs:\n  ay: {unit: m/s^2}\n  p: {unit: deg/s}\n"
                "  phi: {unit: deg}\nparameters:\n  Yb: {unit: 1/s}\n  Lp: {unit: 1/s}\n"
                "  Lda: {unit: 1/s^2}\n  Nr: {unit: 1/s}\n  y_p: {unit: m/(s*deg)}\n"
                "  y_b: {unit: m/(s^2*deg)}\ndrift:\n"
                f"  beta: Yb*beta - r + {bank_term}\n  p: Lp*p + Lda*da\n  r: Nr*r\n  phi: p\n"
                "observations:\n  ay: y_p*p + y_b*beta\n  p: p\n  phi: phi\n"
                "data:\n  time: t_s\n  inputs: {da: {column: da_rad, unit: rad}}\n"
                "  outputs:\n    ay: ay_mps2\n    p: {column: p_radps, unit: rad/s}\n"
                "    phi: {column: phi_rad, unit: rad}\n")

    def warned(name, bank_term, rate_unit="deg/s"):
        path = tmp_path / f"m{abs(hash((name, bank_term, rate_unit)))}.yaml"
        path.write_text(spec(bank_term, rate_unit))
        return {w.message.split("`")[1] for w in compile_spec(path).warnings
                if w.code == "noncoherent_unit"}

    assert warned("ok", "g/V*phi") == set()
    assert {"phi"} <= warned("sin", "g/V*sin(phi)*57.29578")
    assert "y_p" not in warned("sin", "g/V*sin(phi)*57.29578")
    got = warned("rad", "g/V*phi", "rad/s")
    # p in rad/s: its drift adds Lda·da in deg/s², ay adds y_p·p (per deg) to y_b·β, φ̇ = p
    assert {"da", "y_p", "y_b", "phi"} <= got and "r" not in got and "Yb" not in got


@pytest.mark.parametrize("unit", ["9**9**9", "m**99", "m^2^3", "s**(9**9)", "x" * 200])
def test_a_unit_pint_would_evaluate_forever_is_refused_at_once(tmp_path, unit):
    """pint evaluates `9**9**9` literally: a unit in a data map hung `check`, and a column
    header `junk [9**9**9]` hung `check --data` and `fit` of every spec with constants
    (session 44, red team). Refused before pint sees it (the header's unit is then not a
    unit, and the column a plain column)."""
    import time

    from vsidgen.spec import dataunits

    t0 = time.perf_counter()
    with pytest.raises(dataunits.UnitConversionError):
        dataunits.check_unit(unit)
    assert dataunits.column_suffix_unit(f"junk [{unit}]") is None
    assert time.perf_counter() - t0 < 5.0
    path = tmp_path / "u.yaml"
    path.write_text(f"extends: {SPEC}\nname: unitbomb\ndata:\n  time: t_s\n"
                    f"  inputs: {{de: {{column: de_rad, unit: \"{unit}\"}}}}\n")
    with pytest.raises(SpecError) as err:
        compile_spec(path)
    assert ":5:" in str(err.value) or "line 5" in str(err.value), str(err.value)


def test_constant_columns_of_a_wide_header_take_linear_time():
    """`constant_columns` counted every column in the header for every column (quadratic: a
    40 000-column record took 104 s to check). The answer is unchanged."""
    import types

    from vsidgen.spec import dataunits

    header = ["t", "v_mps", "mass_kg", "mass_kg", "V"] + [f"c{i}" for i in range(50000)]
    consts = [types.SimpleNamespace(name=n) for n in ("V", "MASS", "rho")]
    assert dataunits.constant_columns(consts, header, taken=["t"]) == {"V": ["v_mps", "V"]}


def test_a_spec_or_readme_given_as_a_record_is_not_read_as_a_csv(tmp_path):
    """`vsidgen fit spec.yaml spec.yaml` said "line 1 is a comment (...), not the column
    names": the spec was read as a CSV (session 44, a new user). A file whose name says it
    is no record is refused as such."""
    sym = compile_spec(SPEC)
    for name, what in (("notes.md", "Markdown"), ("spec.yaml", "YAML"), ("r.json", "JSON")):
        p = tmp_path / name
        p.write_text("# DHC-6 Twin Otter,longitudinal\nt_s,de_rad\n0,1\n")
        with pytest.raises(DataError) as ei:
            load_record(sym, p)
        assert f"not a supported data file (a {what} file)" in str(ei.value)


def test_an_equation_mixing_degrees_and_radians_names_its_terms(tmp_path):
    """`cos(theta - alpha)` with θ in rad and α in deg had only the generic per-variable
    warnings (session 44, a new user): the equation is named with the two terms whose
    numbers disagree; a consistent equation gets nothing."""
    path = tmp_path / "mix.yaml"
    path.write_text("name: mix\nstates:\n  alpha: {unit: deg}\n  q: {unit: rad/s}\n"
                    "  theta: {unit: rad}\ninputs:\n  de: {unit: rad}\noutputs:\n"
                    "  a_m: {unit: deg}\nparameters:\n  Za: {unit: 1/s}\n  Ma: {unit: 1/s^2}\n"
                    "drift:\n  alpha: Za*alpha\n  q: Ma*theta + cos(theta - alpha)\n"
                    "  theta: q\nobservations:\n  a_m: alpha\n"
                    "data:\n  time: t\n  inputs: {de: de}\n  outputs: {a_m: a}\n")
    got = [w for w in compile_spec(path).warnings if w.code == "unit_scale"]
    assert len(got) == 1 and "drift of `q`" in got[0].message, [w.message for w in got]
    assert "degree-based" in got[0].message and "coherent" in got[0].message
    assert got[0].line == 15


def test_an_expression_undefined_at_a_sample_is_not_called_a_missing_value(tmp_path):
    """`log` of a negative column value was reported as "missing value in input" (session
    44, red team): the expression and the column values at that sample are named."""
    lines = CSV.read_text().splitlines()
    head = lines[0].split(",")
    j = head.index("de_rad")
    row = lines[5].split(",")
    row[j] = "-2"
    lines[5] = ",".join(row)
    rec = tmp_path / "neg.csv"
    rec.write_text("\n".join(lines) + "\n")
    path = tmp_path / "logx.yaml"
    path.write_text(f"extends: {SPEC}\nname: logx\ndata:\n  time: t_s\n"
                    "  inputs:\n    de: {expr: \"log(de_rad + 1)\"}\n")
    with pytest.raises(DataError) as ei:
        load_record(compile_spec(path), rec)
    assert "is undefined (NaN)" in str(ei.value) and "de_rad = -2" in str(ei.value)
    assert ei.value.sample == 4


def test_check_accepts_text_columns_the_data_map_does_not_use(tmp_path, capsys):
    """A record with a `flight` column ("F1") the map does not use: `fit` read it, `check
    --data` refused it as a non-numeric value (session 44, a new user). A text cell in a
    mapped column is still refused, at its column."""
    from vsidgen.cli import main

    lines = CSV.read_text().splitlines()
    text = [lines[0] + ",flight"] + [ln + ",F1" for ln in lines[1:]]
    rec = tmp_path / "text.csv"
    rec.write_text("\n".join(text) + "\n")
    assert main(["check", str(SPEC), "--data", str(rec)]) == 0, capsys.readouterr().err
    head = lines[0].split(",")
    j = head.index("de_rad")
    bad = [lines[0]] + [",".join("x" if i == j and k == 0 else v
                                  for i, v in enumerate(ln.split(",")))
                        for k, ln in enumerate(lines[1:])]
    rec2 = tmp_path / "bad.csv"
    rec2.write_text("\n".join(bad) + "\n")
    assert main(["check", str(SPEC), "--data", str(rec2)]) == 2
    assert "column 'de_rad'" in capsys.readouterr().err


def test_a_named_matrix_column_written_with_the_matrix_name_gets_the_plain_name(mat_files,
                                                                                  tmp_path):
    """`X.t` for the column `t` named in `X_names` was answered "did you mean 'X(:,1..4)'?"
    (session 44, a new user): the hint now gives the name alone, which works."""
    path = tmp_path / "dotted.yaml"
    path.write_text(f"extends: {SPEC}\nname: dotted\ndata: {{time: X.t_s, inputs: {{de: de_rad}}, "
                    "outputs: {alpha: alpha_rad, q: q_radps}}\n")
    with pytest.raises(DataError) as ei:
        load_record(compile_spec(path), mat_files / "named.mat")
    assert "`t_s`" in ei.value.hint and "name alone" in ei.value.hint


def test_a_definition_mixing_degrees_and_radians_names_its_terms(tmp_path):
    """A definition whose terms disagree made every equation using it unknown, so nothing was
    said (session 46, a new user's lateral model: `side: Yb*beta + Y0` with β in deg, used by
    the β equation and the a_y output); written out in the equation it was warned. The
    definition itself is now named, at its line; a consistent definition gets nothing."""
    text = ("name: mixdef\nstates:\n  beta: {unit: BETA_UNIT}\n  r: {unit: rad/s}\n"
            "inputs:\n  dr: {unit: rad}\noutputs:\n  ay_m: {unit: m/s^2}\n"
            "constants:\n  V0: {value: 70, unit: m/s}\n"
            "parameters:\n  Yb: {unit: 1/s}\n  Y0: {unit: 1/s}\n  Nb: {unit: 1/s^2}\n"
            "definitions:\n  side: Yb*beta + Y0\n"
            "drift:\n  beta: side - r\n  r: Nb*beta + dr\n"
            "observations:\n  ay_m: V0*side\n"
            "data:\n  time: t\n  inputs: {dr: dr}\n  outputs: {ay_m: ay}\n")
    path = tmp_path / "mixdef.yaml"
    path.write_text(text.replace("BETA_UNIT", "deg"))
    got = [w for w in compile_spec(path).warnings
           if w.code == "unit_scale"]
    defs = [w for w in got if "definition of `side`" in w.message]
    assert len(defs) == 1, [w.message for w in got]
    assert "`Yb*beta`" in defs[0].message and "`Y0`" in defs[0].message
    assert defs[0].line == 16
    path.write_text(text.replace("BETA_UNIT", "rad"))
    assert not [w for w in compile_spec(path).warnings
                if w.code == "unit_scale"]
