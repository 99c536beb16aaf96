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

from ..errors import VsidgenError
from ..limits import check_input_file, parse_json


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
    """``results.json`` of a results directory, checked: a regular file inside the directory
    (:func:`contained_file`), a JSON object with the entries the report needs (VsidgenError,
    with the path and, for bad JSON, line and column, otherwise)."""
    results_dir = pathlib.Path(results_dir)
    if not results_dir.exists():
        raise VsidgenError(f"{results_dir}: error: results directory does not exist")
    if not results_dir.is_dir():
        raise VsidgenError(f"{results_dir}: error: not a directory (expected a fit's results "
                           "directory containing results.json)")
    path = results_dir / "results.json"
    if not os.path.lexists(path):
        raise VsidgenError(f"{path}: error: results.json not found; is {results_dir} the output "
                           "directory of `vsidgen fit`?")
    path = contained_file(results_dir, "results.json", what="results file")
    try:
        res = parse_json(path.read_text(encoding="utf-8"), strict_ints=True)
    except (OSError, UnicodeDecodeError) as err:
        raise VsidgenError(f"{path}: error: cannot read results file: {err}") from None
    except RecursionError:
        raise VsidgenError(f"{path}: error: results.json is nested too deeply to be one "
                           "vsidgen wrote") from None
    except json.JSONDecodeError as err:
        raise VsidgenError(f"{path}:{err.lineno}:{err.colno}: error: results.json is not valid "
                           f"JSON: {err.msg}") from None
    except ValueError as err:   # nested too deeply (parse_json)
        raise VsidgenError(f"{path}: error: results.json is not one vsidgen wrote: {err}") from None
    if not isinstance(res, dict):
        raise VsidgenError(f"{path}: error: results.json must hold a JSON object")
    for key, typ in (("spec", dict), ("model", dict), ("parameters", dict), ("records", dict)):
        if not isinstance(res.get(key), typ):
            raise VsidgenError(f"{path}: error: results.json has no valid `{key}` entry "
                               "(written by an incompatible vsidgen version?)")
    for key in ("states", "outputs"):
        entries = res["model"].get(key)
        if not isinstance(entries, list):
            raise VsidgenError(f"{path}: error: results.json `model.{key}` is missing or not a list")
        # each name once, as vsidgen writes them: 50 copies of the outputs made `report` run
        # for minutes, a panel per copy (session 44, red team)
        seen: set[str] = set()
        for e in entries:
            n = e.get("name") if isinstance(e, dict) else e
            what = ("has an entry without a name:" if not isinstance(n, str)
                    else "repeats" if n in seen else None)
            if what:
                raise VsidgenError(f"{path}: error: results.json `model.{key}` {what} "
                                   f"{str(n)[:60]!r}: not a file vsidgen wrote")
            seen.add(n)
    return res


def contained_file(results_dir: pathlib.Path, name: object, *, what: str) -> pathlib.Path:
    """The regular file ``results_dir/name``, refusing anything that leaves the directory.

    ``name`` comes from ``results.json`` and is untrusted: it must be a relative
    path without ``..`` parts, and the file it names (after resolving symbolic
    links) must lie inside ``results_dir`` and be a regular file within the size
    limit of :func:`vsidgen.limits.json_limit`. Messages name the path but never
    show the content of a file outside the directory.

    Raises:
        VsidgenError: any of these fails.
    """
    text = name if isinstance(name, str) else None
    shown = repr(text[:200]) if text is not None else type(name).__name__
    if not text or "\x00" in text or os.path.isabs(text) or text.startswith(("/", "\\")):
        raise VsidgenError(f"{results_dir}/results.json: error: {what} {shown} is not a "
                           "relative file name inside the results directory")
    parts = pathlib.PurePosixPath(text.replace("\\", "/")).parts
    if any(part in ("..", "") for part in parts):
        raise VsidgenError(f"{results_dir}/results.json: error: {what} {shown} leaves the "
                           "results directory ('..' is not allowed)")
    path = results_dir / text
    if not os.path.lexists(path):
        raise VsidgenError(f"{path}: error: {what} listed in results.json is missing")
    root = results_dir.resolve()
    try:
        real = path.resolve()
    except (OSError, RuntimeError):
        raise VsidgenError(f"{path}: error: cannot resolve {what} (a symbolic-link loop?)") from None
    if root not in real.parents:
        raise VsidgenError(f"{path}: error: {what} is a symbolic link that leaves the results "
                           "directory; vsidgen reads only files inside it")
    check_input_file(path, what=what, kind="json", data_error=False)
    return path
