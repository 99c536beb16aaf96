"""A refit whose candidate turns a directly measured state into an indirectly measured one is
also fitted from the estimator's "release" noise start (``fitstate.release_alternative``).

The model is the ATTAS short-period spec; the candidate is written the way a user writes a
vane ahead of the centre of gravity, ``alpha: alpha - XV*q`` (XV = x/V, in seconds). The
record is the shipped synthetic ATTAS record with its α channel rewritten by that kinematics
here (numpy, x/V = 0.3 s), not by the candidate's code. Checked: which states the release
start holds (none in the current model, whose α and q are measured directly; α in the
candidate's), that the alternative is fitted and the better converged ELBO kept, with a
note naming the state, and that a candidate that leaves every direct measurement as it was
costs no fit.
"""

from __future__ import annotations

import pathlib

import numpy as np
import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
SPEC = ROOT / "specs" / "attas_sp.yaml"
DATA = ROOT / "data" / "attas_sp_synthetic.csv"
N = 500
XV_TRUE = 0.3

# one worker runs the whole module: its module-scoped fixture is computed once
pytestmark = pytest.mark.xdist_group("test_release_alternative")


def _vane_record(path: pathlib.Path) -> pathlib.Path:
    a = np.loadtxt(DATA, delimiter=",", skiprows=1)[:N]
    hdr = DATA.read_text().splitlines()[0]
    a[:, 2] = a[:, 2] - XV_TRUE * a[:, 3]        # α read by a vane x ahead: α − (x/V)·q
    np.savetxt(path, a, delimiter=",", header=hdr, comments="", fmt="%.17g")
    return path


def _spec_with(path: pathlib.Path, old: str, new: str, extra_param: str) -> pathlib.Path:
    text = SPEC.read_text()
    assert old in text
    text = text.replace(old, new).replace("parameters:\n", f"parameters:\n  {extra_param}\n")
    path.write_text(text)
    return path


@pytest.fixture(scope="module")
def setting(tmp_path_factory):
    from vsidgen.data import load_record
    from vsidgen.model import load_model

    tmp = tmp_path_factory.mktemp("release_alt")
    gen = tmp / "gen"
    data = _vane_record(tmp / "vane.csv")
    base = load_model(SPEC, generated_dir=gen)
    vane = load_model(_spec_with(tmp / "vane.yaml", "observations:\n  alpha: alpha\n",
                                 "observations:\n  alpha: alpha - XV*q\n", "XV: {unit: s}"),
                      generated_dir=gen)
    square = load_model(_spec_with(tmp / "square.yaml", "q: M0 + MAL*alpha", "q: M0 + MA2*alpha**2 + MAL*alpha",
                                   "MA2: {unit: 1/(rad*s^2)}"), generated_dir=gen)
    bias = load_model(_spec_with(tmp / "bias.yaml", "observations:\n  alpha: alpha\n",
                                 "observations:\n  alpha: alpha + BA\n", "BA: {unit: rad}"),
                      generated_dir=gen)
    return base, vane, square, bias, [load_record(vane, data)]


def test_release_states_follow_the_direct_measurements(setting):
    from vsidgen.discrepancy.fitstate import diag_options
    from vsidgen.estimator import release_states

    base, vane, _, bias, recs = setting
    opts = diag_options(50, noise_start="release")
    assert release_states(base, recs, options=opts) == ()
    assert release_states(vane, recs, options=opts) == ("alpha",)
    assert release_states(bias, recs, options=opts) == ("alpha",)


def test_the_release_start_is_tried_and_the_better_optimum_kept(setting):
    from vsidgen.discrepancy.fitstate import diag_options, refit_converged, release_alternative
    from vsidgen.estimator import fit

    base, vane, square, bias, recs = setting
    warm = fit(vane, recs, options=diag_options(100, noise_start="data"))
    kept, note = release_alternative(vane, recs, base, warm, max_iter=100)
    assert note is not None and note.startswith("alpha no longer measured directly")
    alt = fit(vane, recs, options=diag_options(100, noise_start="release"))
    assert refit_converged(alt) and refit_converged(warm)
    assert kept.elbo == pytest.approx(max(alt.elbo, warm.elbo), rel=1e-12, abs=1e-9)
    assert ("used" if kept is not warm else "not used") in note.rsplit(", ", 1)[-1]
    xv = dict(zip(kept.parameter_names, kept.theta))["XV"]
    se = dict(zip(kept.parameter_names, kept.std_errors))["XV"]
    assert abs(xv - XV_TRUE) < 4 * se + 0.02           # the vane found where it was put
    # candidates that leave α and q measured directly cost no second fit: a drift term, and
    # a channel bias (α + b measures α directly at any b, though the release start, which
    # treats a free offset as unknown, would hold α)
    for m in (square, bias):
        res_b = fit(m, recs, options=diag_options(100, noise_start="data"))
        same, none = release_alternative(m, recs, base, res_b, max_iter=100)
        assert same is res_b and none is None
