"""Variational maximum-likelihood estimator (Dutra, "Variational System Identification of Aircraft").

Public API::

    fit(model, records, *, options=FitOptions()) -> FitResult
    smooth(model, records, theta, noise, *, options=FitOptions()) -> FitResult
    validate_own_noise(model, records, theta, *, free=(), options=FitOptions()) -> FitResult
    FitOptions, FitPhase, PhaseKind, FitResult, SmootherPath, StopReason, StdErrorIssue, StdErrorFlag, WarmStart
    Problem(model, records, options)    # decision-vector layout, objective, reduced Newton system
    ModelFamily(models).active()        # problems of these models share one compilation
    Layout, ReducedSystem, Gradient, parameter_start, split_density, join_density
"""

from .fit import fit, smooth, validate_own_noise
from .problem import (DirectMeasurement, Gradient, Layout, ModelFamily, Problem, ReducedSystem, direct_measurements, join_density,
                      measured_states, parameter_start, split_density)
from .results import (FitOptions, FitPhase, FitResult, PhaseKind, SmootherPath, StdErrorFlag, StdErrorIssue,
                      StopReason, WarmStart)

__all__ = ["DirectMeasurement", "FitOptions", "FitPhase", "FitResult", "Gradient", "Layout", "ModelFamily", "PhaseKind", "Problem",
           "ReducedSystem", "SmootherPath", "StdErrorFlag", "StdErrorIssue", "StopReason", "WarmStart", "direct_measurements", "fit",
           "join_density", "measured_states", "parameter_start", "smooth", "split_density",
           "validate_own_noise"]
