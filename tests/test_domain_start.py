"""A model defined near the data but not ±2 rad away from it starts (red team, session 47):
``MAL*sqrt(alpha + 1)`` made every noise start fail at the initial point, Σ = I putting the
sigma points of α at ±2 rad, with a message about "very large initial values"."""

import math
import pathlib

import numpy as np
import pytest

from vsidgen import load_model
from vsidgen.data import load_record
from vsidgen.errors import FitError
from vsidgen.estimator import FitOptions, fit
from vsidgen.estimator.fit import NARROWER_START, _lm_init
from vsidgen.estimator.problem import Problem

ROOT = pathlib.Path(__file__).resolve().parents[1]
DATA = ROOT / "data" / "attas_sp_synthetic.csv"


def _model(tmp_path, term):
    text = (ROOT / "specs" / "attas_sp.yaml").read_text()
    assert "MAL*alpha + MQ*q" in text
    spec = tmp_path / "dom.yaml"
    spec.write_text(text.replace("name: attas_sp", "name: dom_sp")
                    .replace("MAL*alpha + MQ*q", f"MAL*{term} + MQ*q"))
    return load_model(spec, generated_dir=tmp_path / "gen")


def test_sqrt_of_a_state_next_to_its_domain_starts_and_fits(tmp_path):
    m = _model(tmp_path, "sqrt(alpha + 1)")
    rec = load_record(m, DATA)
    P = Problem(m, [rec])
    opts = FitOptions(max_iter=3, noise_start="data")
    s0, recs0 = P.initial(opts, "data")
    assert not math.isfinite(P.value(s0, recs0))        # the plain start: the defect
    s, recs, *_ = _lm_init(P, opts, "data", None)
    f = P.value(s, recs)
    assert math.isfinite(f)
    shrink = np.exp(recs[0][1][:m.nx] - recs0[0][1][:m.nx])
    assert np.allclose(shrink, shrink[0]) and any(np.isclose(shrink[0], k) for k in NARROWER_START)
    res = fit(m, [rec], options=FitOptions(max_iter=30, noise_start="data"))
    assert math.isfinite(res.elbo)


def test_a_model_undefined_at_the_data_still_names_the_equation(tmp_path):
    m = _model(tmp_path, "sqrt(alpha - 1)")                 # NaN at every state mean
    rec = load_record(m, DATA)
    with pytest.raises(FitError, match=r"drift of `q` at sample 0"):
        fit(m, [rec], options=FitOptions(max_iter=3, noise_start="data"))
