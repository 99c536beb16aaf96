"""State-adding refits: one compilation per candidate against one per model family.

Fits the base model (diagnose's base fit, ``search.fit_spec``), proposes the catalogue's
candidates of the given effects that add states, takes the first ``--members`` of the most
common shape (:func:`vsidgen.discrepancy.family.family_shape`) and refits them, in one
process, (a) each with its own compiled model (``search._refit_task``, the path before model
families) and (b) as one :class:`~vsidgen.estimator.ModelFamily`
(``search._family_task``, what a serial diagnose round does now), in the order given by
``--order``. Prints per candidate the wall and compile seconds of each path and the two
statistics (2ΔELBO against the nested reference), then the totals and their ratio. No
persistent compilation cache (each path compiles what it needs; fresh generated code per
path).

    python benchmarks/bench_family.py                    # Twin Otter short period, 3 modes
    python benchmarks/bench_family.py --spec specs/attas_sp.yaml --data WORK/sp_phugoid_5_s0.csv
"""

from __future__ import annotations

import argparse
import collections
import os
import pathlib
import sys
import tempfile
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
FLIGHT = pathlib.Path(os.environ.get("VSIDGEN_FLIGHT_DATA", ROOT.parent / "shared" / "data" / "flight"))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--spec", default=str(ROOT / "specs" / "totter_sp.yaml"))
    ap.add_argument("--data", default=str(FLIGHT / "totter_lon_9752ed20.csv"))
    ap.add_argument("--effects", nargs="+", default=["missing_dynamics"])
    ap.add_argument("--members", type=int, default=3)
    ap.add_argument("--order", choices=("own-first", "family-first"), default="own-first")
    ap.add_argument("--max-iter", type=int, default=200)
    a = ap.parse_args(argv)

    from vsidgen.discrepancy import propose, search
    from vsidgen.discrepancy.family import family_shape
    from vsidgen.discrepancy.refit import compile_seconds

    tmp = pathlib.Path(tempfile.mkdtemp(prefix="bench_family_"))
    print(f"load average {os.getloadavg()[0]:.2f}; work in {tmp}")
    t0 = time.perf_counter()
    st = search.fit_spec(pathlib.Path(a.spec), [pathlib.Path(a.data)],
                         generated_dir=tmp / "gen_base", max_iter=a.max_iter)
    info = search.model_info_of(st)
    print(f"base fit: ELBO {st.elbo:.6g} ({'converged' if st.fit.converged else 'NOT converged'}), "
          f"{time.perf_counter() - t0:.1f} s")
    cands = [c for c in propose(info) if c.effect in a.effects and family_shape(c) is not None]
    if not cands:
        print("no candidate that adds states among", a.effects)
        return 1
    shape = collections.Counter(family_shape(c) for c in cands).most_common(1)[0][0]
    members = [c for c in cands if family_shape(c) == shape][:a.members]
    print(f"shape {shape} (states, parameters, free): {', '.join(c.key for c in members)}")

    def own():
        rows = []
        for i, c in enumerate(members):
            c0, t = compile_seconds(), time.perf_counter()
            ro, _ = search._refit_task(c, st, info, tmp / f"own_{i}.yaml", f"bf_own_{i}",
                                       tmp / "gen_own", a.max_iter)
            rows.append((time.perf_counter() - t, compile_seconds() - c0,
                         2.0 * (ro.state.elbo - ro.elbo_ref), ro.state.fit.converged))
        return rows

    def family():
        c0, t = compile_seconds(), time.perf_counter()
        out = search._family_task([(c, tmp / f"fam_{i}.yaml", f"bf_fam_{i}")
                                   for i, c in enumerate(members)], st, info, tmp / "gen_fam",
                                  a.max_iter)
        rows = []
        for o in out:
            if o.value is None:
                rows.append((o.wall_s, float("nan"), float("nan"), False))
                continue
            ro, _ = o.value
            rows.append((o.wall_s, ro.compile_s, 2.0 * (ro.state.elbo - ro.elbo_ref),
                         ro.state.fit.converged))
        print(f"  (family task: {time.perf_counter() - t:.1f} s, compile {compile_seconds() - c0:.1f} s)")
        return rows

    paths = [("own", own), ("family", family)]
    if a.order == "family-first":
        paths.reverse()
    res = {}
    for name, fn in paths:
        t = time.perf_counter()
        res[name] = fn()
        print(f"{name}: {time.perf_counter() - t:.1f} s (load {os.getloadavg()[0]:.2f})")
    print()
    print("| candidate | own wall s (compile) | family wall s (compile) | 2ΔELBO own | 2ΔELBO family |")
    print("|---|---|---|---|---|")
    for c, r_o, r_f in zip(members, res["own"], res["family"]):
        print(f"| {c.key} | {r_o[0]:.1f} ({r_o[1]:.1f}) | {r_f[0]:.1f} ({r_f[1]:.1f}) | "
              f"{r_o[2]:.6f}{'' if r_o[3] else ' (nc)'} | {r_f[2]:.6f}{'' if r_f[3] else ' (nc)'} |")
    wo, wf = sum(r[0] for r in res["own"]), sum(r[0] for r in res["family"])
    co, cf = sum(r[1] for r in res["own"]), sum(r[1] for r in res["family"])
    dmax = max(abs(x[2] - y[2]) for x, y in zip(res["own"], res["family"]))
    print(f"| **total** | {wo:.1f} ({co:.1f}) | {wf:.1f} ({cf:.1f}) | | |")
    print(f"\nown / family wall: {wo / wf:.2f}x; compile {co:.1f} s -> {cf:.1f} s; "
          f"largest |difference of 2ΔELBO| {dmax:.2e}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
