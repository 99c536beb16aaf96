"""Float64 for every JAX computation in vsidgen, switched on in this one place.

Every module that computes with JAX imports this module first. The ELBO of a long record is
a sum of ~N terms of order one nat, and convergence is judged on changes of 1e-3 nats
(``docs/estimator.md``): float32's 7 digits cannot resolve that beyond a few thousand samples.
"""

from __future__ import annotations

import jax

jax.config.update("jax_enable_x64", True)

# JAX's gc callback must not swallow Ctrl-C (vsidgen.interrupts)
from .interrupts import guard_gc_callbacks  # noqa: E402

guard_gc_callbacks()
