"""Model stage: the runtime model (generated functions + metadata) and its one discrete
transition (``vsidgen.model.dynamics``: Euler / RK4, sub-steps, input hold).

Public API::

    load_model(spec_path, *, generated_dir=None, build=True) -> Model
    theta_vector(model, theta) -> the full parameter vector
"""

from .runtime import Model, default_generated_dir, load_model, theta_vector

__all__ = ["Model", "default_generated_dir", "load_model", "theta_vector"]
