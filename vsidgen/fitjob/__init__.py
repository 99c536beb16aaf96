"""Fit-job stage: ``vsidgen fit`` end to end (``run``: records -> fit -> evaluation ->
results directory) and ``vsidgen fleet`` (``fleet``: one fit per record on the engine).

Public API::

    run_fit(spec, data, *, out, ...) -> FitJob
    run_fleet(spec, data, *, out, workers, ...) -> FleetResult
"""

from .fleet import FleetResult, add_fleet_parser, run_fleet
from .run import FitJob, run_fit

__all__ = ["FitJob", "FleetResult", "add_fleet_parser", "run_fit", "run_fleet"]
