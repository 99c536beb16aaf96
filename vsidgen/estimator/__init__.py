"""Variational maximum-likelihood estimator (Dutra, "Variational System Identification of Aircraft").

Public API::

    fit(model, records, *, options=FitOptions()) -> FitResult
    smooth(model, records, theta, noise, *, options=FitOptions()) -> FitResult
    FitOptions, FitResult, SmootherPath, StopReason, WarmStart
"""

from .fit import fit, measured_states, smooth
from .results import FitOptions, FitResult, SmootherPath, StopReason, WarmStart

__all__ = ["FitOptions", "FitResult", "SmootherPath", "StopReason", "WarmStart", "fit", "measured_states",
           "smooth"]
