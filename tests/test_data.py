"""Data loading: real flight records, every DataError, resolution and write_csv."""

from __future__ import annotations

import csv
import math
import pathlib

import numpy as np
import pytest
import sympy

from vsidgen.data import Record, load_record, resolution, write_csv
from vsidgen.errors import DataError
from vsidgen.metadata import ChannelMap, DataSpec, ProcessNoiseSpec, Variable
from vsidgen.model import Model


def _model(inputs, outputs, *, time="t_s", time_scale=1.0, time_unit=None):
    """inputs/outputs: lists of ChannelMap (channel name = model variable name)."""
    return Model(name="m", drift=None, output=None, states=(),
                 inputs=tuple(Variable(c.name) for c in inputs),
                 outputs=tuple(Variable(c.name) for c in outputs), parameters=(),
                 process_noise=ProcessNoiseSpec(), measurement_noise=(),
                 data=DataSpec(time=time, inputs=tuple(inputs), outputs=tuple(outputs),
                               time_scale=time_scale, time_unit=time_unit))


def _read_columns(path):
    """Independent reference reader (csv module)."""
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    head = rows[0]
    return {h: np.array([float(r[j]) for r in rows[1:]]) for j, h in enumerate(head)}


# ---------------------------------------------------------------- real records

@pytest.mark.flight
def test_hfb320(flight_data_dir):
    path = flight_data_dir / "hfb320_1_10.csv"
    m = _model([ChannelMap("de", "de_rad"), ChannelMap("thrust", "thrust_n", scale=1e-3)],
               [ChannelMap("V", "v_mps"), ChannelMap("alpha", "alpha_rad"),
                ChannelMap("az", "az_mps2", scale=1 / 9.80665, offset=1.0)])
    r = load_record(m, path)
    ref = _read_columns(path)
    assert r.name == "hfb320_1_10" and r.path == path
    assert r.u.shape == (601, 2) and r.y.shape == (601, 3) and r.t.shape == (601,)
    assert r.input_names == ("de", "thrust") and r.output_names == ("V", "alpha", "az")
    assert r.dt == pytest.approx(0.1, rel=1e-6)
    assert r.t[0] == 0.0 and r.t[-1] == pytest.approx(60.0)
    np.testing.assert_array_equal(r.t_raw, ref["t_s"])
    np.testing.assert_array_equal(r.u[:, 0], ref["de_rad"])
    np.testing.assert_allclose(r.u[:, 1], ref["thrust_n"] / 1000, rtol=1e-15)
    np.testing.assert_array_equal(r.y[:, 0], ref["v_mps"])
    np.testing.assert_allclose(r.y[:, 2], ref["az_mps2"] / 9.80665 + 1, rtol=1e-14, atol=1e-15)
    assert not np.isnan(r.y).any()


@pytest.mark.flight
def test_attas_expr_map(flight_data_dir):
    path = flight_data_dir / "attas_elv1.csv"
    right, left = sympy.symbols("da_right_rad da_left_rad")
    m = _model([ChannelMap("da", expr=(right - left) / 2, columns=("da_right_rad", "da_left_rad")),
                ChannelMap("de", "de_rad")],
               [ChannelMap("alpha", "alpha_rad"), ChannelMap("q", "q_radps")])
    r = load_record(m, path, name="elv1")
    ref = _read_columns(path)
    assert r.name == "elv1" and r.u.shape == (626, 2) and r.y.shape == (626, 2)
    assert r.dt == pytest.approx(0.04, rel=1e-9)
    np.testing.assert_allclose(r.u[:, 0], (ref["da_right_rad"] - ref["da_left_rad"]) / 2,
                               rtol=1e-15, atol=1e-18)
    np.testing.assert_array_equal(r.y[:, 1], ref["q_radps"])


@pytest.mark.flight
def test_totter_jittery_time(flight_data_dir):
    path = flight_data_dir / "totter_lon_data.csv"
    m = _model([ChannelMap("de", "de_rad")], [ChannelMap("alpha", "alpha_rad"), ChannelMap("q", "q_radps")])
    r = load_record(m, path)
    steps = np.diff(r.t_raw)
    assert steps.min() < 0.00977 and steps.max() > 0.01000   # the file really jitters
    assert r.n == 1200
    assert r.dt == pytest.approx((r.t_raw[-1] - r.t_raw[0]) / 1199, rel=1e-15)
    assert r.dt == pytest.approx(0.01, rel=1e-5)


# ---------------------------------------------------------------- synthetic files

N = 20


def _write(path, header, rows):
    path.write_text(",".join(header) + "\n" + "".join(",".join(map(str, r)) + "\n" for r in rows))
    return path


def _good_rows(n=N, dt=0.1):
    return [[f"{k * dt:.10g}", f"{0.01 * k:.6g}", f"{math.sin(k):.9g}", f"{k % 3}"] for k in range(n)]


HEADER = ["time", "de_rad", "alpha_rad", "q_radps"]


def _m():
    return _model([ChannelMap("de", "de_rad")],
                  [ChannelMap("alpha", "alpha_rad"), ChannelMap("q", "q_radps")], time="time")


def _err(tmp_path, rows, header=HEADER, model=None) -> DataError:
    path = _write(tmp_path / "rec.csv", header, rows)
    with pytest.raises(DataError) as info:
        load_record(model or _m(), path)
    err = info.value
    assert str(path) in str(err)
    return err


def test_good_synthetic(tmp_path):
    r = load_record(_m(), _write(tmp_path / "r.csv", HEADER, _good_rows()))
    assert isinstance(r, Record) and r.n == N and r.dt == pytest.approx(0.1)
    np.testing.assert_allclose(r.y[:, 0], np.sin(np.arange(N)), atol=1e-8)
    with pytest.raises(ValueError):
        r.u[0, 0] = 1.0  # read-only arrays


def test_missing_file(tmp_path):
    with pytest.raises(DataError, match="file not found"):
        load_record(_m(), tmp_path / "nope.csv")


def test_empty_and_header_only(tmp_path):
    (tmp_path / "e.csv").write_text("")
    with pytest.raises(DataError, match="empty file"):
        load_record(_m(), tmp_path / "e.csv")
    (tmp_path / "h.csv").write_text(",".join(HEADER) + "\n")
    with pytest.raises(DataError, match="header only"):
        load_record(_m(), tmp_path / "h.csv")


def test_missing_column_hint(tmp_path):
    header = ["time", "de_rad", "alpha_rad", "q_rads"]
    err = _err(tmp_path, _good_rows(), header)
    assert err.column == "q_radps"
    assert "'q_radps'" in str(err) and "did you mean 'q_rads'" in str(err)


def test_missing_time_column(tmp_path):
    err = _err(tmp_path, _good_rows(), ["t_s"] + HEADER[1:])
    assert err.column == "time" and "time column" in str(err)


def test_non_numeric_cell(tmp_path):
    rows = _good_rows()
    rows[7][2] = "abc"
    err = _err(tmp_path, rows)
    assert (err.column, err.sample) == ("alpha_rad", 7)
    assert "'abc'" in str(err) and "sample 7" in str(err)


def test_units_row_under_the_header_is_named_as_such(tmp_path):
    """Spreadsheet exports and loggers write a units row under the header: it is named as a
    units row (by the loader and by ``vsidgen check``), not as one odd cell."""
    from vsidgen.data.check import read_first_row

    rows = [["s", "rad", "rad", "rad/s"]] + _good_rows()
    err = _err(tmp_path, rows)
    assert err.sample == 0 and "units or description row" in str(err)
    assert "'s', 'rad', 'rad', 'rad/s'" in str(err) and "delete that row" in str(err)
    with pytest.raises(DataError, match="units or description row"):
        read_first_row(tmp_path / "rec.csv")
    # a first row with one bad cell among numbers is still that cell's error
    rows = _good_rows()
    rows[0][2] = "abc"
    err = _err(tmp_path, rows)
    assert err.column == "alpha_rad" and "units or description" not in str(err)


@pytest.mark.parametrize("cell, fragment", [
    ("1_5", "no digit separators"),                      # float() would read 15
    ("\u0661.\u0665", "U+0661 ARABIC-INDIC DIGIT ONE"),    # float() would read 1.5
    ("\uff11.5", "U+FF11 FULLWIDTH DIGIT ONE"),
    ("1,5", None),
])
def test_cells_python_float_takes_but_numpy_does_not_are_refused(tmp_path, cell, fragment):
    """One rule for every cell, whichever reader meets it: the cell-by-cell reader used to
    take what Python's float() takes (digit separators, other-script digits) silently."""
    rows = _good_rows()
    rows[7][2] = f'"{cell}"' if "," in cell else cell
    err = _err(tmp_path, rows)
    assert (err.column, err.sample) == ("alpha_rad", 7)
    assert "non-numeric value" in str(err)
    if fragment:
        assert fragment in str(err)


def test_truncated_row(tmp_path):
    rows = _good_rows()
    rows[5] = rows[5][:2]
    err = _err(tmp_path, rows)
    assert err.sample == 5 and err.column == "alpha_rad"


def test_row_with_extra_values(tmp_path):
    """A decimal comma (or an unquoted comma) gives a row more fields than the header: the
    columns would shift silently, so it is an error naming the row and the file line."""
    rows = _good_rows()
    rows[9] = [rows[9][0], "0,09", rows[9][2], rows[9][3]]
    err = _err(tmp_path, rows)
    assert err.sample == 9 and "5 fields but the header has 4" in str(err)
    assert "file line 11" in str(err) and "decimal comma" in str(err)


def test_trailing_empty_field_and_quoted_comma_accepted(tmp_path):
    rows = _good_rows()
    path = tmp_path / "t.csv"
    path.write_text(",".join(HEADER) + "\n" + "".join(",".join(r) + ",\n" for r in rows))
    r = load_record(_m(), path)
    ref = load_record(_m(), _write(tmp_path / "ref.csv", HEADER, rows))
    assert np.array_equal(r.y, ref.y) and np.array_equal(r.u, ref.u)
    q = tmp_path / "q.csv"
    q.write_text('"time","de_rad","alpha_rad","q_radps","note"\n'
                 + "".join(",".join(rw) + ',"a, b"\n' for rw in rows))
    rq = load_record(_m(), q)
    assert np.array_equal(rq.y, ref.y)


def test_long_gap_named_where_it_is(tmp_path):
    """A long gap inflates the mean period; the step that breaks the grid is the gap, with the
    number of missing samples, not the first regular step."""
    t = [0.1 * k for k in range(100)] + [0.1 * k for k in range(160, 260)]
    rows = [[repr(tk), "0", "1", "2"] for tk in t]
    err = _err(tmp_path, rows)
    assert err.sample == 100 and "gap of 6.1 s" in str(err) and "60 samples missing" in str(err)


@pytest.mark.parametrize("case", ["duplicate", "backwards", "gap", "short", "rate_change"])
def test_bad_time(tmp_path, case):
    t = [0.1 * k for k in range(200)]
    if case == "duplicate":
        t[12] = t[11]
        expect = 12
    elif case == "backwards":
        t[12] = t[11] - 0.05
        expect = 12
    elif case == "gap":
        t = t[:15] + [x + 0.1 for x in t[15:]]
        expect = 15
    elif case == "short":
        t[20] = t[20] - 0.02
        expect = 20
    else:  # period 0.1 then 0.104: every step within 5 %, but the grid drifts
        t = [0.1 * k if k < 100 else 9.9 + 0.104 * (k - 99) for k in range(200)]
        expect = None
    rows = [[repr(tk), "0", "1", "2"] for tk in t]
    err = _err(tmp_path, rows)
    assert err.column == "time"
    if expect is not None:
        assert err.sample == expect
        assert f"sample {expect}" in str(err)
    else:
        assert err.sample is not None and "non-uniform" in str(err)


def test_jitter_accepted(tmp_path):
    # like totter_lon_data.csv: steps alternate 0.009766 / 0.010010 (±2.4 %)
    t = np.round(np.arange(50) * 0.01 * 4096) / 4096
    assert np.ptp(np.diff(t)) > 2e-4
    rows = [[repr(float(tk)), "0", "1", "2"] for tk in t]
    r = load_record(_m(), _write(tmp_path / "j.csv", HEADER, rows))
    assert r.dt == pytest.approx((t[-1] - t[0]) / 49, rel=1e-15)


def test_too_few_samples(tmp_path):
    err = _err(tmp_path, _good_rows(n=9))
    assert "too few samples: 9" in str(err)


def test_all_nan_output(tmp_path):
    rows = _good_rows()
    for r in rows:
        r[3] = ""
    err = _err(tmp_path, rows)
    assert err.column == "q_radps" and "all NaN" in str(err) and "'q'" in str(err)


def test_all_nan_input(tmp_path):
    rows = _good_rows()
    for r in rows:
        r[1] = "nan"
    err = _err(tmp_path, rows)
    assert err.column == "de_rad" and "all NaN" in str(err)


def test_nan_in_input(tmp_path):
    rows = _good_rows()
    rows[4][1] = ""
    err = _err(tmp_path, rows)
    assert (err.column, err.sample) == ("de_rad", 4)
    assert "input 'de'" in str(err)


def test_nan_in_output_is_missing(tmp_path):
    rows = _good_rows()
    rows[4][2] = ""
    rows[9][3] = "NaN"
    r = load_record(_m(), _write(tmp_path / "r.csv", HEADER, rows))
    assert np.isnan(r.y[4, 0]) and np.isnan(r.y[9, 1])
    assert np.isnan(r.y).sum() == 2
    # each output with gaps is named with its column, count and samples (not an error)
    miss = [w for w in r.warnings if w.code.value == "missing_samples"]
    assert sorted(w.channel for w in miss) == sorted(r.output_names[:2])
    w0 = next(w for w in miss if w.channel == r.output_names[0])
    assert f"1 of {r.n} samples missing (sample 4)" in w0.message and HEADER[2] in w0.message
    full = load_record(_m(), _write(tmp_path / "ok.csv", HEADER, _good_rows()))
    assert not [w for w in full.warnings if w.code.value == "missing_samples"]


@pytest.mark.parametrize("col", [1, 2, 0])
def test_inf(tmp_path, col):
    rows = _good_rows()
    rows[6][col] = "-inf" if col else "inf"
    err = _err(tmp_path, rows)
    assert (err.column, err.sample) == (HEADER[col], 6)
    assert "infinite" in str(err)


def test_expr_map_synthetic(tmp_path):
    a, b = sympy.symbols("de_rad q_radps", real=True)
    m = _model([ChannelMap("x", expr=a * b + 1, columns=("de_rad", "q_radps"), scale=2.0, offset=-1.0)],
               [ChannelMap("alpha", "alpha_rad")], time="time")
    rows = _good_rows()
    r = load_record(m, _write(tmp_path / "r.csv", HEADER, rows))
    de = np.array([float(x[1]) for x in rows])
    q = np.array([float(x[3]) for x in rows])
    np.testing.assert_allclose(r.u[:, 0], 2 * (de * q + 1) - 1, rtol=1e-15)


def test_no_mapping_for_output(tmp_path):
    m = _model([ChannelMap("de", "de_rad")], [ChannelMap("alpha", "alpha_rad")], time="time")
    m = Model(**{**m.__dict__, "outputs": m.outputs + (Variable("nz"),)})
    with pytest.raises(DataError, match="output 'nz' has no data mapping"):
        load_record(m, _write(tmp_path / "r.csv", HEADER, _good_rows()))


# ---------------------------------------------------------------- resolution, write_csv

def test_resolution():
    assert resolution([1.0, 1.0, 1.0]) == 0.0
    assert resolution([]) == 0.0
    y = [0.0, 0.5, np.nan, 0.75, 0.75, 2.0]   # finite diffs: 0.5, 0.25, 0, 1.25
    assert resolution(y) == pytest.approx(0.25 / math.sqrt(12), rel=1e-15)


def test_resolution_ignores_rare_rounding_artifacts():
    # quantised at 1.7222e-4 (like HFB-320 q_radps) with one print-rounding step of 1e-8
    rng = np.random.default_rng(0)
    q = 1.7222e-4
    y = np.round(np.cumsum(rng.normal(size=600)) * 3) * q
    y[300] = y[301] + 1e-8 if y[301] != y[299] else y[300]
    assert resolution(y) == pytest.approx(q / math.sqrt(12), rel=1e-6)
    # continuous noisy channel: floor far below the noise std
    z = 0.01 * rng.normal(size=2000)
    assert 0 < resolution(z) < 0.01 / 50


def test_write_csv_roundtrip(tmp_path):
    rng = np.random.default_rng(1)
    cols = {"t_s": np.arange(100) * 0.01, "a": rng.normal(size=100) * 1e-7,
            "b": rng.normal(size=100) * 1e5}
    cols["b"][3] = np.nan
    path = write_csv(tmp_path / "sub" / "x.csv", cols)
    got = np.loadtxt(path, delimiter=",", skiprows=1)
    np.testing.assert_array_equal(got[:, 0], cols["t_s"])
    np.testing.assert_array_equal(got[:, 1], cols["a"])
    np.testing.assert_array_equal(got[:, 2], cols["b"])   # NaN == NaN for assert_array_equal
    assert [p.name for p in path.parent.iterdir()] == ["x.csv"]   # no temp file left
    assert path.read_text().splitlines()[0] == "t_s,a,b"


def test_large_record_is_fast(tmp_path):
    import time
    n = 200_000
    t = np.arange(n) * 0.01
    write_csv(tmp_path / "big.csv", {"time": t, "de_rad": np.sin(t), "alpha_rad": np.cos(t),
                                     "q_radps": t * 0.0})
    t0 = time.perf_counter()
    r = load_record(_m(), tmp_path / "big.csv")
    assert time.perf_counter() - t0 < 5.0
    assert r.n == n


def test_an_expression_written_as_a_column_name_gets_the_expr_form():
    """A new user writes a combination of columns where a column name goes; the hint gives
    the data map's expression form, and only when every name in it is a column."""
    from vsidgen.suggest import column_hint

    header = ["t_s", "da_left_rad", "da_right_rad", "p_radps"]
    got = column_hint("(da_left_rad - da_right_rad)/2", header)
    assert got == 'to combine columns, write {expr: "(da_left_rad - da_right_rad)/2"}'
    assert "expr" not in (column_hint("(da_left - da_right)/2", header) or "")
    assert "expr" not in (column_hint("p_rad", header) or "")


def test_missing_output_column_names_its_channel_and_the_same_quantity_in_another_unit(tmp_path):
    """A data map asking for `ay_g` in a file that has `ay_mps2`: the message names the channel
    (as for inputs) and the hint offers the same quantity in another unit with the full list."""
    import pathlib

    from vsidgen.errors import DataError
    from vsidgen.suggest import column_hint

    hint = column_hint("ay_g", ["t_s", "p_rps", "ay_mps2", "beta_rad"])
    assert hint.startswith("did you mean 'ay_mps2'?") and "unit" in hint
    assert column_hint("ay_g", ["t_s", "p_rps"]) is None
    from vsidgen.model import load_model
    from vsidgen.data.records import load_record

    root = pathlib.Path(__file__).resolve().parents[1]
    spec_dir = tmp_path / "specs"
    spec_dir.mkdir()
    text = (root / "specs" / "attas_sp.yaml").read_text().replace("q: q_radps", "q: q_dps")
    (spec_dir / "sp.yaml").write_text(text)
    m = load_model(spec_dir / "sp.yaml", generated_dir=tmp_path / "gen")
    with pytest.raises(DataError) as ei:
        load_record(m, root / "data" / "attas_sp_synthetic.csv")
    msg = str(ei.value)
    assert "column 'q_dps' (for output `q`) is not in the file" in msg
    assert "did you mean 'q_radps'?" in msg


@pytest.mark.parametrize("cell, expected", [("abc", "non-numeric value 'abc'"),
                                            ("", "input `de` is missing or not finite")])
def test_check_blames_the_cell_not_the_spec_for_a_bad_first_input(tmp_path, capsys, cell,
                                                                  expected):
    """A text or empty input cell in the first row: `check --data` names the column and sample
    0 (it said 'specs/attas_sp.yaml:32:10: non-finite value ... drift of alpha')."""
    import pathlib

    from vsidgen.cli import main

    root = pathlib.Path(__file__).resolve().parents[1]
    csv = tmp_path / "x.csv"
    csv.write_text(f"t_s,de_rad,alpha_rad,q_radps\n0,{cell},0.1,0.2\n0.04,0.1,0.1,0.2\n")
    assert main(["check", str(root / "specs" / "attas_sp.yaml"), "--data", str(csv)]) == 2
    err = capsys.readouterr().err
    assert "column 'de_rad', sample 0" in err and expected in err and "attas_sp.yaml:" not in err


def test_time_column_in_milliseconds(tmp_path):
    """``time: {column: t_ms, unit: ms}`` reads the stamps in ms; without the unit the same
    column is read as seconds and the record is flagged (one sample every 100 s)."""
    rows = _good_rows(dt=100.0)  # 10 Hz written in milliseconds
    path = _write(tmp_path / "r.csv", HEADER, rows)
    ins, outs = [ChannelMap("de", "de_rad")], [ChannelMap("alpha", "alpha_rad"),
                                               ChannelMap("q", "q_radps")]
    r = load_record(_model(ins, outs, time="time", time_scale=1e-3, time_unit="ms"), path)
    assert r.dt == pytest.approx(0.1) and r.t[-1] == pytest.approx(0.1 * (N - 1))
    assert not [w for w in r.warnings if w.code.value == "slow_sampling"]
    plain = load_record(_model(ins, outs, time="time"), path)
    assert plain.dt == pytest.approx(100.0)
    (w,) = [w for w in plain.warnings if w.code.value == "slow_sampling"]
    assert "100 s" in w.message and "unit: ms" in w.hint and w.channel == "time"


def test_time_unit_in_the_spec(tmp_path):
    """The spec's ``data.time`` mapping: its unit is converted by pint, checked for the
    dimension of time, and its keys are checked."""
    from vsidgen.errors import SpecError
    from vsidgen.spec import compile_spec as load_symbolic

    base = (pathlib.Path(__file__).resolve().parents[1] / "specs" / "attas_sp.yaml").read_text()
    def spec(time):
        f = tmp_path / "s.yaml"
        f.write_text(base.replace("time: t_s", f"time: {time}"))
        return f
    sym = load_symbolic(spec("{column: t_ms, unit: ms}"))
    assert sym.data.time == "t_ms" and sym.data.time_scale == pytest.approx(1e-3)
    assert load_symbolic(spec("{column: t, unit: min}")).data.time_scale == pytest.approx(60.0)
    for text, fragment in (("{column: t, unit: m}", "cannot be converted"),
                           ("{unit: ms}", "needs a `column`"),
                           ("{column: t, scale: 2}", "unknown key `scale`")):
        with pytest.raises(SpecError) as info:
            load_symbolic(spec(text))
        assert fragment in str(info.value) and "s.yaml:" in str(info.value)


def test_a_missing_time_column_names_the_time_like_columns(tmp_path):
    """`data: {time: time}` on a file whose time is `t_s`: the hint names `t_s` as the
    time-like column and lists the columns (session 43: no hint at all)."""
    from vsidgen.data.records import time_hint

    hint = time_hint("time", ["t_s", "de_rad", "alpha_rad"])
    assert "time-like columns: t_s" in hint and "columns in the file: t_s, de_rad, alpha_rad" in hint
    assert time_hint("t_s", ["t_S", "x"]).startswith("did you mean")
    assert "time-like" not in time_hint("time", ["de_rad", "alpha_rad"])
