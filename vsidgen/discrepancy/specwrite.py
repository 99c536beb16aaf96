"""Specs that diagnose writes: YAML text of a spec mapping, and parameter entries warm-started
from a fit's estimates."""

from __future__ import annotations

import pathlib
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


__all__ = ["clip_to_bounds", "warm_parameters", "write_spec"]
