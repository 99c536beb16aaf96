"""Command-line control of a fit: ``--fix``, ``--free``, ``--init``, ``--init-from``, ``--method``.

Overrides change the spec's parameter records, never the equations, so the
generated module is reused:

* ``--init-from results.json``: ``initial = estimate`` for every parameter of
  the results file that the model has (others keep the spec's value);
* ``--init NAME=VALUE``: ``initial = VALUE``;
* ``--fix NAME=VALUE``: ``initial = VALUE`` and ``fixed = true`` — exactly a
  spec entry ``NAME: {initial: VALUE, fixed: true}``;
* ``--free NAME``: ``fixed = false``;

applied in that order. ``--method output-error`` removes the process noise
(every state deterministic: the estimator fits the exact limit of vanishing
process noise, i.e. the output-error method; docs/estimator.md); ``filter-error`` (default)
keeps the spec's process noise. Unknown names raise a VsidgenError with a
role-aware suggestion (:func:`vsidgen.suggest.suggest`).
"""

from __future__ import annotations

import dataclasses
import enum
import json
import math
import pathlib
from collections.abc import Mapping, Sequence
from typing import Any

from ..errors import VsidgenError, printable
from ..metadata import ProcessNoiseSpec


class Method(enum.Enum):
    """Estimation method: with process noise (filter error) or without (output error)."""

    FILTER_ERROR = "filter-error"
    OUTPUT_ERROR = "output-error"


@dataclasses.dataclass(frozen=True)
class Overrides:
    """Parameter overrides and method of one fit (all empty: the spec as written)."""

    fix: Mapping[str, float] = dataclasses.field(default_factory=dict)
    free: tuple[str, ...] = ()
    init: Mapping[str, float] = dataclasses.field(default_factory=dict)
    init_from: str | None = None
    init_from_values: Mapping[str, float] = dataclasses.field(default_factory=dict)
    method: Method = Method.FILTER_ERROR

    @property
    def empty(self) -> bool:
        return (not self.fix and not self.free and not self.init and self.init_from is None
                and self.method is Method.FILTER_ERROR)

    def to_json(self) -> dict[str, Any]:
        return {"fix": dict(self.fix), "free": list(self.free), "init": dict(self.init),
                "init_from": self.init_from, "method": self.method.value}


def _name_value(item: str, option: str) -> tuple[str, float]:
    name, sep, value = item.partition("=")
    if not sep or not name.strip():
        raise VsidgenError(f"--{option} {item!r}: expected NAME=VALUE")
    try:
        x = float(value)
    except ValueError:
        raise VsidgenError(f"--{option} {item!r}: {value!r} is not a number") from None
    if not math.isfinite(x):
        raise VsidgenError(f"--{option} {item!r}: the value must be finite")
    return name.strip(), x


def _name_values(items: Sequence[str] | None, option: str) -> dict[str, float]:
    """``{name: value}`` of repeated ``--option NAME=VALUE``; a name given twice with
    different values is refused (`--fix MQ=1 --fix MQ=2` kept the last silently; session 46)."""
    out: dict[str, float] = {}
    for item in items or ():
        name, x = _name_value(item, option)
        if name in out and out[name] != x:
            raise VsidgenError(f"--{option} {name} is given twice, with different values "
                               f"({out[name]:g} and {x:g})")
        out[name] = x
    return out


def read_estimates(path, *, option: str = "--init-from") -> dict[str, float]:
    """``{parameter: estimate}`` of a ``results.json`` written by ``vsidgen fit`` (``option``
    names the command-line option that gave ``path`` in error messages)."""
    from ..limits import check_input_file, parse_json

    path = pathlib.Path(path)
    if not path.exists() and not path.is_symlink():
        raise VsidgenError(f"{option} {path}: file not found")
    # a regular file within VSIDGEN_MAX_JSON_BYTES (a device such as /dev/zero or a named
    # pipe would be read without end)
    try:
        check_input_file(path, what=f"{option} file", kind="json", data_error=False)
    except VsidgenError as err:
        raise VsidgenError(f"{option} {err}") from None
    try:
        doc = parse_json(path.read_text(encoding="utf-8"))
        params = doc["parameters"]
        out = {}
        for k, v in params.items():
            est = v["estimate"]
            if isinstance(est, bool) or not isinstance(est, (int, float)):
                # `true` or "1e3" is not an estimate vsidgen wrote (float() would take both)
                raise TypeError(f"the estimate of `{k}` is {json.dumps(est)[:40]}, not a number")
            out[str(k)] = float(est)
    except FileNotFoundError:
        raise VsidgenError(f"{option} {path}: file not found") from None
    except (OSError, UnicodeDecodeError, ValueError, KeyError, TypeError, AttributeError,
            RecursionError) as exc:
        raise VsidgenError(f"{option} {path}: not a vsidgen results.json with parameter "
                           f"estimates ({type(exc).__name__}: {str(exc)[:200]})") from None
    bad = [k for k, v in out.items() if not math.isfinite(v)]
    if bad:
        raise VsidgenError(f"{option} {path}: the estimate of `{bad[0]}` is not a finite "
                           "number")
    return out


def parse_overrides(*, fix: Sequence[str] | None = None, free: Sequence[str] | None = None,
                    init: Sequence[str] | None = None, init_from: str | None = None,
                    method: str = "filter-error") -> Overrides:
    """Overrides from the CLI's option strings (VsidgenError on malformed ones)."""
    fixd = _name_values(fix, "fix")
    initd = _name_values(init, "init")
    freed = tuple(n.strip() for n in free or ())
    both = sorted(set(fixd) & set(freed))
    if both:
        raise VsidgenError(f"`{both[0]}` is given to both --fix and --free")
    values = read_estimates(init_from) if init_from is not None else {}
    try:
        m = Method(method)
    except ValueError:
        raise VsidgenError(f"--method {method!r}: use filter-error or output-error") from None
    return Overrides(fixd, freed, initd, None if init_from is None else str(init_from), values, m)


def apply_overrides(model, ov: Overrides):
    """``model`` (a Model or SymbolicModel) with its parameters and process noise overridden.

    Raises:
        VsidgenError: an unknown parameter name (with a role-aware suggestion) or
            a value outside the parameter's bounds.
    """
    from ..suggest import unknown_name_error

    if ov.empty:
        return model
    names = [p.name for p in model.parameters]
    for option, given in (("fix", ov.fix), ("free", ov.free), ("init", ov.init)):
        for name in given:
            if name not in names:
                raise unknown_name_error(name, "parameter", model, option=f"--{option}")
    if ov.init_from is not None and names and not set(names) & set(ov.init_from_values):
        # a results.json of another model set nothing, and the fit went on silently from the
        # spec's initial values (session 46)
        given = ", ".join(sorted(ov.init_from_values)[:8]) or "none"
        raise VsidgenError(f"--init-from {printable(ov.init_from)}: none of its parameters "
                           f"is a parameter of model `{model.name}` (it has: "
                           f"{printable(given)[:200]})\n"
                           f"  hint: give the results.json of a fit of this model; its "
                           f"parameters: {', '.join(names[:20])}")
    params = []
    for p in model.parameters:
        initial, fixed = p.initial, p.fixed
        if p.name in ov.init_from_values:
            initial = ov.init_from_values[p.name]
        if p.name in ov.init:
            initial = ov.init[p.name]
        if p.name in ov.fix:
            initial, fixed = ov.fix[p.name], True
        if p.name in ov.free:
            fixed = False
        if (p.lower is not None and initial < p.lower) or (p.upper is not None and initial > p.upper):
            if p.name in ov.init_from_values and p.name not in ov.init and p.name not in ov.fix:
                initial = min(max(initial, p.lower if p.lower is not None else initial),
                              p.upper if p.upper is not None else initial)
            else:
                raise VsidgenError(f"value {initial:g} of parameter `{p.name}` is outside its "
                                   f"bounds [{p.lower}, {p.upper}]")
        params.append(dataclasses.replace(p, initial=float(initial), fixed=bool(fixed)))
    changes: dict[str, Any] = {"parameters": tuple(params)}
    if ov.method is Method.OUTPUT_ERROR:
        changes["process_noise"] = ProcessNoiseSpec(states=tuple(s.name for s in model.states), estimate=False)
    return dataclasses.replace(model, **changes)


def override_spec_text(spec_path, ov: Overrides, *, name: str, model) -> str:
    """A spec that ``extends`` ``spec_path`` with the overrides (for ``vsidgen diagnose``).

    Parameter entries are merged field by field onto the parent's, so units,
    bounds and descriptions are kept.
    """
    import yaml

    applied = apply_overrides(model, ov)
    params = {}
    for old, new in zip(model.parameters, applied.parameters):
        if (old.initial, old.fixed) != (new.initial, new.fixed):
            params[new.name] = {"initial": float(new.initial), "fixed": bool(new.fixed)}
    doc: dict[str, Any] = {"extends": str(pathlib.Path(spec_path).resolve()), "name": name}
    if params:
        doc["parameters"] = params
    if ov.method is Method.OUTPUT_ERROR:
        doc["noise"] = {"process": {"states": [s.name for s in model.states], "estimate": False}}
    return ("# vsidgen: command-line overrides " + json.dumps(ov.to_json()) + "\n"
            + yaml.safe_dump(doc, sort_keys=False))


def add_override_arguments(p) -> None:
    """``--fix/--free/--init/--init-from/--method`` (shared by fit and diagnose)."""
    g = p.add_argument_group("parameters and method (override the spec for this run; "
                             "recorded in the results)")
    g.add_argument("--fix", action="append", metavar="NAME=VALUE", default=None,
                   help="fix a parameter at VALUE (as `fixed: true, initial: VALUE` in the spec)")
    g.add_argument("--free", action="append", metavar="NAME", default=None,
                   help="estimate a parameter the spec fixes")
    g.add_argument("--init", action="append", metavar="NAME=VALUE", default=None,
                   help="initial value of a parameter")
    g.add_argument("--init-from", metavar="RESULTS_JSON", default=None,
                   help="initial values from an earlier fit's results.json (--init and --fix win)")
    g.add_argument("--method", choices=("filter-error", "output-error"), default="filter-error",
                   help="filter-error (default): process and measurement noise; output-error: "
                        "no process noise (deterministic state path)")


def overrides_of(args):
    """The :class:`vsidgen.spec.overrides.Overrides` of parsed fit/diagnose arguments."""
    return parse_overrides(fix=args.fix, free=args.free, init=args.init,
                           init_from=args.init_from, method=args.method)


__all__ = ["Method", "Overrides", "add_override_arguments", "apply_overrides", "override_spec_text",
           "overrides_of", "parse_overrides", "read_estimates"]


def write_override_spec(spec_path, ov: Overrides, out_dir) -> pathlib.Path:
    """Write ``out_dir/overrides.yaml`` (:func:`override_spec_text`) and return its path.

    ``vsidgen diagnose`` fits this spec instead of ``spec_path``, so the base fit
    and every candidate (which ``extends`` the base) carry the overrides.
    """
    from ..atomic import write_text_atomic
    from .symbolic import compile_spec

    sym = compile_spec(spec_path)
    apply_overrides(sym, ov)  # unknown names and bounds fail here, before any fit
    out = pathlib.Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    path = out / "overrides.yaml"
    write_text_atomic(path, override_spec_text(spec_path, ov, name=f"{sym.name}_cli"[:60], model=sym))
    return path
