"""Flight conditions the physical candidates need and a short-period spec may not carry:
the trim airspeed, the gravity acceleration and the sensor positions of the aircraft.

Each value comes with its source, in this order of preference:

* **airspeed** ``V₀`` (m/s): the model's own airspeed (a state named like V/VT/TAS, or a
  constant named like Vo/V0/U0/Vtrim; then no number is needed), else the mean of the
  record's true-airspeed column (the column the spec maps to an airspeed channel, else a
  column named ``v_mps``/``vtas_mps``/``tas_mps``/``vt_mps`` of the estimation records),
  else a trim airspeed given in the aircraft's constants file (``Vo_ftps``/``Vo_mps``);
* **gravity** ``g`` (m/s²): a spec constant named g/g0, else the constants file's
  ``gravity`` section (SIDPAC's 32.174 ft/s²), else standard gravity 9.80665;
* **sensor positions** (m, body axes from the CG): ``*_wrt_cg_m`` entries of the constants
  file (ATTAS: the noseboom carrying the flow vanes, the accelerometer package).

The aircraft constants file is found next to the estimation record: the
``*.constants.yaml`` of that folder whose ``data_files`` list names the record, or whose
text names it (the Twin Otter file lists its records per record), or whose stem is the
first ``_``-separated word of the record's name. The file is read with ``yaml.safe_load``;
nothing in it is evaluated.
"""

from __future__ import annotations

import dataclasses
import math
import pathlib
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import yaml

FT = 0.3048
STANDARD_GRAVITY = 9.80665

_SPEED_COLUMNS = ("v_mps", "vtas_mps", "tas_mps", "vt_mps", "v_tas_mps", "airspeed_mps")
_G_CONSTANTS = ("g", "g0", "gravity")


@dataclasses.dataclass(frozen=True)
class Sourced:
    """A number with the plain-words source it was taken from."""

    value: float
    source: str

    def to_json(self) -> dict:
        return {"value": float(self.value), "source": self.source}


@dataclasses.dataclass(frozen=True)
class FlightConditions:
    """What the record and the aircraft constants say about the flight condition.

    ``airspeed`` is None when the model carries its own (``speed_name`` then names it) or
    when nothing gives one; ``sensors`` maps a sensor name of the constants file
    (``noseboom``, ``accelerometer``) to its (x, y, z) position from the CG in metres.
    """

    airspeed: Sourced | None = None
    gravity: Sourced = Sourced(STANDARD_GRAVITY, "standard gravity")
    aircraft: str | None = None
    constants_file: pathlib.Path | None = None
    sensors: Mapping[str, tuple[float, float, float]] = dataclasses.field(default_factory=dict)


def constants_file_for(record_path) -> pathlib.Path | None:
    """The aircraft constants file of a record (see the module docstring), or None."""
    if record_path is None:
        return None
    rp = pathlib.Path(record_path)
    folder = rp.parent
    try:
        files = sorted(folder.glob("*.constants.yaml"))
    except OSError:
        return None
    by_text = None
    for f in files:
        doc = _load(f)
        if doc is None:
            continue
        if rp.name in (doc.get("data_files") or ()):
            return f
        if by_text is None:
            try:
                if rp.name in f.read_text(encoding="utf-8"):
                    by_text = f
            except OSError:
                pass
    if by_text is not None:
        return by_text
    stem = rp.stem.split("_", 1)[0]
    for f in files:
        if f.name.split(".", 1)[0] == stem:
            return f
    return None


def _load(path: pathlib.Path) -> dict | None:
    try:
        doc = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (OSError, yaml.YAMLError, UnicodeDecodeError):
        return None
    return doc if isinstance(doc, dict) else None


def _walk(doc, key_pred, path=()):
    """(path, value) of every mapping entry whose key satisfies ``key_pred``."""
    if isinstance(doc, Mapping):
        for k, v in doc.items():
            if isinstance(k, str) and key_pred(k):
                yield path + (k,), v
            yield from _walk(v, key_pred, path + (str(k),))


def _number(v) -> float | None:
    if isinstance(v, bool):
        return None
    if isinstance(v, (int, float)) and math.isfinite(float(v)):
        return float(v)
    return None


def sensors_of(doc: Mapping) -> dict[str, tuple[float, float, float]]:
    """``{name: (x, y, z)}`` of every ``<name>_wrt_cg_m: {x, y, z}`` entry (metres)."""
    out = {}
    for path, v in _walk(doc, lambda k: k.endswith("_wrt_cg_m")):
        if isinstance(v, Mapping):
            xyz = tuple(_number(v.get(a)) for a in ("x", "y", "z"))
            if all(c is not None for c in xyz):
                out[path[-1][: -len("_wrt_cg_m")]] = xyz
    return out


def _gravity_of(doc: Mapping, fname: str) -> Sourced | None:
    for path, v in _walk(doc, lambda k: k.lower().startswith(("g_", "sidpac_g"))
                         or k.lower() in ("g", "gravity_mps2")):
        x = _number(v)
        if x is None:
            continue
        key = path[-1].lower()
        if key.endswith("ftps2"):
            return Sourced(x * FT, f"{fname}: {'.'.join(path)} = {x:g} ft/s²")
        if key.endswith("mps2") or key == "g":
            return Sourced(x, f"{fname}: {'.'.join(path)}")
    return None


def _speed_of(doc: Mapping, fname: str, record: str | None) -> Sourced | None:
    """A trim airspeed of the constants file: ``Vo_mps``/``Vo_ftps``-like keys, preferring an
    entry whose section names the record."""
    found = []
    for path, v in _walk(doc, lambda k: k.lower().startswith(("vo_", "v0_", "vtrim_"))):
        x = _number(v)
        if x is None:
            continue
        key = path[-1].lower()
        val = x * FT if key.endswith("ftps") else x if key.endswith("mps") else None
        if val is None:
            continue
        section = doc
        for p in path[:-1]:
            section = section.get(p, {}) if isinstance(section, Mapping) else {}
        names_record = record is not None and record in yaml.safe_dump(section)
        found.append((not names_record, Sourced(val, f"{fname}: {'.'.join(path)} = {x:g}")))
    if not found:
        return None
    found.sort(key=lambda t: t[0])
    return found[0][1]


def _column(path: pathlib.Path, names: Sequence[str]) -> tuple[str, np.ndarray] | None:
    """(name, values) of the first of ``names`` that is a column of the CSV file, else None.
    Unreadable files and non-numeric cells give None (the airspeed is then looked up
    elsewhere; the record itself is checked where it is loaded)."""
    import csv

    try:
        with open(path, newline="", encoding="utf-8-sig") as fh:
            header = next(csv.reader(fh), [])
            header = [h.strip() for h in header]
            col = next((c for c in names if c in header), None)
            if col is None:
                return None
            j = header.index(col)
            vals = []
            for row in csv.reader(fh):
                if len(row) > j and row[j].strip():
                    vals.append(float(row[j]))
    except (OSError, UnicodeDecodeError, ValueError, csv.Error):
        return None
    return col, np.asarray(vals, float)


def record_airspeed(records: Sequence[Any], *, mapped_column: str | None = None) -> Sourced | None:
    """Mean true airspeed over the records' airspeed column (m/s), or None."""
    vals, names, col_used = [], [], None
    cols = ([mapped_column] if mapped_column else []) + list(_SPEED_COLUMNS)
    for r in records:
        path = getattr(r, "path", None)
        if path is None or pathlib.Path(path).suffix.lower() != ".csv":
            continue
        got = _column(pathlib.Path(path), cols)
        if got is None:
            continue
        col, v = got
        v = v[np.isfinite(v)]
        if v.size:
            vals.append(v)
            names.append(pathlib.Path(path).name)
            col_used = col
    if not vals:
        return None
    v = np.concatenate(vals)
    if not (np.mean(v) > 0):
        return None
    return Sourced(float(np.mean(v)), f"mean of column {col_used} of {', '.join(names)} "
                                      f"({float(np.min(v)):.1f}–{float(np.max(v)):.1f} m/s)")


def flight_conditions(records: Sequence[Any] = (), *, spec_constants: Mapping[str, float] = {},
                      own_speed: str | None = None) -> FlightConditions:
    """Collect :class:`FlightConditions` for a model and its estimation records.

    ``spec_constants`` are the spec's constant values (to take ``g`` from), ``own_speed`` the
    name of the model's own airspeed state/constant when it has one (then no airspeed
    number is looked up).
    """
    path = next((getattr(r, "path", None) for r in records if getattr(r, "path", None)), None)
    cfile = constants_file_for(path)
    doc = _load(cfile) if cfile is not None else None
    fname = cfile.name if cfile is not None else ""
    gravity = None
    for k, v in spec_constants.items():
        if k.lower() in _G_CONSTANTS and _number(v) is not None:
            gravity = Sourced(float(v), f"spec constant {k}")
            break
    if gravity is None and doc is not None:
        gravity = _gravity_of(doc, fname)
    airspeed = None
    if own_speed is None:
        airspeed = record_airspeed(records)
        if airspeed is None and doc is not None:
            airspeed = _speed_of(doc, fname, pathlib.Path(path).name if path else None)
    return FlightConditions(
        airspeed=airspeed, gravity=gravity or Sourced(STANDARD_GRAVITY, "standard gravity"),
        aircraft=(str(doc.get("aircraft")) if doc and doc.get("aircraft") else None),
        constants_file=cfile, sensors=sensors_of(doc) if doc else {})


def flight_conditions_of(info, records: Sequence[Any] = ()) -> FlightConditions:
    """:func:`flight_conditions` for the model summarised by ``info`` (a
    :class:`~.base.ModelInfo`) and its estimation records."""
    from .catalogue import airspeed_name

    return flight_conditions(records, spec_constants=info.constant_values,
                             own_speed=airspeed_name(info))


__all__ = ["FlightConditions", "Sourced", "constants_file_for", "flight_conditions",
           "flight_conditions_of",
           "record_airspeed", "sensors_of"]
