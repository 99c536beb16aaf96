"""Variational maximum-likelihood estimator (Dutra, "Variational System Identification of Aircraft").

Public API::

    fit(model, records, *, options=FitOptions()) -> FitResult
    smooth(model, records, theta, noise, *, options=FitOptions()) -> FitResult
    FitOptions, FitResult, SmootherPath, StopReason, StdErrorIssue, StdErrorFlag, WarmStart
    Problem(model, records, options)    # decision-vector layout, objective, reduced Newton system
    Layout, ReducedSystem, Gradient, parameter_start, split_density, join_density
"""

from .fit import fit, measured_states, smooth
from .problem import Gradient, Layout, Problem, ReducedSystem, join_density, parameter_start, split_density
from .results import FitOptions, FitResult, SmootherPath, StdErrorFlag, StdErrorIssue, StopReason, WarmStart

__all__ = ["FitOptions", "FitResult", "Gradient", "Layout", "Problem", "ReducedSystem", "SmootherPath",
           "StdErrorFlag", "StdErrorIssue", "StopReason", "WarmStart", "fit", "join_density", "measured_states",
           "parameter_start", "smooth", "split_density"]
