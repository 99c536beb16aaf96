"""Spec files: YAML with positions, duplicate-key detection and ``extends`` merging.

:func:`load_spec` reads a spec (and the specs it ``extends``) into a
:class:`RawSpec`: an ordered tree of :class:`YNode` that remembers the file,
line and column of every key and value, so that later validation errors point
into the file that contains the offending text. No model semantics here:
:mod:`vsidgen.spec.typed` reads the merged tree once into the typed spec that
:mod:`vsidgen.spec.symbolic` compiles.

Merge rules for ``extends`` (child onto parent): entries of ``states``,
``inputs``, ``outputs``, ``constants``, ``parameters``, ``definitions``,
``drift``, ``observations`` with new names are appended, existing names are
replaced in place (a definition keeps its position), except that a
declaration (state, input, output, constant, parameter) given as a mapping in
both files is merged field by field — ``Lp: {bounds: [-5, 0]}`` in a child
keeps the parent's unit, description and initial value (write ``fixed: false``
to free a parameter the parent fixes); ``add_terms`` of parent
and child are all applied (parent first); ``noise`` and ``data`` mappings are
merged key by key (recursively); ``name``, ``description`` and ``integrator``
come from the child when given.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import re
import pathlib
import stat
from typing import Any

import yaml

from ..errors import SpecError
from .expr import did_you_mean, parse_expression, parse_expression_free

TOP_LEVEL_KEYS = ("name", "description", "extends", "integrator", "states", "inputs", "outputs",
                  "constants", "parameters", "definitions", "drift", "observations", "add_terms",
                  "noise", "data")
NAMED_SECTIONS = ("states", "inputs", "outputs", "constants", "parameters", "definitions",
                  "drift", "observations")
MERGED_SECTIONS = ("noise", "data")
FIELD_MERGED_SECTIONS = ("states", "inputs", "outputs", "constants", "parameters")
ADD_TERM_SECTIONS = ("definitions", "drift", "observations")

#: largest spec file read (bytes); the shipped specs are 1-4 KiB
MAX_SPEC_BYTES = 1 << 20
#: most YAML values one spec file may expand to, aliases (``*name``) counted at every use
MAX_YAML_NODES = 100_000
#: file name endings an ``extends`` target must have
SPEC_SUFFIXES = (".yaml", ".yml")
#: most specs in one ``extends`` chain (the spec named on the command line counts as one);
#: the shipped specs use one or two levels
MAX_EXTENDS_DEPTH = 32

_ENTRY_WORD = {
    "drift": "equation for state", "observations": "equation for output",
    "definitions": "definition", "parameters": "parameter", "constants": "constant",
    "states": "state", "inputs": "input", "outputs": "output",
}


#: a decimal number with an exponent, as YAML 1.2 reads it (``1e-3``, ``-2.5E+4``, ``.5e1``)
_EXP_NUMBER = re.compile(r"[+-]?(?:\d+\.?\d*|\.\d+)[eE][+-]?\d+")
#: a number as a reader writes it: decimal digits (underscores between them), a point, an
#: exponent; not YAML 1.1's base-60 (`1:30`), octal (`010`), hex or binary forms
_DECIMAL = re.compile(r"[+-]?(?:0|[1-9][\d_]*|(?:0|[1-9][\d_]*)?\.\d[\d_]*|(?:0|[1-9][\d_]*)\.)"
                      r"(?:[eE][+-]?\d+)?|[+-]?0\d*\.\d*(?:[eE][+-]?\d+)?")
_INF_NAN = {".inf", "+.inf", "-.inf", ".nan"}


class SourceText(str):
    """The text of one spec file, split into lines once.

    Every :class:`YNode` of a file shares one ``SourceText``; error messages and
    :class:`~vsidgen.spec.typed.Located` show a node's source line, and splitting the
    whole file for each of its (up to :data:`MAX_YAML_NODES`) nodes made reading a spec
    quadratic in its size. :meth:`splitlines` (without ``keepends``) returns the cached
    lines as a tuple (read-only, as it is shared); :meth:`line` is one 1-based line.
    """

    def splitlines(self, keepends: bool = False):  # type: ignore[override]
        if keepends:
            return str.splitlines(self, True)
        lines = self.__dict__.get("_lines")
        if lines is None:
            lines = self.__dict__["_lines"] = tuple(str.splitlines(self))
        return lines

    def line(self, number: int | None) -> str:
        """Line ``number`` (1-based) stripped of surrounding blanks; "" when out of range."""
        lines = self.splitlines()
        if number is not None and 1 <= number <= len(lines):
            return lines[number - 1].strip()
        return ""


def source_text(src: str) -> SourceText:
    """``src`` as a :class:`SourceText` (itself when it already is one)."""
    return src if isinstance(src, SourceText) else SourceText(src)


@dataclasses.dataclass(eq=False)
class YNode:
    """A YAML value with its location.

    ``value``: dict[str, YNode] (ordered) for mappings, list[YNode] for
    sequences, the constructed Python value for scalars. ``text``: the scalar
    as written (after YAML unquoting), used for expressions and names.
    ``line``/``column``: 1-based position of the value; ``key_line``/
    ``key_column``: position of its key when it is a mapping entry.
    """

    kind: str  # "map" | "seq" | "scalar"
    value: Any
    path: pathlib.Path
    line: int
    column: int
    text: str | None = None
    style: str | None = None
    key_line: int | None = None
    key_column: int | None = None
    src: str = dataclasses.field(default="", repr=False)
    start_index: int = 0
    end_index: int = 0

    # -- locations --------------------------------------------------------
    @property
    def key_loc(self) -> dict:
        return {"path": self.path, "line": self.key_line or self.line,
                "column": self.key_column or self.column}

    @property
    def loc(self) -> dict:
        return {"path": self.path, "line": self.line, "column": self.column}

    def source_line(self) -> str:
        return _line_text(self.src, self.line)

    def line_text(self, line: int | None) -> str:
        """Line ``line`` (1-based) of this node's file, stripped; "" when out of range."""
        return _line_text(self.src, line)

    def locate(self, offset: int) -> tuple[int, int | None]:
        """File (line, column) of character ``offset`` of :attr:`text` (best effort)."""
        text = self.text or ""
        try:
            if self.style in (None, "'", '"'):
                raw = self.src[self.start_index:self.end_index]
                shift = 0
                if self.style:
                    raw = raw[1:-1]
                    shift = 1
                segs = []
                for i, piece in enumerate(raw.split("\n")):
                    if i == 0:
                        segs.append((self.line, self.column + shift, piece.rstrip()))
                    else:
                        lead = len(piece) - len(piece.lstrip())
                        segs.append((self.line + i, lead + 1, piece.strip()))
                segs = [s for s in segs if s[2] or s is segs[0]]
                if " ".join(s[2] for s in segs) == text:
                    pos = 0
                    for ln, col, piece in segs:
                        if offset <= pos + len(piece):
                            return ln, col + (offset - pos)
                        pos += len(piece) + 1
                return self.line, (self.column + shift if offset == 0 else None)
            if self.style == "|":
                before = text[:offset]
                index = before.count("\n")
                col_in = len(before) - (before.rfind("\n") + 1)
                file_lines = source_text(self.src).splitlines()
                ln = self.line + 1 + index
                first = next((file_lines[i] for i in range(self.line, len(file_lines))
                              if file_lines[i].strip()), None)
                if 1 <= ln <= len(file_lines) and first is not None:
                    indent = len(first) - len(first.lstrip())  # block indentation
                    return ln, indent + 1 + col_in
                return ln, None
        except Exception:  # pragma: no cover - locating must never fail
            pass
        return self.line + (1 if self.style in ("|", ">") else 0), None

    # -- typed accessors -------------------------------------------------
    def expect_map(self, what: str) -> dict:
        if self.kind == "scalar" and self.value is None:
            return {}
        if self.kind != "map":
            raise SpecError(f"{what} must be a mapping (name: value), got {self.describe()}",
                            **self.loc, text=self.source_line())
        return self.value

    def describe(self) -> str:
        if self.kind == "map":
            return "a mapping"
        if self.kind == "seq":
            return "a list"
        if self.value is None:
            return "nothing (null)"
        return f"{type(self.value).__name__} `{self.text}`"

    def number(self, what: str, *, allow_none: bool = False) -> float | None:
        v = self.value if self.kind == "scalar" else self
        if self.kind == "scalar" and v is None and allow_none:
            return None
        if self.kind == "scalar" and isinstance(v, str) and _EXP_NUMBER.fullmatch(v.strip()):
            # YAML 1.1 (PyYAML) reads `1e-3` and `1e5` as text (its floats need a dot); they
            # are numbers in YAML 1.2 and to every reader of a spec
            v = float(v.strip())
        if self.kind != "scalar" or isinstance(v, bool) or not isinstance(v, (int, float)):
            raise SpecError(f"{what} must be a number, got {self.describe()}", **self.loc,
                            text=self.source_line(),
                            hint="write a plain number such as 0.5 or 1e-3")
        raw = (self.text or "").strip() if self.kind == "scalar" else ""
        if raw and not _DECIMAL.fullmatch(raw) and raw.lower() not in _INF_NAN:
            # YAML 1.1 reads `1:30` as 90 (base 60), `010` as 8 (octal), `0x1F` as 31
            raise SpecError(f"{what} `{raw}` is not a plain decimal number (YAML 1.1 would read "
                            f"it as {v!r})", **self.loc, text=self.source_line(),
                            hint="write a plain decimal number such as 90, 0.5 or 1e-3")
        try:
            f = float(v)
        except OverflowError:
            f = float("inf")
        if f != f or f in (float("inf"), float("-inf")):
            raise SpecError(f"{what} must be a finite number", **self.loc, text=self.source_line())
        if f == 0.0 and raw and re.search(r"[1-9]", re.split(r"[eE]", raw, maxsplit=1)[0]):
            # `initial: 1e-400` became 0 without a word, and a later error said "K = 0"
            # (red team, session 47; the same rule as for literals in equations)
            raise SpecError(f"{what} `{raw}` is too small: it becomes 0 in double precision",
                            **self.loc, text=self.source_line(),
                            hint="write 0, or a number of magnitude at least 1e-300")
        return f

    def boolean(self, what: str) -> bool:
        if self.kind != "scalar" or not isinstance(self.value, bool):
            raise SpecError(f"{what} must be true or false, got {self.describe()}", **self.loc,
                            text=self.source_line())
        return self.value

    def string(self, what: str, *, allow_none: bool = False) -> str | None:
        if self.kind == "scalar" and self.value is None and allow_none:
            return None
        if self.kind != "scalar" or self.value is None or isinstance(self.value, (list, dict)):
            raise SpecError(f"{what} must be a text, got {self.describe()}", **self.loc,
                            text=self.source_line())
        return self.text if self.text is not None else str(self.value)

    def expression(self, namespace, *, free_names: bool = False):
        """Parse this scalar as an expression; errors point at the exact file position."""
        if self.kind != "scalar" or self.value is None or isinstance(self.value, bool):
            raise SpecError(f"expected an expression, got {self.describe()}", **self.loc,
                            text=self.source_line())
        text = self.text
        try:
            if free_names:
                return parse_expression_free(text, namespace, path=self.path, line=1, column=1)
            return parse_expression(text, namespace, path=self.path, line=1, column=1)
        except SpecError as err:
            raise self.relocate(err) from None

    def relocate(self, err: SpecError) -> SpecError:
        offset = (err.column - 1) if err.column is not None else 0
        line, column = self.locate(offset)
        return SpecError(err.message, path=self.path, line=line, column=column, text=err.text,
                         hint=err.hint, span=err.span)


#: keys other tools use for a parameter's limits (vsidgen: ``bounds: [lower, upper]``)
_BOUND_KEYS = frozenset({"min", "max", "lower", "upper", "lb", "ub", "lo", "hi", "minimum",
                         "maximum", "low", "high", "limits", "range"})


def keys_check(node: YNode, allowed, what: str) -> dict:
    """The mapping of ``node``; unknown keys raise SpecError with a did-you-mean hint."""
    mapping = node.expect_map(what)
    for key, child in mapping.items():
        if key not in allowed:
            hint = did_you_mean(key, allowed) or ("allowed keys: " + ", ".join(allowed))
            if "bounds" in allowed and str(key).lower() in _BOUND_KEYS:
                hint = "a parameter's limits are one key: `bounds: [lower, upper]`"
            if (child.kind == "scalar" and child.value is None) \
                    or not re.fullmatch(r"[A-Za-z_][\w-]*", str(key)):
                # `{description: roll rate, measured}`: in a {...} mapping a comma ends the
                # value, and the rest becomes a key without a value (or one with spaces)
                hint = ("a comma inside an unquoted value in `{...}` starts a new entry: put "
                        "the value in quotes, e.g. `description: \"... , ...\"`; " + hint)
            raise SpecError(f"unknown key `{key}` in {what}", **child.key_loc,
                            text=_line_text(child.src, child.key_line),
                            hint=hint)
    return mapping


def _line_text(src: str, line: int | None) -> str:
    return source_text(src).line(line)


# ---------------------------------------------------------------------------
# YAML with positions
# ---------------------------------------------------------------------------

class _Constructor(yaml.constructor.SafeConstructor):
    pass


class _Budget:
    """Counts the YAML values built from one file (an alias counts at every use)."""

    def __init__(self, limit: int):
        self.left = limit

    def take(self, node, path) -> None:
        self.left -= 1
        if self.left < 0:
            raise SpecError(f"the spec expands to more than {MAX_YAML_NODES} YAML values",
                            path=path, line=node.start_mark.line + 1,
                            column=node.start_mark.column + 1,
                            hint="YAML aliases (*name) repeat their anchor's content at every "
                                 "use; nested aliases multiply it (an alias bomb)")


_SURROGATE = re.compile("[\ud800-\udfff]")


def _refuse_surrogates(text, node, path, src) -> None:
    """SpecError at a scalar whose text holds a lone surrogate (U+D800-U+DFFF), which a
    double-quoted YAML escape such as "\\ud800" can produce: it is not a character, and
    printing or writing it as UTF-8 failed (`show`, `fit --report`: internal error; session 46)."""
    m = _SURROGATE.search(text) if isinstance(text, str) else None
    if m is None:
        return
    line, col = node.start_mark.line + 1, node.start_mark.column + 1
    raise SpecError(f"text holds U+{ord(m.group()):04X}, a lone surrogate (not a character)",
                    path=path, line=line, column=col, text=_line_text(src, line),
                    hint="remove the \\u escape or write the character itself (YAML takes "
                         "characters beyond U+FFFF as one 8-digit escape, \\U0001F600)")


def _convert(node, path, src, parent_key, constructor, depth=0, budget=None) -> YNode:
    if depth > 50:
        raise SpecError("YAML nesting is too deep", path=path, line=node.start_mark.line + 1,
                        column=node.start_mark.column + 1)
    if budget is None:
        budget = _Budget(MAX_YAML_NODES)
    budget.take(node, path)
    line, col = node.start_mark.line + 1, node.start_mark.column + 1
    if isinstance(node, yaml.MappingNode):
        out: dict[str, YNode] = {}
        for knode, vnode in node.value:
            if not isinstance(knode, yaml.ScalarNode):
                raise SpecError("mapping keys must be plain names", path=path,
                                line=knode.start_mark.line + 1, column=knode.start_mark.column + 1,
                                text=_line_text(src, knode.start_mark.line + 1))
            key = knode.value
            _refuse_surrogates(key, knode, path, src)
            if knode.tag == "tag:yaml.org,2002:merge":
                raise SpecError("YAML merge keys (<<) are not supported", path=path,
                                line=knode.start_mark.line + 1, column=knode.start_mark.column + 1)
            if key in out:
                word = _ENTRY_WORD.get(parent_key)
                msg = (f"duplicate {word} `{key}`" if word else
                       (f"duplicate top-level key `{key}`" if parent_key is None else
                        f"duplicate key `{key}`"))
                first = out[key]
                raise SpecError(msg, path=path, line=knode.start_mark.line + 1,
                                column=knode.start_mark.column + 1,
                                text=_line_text(src, knode.start_mark.line + 1),
                                hint=f"`{key}` is already given on line {first.key_line}; "
                                     f"YAML would silently keep only the last one")
            child = _convert(vnode, path, src, key, constructor, depth + 1, budget)
            child.key_line = knode.start_mark.line + 1
            child.key_column = knode.start_mark.column + 1
            out[key] = child
        return YNode("map", out, path, line, col, src=src, start_index=node.start_mark.index,
                     end_index=node.end_mark.index)
    if isinstance(node, yaml.SequenceNode):
        items = [_convert(v, path, src, parent_key, constructor, depth + 1, budget)
                 for v in node.value]
        return YNode("seq", items, path, line, col, src=src, start_index=node.start_mark.index,
                     end_index=node.end_mark.index)
    if parent_key != "extends":   # a path: file names that are not UTF-8 arrive as
        _refuse_surrogates(node.value, node, path, src)   # surrogates (diagnose writes them)
    try:
        value = constructor.construct_object(node, deep=True)
    except yaml.YAMLError as exc:
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise SpecError(f"invalid YAML value: {problem}", path=path, line=line, column=col,
                        text=_line_text(src, line),
                        hint="vsidgen reads plain YAML: no language-specific tags") from None
    except Exception:
        value = node.value
    if not isinstance(value, (str, int, float, bool, type(None))):
        value = node.value  # dates, binary...: keep the text
    return YNode("scalar", value, path, line, col, text=node.value, style=node.style, src=src,
                 start_index=node.start_mark.index, end_index=node.end_mark.index)


def read_spec_text(path, *, where: dict | None = None) -> str:
    """The text of a spec file, refusing anything that is not a small regular file.

    The file is opened non-blocking (a FIFO cannot hang the open), checked with
    ``fstat`` on the open descriptor (a regular file, at most :data:`MAX_SPEC_BYTES`)
    and read to at most that many bytes; so ``/dev/zero``, FIFOs, sockets, directories
    and huge files are refused before their content is read. ``where``: the location
    to report (the ``extends`` line) instead of the file itself.
    """
    path = pathlib.Path(path)
    loc = where if where is not None else {"path": path}
    what = "`extends` target" if where is not None else "spec file"
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    except FileNotFoundError:
        raise SpecError(f"{what} not found", **loc,
                        hint="check the path (relative paths are relative to the current "
                             "directory, or to the extending spec for `extends`)") from None
    except IsADirectoryError:
        raise SpecError(f"{what} is a directory, not a file", **loc) from None
    except OSError as exc:
        raise SpecError(f"cannot open {what}: {exc.strerror}", **loc) from None
    try:
        info = os.fstat(fd)
        if stat.S_ISDIR(info.st_mode):
            raise SpecError(f"{what} is a directory, not a file", **loc)
        if not stat.S_ISREG(info.st_mode):
            raise SpecError(f"{what} is not a regular file (a device, FIFO or socket)", **loc,
                            hint="a spec is a YAML text file")
        if info.st_size > MAX_SPEC_BYTES:
            raise SpecError(f"{what} is too large ({info.st_size} bytes; at most "
                            f"{MAX_SPEC_BYTES} bytes)", **loc)
        with os.fdopen(fd, "rb", closefd=True) as fh:
            fd = -1
            data = fh.read(MAX_SPEC_BYTES + 1)
    except OSError as exc:
        raise SpecError(f"cannot read {what}: {exc.strerror}", **loc) from None
    finally:
        if fd >= 0:
            os.close(fd)
    if len(data) > MAX_SPEC_BYTES:
        raise SpecError(f"{what} is too large (more than {MAX_SPEC_BYTES} bytes)", **loc)
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise SpecError(f"{what} is not UTF-8 text ({exc.reason} at byte {exc.start})",
                        **loc) from None


#: characters YAML refuses (controls other than tab and line ends) and the line breaks it
#: counts but editors and `\n` do not (NEL, U+2028, U+2029): an ESC byte gave "YAML error …
#: position 1415" with no line, and three U+2028 in a description moved every later error
#: three lines down (session 44, red team)
#: and the bidirectional controls (U+202A-U+202E, U+2066-U+2069), which make a comment look
#: like part of the equation in an editor ("Trojan Source"; refused in expressions already,
#: accepted in comments: red team, session 47)
_BIDI = "\u202a-\u202e\u2066-\u2069"
_UNSAFE = re.compile("[\x85\u2028\u2029" + _BIDI + "]|[^\x09\x0a\x0d\x20-\x7e\xa0-\ud7ff"
                     "\ue000-\ufffd\U00010000-\U0010ffff]")
_BREAK = re.compile("\r\n|\r|\n")


def _refuse_unsafe_characters(src: str, path) -> None:
    """SpecError at the first character of ``src`` that YAML refuses or counts as a line
    break where a text editor does not, located by the file's own line ends."""
    m = _UNSAFE.search(src)
    if m is None:
        return
    import unicodedata

    ch, pos = m.group(), m.start()
    breaks = list(_BREAK.finditer(src, 0, pos))
    line = len(breaks) + 1
    col = pos - (breaks[-1].end() if breaks else 0) + 1
    what = unicodedata.name(ch, "a control character")
    raise SpecError(f"character U+{ord(ch):04X} ({what}) in the spec", path=path, line=line,
                    column=col, text=_BREAK.split(src[pos - col + 1:pos + 80], 1)[0],
                    hint=("YAML counts it as a line break; remove it (often pasted from a word "
                          "processor)" if ch in "\x85\u2028\u2029" else
                          "remove it: it reorders how an editor shows the text after it, so the "
                          "file would not read as it is parsed" if re.match(f"[{_BIDI}]", ch)
                          else "remove it: a spec is plain text (tabs and line ends only)"))


def load_yaml(path) -> YNode:
    """Read one YAML file into a :class:`YNode` tree (SpecError on any problem)."""
    path = pathlib.Path(path)
    src = SourceText(read_spec_text(path))
    if "\x00" in src:
        raise SpecError("spec file contains a NUL character", path=path,
                        line=src[:src.index("\x00")].count("\n") + 1)
    _refuse_unsafe_characters(src, path)
    try:
        node = yaml.compose(src, Loader=yaml.SafeLoader)
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        line = mark.line + 1 if mark else None
        col = mark.column + 1 if mark else None
        raise SpecError(f"YAML syntax error: {exc.problem or exc.context}", path=path, line=line,
                        column=col, text=_line_text(src, line),
                        hint=("YAML needs `key: value` with consistent indentation; quote "
                              "expressions that start with special characters")) from None
    except yaml.YAMLError as exc:
        raise SpecError(f"YAML error: {exc}", path=path) from None
    except RecursionError:
        raise SpecError("YAML nesting is too deep", path=path, line=1, column=1) from None
    if node is None:
        raise SpecError("spec file is empty", path=path, line=1, column=1,
                        hint="a spec needs at least name, states, drift")
    root = _convert(node, path, src, None, _Constructor())
    if root.kind != "map":
        raise SpecError("a spec must be a YAML mapping (key: value) at the top level",
                        **root.loc, text=root.source_line())
    return root


# ---------------------------------------------------------------------------
# extends + merge
# ---------------------------------------------------------------------------

@dataclasses.dataclass
class AddTerm:
    """One ``add_terms`` entry: add ``node`` (an expression) to ``section[name]``."""

    section: str
    name: str
    node: YNode


@dataclasses.dataclass
class RawSpec:
    """A merged spec: top-level key -> YNode, plus the add_terms in application order."""

    path: pathlib.Path
    top: dict[str, YNode]
    add_terms: list[AddTerm]
    files: tuple[pathlib.Path, ...]

    def section(self, key: str) -> dict[str, YNode]:
        node = self.top.get(key)
        if node is None:
            return {}
        return node.expect_map(f"`{key}`")

    def canonical(self) -> str:
        """Canonical JSON of the merged content (file positions excluded)."""
        content = [[k, _plain(self.top[k])] for k in TOP_LEVEL_KEYS
                   if k in self.top and k not in ("extends", "add_terms")]
        content.append(["add_terms", [[a.section, a.name, _plain(a.node)] for a in self.add_terms]])
        return json.dumps(content, separators=(",", ":"), ensure_ascii=True)

    def hash(self, generator_version: str) -> str:
        h = hashlib.sha256()
        h.update(self.canonical().encode())
        h.update(b"\0" + generator_version.encode())
        return h.hexdigest()


def _plain(node: YNode):
    if node.kind == "map":
        return [[k, _plain(v)] for k, v in node.value.items()]
    if node.kind == "seq":
        return [_plain(v) for v in node.value]
    v = node.value
    if isinstance(v, float) and (v != v or v in (float("inf"), float("-inf"))):
        return repr(v)
    return v


def _merge_maps(parent: YNode, child: YNode, *, recursive: bool) -> YNode:
    if parent.kind != "map" or child.kind != "map":
        return child
    merged = dict(parent.value)
    for key, value in child.value.items():
        if recursive and key in merged and merged[key].kind == "map" and value.kind == "map":
            merged[key] = _merge_maps(merged[key], value, recursive=True)
        else:
            merged[key] = value
    return dataclasses.replace(child, value=merged)


def _merge_entries(parent: YNode, child: YNode) -> YNode:
    """Named entries of a declaration section: an entry given as a mapping in both files
    is merged field by field (the child's fields win), anything else is replaced."""
    if parent.kind != "map" or child.kind != "map":
        return child
    merged = dict(parent.value)
    for key, value in child.value.items():
        old = merged.get(key)
        if old is not None and old.kind == "map" and value.kind == "map":
            merged[key] = _merge_maps(old, value, recursive=False)
        else:
            merged[key] = value
    return dataclasses.replace(child, value=merged)


def _collect_add_terms(root: YNode) -> list[AddTerm]:
    node = root.value.get("add_terms")
    if node is None:
        return []
    out = []
    for section, sub in keys_check(node, ADD_TERM_SECTIONS, "`add_terms`").items():
        for name, expr in sub.expect_map(f"`add_terms.{section}`").items():
            out.append(AddTerm(section, name, expr))
    return out


def _extends_target(ext: YNode, path: pathlib.Path) -> pathlib.Path:
    """The file an ``extends`` value names, checked before anything is read from it.

    Allowed: a path (relative to the extending spec's folder, or absolute) to a regular
    file whose name -- and, through symbolic links, whose target's name -- ends in
    ``.yaml`` or ``.yml``, of at most :data:`MAX_SPEC_BYTES` bytes. Errors point at the
    ``extends`` line and never show the target's content.
    """
    target = ext.string("`extends`")
    shown = repr(target)[1:-1]
    if len(shown) > 200:
        shown = shown[:200] + "..."
    hint = (f"`extends` names a YAML spec (.yaml or .yml), relative to "
            f"{path.parent.as_posix() or '.'} or absolute")
    if not target.strip() or "\x00" in target:
        raise SpecError("`extends` must name a spec file", **ext.loc, text=ext.source_line(),
                        hint=hint)
    ppath = path.parent / target
    if not target.lower().endswith(SPEC_SUFFIXES):
        raise SpecError(f"`extends`: `{shown}` is not a YAML spec file", **ext.loc,
                        text=ext.source_line(), hint=hint)
    try:
        real = ppath.resolve()
        exists = ppath.exists()
    except (OSError, RuntimeError, ValueError):
        raise SpecError(f"`extends`: cannot resolve `{shown}`", **ext.loc,
                        text=ext.source_line(), hint=hint) from None
    if not exists:
        raise SpecError(f"`extends`: file `{shown}` not found", **ext.loc,
                        text=ext.source_line(), hint=hint)
    if not real.name.lower().endswith(SPEC_SUFFIXES):
        raise SpecError(f"`extends`: `{shown}` links to a file that is not a YAML spec "
                        f"(.yaml/.yml)", **ext.loc, text=ext.source_line(), hint=hint)
    try:
        info = real.stat()
    except OSError as exc:
        raise SpecError(f"`extends`: cannot read `{shown}`: {exc.strerror}", **ext.loc,
                        text=ext.source_line(), hint=hint) from None
    if not stat.S_ISREG(info.st_mode):
        raise SpecError(f"`extends`: `{shown}` is not a regular file", **ext.loc,
                        text=ext.source_line(), hint=hint)
    if info.st_size > MAX_SPEC_BYTES:
        raise SpecError(f"`extends`: `{shown}` is too large ({info.st_size} bytes; at most "
                        f"{MAX_SPEC_BYTES})", **ext.loc, text=ext.source_line(), hint=hint)
    return ppath


def load_spec(path) -> RawSpec:
    """Load a spec and everything it ``extends``, merged (see module docstring).

    The ``extends`` chain is followed iteratively, child to parent, and refused with a
    SpecError at the ``extends`` line that closes a cycle or that would make the chain
    longer than :data:`MAX_EXTENDS_DEPTH` specs; the specs are then merged from the
    chain's root down to the file named here.
    """
    path = pathlib.Path(path)
    chain: list[tuple[pathlib.Path, YNode, dict]] = []  # (path, root, top), child first
    seen: list[pathlib.Path] = []
    current = path
    while True:
        seen.append(current.resolve())
        root = load_yaml(current)
        top = keys_check(root, TOP_LEVEL_KEYS, "the spec (top level)")
        chain.append((current, root, top))
        ext = top.get("extends")
        if ext is None:
            break
        ppath = _extends_target(ext, current)
        resolved = ppath.resolve()
        if resolved in seen:
            names = " -> ".join(p.name for p in seen + [resolved])
            raise SpecError(f"`extends` cycle: {names}", **ext.loc, text=ext.source_line(),
                            hint="a spec cannot extend itself, directly or indirectly")
        if len(chain) >= MAX_EXTENDS_DEPTH:
            shown = [p.name for p, _, _ in chain[:2]] + ["..."] + \
                [p.name for p, _, _ in chain[-2:]] + [ppath.name]
            raise SpecError(f"`extends` chain is longer than {MAX_EXTENDS_DEPTH} specs: "
                            + " -> ".join(shown), **ext.loc, text=ext.source_line(),
                            hint=f"a spec can build on at most {MAX_EXTENDS_DEPTH - 1} others "
                                 f"through `extends`; merge some of the intermediate specs "
                                 f"into one file")
        current = ppath

    raw: RawSpec | None = None
    for current, root, top in reversed(chain):
        raw = _merge_spec(raw, current, root, top)
    assert raw is not None
    return raw


def _merge_spec(parent: RawSpec | None, path: pathlib.Path, root: YNode, top: dict) -> RawSpec:
    """The spec of ``path`` (``root``, its top-level mapping ``top``) merged onto ``parent``."""
    add_terms = _collect_add_terms(root)
    if parent is None:
        return RawSpec(path, dict(top), add_terms, (path,))
    merged = dict(parent.top)
    for key, node in top.items():
        if key in ("extends", "add_terms"):
            continue
        if key in FIELD_MERGED_SECTIONS and key in merged:
            merged[key] = _merge_entries(merged[key], node)
        elif key in NAMED_SECTIONS and key in merged:
            merged[key] = _merge_maps(merged[key], node, recursive=False)
        elif key in MERGED_SECTIONS and key in merged:
            merged[key] = _merge_maps(merged[key], node, recursive=True)
        else:
            merged[key] = node
    merged.pop("extends", None)
    return RawSpec(path, merged, parent.add_terms + add_terms, parent.files + (path,))


__all__ = ["YNode", "RawSpec", "AddTerm", "load_yaml", "load_spec", "keys_check",
           "read_spec_text", "SourceText", "source_text", "TOP_LEVEL_KEYS", "MAX_SPEC_BYTES",
           "MAX_YAML_NODES", "MAX_EXTENDS_DEPTH", "SPEC_SUFFIXES"]
