"""Check a speed (phugoid) finding of `vsidgen diagnose` against the measured airspeed.

The speed candidate (`speed_dynamics`) reconstructs the airspeed perturbation ΔV from the α,
q (and az) channels alone, through gravity along the flight path; the record's own airspeed
column was not used. This script refits the spec diagnose wrote (warm: its initial values are
the diagnose estimates) and prints the reconstructed ΔV against the measured airspeed minus
its mean: correlation, the regression slope and the RMS of both (a slope near 1 and a high
correlation mean the new state is the speed motion, not a generic slow mode).

    python benchmarks/real_records/phugoid_check.py SPEC RECORD.csv [--column v_mps]
"""

from __future__ import annotations

import argparse
import sys

import numpy as np


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("spec")
    ap.add_argument("record")
    ap.add_argument("--column", default="v_mps")
    ap.add_argument("--state", default="D_dV")
    ap.add_argument("--max-iter", type=int, default=100)
    a = ap.parse_args(argv)

    from vsidgen.data import _read_block, _read_header, load_record
    from vsidgen.discrepancy.refit import REFIT_DETERMINISTIC_STD
    from vsidgen.estimator import FitOptions, fit
    from vsidgen.model import load_model

    m = load_model(a.spec)
    rec = load_record(m, a.record)
    res = fit(m, [rec], options=FitOptions(max_iter=a.max_iter, deterministic="quasi",
                                           deterministic_std=REFIT_DETERMINISTIC_STD))
    j = list(m.state_names).index(a.state)
    dv = np.asarray(res.smoothers[0].mu, float)[:, j]
    header = _read_header(rec.path)
    v = _read_block(rec.path, header, [header.index(a.column)])[:, 0]
    n = min(len(v), len(dv))
    dv, v = dv[:n] - dv[:n].mean(), v[:n] - v[:n].mean()
    r = float(np.corrcoef(dv, v)[0, 1])
    slope = float(np.dot(dv, v) / np.dot(dv, dv))
    print(f"fit: ELBO {res.elbo:.1f}, {res.status}")
    names = list(m.parameter_names)
    for p in ("D_XV", "D_Xalpha", "D_ZV", "D_MV"):
        if p in names:
            i = names.index(p)
            print(f"  {p} = {res.theta[i]:.5g} ± {res.std_errors[i]:.2g}")
    print(f"reconstructed {a.state} vs measured {a.column} − mean: correlation {r:.3f}, "
          f"slope (measured on reconstructed) {slope:.3f}, RMS {np.std(dv):.3f} vs "
          f"{np.std(v):.3f} m/s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
