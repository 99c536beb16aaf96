"""The results directory of a fit: ``results.json`` plus CSV time histories.

Layout and keys are documented in docs/architecture.md ("Results directory").
Everything is written into a temporary directory beside the target and swapped
in at the end, so a failed or interrupted run leaves earlier results intact.
"""

from __future__ import annotations

import json
import math
import os
import pathlib
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from . import __version__
from .atomic import atomic_directory, write_text_atomic  # noqa: F401  (re-exported)
from .errors import VsidgenError


def finite_or_none(v: Any) -> float | None:
    """``float(v)`` when it is a finite number, else None (JSON has no NaN)."""
    try:
        v = float(v)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def _clean(obj: Any) -> Any:
    """Convert numpy scalars/arrays to JSON types; NaN/inf become None."""
    if isinstance(obj, Mapping):
        return {str(k): _clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_clean(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _clean(obj.tolist())
    if isinstance(obj, (np.bool_, bool)):
        return bool(obj)
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        v = float(obj)
        return v if math.isfinite(v) else None
    if isinstance(obj, pathlib.Path):
        return obj.as_posix()
    return obj


def dumps(results: Mapping[str, Any]) -> str:
    """Serialise a results mapping to JSON text (strict: no NaN literals)."""
    return json.dumps(_clean(results), indent=1, allow_nan=False) + "\n"


def signals_table(signals, state_names: Sequence[str], output_names: Sequence[str],
                  mu_std: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Columns of ``signals_<record>.csv`` for one record's evaluation signals."""
    n = len(signals.t)
    cols: dict[str, np.ndarray] = {"t_s": np.asarray(signals.t, float)}
    for j, name in enumerate(output_names):
        cols[f"{name}_meas"] = np.asarray(signals.y_meas)[:, j]
        cols[f"{name}_smooth"] = np.asarray(signals.y_smooth)[:, j]
        cols[f"{name}_sim"] = np.asarray(signals.y_sim)[:, j]
        cols[f"{name}_pred"] = np.asarray(signals.y_pred)[:, j]
    pad = np.full(1, np.nan)
    for i, name in enumerate(state_names):
        cols[f"{name}_mu"] = np.asarray(signals.x_smooth)[:, i]
        std = np.full(n, np.nan) if mu_std is None else np.full(n, float(mu_std[i]))
        cols[f"{name}_mu_std"] = std
        cols[f"{name}_dot_fd"] = np.concatenate([np.asarray(signals.xdot_fd)[:, i], pad])
        cols[f"{name}_drift"] = np.concatenate([np.asarray(signals.f_smooth)[:, i], pad])
    return cols


def read_results(results_dir: str | os.PathLike) -> dict[str, Any]:
    """Read ``results.json`` of a results directory (VsidgenError when absent/corrupt)."""
    path = pathlib.Path(results_dir) / "results.json"
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise VsidgenError(f"{path}: no results.json here; run `vsidgen fit ... --out "
                           f"{results_dir}` first") from None
    except (OSError, json.JSONDecodeError) as exc:
        raise VsidgenError(f"{path}: cannot read results ({exc})") from None


def results_version() -> str:
    return __version__
