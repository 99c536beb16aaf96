"""Variational maximum-likelihood estimator (Dutra, "Variational System Identification of Aircraft").

Public API::

    fit(model, records, *, options=FitOptions()) -> FitResult
    smooth(model, records, theta, noise, *, options=FitOptions()) -> FitResult
    FitOptions, FitResult, SmootherPath, StopReason, StdErrorIssue, StdErrorFlag, WarmStart
"""

from .fit import DirectMeasurement, direct_measurements, fit, measured_states, smooth
from .results import FitOptions, FitResult, SmootherPath, StdErrorFlag, StdErrorIssue, StopReason, WarmStart

__all__ = ["DirectMeasurement", "FitOptions", "FitResult", "SmootherPath", "StdErrorFlag", "StdErrorIssue", "StopReason", "WarmStart",
           "direct_measurements", "fit", "measured_states", "smooth"]
