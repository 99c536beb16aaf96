"""``vsidgen fleet``: one spec fitted to many records, each on its own, in parallel.

Every record is an independent ``vsidgen fit`` (:func:`vsidgen.fitjob.run.run_fit`) writing
its own results directory ``DIR/<record>/``; the fits run on the task engine
(:mod:`vsidgen.engine`: serially, on a local ``dask.distributed`` cluster — one worker per two
cores — or on an existing cluster). ``DIR/fleet.json`` lists every record with a typed
:class:`FleetStatus` and is written atomically after each fit, so an interrupted fleet
keeps the fits that finished. A record with bad data does not stop the others.
"""

from __future__ import annotations

import dataclasses
import enum
import pathlib
import re
import time
from collections.abc import Callable, Sequence

from ..errors import VsidgenError, eprint


class FleetStatus(enum.Enum):
    """Outcome of one record's fit."""

    CONVERGED = "converged"
    NOT_CONVERGED = "not_converged"    # results written; the optimizer stopped early
    BAD_INPUT = "bad_input"            # spec/data error for this record (message kept)
    FAILED = "failed"                  # unexpected error in the fit
    LOST = "lost"                      # its worker process died, also on the retry
    CANCELLED = "cancelled"            # not run (interrupted)


@dataclasses.dataclass(frozen=True)
class FleetEntry:
    """One record of a fleet: where its results are and how its fit ended."""

    record: str
    out_dir: pathlib.Path
    status: FleetStatus
    elbo: float | None = None
    iterations: int | None = None
    wall_s: float = 0.0
    error: str | None = None

    def to_json(self) -> dict:
        return {"record": self.record, "results": self.out_dir.as_posix(),
                "status": self.status.value, "elbo": self.elbo, "iterations": self.iterations,
                "wall_s": round(self.wall_s, 2), "error": self.error}


@dataclasses.dataclass(frozen=True)
class FleetResult:
    out_dir: pathlib.Path
    entries: tuple[FleetEntry, ...]
    engine: str
    wall_s: float


def _dir_names(paths: Sequence[str]) -> list[str]:
    """A results-directory name per record: the file stem, made unique (``_2``, ``_3``).

    Leading dots are dropped (``.``, ``..`` and hidden names: a record ``..csv`` was the fleet
    directory itself) and the fleet's own names (``fleet.json``, the manifest) are renamed
    (a record ``fleet.json.csv`` was refused with an ``--out`` the user never gave: red team,
    session 47)."""
    from ..atomic import MANIFEST

    reserved = {"fleet.json", MANIFEST}
    seen: dict[str, int] = {}
    out = []
    for p in paths:
        stem = re.sub(r"[^A-Za-z0-9_.-]+", "_", pathlib.Path(p).stem).lstrip(".") or "record"
        if stem in reserved:
            stem = f"{stem}_record"
        name = stem
        while name in seen:              # `a`, `a` and `a_2` give a, a_2, a_2_2
            seen[stem] += 1
            name = f"{stem}_{seen[stem]}"
        seen.setdefault(stem, 1)
        seen[name] = seen.get(name, 1)
        out.append(name)
    return out


def _fit_one(spec: str, data: str, out: str, generated_dir: str | None, kwargs: dict) -> dict:
    """One record's fit (runs on an engine worker); a small summary, never the arrays."""
    from .run import run_fit

    try:
        job = run_fit(spec, [data], out=out, generated_dir=generated_dir, **kwargs)
    except VsidgenError as err:
        return {"status": FleetStatus.BAD_INPUT.value, "error": str(err).strip().splitlines()[0]}
    r = job.results
    return {"status": (FleetStatus.CONVERGED if r["converged"] else FleetStatus.NOT_CONVERGED).value,
            "elbo": float(r["elbo"]), "iterations": int(r["iterations"])}


def run_fleet(spec, data: Sequence[str], *, out, workers: int | None = 1,
              scheduler: str | None = None, generated_dir=None, max_iter: int = 200,
              integrator: str | None = None, substeps: int | None = None,
              noise_start: str = "auto", init_states: str = "measured",
              overrides=None, report: bool = False, overwrite: bool = False,
              progress: Callable[[str], None] | None = None) -> FleetResult:
    """Fit ``spec`` to every record of ``data`` separately; results in ``out/<record>/``.

    ``noise_start``, ``init_states`` and ``overrides`` (:class:`vsidgen.Overrides`: fixed,
    freed and initial parameter values, output-error method) are those of
    :func:`vsidgen.run_fit` and apply to every record's fit; the overrides are checked
    against the spec here, before any fit starts, and recorded in each ``results.json``.

    ``workers`` worker processes of a local dask cluster (1: serially in this process; None:
    one per two local cores) or the cluster at ``scheduler``. The spec is compiled once here
    first (a bad spec is an error before any fit starts). ``out`` follows the rules of every
    results directory (:mod:`vsidgen.atomic`): a folder holding files vsidgen did not write
    is refused unless ``overwrite`` (then only vsidgen's files are replaced), and the
    files the command reads are never written over.
    """
    from ..atomic import plan_output_dir, print_recovered, results_in_place
    from ..engine import Engine
    from ..model import load_model
    from ..model.dynamics import check_settings

    from ..data import as_paths

    data = as_paths(data)
    if not data:
        raise VsidgenError("no data records given: `vsidgen fleet SPEC DATA [DATA...] --out DIR`")
    if max_iter < 1:
        raise VsidgenError(f"--max-iter must be >= 1, got {max_iter}")
    if substeps is not None:
        check_settings(integrator or "euler", substeps)
    from ..spec.overrides import Overrides, apply_overrides

    overrides = overrides if overrides is not None else Overrides()
    if not isinstance(overrides, Overrides):
        raise VsidgenError(f"overrides must be a vsidgen.Overrides, got {type(overrides).__name__}\n"
                           "  hint: Overrides(fix={'CL_0': 0.45})")
    engine = Engine(workers=workers, scheduler=scheduler)
    plan = plan_output_dir(out, overwrite=overwrite,
                           reads=[spec, *data, *([overrides.init_from] if overrides.init_from else [])])
    print_recovered(plan)
    apply_overrides(load_model(spec, generated_dir=generated_dir), overrides)   # unknown names: now
    names = _dir_names(data)
    # the cluster is reached before the previous results are cleared (red team, session 47)
    with engine, results_in_place(plan, command="fleet", owns=(*names, "fleet.json")) as out_dir:
        return _run_fleet(spec, data, names, out_dir, engine, generated_dir=generated_dir,
                          kwargs={"max_iter": max_iter, "integrator": integrator, "substeps": substeps,
                                  "noise_start": noise_start, "init_states": init_states,
                                  "overrides": overrides, "report": report},
                          progress=progress)


def _run_fleet(spec, data, names, out, engine, *, generated_dir, kwargs, progress) -> FleetResult:
    from ..atomic import write_text_atomic
    from ..engine import TaskStatus
    from ..model import default_generated_dir
    from ..report import dumps

    gen = pathlib.Path(generated_dir) if generated_dir is not None else default_generated_dir(spec)
    out = pathlib.Path(out)
    tasks = [(n, (str(spec), str(d), str(out / n), str(gen.resolve()), kwargs))
             for n, d in zip(names, data)]
    done: dict[str, FleetEntry] = {}
    t0 = time.perf_counter()

    def entry(oc) -> FleetEntry:
        if oc.status is TaskStatus.DONE:
            v = oc.value
            return FleetEntry(oc.key, out / oc.key, FleetStatus(v["status"]), v.get("elbo"),
                              v.get("iterations"), oc.wall_s, v.get("error"))
        st = {TaskStatus.FAILED: FleetStatus.FAILED, TaskStatus.LOST: FleetStatus.LOST,
              TaskStatus.CANCELLED: FleetStatus.CANCELLED}[oc.status]
        return FleetEntry(oc.key, out / oc.key, st, wall_s=oc.wall_s, error=oc.error)

    def write(final: bool):
        rows = [done[n].to_json() if n in done else
                {"record": n, "results": (out / n).as_posix(),
                 "status": "cancelled" if final else "pending"} for n in names]
        write_text_atomic(out / "fleet.json", dumps({
            "spec": str(spec), "engine": engine.describe(), "records": rows,
            "complete": final, "wall_s": time.perf_counter() - t0}))

    def on_done(oc):
        e = entry(oc)
        done[e.record] = e
        if progress is not None:
            what = e.status.value + (f", ELBO {e.elbo:.6g}, {e.iterations} iterations"
                                     if e.elbo is not None else f": {e.error}")
            progress(f"[{len(done)}/{len(names)}] {e.record}: {what} ({e.wall_s:.0f} s)")
        write(False)

    write(False)
    if progress is not None:
        progress(f"fitting {len(names)} records ({engine.describe()})")
    try:
        with engine:
            engine.run(_fit_one, tasks, on_done=on_done)
    finally:
        write(True)
    return FleetResult(out, tuple(done.get(n) or FleetEntry(n, out / n, FleetStatus.CANCELLED)
                                  for n in names), engine.describe(), time.perf_counter() - t0)


def add_fleet_parser(subparsers):
    """Register ``vsidgen fleet`` (sets ``handler``)."""
    p = subparsers.add_parser(
        "fleet", help="fit one spec to many records, each separately, in parallel",
        description="Fit SPEC to each record on its own (one `vsidgen fit` per record) on a "
                    "local dask cluster (--workers, default one per two cores) or an existing one "
                    "(--scheduler). Writes DIR/<record>/ (results of each fit) and "
                    "DIR/fleet.json (status of every record, updated after each fit). Exit "
                    "status 0 when every fit converged, 1 when some did not or were lost, "
                    "2 when a record had bad input (the others are still fitted).")
    p.add_argument("spec", help="model spec (YAML)")
    p.add_argument("data", nargs="+", help="records (CSV or MATLAB .mat), one fit each")
    p.add_argument("-o", "--out", required=True, help="output directory (one results folder per record)")
    from ..engine import add_engine_arguments

    add_engine_arguments(p, what="record fits")
    p.add_argument("--integrator", choices=("euler", "rk4"), default=None)
    p.add_argument("--substeps", type=int, default=None)
    p.add_argument("--max-iter", type=int, default=200,
                   help="optimizer iterations per noise start (each start is a fit of its own; a stage of the deterministic limit of states without process noise gets max(30, MAX_ITER/4)) (default 200)")
    p.add_argument("--init-states", choices=("measured", "zero"), default="measured",
                   help="initial state-path mean: measured states where possible, or zero")
    p.add_argument("--noise-start", choices=("auto", "release", "data", "data-meas", "unit"),
                   default="auto", help="starting noise levels, as for `vsidgen fit` (default auto)")
    p.add_argument("--report", action="store_true", help="also write a report per record")
    from ..spec.overrides import add_override_arguments

    add_override_arguments(p)
    p.add_argument("--quiet", action="store_true", help="no progress messages")
    p.add_argument("--overwrite", action="store_true",
                   help="write into a non-empty DIR that is not a vsidgen results directory "
                        "(only vsidgen's files are replaced; other files are kept)")
    p.set_defaults(handler=fleet_command)
    return p


def fleet_command(args) -> int:
    from ..compilecache import enable_compilation_cache
    from ..engine import terminate_as_interrupt

    from ..spec.overrides import overrides_of

    enable_compilation_cache()
    overrides = overrides_of(args)
    progress = None if args.quiet else (lambda m: eprint(m, flush=True))
    with terminate_as_interrupt():
        res = run_fleet(args.spec, args.data, out=args.out, workers=args.workers,
                        scheduler=args.scheduler, max_iter=args.max_iter,
                        integrator=args.integrator, substeps=args.substeps,
                        noise_start=args.noise_start, init_states=args.init_states,
                        overrides=overrides, report=args.report,
                        overwrite=args.overwrite, progress=progress)
    for e in res.entries:
        extra = f"ELBO {e.elbo:.6g}" if e.elbo is not None else (e.error or "")
        print(f"{e.record}: {e.status.value} {extra} -> {e.out_dir}")   # stdout is escaped
    counts = {s: sum(e.status is s for e in res.entries) for s in FleetStatus}
    print(f"{len(res.entries)} records, {counts[FleetStatus.CONVERGED]} converged, "
          f"{res.wall_s:.0f} s ({res.engine}); summary in {res.out_dir / 'fleet.json'}")
    if counts[FleetStatus.BAD_INPUT]:
        return 2
    return 0 if counts[FleetStatus.CONVERGED] == len(res.entries) else 1
