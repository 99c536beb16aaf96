"""Evaluation stage: the paper's four evaluation signals of an identified model (smoother,
simulation, Kalman prediction, derivative) and fit metrics (``signals``).

Public API::

    evaluate(model, record, theta, *, mu, G, R) -> Signals
    fit_metrics(measured, predicted) -> dict
"""

from .signals import Signals, evaluate, fit_metrics

__all__ = ["Signals", "evaluate", "fit_metrics"]
