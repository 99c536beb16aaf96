"""Model zoo: fits from null guesses on records of an independent simulator (benchmarks/zoo).

The records come from hand-written numpy dynamics (benchmarks/zoo/models.py), not from
vsidgen's simulator or generated code; the truth is the simulator's parameter set. Checks:
convergence by the estimator's own test, recovery within 3 standard errors, a converged
validation smoothing whose ELBO per sample is close to the estimation ELBO per sample
(same aircraft, same kind of record).
"""

from __future__ import annotations

import pathlib
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import zoo  # noqa: E402  (benchmarks/zoo.py)


def _check(r):
    assert "error" not in r, r.get("error")
    assert r["converged"], r["status"]
    assert r["within3"] == 1.0, r["z"]
    assert r["val_converged"]
    assert abs(r["val_elbo_per_sample"] - r["elbo_per_sample"]) < 0.5, r


def test_zoo_short_period_in_turbulence_from_null_guesses():
    _check(zoo.run_one("sp_pn", 1))


@pytest.mark.slow
@pytest.mark.parametrize("name", ["sp_oe", "lat4_nobeta"])
@pytest.mark.xfail(strict=True, reason="measured: sp_oe (no process noise: quasi-deterministic states, "
                                       "docs/estimator.md) and lat4_nobeta (indefinite Hessian) do not "
                                       "converge from null guesses in 3 x 200 iterations")
def test_zoo_models_not_yet_fitted_from_null_guesses(name):
    _check(zoo.run_one(name, 1))
