"""Metadata of a model kept apart from values (dynamax habit).

These records describe names, units, bounds, fixed flags, noise structure and
the data mapping. They are produced by :mod:`vsidgen.spec.symbolic` from a spec and
consumed by the runtime :class:`vsidgen.model.Model`, the data loader and the
estimator. Numeric values being estimated live in the estimator, not here.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any, Literal


@dataclasses.dataclass(frozen=True)
class Variable:
    """A state, input or output: name, unit and description."""

    name: str
    unit: str | None = None
    description: str = ""
    symbol: Any = None  # sympy.Symbol when built from a spec
    #: inputs only: pure transport delay in seconds, the model sees u(t − delay)
    #: (:func:`vsidgen.data.delay_input`); 0 = none
    delay: float = 0.0


class VariableNames:
    """Mixin for records with ``states``, ``inputs`` and ``outputs`` tuples of named variables."""

    @property
    def state_names(self) -> tuple[str, ...]:
        return tuple(v.name for v in self.states)

    @property
    def input_names(self) -> tuple[str, ...]:
        return tuple(v.name for v in self.inputs)

    @property
    def output_names(self) -> tuple[str, ...]:
        return tuple(v.name for v in self.outputs)


@dataclasses.dataclass(frozen=True)
class Constant:
    """A named constant with its value, unit and source."""

    name: str
    value: float
    unit: str | None = None
    source: str = ""
    symbol: Any = None


@dataclasses.dataclass(frozen=True)
class Parameter:
    """An unknown model parameter θ_i.

    ``initial`` is the starting value (0 by default: vsidgen starts from null
    guesses). ``lower``/``upper`` are optional bounds honoured through a smooth
    unconstrained map; ``fixed`` parameters keep ``initial`` and are not estimated.
    """

    name: str
    unit: str | None = None
    description: str = ""
    initial: float = 0.0
    lower: float | None = None
    upper: float | None = None
    fixed: bool = False
    symbol: Any = None


@dataclasses.dataclass(frozen=True)
class ProcessNoiseSpec:
    """Process noise G dW on the listed states.

    ``structure`` "diagonal": G = diag(std) on ``states``; "full": G lower
    triangular. ``std`` values are in state-unit/sqrt(s); when ``estimate`` is
    false they are the fixed values (missing = 0). ``floor`` is a lower bound
    on each diagonal std (default 0).

    ``degenerate`` (structure "full" only): states whose diagonal entry G_ii is zero, so
    that their process noise is a combination of the noise sources of the states before
    them (state order): a rank-deficient Q, e.g. one vertical gust driving the α and q
    equations through Z_α/V and M_α/V. The estimator fits such a model as the limit
    G_ii → 0 (:mod:`vsidgen.estimator.fit`, as for states without process noise).
    """

    states: tuple[str, ...] = ()
    structure: Literal["diagonal", "full"] = "diagonal"
    estimate: bool = True
    std: Mapping[str, float] = dataclasses.field(default_factory=dict)
    floor: Mapping[str, float] = dataclasses.field(default_factory=dict)
    degenerate: tuple[str, ...] = ()


@dataclasses.dataclass(frozen=True)
class MeasurementNoiseSpec:
    """Measurement noise of one output: v ~ N(0, std²).

    ``floor`` "auto" derives the lower bound from the data resolution
    (smallest non-zero step / sqrt(12)); a number sets it; 0 disables it.
    """

    output: str
    estimate: bool = True
    std: float | None = None
    floor: float | Literal["auto"] = "auto"


@dataclasses.dataclass(frozen=True)
class ChannelMap:
    """How one input or output is read from a CSV record.

    Either ``column`` (value = scale * (a * column + b) + offset) or ``expr``, a
    sympy expression in the column symbols listed in ``columns`` (then the unit
    conversion and scale/offset are applied to the expression's value).
    ``unit`` is the unit the data map declares for the column (None: the
    column is taken to be in the spec's unit) and ``(a, b) = unit_conversion``
    converts it to the spec's unit (:mod:`vsidgen.spec.dataunits`).
    """

    name: str
    column: str | None = None
    scale: float = 1.0
    offset: float = 0.0
    expr: Any = None
    columns: tuple[str, ...] = ()
    unit: str | None = None
    unit_conversion: tuple[float, float] = (1.0, 0.0)

    def source_columns(self) -> tuple[str, ...]:
        """The record columns this channel reads: ``columns`` (or the expression's symbols,
        sorted) for an ``expr`` map, else ``column``, else a column named after the channel."""
        if self.expr is not None:
            return tuple(self.columns) or tuple(sorted(str(s) for s in self.expr.free_symbols))
        if self.column is not None:
            return (self.column,)
        return (self.name,)

    def apply(self, value):
        """The channel's value in the spec's unit from the column (or expression) value."""
        a, b = self.unit_conversion
        if a != 1.0:
            value = value * a
        if b != 0.0:
            value = value + b
        if self.scale != 1.0:
            value = value * float(self.scale)
        if self.offset != 0.0:
            value = value + float(self.offset)
        return value


@dataclasses.dataclass(frozen=True)
class DataSpec:
    """The data mapping of a spec: time column and channel maps."""

    time: str = "t_s"
    inputs: tuple[ChannelMap, ...] = ()
    outputs: tuple[ChannelMap, ...] = ()
    #: seconds per unit of the time column (``time: {column: t_ms, unit: ms}``: 0.001)
    time_scale: float = 1.0
    #: the time column's declared unit (None: seconds)
    time_unit: str | None = None
