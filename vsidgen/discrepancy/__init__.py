"""Discrepancy discovery (``vsidgen diagnose``): locate where a fitted model and the
recordings disagree, explain it with a catalogue of physical effects, add the
effect to the spec, refit and confirm it statistically.

Public API::

    run_diagnose(spec, data, *, validate=(), out, ...) -> DiagnoseResult   # the whole job
    locate(records, *, state_names, input_names, output_names, ...) -> Evidence
    Effect, Candidate, register_effect, registered_effects, load_effects_module
    add_diagnose_parser(subparsers)                                        # CLI wiring
"""

from .base import (Candidate, DiscrepancyError, Effect, ModelInfo, NewParameter, NewState,
                   load_effects_module, model_info, propose, register_effect, registered_effects,
                   unregister_effect)
from .locate import Evidence, LocateRecord, locate
from . import catalogue  # noqa: F401  (the built-in effects register themselves)

__all__ = ["Candidate", "DiagnoseResult", "DiscrepancyError", "Effect",
           "Evidence", "LocateRecord", "ModelInfo", "NewParameter", "NewState",
           "add_diagnose_parser", "load_effects_module", "locate", "model_info", "propose",
           "register_effect", "registered_effects", "run_diagnose", "unregister_effect"]


def __getattr__(name):  # lazy: search pulls in the estimator (jax)
    if name in ("run_diagnose", "DiagnoseResult", "add_diagnose_parser",
                "diagnose_command"):
        from . import search
        return getattr(search, name)
    raise AttributeError(name)
