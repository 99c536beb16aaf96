"""The public Python API given what a new user passes by mistake (session 44: a first-time
user scripting with the API, and a red team): every call below raised AttributeError or
TypeError from deep inside (pathlib, numpy, the optimizer) or returned NaN without a word.
Each now raises a vsidgen error that says what to pass. No fitting: all are refused before
any computation."""

from __future__ import annotations

import math
import pathlib

import numpy as np
import pytest

import vsidgen
from vsidgen import DataError, SpecError, VsidgenError
from vsidgen.errors import FitError

ROOT = pathlib.Path(__file__).resolve().parents[1]
SPEC = ROOT / "specs" / "attas_sp.yaml"
DATA = ROOT / "data" / "attas_sp_synthetic.csv"


@pytest.fixture(scope="module")
def model():
    return vsidgen.load_model(SPEC)


@pytest.fixture(scope="module")
def record(model):
    return vsidgen.load_record(model, DATA)


def test_fit_is_told_what_a_model_record_and_options_are(model, record):
    for call, said in ((lambda: vsidgen.fit(model, str(DATA)), "must be a vsidgen Record"),
                       (lambda: vsidgen.fit(model, np.zeros((10, 3))), "must be a vsidgen Record"),
                       (lambda: vsidgen.fit(model, None), "must be a vsidgen Record"),
                       (lambda: vsidgen.fit(str(SPEC), record), "must be a vsidgen Model"),
                       (lambda: vsidgen.fit(model, record, options={"max_iter": 3}),
                        "options must be a FitOptions")):
        with pytest.raises(FitError, match=said):
            call()


@pytest.mark.parametrize("kw", [dict(max_iter=-1), dict(max_iter=2.5), dict(max_iter=True),
                                dict(gtol=0.0), dict(gtol=math.nan), dict(substeps=0),
                                dict(substeps=65), dict(integrator="rk5"),
                                dict(input_hold="linear"), dict(time_limit=-1.0)])
def test_fit_options_refuse_values_that_cannot_work(kw):
    """`FitOptions(max_iter=-1)` ended in `TypeError: 'NoneType' object is not iterable`
    inside the optimizer (the CLI refused the same value)."""
    with pytest.raises(FitError, match=f"FitOptions: {next(iter(kw))}"):
        vsidgen.FitOptions(**kw)
    vsidgen.FitOptions(max_iter=1, stall_window=0, substeps=64, integrator="rk4",
                       input_hold="foh", time_limit=1e-3)


def test_load_record_and_compile_spec_say_what_they_read(model, tmp_path):
    with pytest.raises(DataError, match="needs the compiled spec or the model"):
        vsidgen.load_record(str(SPEC), DATA)
    for bad in (None, np.zeros((10, 3)), {"t": [0, 1]}):
        with pytest.raises(DataError, match="reads a file") as err:
            vsidgen.load_record(model, bad)
        assert "Record.from_arrays" in str(err.value)
    with pytest.raises(SpecError, match="reads a spec file"):
        vsidgen.compile_spec(None)
    with pytest.raises(SpecError, match="several lines"):
        vsidgen.compile_spec(SPEC.read_text())


def test_a_record_from_arrays_is_checked_like_a_file(model, record):
    """There was no documented way to build a Record from arrays; `Record.from_arrays`
    applies the file reader's rules and gives the same record as the file."""
    again = vsidgen.Record.from_arrays(model, record.t_raw, record.u, record.y, name="arrays")
    assert again.dt == pytest.approx(record.dt, rel=1e-12)
    np.testing.assert_array_equal(again.u, record.u)
    np.testing.assert_array_equal(again.y, record.y)
    n = record.n
    with pytest.raises(DataError, match="the model needs"):
        vsidgen.Record.from_arrays(model, record.t_raw, record.u[:, :0], record.y)
    u = record.u.copy()
    u[5, 0] = np.nan
    with pytest.raises(DataError) as err:
        vsidgen.Record.from_arrays(model, record.t_raw, u, record.y)
    assert err.value.sample == 5
    t = record.t_raw.copy()
    t[7] = t[6]
    with pytest.raises(DataError, match="not increasing"):
        vsidgen.Record.from_arrays(model, t, record.u, record.y)
    y = record.y.copy()
    y[3, 1] = np.inf
    with pytest.raises(DataError, match="finite"):
        vsidgen.Record.from_arrays(model, record.t_raw, record.u, y)
    assert n == again.n


def test_simulate_and_evaluate_refuse_unusable_arguments(model, record):
    t = np.arange(50) * 0.04
    x0 = np.zeros(model.nx)
    u = np.zeros((50, model.nu))
    base = dict(theta=None, t=t, u=u, x0=x0)
    for kw, said in ((dict(seed=-1), "seed"), (dict(seed=1.5), "seed"),
                     (dict(substeps=0), "substeps"),
                     (dict(theta={model.parameter_names[0]: "abc"}), "is not a number"),
                     (dict(theta={model.parameter_names[0]: math.nan}), "not finite")):
        with pytest.raises(VsidgenError, match=said):
            vsidgen.simulate(model, **{**base, **kw})
    mu = np.zeros((record.n, model.nx))
    G = np.zeros((model.nx, model.nx))
    R = np.eye(model.ny)
    with pytest.raises(VsidgenError, match="not finite"):
        vsidgen.evaluate(model, record, np.full(model.np, np.nan), mu=mu, G=G, R=R)
    with pytest.raises(VsidgenError, match="R holds NaN"):
        vsidgen.evaluate(model, record, np.zeros(model.np), mu=mu, G=G, R=R * np.nan)


def test_run_fit_takes_one_path_and_checks_its_overrides(tmp_path):
    """`run_fit(spec, "est.csv")` split the path into characters ("/: data file is a
    directory"); a dict as `overrides` raised AttributeError ('empty')."""
    from vsidgen.data import as_paths

    assert as_paths(str(DATA)) == [str(DATA)] and as_paths(DATA) == [DATA]
    assert as_paths([DATA, DATA]) == [DATA, DATA] and as_paths(None) == []
    with pytest.raises(VsidgenError, match="overrides must be"):
        vsidgen.run_fit(SPEC, str(DATA), out=tmp_path / "o", overrides={"fix": {"Za": 0.0}})
    assert not (tmp_path / "o").exists()


def test_smooth_reads_theta_as_a_mapping_like_evaluate(model, record):
    """`smooth(model, rec, {"CL_0": 0.45}, noise)` raised `TypeError: float() argument…`
    although evaluate and simulate accept the same mapping (session 44)."""
    names = model.parameter_names
    with pytest.raises(FitError, match="is not a number"):
        vsidgen.smooth(model, record, {names[0]: "x"}, {"G": np.eye(model.nx),
                                                         "R": np.eye(model.ny)})
    with pytest.raises(FitError, match="theta has 1 values"):
        vsidgen.smooth(model, record, [0.0], {"G": np.eye(model.nx), "R": np.eye(model.ny)})
