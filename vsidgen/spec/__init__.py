"""Spec stage: YAML spec files -> validated sympy model.

Modules, in order::

    expr       safe expression parser (no eval/sympify of raw text)
    units      unit strings -> dimensions, dimensional-consistency warnings
    dataunits  data-map units: pint conversion of a column to the spec's unit
    load       YAML with line/column marks, ``extends`` resolved (RawSpec)
    typed      the typed, immutable, located Spec
    symbolic   Spec -> SymbolicModel (sympy drift f, outputs h, noise, data map)
    identifiability  parameter combinations the equations cannot separate (warnings)
    overrides  --fix/--free/--init/--init-from/--method applied to a model

Public API (what later stages use)::

    compile_spec(path) -> SymbolicModel
"""

from .symbolic import GENERATED_MODULE_NAMES, GENERATOR_VERSION, SymbolicModel, compile_spec

__all__ = ["GENERATED_MODULE_NAMES", "GENERATOR_VERSION", "SymbolicModel", "compile_spec"]
