"""Role-aware "did you mean" suggestions.

A name is compared with candidates of the role it must have first (a
``--fix`` name with the parameters, a missing data column with the columns
that no other channel uses) and only then with names of other roles, which
are named with their role ("`beta` is a state, not a parameter"). Candidates
are ranked by whether they share the first character — typos rarely hit it,
and aircraft notation groups names by it (``L*``, ``M*``, ``C*``) — then by
:class:`difflib.SequenceMatcher` ratio; a candidate that is a prefix of the
name or the name a prefix of it (abbreviations: ``Lb`` for ``Lbeta``) counts as
similar.
"""

from __future__ import annotations

import difflib
import re
from collections.abc import Iterable, Mapping

CUTOFF = 0.6
CUTOFF_SAME_START = 0.55


def _score(name: str, cand: str) -> tuple[int, float] | None:
    ratio = difflib.SequenceMatcher(None, name, cand).ratio()
    same_start = bool(name) and bool(cand) and name[0] == cand[0]
    prefix = min(len(name), len(cand)) >= 2 and (name.startswith(cand) or cand.startswith(name))
    if prefix or ratio >= CUTOFF or (same_start and ratio >= CUTOFF_SAME_START):
        return (int(same_start or prefix), ratio)
    return None


def closest(name: str, candidates: Iterable[str], n: int = 1) -> list[str]:
    """Up to ``n`` candidates similar to ``name``, best first (see the module docstring)."""
    cands = [c for c in dict.fromkeys(candidates) if c != name]
    # a name that differs only in case is the likeliest meaning (`Cl_P` for `Cl_p`, not the
    # equally close `Cl_b`)
    folded = [c for c in cands if c.casefold() == name.casefold()]
    scored = [(s, c) for c in cands if c not in folded
              for s in [_score(name, c)] if s is not None]
    scored.sort(key=lambda sc: (-sc[0][0], -sc[0][1], sc[1]))
    return (folded + [c for _, c in scored])[:n]


def suggest(name: str, same_role: Iterable[str], others: Mapping[str, str] | None = None, *,
            role: str = "name") -> str | None:
    """A hint for an unknown ``name`` that must be a ``role``.

    ``same_role``: candidates of the right role; ``others``: {candidate: its
    role} of names that exist but have another role.
    """
    others = dict(others or {})
    if name in others:
        return f"`{name}` is {others[name]}, not a {role}"
    best = closest(name, same_role)
    if best:
        return f"did you mean `{best[0]}`?"
    best = closest(name, others)
    if best:
        return f"`{best[0]}` is {others[best[0]]}, not a {role}"
    return None


def _same_quantity(name: str, cand: str) -> bool:
    """Whether two column names can name the same quantity: names like ``dr_deg`` are
    ``<quantity>_<unit>``, so a shared unit suffix alone (``p_deg``) is no likeness — the
    leading parts must be alike (or the whole names nearly equal)."""
    a, b = name.split("_", 1)[0], cand.split("_", 1)[0]
    if a == b or difflib.SequenceMatcher(None, name, cand).ratio() >= 0.8:
        return True
    return bool(closest(a, [b])) and len(a) > 2


def column_hint(name: str, header: list[str], taken: Mapping[str, str] | None = None) -> str | None:
    """Role-aware suggestion for a missing column ``name``.

    Columns that the data map already reads for another channel (``taken``:
    {column: "input `da`"}) are not offered as the missing one (a missing
    rudder column ``dr_deg`` must not suggest the aileron's ``da_deg``); when
    only such a column is similar, the hint says whose column it is.
    """
    words = re.findall(r"[A-Za-z_]\w*", name)
    if re.search(r"[-+*/()]", name) and words and all(w in header for w in words):
        return f'to combine columns, write {{expr: "{name}"}}'
    taken = {c: who for c, who in (taken or {}).items() if c != name}
    free = [h for h in header if h not in taken]
    close = [c for c in closest(name, free, n=3) if _same_quantity(name, c)]
    if not close and "_" in name:
        # the same quantity with another unit suffix (`ay_g` missing, `ay_mps2` present):
        # too different for a spelling match, but what the user most likely means
        stem = name.split("_", 1)[0]
        close = [h for h in free if "_" in h and h.split("_", 1)[0] == stem][:3]
        if close:
            return ("did you mean " + " or ".join(f"'{c}'" for c in close) + "? (the same "
                    "quantity in another unit: declare the column's unit, e.g. "
                    f"`{{column: {close[0]}, unit: ...}}`, and it is converted)")
    if close:
        return "did you mean " + " or ".join(f"'{c}'" for c in close) + "?"
    used = [c for c in closest(name, [h for h in header if h in taken], n=1)
            if _same_quantity(name, c) or c[:1] == name[:1]]
    if used:
        return (f"no similar unused column ('{used[0]}' is already the column of "
                f"{taken[used[0]]})")
    return None


def model_roles(model) -> dict[str, str]:
    """{name: "a state" | "an input" | ...} of a Model or SymbolicModel."""
    roles: dict[str, str] = {}
    for attr, what in (("outputs", "an output"), ("inputs", "an input"), ("states", "a state"),
                       ("constants", "a constant"), ("parameters", "a parameter")):
        for v in getattr(model, attr, ()) or ():
            roles[v.name] = what
    return roles


def unknown_name_error(name: str, role: str, model, *, option: str):
    """VsidgenError for an unknown ``role`` name given to ``option`` (role-aware hint)."""
    from .errors import VsidgenError, printable

    attr = {"output": "outputs", "input": "inputs", "state": "states",
            "constant": "constants", "parameter": "parameters"}.get(role)
    # the names of this role from the model itself: a name that is both a state and an output
    # (`alpha`, `q`: most specs) kept only its last role in model_roles, so the outputs read
    # "none" (red team, session 47)
    same = [v.name for v in getattr(model, attr, ()) or ()] if attr else []
    others = {n: r for n, r in model_roles(model).items() if n not in same}
    hint = suggest(name, same, others, role=role)
    listing = ", ".join(same) if same else "none"
    shown = printable(name)   # a name from a results.json may hold terminal escapes
    msg = f"{option} {shown}: unknown {role} `{shown}`"
    return VsidgenError(msg + (f" — {hint}" if hint else "") + f"\n  hint: {role}s: {listing}")


__all__ = ["closest", "column_hint", "model_roles", "suggest", "unknown_name_error"]
