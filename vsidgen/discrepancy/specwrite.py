"""Specs that diagnose writes: YAML text of a spec mapping, and parameter entries warm-started
from a fit's estimates."""

from __future__ import annotations

import os
import pathlib
import re
from typing import Any

import yaml

from ..atomic import write_text_atomic


def write_spec(path: pathlib.Path, header: str, d: dict) -> pathlib.Path:
    """Write a generated spec mapping ``d`` as YAML under a ``# header`` comment line (atomically)."""
    return write_text_atomic(path, f"# {header}\n" + yaml.safe_dump(
        d, sort_keys=False, width=100, allow_unicode=True))


def clip_to_bounds(x: float, bounds) -> float:
    """``x`` clipped to a parameter's ``[lower, upper]`` bounds (``None`` = unbounded)."""
    lo, hi = bounds or (None, None)
    x = float(x) if lo is None else max(float(x), lo)
    return x if hi is None else min(x, hi)


def warm_parameters(model, theta) -> dict:
    """Spec entries of ``model``'s parameters with the estimates ``theta`` (all parameters, in
    model order) as initial values (clipped to the bounds; fixed parameters keep theirs)."""
    out = {}
    for p, v in zip(model.parameters, theta):
        d: dict[str, Any] = {"unit": p.unit if p.unit is not None else "1",
                             "description": p.description or "",
                             "initial": float(p.initial if p.fixed else v)}
        if p.lower is not None or p.upper is not None:
            d["bounds"] = [p.lower, p.upper]
            d["initial"] = clip_to_bounds(d["initial"], d["bounds"])
        if p.fixed:
            d["fixed"] = True
        out[p.name] = d
    return out


def extends_text(spec_path, path: pathlib.Path) -> str:
    """``extends:`` text of a spec written at ``path`` that extends ``spec_path``."""
    return os.path.relpath(pathlib.Path(spec_path).resolve(), path.resolve().parent)


def safe_name(key: str) -> str:
    """``key`` as a file-name part: runs of other characters than letters, digits and _ become
    one _, at most 60 characters."""
    return re.sub(r"[^A-Za-z0-9_]+", "_", key).strip("_")[:60]


__all__ = ["clip_to_bounds", "extends_text", "safe_name", "warm_parameters", "write_spec"]
