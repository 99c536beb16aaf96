"""vsidgen: aircraft system identification from YAML model specs.

Pipeline (one subpackage per stage, data flowing one way; docs/architecture.md)::

    compile_spec(path) -> SymbolicModel          # spec -> validated sympy model
    build(spec_paths) -> [BuildResult]           # generated/<name>.py (JAX, symbolic Jacobians)
    load_model(path) -> Model                    # generated functions + metadata
    load_record(model, csv) -> Record            # flight record through the spec's data map
    Record.from_arrays(model, t, u, y)           # a record from arrays in the spec's units
    fit(model, records, *, options) -> FitResult # variational ML (ELBO), process + measurement noise
    smooth(model, records, theta, noise)         # validation: θ fixed, smoothing only
    validate_own_noise(model, records, theta)    # validation: θ fixed, the records' own noise
    evaluate(model, record, theta, *, mu, G, R) -> Signals   # the four evaluation signals
    run_fit(spec, data, *, out, ...) -> FitJob   # the whole `vsidgen fit` job
    Overrides(fix=..., free=..., init=...)       # --fix/--free/--init of run_fit
    write_report(results_dir) -> Path            # self-contained HTML report
    run_diagnose(spec, data, *, out, ...)        # discrepancy discovery
    simulate(model, *, theta, t, u, x0, ...)     # synthetic records

Names are imported lazily, so ``import vsidgen`` stays cheap (no jax until needed).
"""

__version__ = "0.2.0"

from .errors import DataError, SpecError, SpecWarning, VsidgenError  # noqa: E402

_LAZY = {
    "compile_spec": "spec", "SymbolicModel": "spec",
    "build": "codegen",
    "Model": "model", "load_model": "model",
    "Record": "data", "load_record": "data",
    "fit": "estimator", "smooth": "estimator", "validate_own_noise": "estimator",
    "FitOptions": "estimator", "FitResult": "estimator", "Overrides": "spec.overrides",
    "evaluate": "evaluation", "Signals": "evaluation",
    "simulate": "data.simulate",
    "run_fit": "fitjob",
    "write_report": "report",
    "run_diagnose": "discrepancy",
}

__all__ = ["DataError", "SpecError", "SpecWarning", "VsidgenError", "__version__", *_LAZY]


def __getattr__(name):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
    raise AttributeError(f"module 'vsidgen' has no attribute {name!r}")
