"""Runtime model: generated JAX functions bound to the spec's metadata."""

from __future__ import annotations

import dataclasses
import pathlib
import types
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from ..errors import VsidgenError
from ..metadata import (DataSpec, MeasurementNoiseSpec, Parameter, ProcessNoiseSpec, Variable,
                       VariableNames)


@dataclasses.dataclass(frozen=True)
class Jacobians:
    """The generated first derivatives of the drift ``f`` and the output ``h``.

    Each takes one sample ``(x, u, p)`` like ``f`` and ``h`` and returns a matrix:
    ``drift_x = ∂f/∂x`` (nx, nx), ``drift_u = ∂f/∂u`` (nx, nu), ``drift_p = ∂f/∂p`` (nx, np),
    ``output_x = ∂h/∂x`` (ny, nx), ``output_u = ∂h/∂u`` (ny, nu), ``output_p = ∂h/∂p`` (ny, np),
    derived symbolically by :mod:`vsidgen.codegen` (definitions expanded).
    """

    drift_x: Callable
    drift_u: Callable
    drift_p: Callable
    output_x: Callable
    output_u: Callable
    output_p: Callable

    @classmethod
    def of_module(cls, module: types.ModuleType) -> "Jacobians":
        """The six ``drift_jac_*`` / ``output_jac_*`` functions of a generated module."""
        return cls(drift_x=module.drift_jac_x, drift_u=module.drift_jac_u, drift_p=module.drift_jac_p,
                   output_x=module.output_jac_x, output_u=module.output_jac_u,
                   output_p=module.output_jac_p)


@dataclasses.dataclass(frozen=True)
class Model(VariableNames):
    """Everything the estimator needs to know about a model.

    ``drift(x, u, p)`` and ``output(x, u, p)`` take one sample (1-D arrays;
    ``p`` holds all parameters in ``parameters`` order, fixed ones included)
    and return jnp arrays of shape (nx,) and (ny,).

    ``jacobians`` holds their generated first derivatives (:class:`Jacobians`) when the
    model comes from a spec; :meth:`drift_jacobian` and :meth:`output_jacobian` are what
    every first derivative of ``f`` or ``h`` at run time goes through (forward-mode
    autodiff of ``drift``/``output`` for a model built from bare functions).
    """

    name: str
    drift: Callable
    output: Callable
    states: tuple[Variable, ...]
    inputs: tuple[Variable, ...]
    outputs: tuple[Variable, ...]
    parameters: tuple[Parameter, ...]
    process_noise: ProcessNoiseSpec
    measurement_noise: tuple[MeasurementNoiseSpec, ...]
    data: DataSpec = dataclasses.field(default_factory=DataSpec)
    integrator: str = "euler"
    substeps: int = 1
    #: input hold between samples: "zoh" | "foh" (spec ``integrator: {inputs: ...}``)
    input_hold: str = "zoh"
    symbolic: Any = None                 # SymbolicModel when loaded from a spec
    module: types.ModuleType | None = None
    module_path: pathlib.Path | None = None
    jacobians: Jacobians | None = None

    def drift_jacobian(self, x, u, p):
        """``(∂f/∂x, ∂f/∂u, ∂f/∂p)`` at one sample, shapes (nx, nx), (nx, nu), (nx, np)."""
        if self.jacobians is None:
            import jax
            return jax.jacfwd(self.drift, argnums=(0, 1, 2))(x, u, p)
        j = self.jacobians
        return j.drift_x(x, u, p), j.drift_u(x, u, p), j.drift_p(x, u, p)

    def output_jacobian(self, x, u, p):
        """``(∂h/∂x, ∂h/∂u, ∂h/∂p)`` at one sample, shapes (ny, nx), (ny, nu), (ny, np)."""
        if self.jacobians is None:
            import jax
            return jax.jacfwd(self.output, argnums=(0, 1, 2))(x, u, p)
        j = self.jacobians
        return j.output_x(x, u, p), j.output_u(x, u, p), j.output_p(x, u, p)

    @property
    def parameter_names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.parameters)

    @property
    def nx(self) -> int:
        return len(self.states)

    @property
    def nu(self) -> int:
        return len(self.inputs)

    @property
    def ny(self) -> int:
        return len(self.outputs)

    @property
    def np(self) -> int:
        return len(self.parameters)


def theta_vector(model, theta) -> np.ndarray:
    """Full parameter vector from a dict name->value (missing: ``Parameter.initial``) or an array."""
    names = model.parameter_names
    if isinstance(theta, Mapping):
        unknown = [k for k in theta if k not in names]
        if unknown:
            raise VsidgenError(f"unknown parameter(s) {', '.join(map(repr, unknown))}\n"
                               f"  hint: model {model.name} has parameters {', '.join(names)}")
        out = []
        for p in model.parameters:
            v = theta.get(p.name, p.initial)
            try:
                out.append(float(v))
            except (TypeError, ValueError):
                raise VsidgenError(f"parameter {p.name!r}: {v!r} is not a number") from None
        arr = np.array(out)
    elif theta is None:
        arr = np.array([float(p.initial) for p in model.parameters])
    else:
        try:
            arr = np.asarray(theta, dtype=np.float64).ravel()
        except (TypeError, ValueError):
            raise VsidgenError(f"theta must be a dict name -> number or an array of "
                               f"{model.np} numbers, got {type(theta).__name__}") from None
        if arr.shape != (model.np,):
            raise VsidgenError(f"theta has {arr.size} values, model {model.name} has {model.np} parameters")
    return arr


def finite_theta(model, theta, *, who: str) -> np.ndarray:
    """:func:`theta_vector`, refused with the parameters' names where a value is NaN or inf
    (``simulate`` and ``evaluate`` returned NaN signals without a word; session 44)."""
    arr = theta_vector(model, theta)
    bad = [n for n, v in zip(model.parameter_names, arr) if not np.isfinite(v)]
    if bad:
        raise VsidgenError(f"{who}: parameter(s) {', '.join(map(repr, bad))} not finite "
                           "(NaN or inf)")
    return arr


def default_generated_dir(spec_path) -> pathlib.Path:
    """``<parent of specs>/generated`` when the spec lies in a folder named ``specs``, else ``./generated``."""
    spec_path = pathlib.Path(spec_path).resolve()
    if spec_path.parent.name == "specs":
        return spec_path.parent.parent / "generated"
    return pathlib.Path("generated")


def _import_module(module_path: pathlib.Path, name: str, spec_hash: str,
                   text: str) -> types.ModuleType:
    """A module made by executing ``text`` — the text :func:`~vsidgen.codegen.generate`
    gives for the spec, which ``module_path`` holds — never the file itself.

    Python's import system would run a matching ``__pycache__/*.pyc`` instead of the checked
    source (a bytecode file unpacked with the project keeps the timestamps that make it
    match: red team, session 47), and would read the file again after the check (another
    process may have replaced it). The text is compiled here with the file's name, so
    tracebacks and ``inspect`` still point at the file, and no bytecode is read or written.
    """
    import hashlib
    import linecache

    filename = str(module_path)
    module = types.ModuleType(f"vsidgen_generated_{name}_{spec_hash[:16]}")
    module.__file__ = filename
    module.__vsidgen_source_sha256__ = hashlib.sha256(text.encode("utf-8")).hexdigest()
    linecache.cache[filename] = (len(text), None, text.splitlines(True), filename)
    exec(compile(text, filename, "exec", dont_inherit=True), module.__dict__)
    return module


def load_model(spec_path, *, generated_dir=None, build: bool = True) -> Model:
    """Compile ``spec_path``, (re)build its generated module if needed, import it.

    Args:
        spec_path: the YAML spec.
        generated_dir: where ``<name>.py`` lives (default: :func:`default_generated_dir`).
        build: write the module when it is missing or its SPEC_HASH is stale; with
            ``build=False`` a missing/stale module raises SpecError.

    Raises:
        SpecError: invalid spec, or stale module with ``build=False``.
    """
    from ..codegen import build_model, generate, is_up_to_date
    from ..errors import SpecError
    from ..spec import compile_spec

    symbolic = compile_spec(spec_path)
    out_dir = pathlib.Path(generated_dir) if generated_dir is not None else default_generated_dir(spec_path)
    module_path = out_dir / f"{symbolic.name}.py"
    text = generate(symbolic)
    if build:
        build_model(symbolic, out_dir=out_dir, text=text)
    elif not is_up_to_date(symbolic, module_path, text=text):
        raise SpecError(f"generated module {module_path} is missing or out of date",
                        path=spec_path, hint=f"run `vsidgen build {spec_path}`")
    module = _import_module(module_path, symbolic.name, symbolic.source_hash, text)
    return Model(
        name=symbolic.name, drift=module.drift, output=module.output,
        states=symbolic.states, inputs=symbolic.inputs, outputs=symbolic.outputs,
        parameters=symbolic.parameters, process_noise=symbolic.process_noise,
        measurement_noise=symbolic.measurement_noise, data=symbolic.data,
        integrator=symbolic.integrator, substeps=symbolic.substeps,
        input_hold=getattr(symbolic, "input_hold", "zoh"), symbolic=symbolic,
        module=module, module_path=module_path, jacobians=Jacobians.of_module(module),
    )
