"""Evaluation stage: the paper's four evaluation signals of an identified model (smoother,
simulation, Kalman prediction, derivative) and fit metrics (``signals``).

Public API::

    evaluate(model, record, theta, *, mu, G, R) -> Signals
    fit_metrics(measured, predicted) -> dict
    predictive_loglik(signals) -> (N,) array | None       # per-sample one-step log-likelihood
    unexplained_outputs(signals, *, kind) -> list[dict]   # warnings: R² <= 0 per output
    iid_gaussian_loglik(y) -> float                       # log-likelihood without dynamics
    validation_elbo_warning(elbo, n, val_elbo, val_ys) -> dict | None   # per-sample ELBO check
"""

from .signals import (Signals, evaluate, fit_metrics, iid_gaussian_loglik, predictive_loglik,
                      unexplained_outputs, validation_elbo_warning)

__all__ = ["Signals", "evaluate", "fit_metrics", "iid_gaussian_loglik", "predictive_loglik",
           "unexplained_outputs", "validation_elbo_warning"]
