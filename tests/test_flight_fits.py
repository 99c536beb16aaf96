"""Real flight records fitted from null initial guesses with `vsidgen fit` (issues 3 and 7).

Each case runs the command line once (module-scoped) and checks: convergence on the
gradient criterion; no measurement standard deviation below its channel's floor unless
flagged; smoothed states within a few measurement standard deviations of their direct
measurements; and, for HFB-320, the estimates against the textbook filter-error results
in ../shared/reference/hfb320_reference.json.
"""

import csv
import json
import pathlib

import numpy as np
import pytest

from vsidgen.cli import main

# one worker runs the whole module: its module-scoped fixtures are computed once
pytestmark = pytest.mark.xdist_group("test_flight_fits")

ROOT = pathlib.Path(__file__).resolve().parents[1]
CASES = {
    "hfb320": ("hfb320.yaml", ["hfb320_1_10.csv"], []),
    "attas_sp": ("attas_sp.yaml", ["attas_elv1.csv"], ["attas_elv2.csv"]),
    "totter_sp": ("totter_sp.yaml", ["totter_lon_9752ed20.csv"], []),
    "attas_lat": ("attas_lat.yaml", ["attas_ail1.csv", "attas_rud1.csv"],
                  ["attas_ail2.csv", "attas_rud2.csv"]),
    "tu144_sp": ("tu144_sp.yaml", ["tu144_lon_f20_4d.csv"], ["tu144_lon_f20_4f.csv"]),
    # totter_lat (specs/totter_lat.yaml, f1_017 / f1_014) passes these checks but costs ~140 s
    # (509 iterations over three noise starts), so it is not run here; see docs/real-data.md.
    "totter_sp_020213": ("totter_sp_020213.yaml", ["totter_lon_020213f1_018.csv"],
                         ["totter_lon_020213f1_017.csv"]),
    "totter_sp_lon_data": ("totter_sp_lon_data.yaml", ["totter_lon_data.csv"], []),
}


_RUNS: dict = {}


def _run_case(case, flight_data_dir, tmp_path_factory):
    """Fit one case through the command line (once per test session)."""
    if case in _RUNS:
        return _RUNS[case]
    spec, data, val = CASES[case]
    out = tmp_path_factory.mktemp(case) / "fit"
    argv = ["fit", str(ROOT / "specs" / spec), *[str(flight_data_dir / d) for d in data]]
    if val:
        argv += ["--validate", *[str(flight_data_dir / d) for d in val]]
    argv += ["--out", str(out), "--quiet"]
    rc = main(argv)
    res = json.loads((out / "results.json").read_text())
    _RUNS[case] = (case, rc, res, out)
    return _RUNS[case]


#: variants of an aircraft already fitted above (another Twin Otter record set, the Tu-144):
#: in the slow suite, to keep the default suite near ten minutes on the 2-core CI machine
SLOW_CASES = {"tu144_sp", "totter_sp_020213", "totter_sp_lon_data"}


@pytest.fixture(scope="module", params=[pytest.param(c, marks=pytest.mark.slow) if c in SLOW_CASES else c
                                        for c in sorted(CASES)])
def flight_fit(request, flight_data_dir, tmp_path_factory):
    return _run_case(request.param, flight_data_dir, tmp_path_factory)


def _signals(out, fname):
    with open(out / fname, newline="") as fh:
        rows = list(csv.reader(fh))
    header, body = rows[0], np.array(rows[1:], dtype=float)
    return {name: body[:, i] for i, name in enumerate(header)}


def test_converges_on_gradient_criterion(flight_fit):
    case, rc, res, _ = flight_fit
    assert rc == 0, res["status"]
    assert res["converged"] is True
    assert "gradient" in res["status"]
    codes = {w["code"] for w in res["warnings"]}
    assert "step_size_stop" not in codes and "iteration_limit" not in codes


def test_measurement_noise_not_below_floor_unless_flagged(flight_fit):
    case, rc, res, _ = flight_fit
    floors = res["noise"]["measurement_floor"]
    flagged = " ".join(w["message"] for w in res["warnings"] if w["code"] == "noise_at_floor")
    for name, std in res["noise"]["measurement_std"].items():
        floor = floors.get(name) or 0.0
        assert std >= floor * (1 - 1e-9), (name, std, floor)
        if std < 1.01 * floor:
            assert name in flagged, (name, std, floor, res["warnings"])


def test_smoothed_states_follow_their_measurements(flight_fit):
    case, rc, res, out = flight_fit
    states = {s["name"] for s in res["model"]["states"]}
    meas_std = res["noise"]["measurement_std"]
    for rec, fname in res["signals"].items():
        sig = _signals(out, fname)
        for name in states & set(meas_std):
            resid = sig[f"{name}_mu"] - sig[f"{name}_meas"]
            resid = resid[np.isfinite(resid)]
            rms = float(np.sqrt(np.mean(resid**2)))
            scale = max(meas_std[name], 1e-12)
            assert rms < 5 * scale, (case, rec, name, rms, meas_std[name])
            # no sample-to-sample sign flipping of the smoothed state (issue 7)
            mu = sig[f"{name}_mu"]
            assert np.std(np.diff(mu)) < 3 * np.std(np.diff(sig[f"{name}_meas"])) + 5 * scale


def test_hfb320_against_filter_error_reference(flight_data_dir, tmp_path_factory):
    _, rc, res, _ = _run_case("hfb320", flight_data_dir, tmp_path_factory)
    ref_path = flight_data_dir.parent.parent / "reference" / "hfb320_reference.json"
    ref = json.loads(ref_path.read_text())
    fem = ref["fem"]["parameters"]
    far = {}
    for name, r in fem.items():
        p = res["parameters"][name]
        diff = abs(p["estimate"] - r["value"])
        if not (diff < 3 * p["std_error"] or diff < 0.15 * abs(r["value"])):
            far[name] = (p["estimate"], r["value"], diff / p["std_error"])
    # docs/hfb320.md explains the remaining differences: they follow the noise estimates (see the
    # next test); at most CM0, CMV and CMQ may differ by more than 3 SE and 15 %.
    assert set(far) <= {"CM0", "CMV", "CMQ"}, far


@pytest.mark.slow  # a second HFB-320 fit (~20-30 s); the reference test above stays in the default suite
def test_hfb320_reproduces_filter_error_estimates_given_its_noise(flight_data_dir, tmp_path, tmp_path_factory,
                                                                  monkeypatch):
    """With G and R fixed at the filter-error method's own noise estimates (process-noise
    matrix F, residual covariance R), vsidgen's estimator gives every coefficient within
    3 SE or 15 % of the FEM estimates; and the free fit's ELBO is higher than this one's.

    So the CM0/CMV/CMQ differences of the free fit (test above) come from the noise
    estimates (the channel weighting), not from the estimator or the optimizer: the free
    fit is a better optimum of the same objective (docs/hfb320.md).
    """
    ref = json.loads((flight_data_dir.parent.parent / "reference" / "hfb320_reference.json").read_text())
    fem = ref["fem"]
    lines = [f"extends: {ROOT / 'specs' / 'hfb320.yaml'}", "name: hfb320_fem_noise",
             "noise:", "  process:", "    estimate: false", "    std:"]
    lines += [f"      {s}: {v!r}" for s, v in fem["process_noise_F_diag"].items()]
    lines += ["  measurement:"]
    lines += [f"    {o}: {{estimate: false, std: {float(np.sqrt(v))!r}}}" for o, v in fem["R_diag"].items()]
    monkeypatch.chdir(tmp_path)  # its generated module goes to ./generated, not the repository
    spec = tmp_path / "hfb320_fem_noise.yaml"
    spec.write_text("\n".join(lines) + "\n")
    out = tmp_path / "fit"
    rc = main(["fit", str(spec), str(flight_data_dir / "hfb320_1_10.csv"), "--out", str(out), "--quiet"])
    res = json.loads((out / "results.json").read_text())
    assert rc == 0 and res["converged"], res["status"]
    for o, v in fem["R_diag"].items():  # the noise really was fixed
        assert res["noise"]["measurement_std"][o] == pytest.approx(np.sqrt(v), rel=1e-9)
    far = {}
    for name, r in fem["parameters"].items():
        p = res["parameters"][name]
        diff = abs(p["estimate"] - r["value"])
        if not (diff < 3 * p["std_error"] or diff < 0.15 * abs(r["value"])):
            far[name] = (p["estimate"], r["value"], diff / p["std_error"])
    assert not far, far
    _, _, free, _ = _run_case("hfb320", flight_data_dir, tmp_path_factory)
    assert free["elbo"] > res["elbo"] + 10.0, (free["elbo"], res["elbo"])



@pytest.mark.slow  # a second HFB-320 fit (~20-30 s); the reference test above stays in the default suite
def test_hfb320_auto_keeps_the_best_converged_noise_start(flight_data_dir, tmp_path_factory, tmp_path):
    """`--noise-start auto` runs every start and keeps the best converged optimum.

    On HFB-320 the `data` start converges to a genuine local maximum (positive-definite
    Hessian, Newton decrement below tolerance) that lies tens of nats below the optimum the
    `unit` start reaches; returning the first converged start would report the worse one.
    """
    _, rc, res, _ = _run_case("hfb320", flight_data_dir, tmp_path_factory)
    assert rc == 0 and res["converged"]
    out = tmp_path / "data_start"
    rc1 = main(["fit", str(ROOT / "specs" / "hfb320.yaml"), str(flight_data_dir / "hfb320_1_10.csv"),
                "--out", str(out), "--quiet", "--noise-start", "data"])
    one = json.loads((out / "results.json").read_text())
    assert rc1 == 0 and one["converged"], one["status"]
    assert res["elbo"] >= one["elbo"] - 1e-6
    assert res["elbo"] > one["elbo"] + 10.0, (res["elbo"], one["elbo"])
