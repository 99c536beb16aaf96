"""User-facing errors and warnings.

Every problem the user can fix (a bad spec, a bad data file) is raised as a
:class:`VsidgenError` subclass. The command line prints ``str(error)`` and
exits with a non-zero status; it never shows a traceback for these.
"""

from __future__ import annotations

import dataclasses
import pathlib


class VsidgenError(Exception):
    """Base class of every user-facing vsidgen error."""


#: longest source line shown under an error message (longer lines are cut)
MAX_SHOWN_LINE = 200


def printable(text) -> str:
    """``text`` with every non-printable character (line breaks, terminal escapes, NUL...)
    written as its Python escape sequence, so a message is one harmless line per part."""
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in str(text))


def printable_lines(text) -> str:
    """:func:`printable` of each line of ``text``, the line breaks kept: for a message of
    several lines ("error ...\n  hint: ...") that may quote a record's column names, a data
    file's name or a MAT variable's name, so that no terminal escape in them reaches the
    terminal (red team, session 47)."""
    return "\n".join(printable(line) for line in str(text).split("\n"))


def eprint(text, *, flush: bool = False) -> None:
    """Print a message (error, warning, note, progress) to stderr, one harmless line per line
    (:func:`printable_lines`)."""
    import sys

    print(printable_lines(text), file=sys.stderr, flush=flush)


def _caret_block(text: str | None, column: int | None, length: int | None) -> str:
    if not text:
        return ""
    first = text.splitlines()[0] if text.splitlines() else text
    # one character per character, so the caret column stays right
    first = "".join(c if c.isprintable() else "?" for c in first)
    if len(first) > MAX_SHOWN_LINE:
        first = first[:MAX_SHOWN_LINE] + "..."
        if column is not None and column > MAX_SHOWN_LINE:
            column = None
    out = f"\n    {first}"
    if column is not None and column >= 1:
        n = max(1, length or 1)
        out += "\n    " + " " * (column - 1) + "^" * n
    return out


@dataclasses.dataclass(frozen=True)
class Location:
    """A place in a spec file (1-based line and column)."""

    path: pathlib.Path | str | None = None
    line: int | None = None
    column: int | None = None

    def __str__(self) -> str:
        s = str(self.path) if self.path is not None else "<spec>"
        if self.line is not None:
            s += f":{self.line}"
            if self.column is not None:
                s += f":{self.column}"
        return s


class SpecError(VsidgenError):
    """An error in a model spec, with its location, the offending text and a hint.

    Attributes:
        path, line, column: where the problem is (1-based line/column; may be None).
        message: what is wrong.
        text: the offending source text (one line), shown with a caret marker.
        hint: how to fix it (may be empty).
        span: optional (column, length) inside ``text`` to underline.
    """

    def __init__(self, message: str, *, path=None, line=None, column=None,
                 text: str | None = None, hint: str | None = None,
                 span: tuple[int, int] | None = None):
        self.message = message
        self.path = path
        self.line = line
        self.column = column
        self.text = text
        self.hint = hint or ""
        self.span = span
        super().__init__(self.render())

    @property
    def location(self) -> Location:
        return Location(self.path, self.line, self.column)

    def render(self) -> str:
        out = f"{printable(self.location)}: error: {printable(self.message)}"
        if self.span is not None:
            out += _caret_block(self.text, self.span[0], self.span[1])
        else:
            out += _caret_block(self.text, None, None)
        if self.hint:
            out += f"\n  hint: {printable(self.hint)}"
        return out


@dataclasses.dataclass(frozen=True)
class SpecWarning:
    """A non-fatal finding about a spec (unused symbol, unit inconsistency...)."""

    message: str
    path: pathlib.Path | str | None = None
    line: int | None = None
    column: int | None = None
    text: str | None = None
    hint: str = ""
    code: str = "warning"

    def __str__(self) -> str:
        out = (f"{printable(Location(self.path, self.line, self.column))}: warning: "
               f"{printable(self.message)}")
        out += _caret_block(self.text, None, None)
        if self.hint:
            out += f"\n  hint: {printable(self.hint)}"
        return out


class DataError(VsidgenError):
    """An error in a data record, naming the file, the column and/or the sample."""

    def __init__(self, message: str, *, path=None, column: str | None = None,
                 sample: int | None = None, hint: str | None = None):
        self.message = message
        self.path = path
        self.column = column
        self.sample = sample
        self.hint = hint or ""
        where = str(path) if path is not None else "<data>"
        if column is not None:
            where += f", column '{column}'"
        if sample is not None:
            where += f", sample {sample}"
        text = f"{where}: error: {message}"
        if self.hint:
            text += f"\n  hint: {self.hint}"
        super().__init__(text)


class FitError(VsidgenError):
    """The estimator could not run (not: did not converge, which is a result status)."""
