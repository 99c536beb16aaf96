"""Runtime model: generated JAX functions bound to the spec's metadata."""

from __future__ import annotations

import dataclasses
import pathlib
import types
from collections.abc import Callable
from typing import Any

from .metadata import DataSpec, MeasurementNoiseSpec, Parameter, ProcessNoiseSpec, Variable


@dataclasses.dataclass(frozen=True)
class Model:
    """Everything the estimator needs to know about a model.

    ``drift(x, u, p)`` and ``output(x, u, p)`` take one sample (1-D arrays;
    ``p`` holds all parameters in ``parameters`` order, fixed ones included)
    and return jnp arrays of shape (nx,) and (ny,).
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
    symbolic: Any = None                 # SymbolicModel when loaded from a spec
    module: types.ModuleType | None = None
    module_path: pathlib.Path | None = None

    @property
    def state_names(self) -> tuple[str, ...]:
        return tuple(v.name for v in self.states)

    @property
    def input_names(self) -> tuple[str, ...]:
        return tuple(v.name for v in self.inputs)

    @property
    def output_names(self) -> tuple[str, ...]:
        return tuple(v.name for v in self.outputs)

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
