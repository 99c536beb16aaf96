"""The fit job end to end: spec + records → estimator → evaluation → results directory.

This is what ``vsidgen fit`` runs; it holds no numerics of its own.
"""

from __future__ import annotations

import dataclasses
import os
import pathlib
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from .. import __version__
from ..codegen import display_path
from ..data import Record, as_paths, load_records, write_csv
from ..errors import VsidgenError, eprint
from ..model import Model, load_model
from ..spec.overrides import Overrides, apply_overrides
from ..atomic import atomic_directory, plan_output_dir, print_recovered, write_text_atomic
from ..limits import check_input_file
from ..report import dumps, finite_or_none, signals_table


@dataclasses.dataclass(frozen=True)
class FitJob:
    """What a finished ``vsidgen fit`` produced."""

    out_dir: pathlib.Path
    results: dict[str, Any]
    fit: Any                 # estimator FitResult (estimation records)
    validation: Any | None   # estimator FitResult of the smoothing-only validation run
    #: how many of ``results["warnings"]`` (the first ones: the spec's) were printed before the
    #: fit, with their file and line; the command line does not print them again
    shown_before: int = 0
    #: the report could not be written (a defect in the report, not in the fit): its error;
    #: the results were written all the same (``vsidgen report DIR`` retries)
    report_error: str | None = None

    def __repr__(self) -> str:
        return f"FitJob(out_dir={str(self.out_dir)!r}, fit={self.fit!r})"


def _latex_equations(model: Model) -> dict[str, dict[str, str]]:
    sym = model.symbolic
    if sym is None:
        return {}
    import sympy

    def tex(e):
        return sympy.latex(e)

    out = {"definitions": {name: tex(expr) for name, expr in sym.definitions},
           "drift": {}, "observations": {}}
    for v, e in zip(sym.states, sym.drift):
        out["drift"][v.name] = tex(e)
    for v, e in zip(sym.outputs, sym.observations):
        out["observations"][v.name] = tex(e)
    return out


def _variables(vs) -> list[dict[str, Any]]:
    return [{"name": v.name, "unit": v.unit, "description": v.description} for v in vs]


def _record_info(rec: Record) -> dict[str, Any]:
    n = len(rec.t)
    return {"name": rec.name, "path": None if rec.path is None else str(rec.path),
            "n_samples": n, "dt": float(rec.dt), "duration_s": float(rec.dt * (n - 1))}


def _evaluate_all(model, records, fit, *, integrator, substeps):
    from ..evaluation import evaluate  # imports jax: not needed to refuse bad arguments

    signals = []
    for rec, sm in zip(records, fit.smoothers):
        signals.append(evaluate(model, rec, fit.theta, mu=np.asarray(sm.mu), G=fit.G, R=fit.R,
                                integrator=integrator, substeps=substeps))
    return signals


def _reason(result) -> str | None:
    """Stable code of the typed stop reason (:class:`vsidgen.estimator.StopReason`)."""
    r = getattr(result, "stop_reason", None)
    return None if r is None else r.value


def _validation_warnings(result, vresult, records, vrecords) -> list[dict]:
    """Warnings about the validation smoothing (θ and noise fixed): not at its optimum, or a
    validation ELBO per sample far below the estimation's
    (:func:`vsidgen.evaluation.validation_elbo_warning`).
    """
    if vresult is None:
        return []
    out = []
    if not vresult.converged:
        r = _reason(vresult)
        out.append({"code": "validation_not_converged", "reliable": True, "stop_reason": r,
                    "message": f"validation smoothing did not converge ({vresult.status}): the validation "
                               f"ELBO {vresult.elbo:.6g} is not its maximum and must not be compared"})
    from ..evaluation import validation_elbo_warning

    w = validation_elbo_warning(result.elbo, sum(len(r.t) for r in records), vresult.elbo,
                                [r.y for r in vrecords])
    if w is not None:
        out.append(w)
    return out


def _same_data(a, b) -> bool:
    """Two records hold the same samples (the same file given twice, or a copy of it)."""
    return (a.n == b.n and a.dt == b.dt and np.array_equal(a.u, b.u)
            and np.array_equal(a.y, b.y, equal_nan=True))


def repeated_record_warnings(records, vrecords) -> list[dict]:
    """Warnings for a validation record that holds the estimation data (validation then says
    nothing about prediction) and for an estimation record given twice (its evidence counted
    twice: standard errors √2 too small)."""
    out = []
    for j, b in enumerate(records):
        for a in records[:j]:
            if _same_data(a, b):
                out.append({"code": "estimation_record_repeated", "reliable": True,
                            "records": [a.name, b.name],
                            "message": f"estimation records '{a.name}' and '{b.name}' hold the same "
                                       "samples: the fit counts them twice (the standard errors are "
                                       "too small by a factor of sqrt(2)); give each record once"})
    for b in vrecords:
        for a in records:
            if _same_data(a, b):
                out.append({"code": "validation_is_estimation_record", "reliable": True,
                            "records": [a.name, b.name],
                            "message": f"validation record '{b.name}' holds the same samples as the "
                                       f"estimation record '{a.name}': its ELBO and fit metrics "
                                       "measure the fit itself, not prediction; validate on "
                                       "another record"})
    return out


def _fit_located(fit, model, records, options):
    """``fit(...)``, turning a start-up failure caused by the data into a located DataError.

    Records have passed :func:`vsidgen.data.load_record` (finite values of magnitude
    at most 1e150); a failure of the linear algebra can then still come from an
    absurd sample: the message names the sample farthest from its channel's bulk
    (:func:`most_extreme_sample`) instead of an internal error.
    """
    from ..data.records import most_extreme_sample, fmt_number
    from ..errors import DataError, FitError

    try:
        return fit(model, records, options=options)
    except (np.linalg.LinAlgError, FloatingPointError) as err:
        where = most_extreme_sample(records)
        if where is None:
            raise FitError(f"the estimator cannot start on these records ({err})") from None
        rec, channel, k, value = where
        raise DataError(f"the estimator cannot start on this record ({type(err).__name__}); "
                        f"the most extreme sample is {channel} = {fmt_number(value)}",
                        path=rec.path, column=channel, sample=k,
                        hint="check that sample (a corrupt value or a unit mistake) and the "
                             "spec's initial values") from None


def run_fit(spec: str | os.PathLike, data: Sequence[str | os.PathLike], *,
            out: str | os.PathLike, validate: Sequence[str | os.PathLike] = (),
            integrator: str | None = None, substeps: int | None = None,
            optimizer: str = "structured-newton", max_iter: int = 200,
            init_states: str = "measured", noise_start: str = "auto",
            generated_dir: str | os.PathLike | None = None,
            progress: Callable | None = None, report: bool = False,
            reference: str | None = None, overwrite: bool = False,
            overrides: Overrides | None = None) -> FitJob:
    """Fit ``spec`` to the ``data`` records and write the results directory ``out``.

    Validation records (``validate``) are smoothed with θ and the noise fixed at
    the estimates (the paper's validation mode) and evaluated separately.
    ``overrides`` (:mod:`vsidgen.spec.overrides`: fixed, freed and initial parameter
    values, output-error method) change the spec's parameter records for this
    fit and are recorded in ``results.json``.

    Every argument is checked before any computation: the records are regular
    files within the size limit, the reference file exists and parses, and
    ``out`` may be written (:func:`vsidgen.atomic.plan_output_dir`: a non-empty
    directory that is not a vsidgen results directory needs ``overwrite``, and
    even then only vsidgen's files in it are replaced).
    """
    data, validate = as_paths(data), as_paths(validate)
    if not data:
        raise VsidgenError("no data records given: `vsidgen fit SPEC DATA [DATA...]`")
    overrides = overrides if overrides is not None else Overrides()
    if not isinstance(overrides, Overrides):
        raise VsidgenError(f"overrides must be a vsidgen.spec.overrides.Overrides, got "
                           f"{type(overrides).__name__}\n  hint: Overrides(fix={{'CL_0': 0.45}})")
    for p in list(data) + list(validate):
        check_input_file(p, what="data file")
    ref_path = None
    if reference is not None:
        from ..report import parse_reference
        ref_path = parse_reference(reference)[2]
    # --init-from's results.json was read already, but a results directory that holds it is
    # not replaced (as --reference's): a command never writes over a file it reads
    plan = plan_output_dir(out, overwrite=overwrite,
                           reads=[spec, *data, *validate, *([ref_path] if ref_path else []),
                                  *([overrides.init_from] if overrides.init_from else [])])
    print_recovered(plan)
    from ..spec import compile_spec
    from ..spec.identifiability import symmetry_warnings
    from ..spec.symbolic import data_map_warnings

    symbolic = compile_spec(spec)  # records are checked before the module is built and JAX loads
    # unknown names and bounds, before any computation; then the parameter combinations the
    # equations cannot separate with the overrides' fixed and free parameters
    # a column read in another unit than its name says: shown before the fit, not only by check
    spec_warnings = data_map_warnings(symbolic) + list(
        symmetry_warnings(apply_overrides(symbolic, overrides)))
    for w in spec_warnings:
        eprint(str(w))
    records, vrecords = load_records(symbolic, data, validate)     # names unique across both
    repeated = repeated_record_warnings(records, vrecords)
    from ..errors import FitError
    from ..estimator import FitOptions, fit, smooth, validate_own_noise

    model = apply_overrides(load_model(spec, generated_dir=generated_dir), overrides)
    integrator = integrator or model.integrator
    substeps = int(substeps or model.substeps)
    t0 = time.perf_counter()
    options = FitOptions(integrator=integrator, substeps=substeps, max_iter=max_iter,
                         init_states=init_states, noise_start=noise_start, optimizer=optimizer,
                         progress=progress)
    result = _fit_located(fit, model, records, options)
    vresult = vown = None
    if vrecords:
        vresult = smooth(model, vrecords, result.theta, result,
                         options=dataclasses.replace(options, progress=None))
        # the same physics at the validation records' own noise (the flight's turbulence and
        # sensor noise): the comparison of models by their physics (estimator.validate_own_noise)
        # and its own trim constants (Z0, biases: properties of the flight condition)
        free_names = {p.name for p in model.parameters if not p.fixed}
        own_free = tuple(n for n in symbolic.trim_parameters() if n in free_names)
        # one fit per validation record: two flights share neither noise nor trim
        try:
            vown = [validate_own_noise(model, [r], result.theta, free=own_free,
                                       options=dataclasses.replace(options, progress=None))
                    for r in vrecords]
        except FitError:
            vown = None
    signals = _evaluate_all(model, records, result, integrator=integrator, substeps=substeps)
    vsignals = (_evaluate_all(model, vrecords, vresult, integrator=integrator, substeps=substeps)
                if vresult is not None else [])
    total_time = time.perf_counter() - t0
    from ..evaluation import unexplained_outputs

    names = model.parameter_names
    params: dict[str, Any] = {}
    for i, p in enumerate(model.parameters):
        params[p.name] = {
            "estimate": float(result.theta[i]),
            "std_error": None if p.fixed else float(result.std_errors[i]),
            "fixed": bool(p.fixed), "unit": p.unit, "lower": p.lower, "upper": p.upper,
            "description": p.description, "reference": None,
        }
    free_names = [n for n, f in zip(names, result.free_mask) if f]
    sym = model.symbolic
    results: dict[str, Any] = {
        "vsidgen_version": __version__,
        "spec": {"name": model.name,
                 "path": None if sym is None else str(sym.source_path),
                 "hash": None if sym is None else sym.source_hash,
                 "module": None if model.module_path is None else display_path(model.module_path)},
        "model": {"states": _variables(model.states), "inputs": _variables(model.inputs),
                  "outputs": _variables(model.outputs),
                  "equations_latex": _latex_equations(model)},
        "method": {"estimator": "variational (ELBO)", "integrator": integrator,
                   "substeps": substeps, "inputs": getattr(model, "input_hold", "zoh"),
                   "optimizer": optimizer, "noise_start": noise_start,
                   "method": overrides.method.value},
        "overrides": overrides.to_json(),
        "records": {"estimation": [_record_info(r) for r in records],
                    "validation": [_record_info(r) for r in vrecords]},
        "parameters": params,
        "correlation": {"names": free_names, "matrix": np.asarray(result.correlation)},
        "noise": {"measurement_std": dict(result.measurement_std),
                  "process_std": dict(result.process_std),
                  "measurement_floor": dict(getattr(result, "measurement_floor", {}) or {}),
                  "G": np.asarray(result.G), "R": np.asarray(result.R)},
        "elbo": float(result.elbo), "converged": bool(result.converged), "status": result.status,
        "stop_reason": _reason(result), "newton_decrement": finite_or_none(getattr(result, "newton_decrement", None)),
        "deterministic_states": list(getattr(result, "deterministic_states", ())),
        "deterministic_limit": getattr(result, "deterministic_limit", None),
        "iterations": int(result.iterations), "wall_time_s": float(result.wall_time_s),
        "total_time_s": total_time,
        "metrics": {"estimation": {s.record: s.metrics for s in signals},
                    "validation": {s.record: s.metrics for s in vsignals}},
        "validation": ({"elbo": None} if vresult is None else
                       {"elbo": float(vresult.elbo), "converged": bool(vresult.converged),
                        "elbo_own_noise": None if vown is None else float(sum(v.elbo for v in vown)),
                        "own_noise_converged": None if vown is None
                        else all(bool(v.converged) for v in vown),
                        "own_noise_free": list(own_free),
                        "stop_reason": _reason(vresult), "status": vresult.status,
                        "iterations": int(vresult.iterations),
                        "deterministic_limit": getattr(vresult, "deterministic_limit", None),
                        "newton_decrement": finite_or_none(getattr(vresult, "newton_decrement", None))}),
        "warnings": [{"code": w.code, "message": w.message, "hint": w.hint} for w in spec_warnings]
        + [w.to_json() for r in records + vrecords
           for w in r.warnings] + list(result.warnings)
        + repeated + _validation_warnings(result, vresult, records, vrecords) + [
            {"code": "evaluation", "message": f"{s.record}: {w}"}
            for s in signals + vsignals for w in getattr(s, "warnings", ())]
        + [w for s in signals for w in unexplained_outputs(s, kind="estimation")]
        + [w for s in vsignals for w in unexplained_outputs(s, kind="validation")],
        "std_errors_reliable": bool(getattr(result, "std_errors_reliable", True)),
        "std_error_issues": [f.to_json() for f in getattr(result, "std_error_flags", ())],
        "signals": {s.record: f"signals_{s.record}.csv" for s in signals + vsignals},
    }

    with atomic_directory(out, plan=plan, command="fit") as tmp:
        for s, sm in list(zip(signals, result.smoothers)) + list(
                zip(vsignals, vresult.smoothers if vresult is not None else [])):
            mu_std = np.sqrt(np.diag(np.asarray(sm.cov_marg)))
            write_csv(tmp / f"signals_{s.record}.csv",
                      signals_table(s, model.state_names, model.output_names, mu_std))
        write_text_atomic(tmp / "results.json", dumps(results))
        report_error = None
        if report:
            from ..report import write_report
            try:
                write_report(tmp, reference=reference, display_dir=out)
            except (KeyboardInterrupt, VsidgenError):
                raise
            except Exception as err:   # noqa: BLE001 — a report defect must not lose the fit
                if os.environ.get("VSIDGEN_DEBUG"):
                    raise
                first = (str(err).strip().splitlines() or [""])[0][:300]
                report_error = f"{type(err).__name__}: {first}"
                for leftover in tmp.glob("report*"):
                    if leftover.is_file():
                        leftover.unlink()
    return FitJob(out_dir=pathlib.Path(out), results=results, fit=result, validation=vresult,
                  shown_before=len(spec_warnings), report_error=report_error)
