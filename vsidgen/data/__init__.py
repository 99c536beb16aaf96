"""Data stage: flight records through a spec's data map, record checks and simulation.

Modules::

    formats   CSV and MATLAB .mat files, column references
    records   files -> Record (t, u, y) through the data map; data errors; resolution
    check     ``vsidgen check --data``: a whole record checked against a compiled spec
    simulate  manoeuvre generators and stochastic simulation (synthetic records)

Public API (what later stages use)::

    load_record(model, path) -> Record
    load_records(model, data, validate) -> (records, validation records), names unique
    as_paths(paths) -> [path, ...] (one path is a list of one)
    resolution, unique_names, delay_input, write_csv
"""

from .records import (Record, as_paths, delay_input, load_record, load_records, resolution,
                      unique_names, write_csv)

__all__ = ["Record", "as_paths", "delay_input", "load_record", "load_records", "resolution", "unique_names", "write_csv"]
