"""HTML report of a fit's results directory.

``write_report(DIR)`` reads ``DIR/results.json`` and the ``signals_<record>.csv``
time histories (format: docs/architecture.md, "Results directory") and writes
one self-contained ``DIR/report.html``: figures are PNG images embedded as
``data:`` URIs, equations are typeset with matplotlib's mathtext (no MathJax,
no CDN), the page loads nothing from the network (a Content-Security-Policy
forbids it). The page is rendered from ``vsidgen/report/templates/report.html.j2``.

Content: run summary and warnings; parameter table with standard errors,
relative standard errors, bounds and reference values; correlation heat map
with strongly correlated pairs; the model equations; estimated noise; for
each record (estimation and validation sections) the four evaluation signals
per output with residuals, the smoother-mean finite difference against the
drift per state, residual diagnostics (autocorrelation with 95 % band,
Ljung-Box whiteness test, Welch spectrum) and fit metrics.

Colours are the same in every figure: measured black, output at the smoother
mean blue, free simulation orange dashed, Kalman-filter prediction green
dotted (see :data:`SIGNAL_STYLE`).
"""

from __future__ import annotations

import base64
import csv
import datetime as _dt
import hashlib
import io
import json
import math
import pathlib
import os
import platform
import re
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np

from ..atomic import write_text_atomic
from ..errors import VsidgenError
from ..limits import check_input_file, parse_json
from .resultsdir import contained_file, read_results

__all__ = ["new_figure", "parse_reference", "png_data_uri", "write_report", "SIGNAL_STYLE",
           "STRONG_CORRELATION"]

#: |r| above which a parameter pair is flagged as strongly correlated.
STRONG_CORRELATION = 0.9

#: Plot style of the four evaluation signals (and the residuals), shared by all figures.
SIGNAL_STYLE: dict[str, dict[str, Any]] = {
    "meas": {"color": "black", "lw": 0.8, "ls": "-", "label": "measured"},
    "smooth": {"color": "#1f77b4", "lw": 1.4, "ls": "-", "label": "output at smoother mean"},
    "sim": {"color": "#ff7f0e", "lw": 1.4, "ls": "--", "label": "free simulation"},
    "pred": {"color": "#2ca02c", "lw": 1.4, "ls": ":", "label": "Kalman-filter prediction"},
    "drift": {"color": "#d62728", "lw": 1.2, "ls": "--", "label": "drift f(μ, u, θ)"},
}
_RESIDUALS = (("smooth", "smoother residual (measured − smoother output)"),
              ("pred", "innovation (measured − KF prediction)"))
_CRITERIA = (("smoother", "output at smoother mean"), ("simulation", "free simulation"),
             ("prediction", "Kalman-filter prediction"))
_GREEK = {"alpha", "beta", "gamma", "delta", "epsilon", "zeta", "eta", "theta", "iota", "kappa",
          "lambda", "mu", "nu", "xi", "pi", "rho", "sigma", "tau", "upsilon", "phi", "chi", "psi",
          "omega", "Gamma", "Delta", "Theta", "Lambda", "Xi", "Pi", "Sigma", "Upsilon", "Phi",
          "Psi", "Omega"}

FIG_DPI = 100


# --------------------------------------------------------------------------- input


def _templates_dir() -> pathlib.Path:
    """The templates shipped inside the package (``vsidgen/report/templates``)."""
    return pathlib.Path(__file__).resolve().parent / "templates"


def _num(v) -> float:
    """JSON value -> float (None/'' -> nan)."""
    if v is None or v == "":
        return math.nan
    try:
        return float(v)
    except (TypeError, ValueError):
        return math.nan


def _read_signals(path: pathlib.Path) -> dict[str, np.ndarray]:
    """Read a signals CSV into {column: float array}; empty cells are NaN."""
    if not os.path.lexists(path):
        raise VsidgenError(f"{path}: error: signals file listed in results.json is missing")
    try:
        with open(path, newline="", encoding="utf-8") as fh:
            rows = list(csv.reader(fh))
    except (OSError, UnicodeDecodeError) as err:
        raise VsidgenError(f"{path}: error: cannot read signals file: {err}") from None
    if len(rows) < 2:
        raise VsidgenError(f"{path}: error: signals file has no data rows")
    header = [h.strip() for h in rows[0]]
    if "t_s" not in header:
        raise VsidgenError(f"{path}: error: signals file has no `t_s` column")
    data = np.full((len(rows) - 1, len(header)), np.nan)
    for i, row in enumerate(rows[1:]):
        if len(row) != len(header):
            raise VsidgenError(f"{path}:{i + 2}: error: expected {len(header)} values, "
                               f"found {len(row)}")
        for j, cell in enumerate(row):
            cell = cell.strip()
            if cell:
                try:
                    data[i, j] = float(cell)
                except ValueError:
                    raise VsidgenError(f"{path}:{i + 2}: error: column `{header[j][:80]}`: "
                                       f"not a number: {cell[:40]!r}") from None
    return {h: data[:, j] for j, h in enumerate(header)}


def parse_reference(reference) -> tuple[dict[str, dict], str, pathlib.Path | None]:
    """``PATH`` or ``PATH:method`` -> ({name: {value, std}}, label, path)."""
    if reference is None:
        return {}, "", None
    text = str(reference)
    path, method = pathlib.Path(text), None
    if not path.is_file():
        m = re.match(r"^(.*):([A-Za-z0-9_\-]+)$", text)
        if m and pathlib.Path(m.group(1)).is_file():
            path, method = pathlib.Path(m.group(1)), m.group(2)
        else:
            raise VsidgenError(f"{text}: error: reference file not found "
                               "(expected PATH or PATH:method)")
    check_input_file(path, what="reference file", kind="json", data_error=False)
    try:
        ref = parse_json(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as err:
        where = (f" at {err.lineno}:{err.colno}" if isinstance(err, json.JSONDecodeError) else "")
        raise VsidgenError(f"{path}: error: cannot read reference JSON: "
                           f"{getattr(err, 'msg', None) or err}{where}") from None
    if not isinstance(ref, dict):
        raise VsidgenError(f"{path}: error: reference file must hold a JSON object")
    methods = [k for k, v in ref.items() if isinstance(v, dict) and isinstance(v.get("parameters"), dict)]
    if method is None:
        if isinstance(ref.get("parameters"), dict) and not methods:
            section, label = ref, path.name
        elif methods:
            method = "fem" if "fem" in methods else ("oem" if "oem" in methods else methods[0])
            section, label = ref[method], f"{path.name}:{method}"
        else:
            raise VsidgenError(f"{path}: error: reference file has no `parameters` "
                               "(neither at the top level nor in a method section)")
    else:
        if method not in methods:
            raise VsidgenError(f"{path}: error: reference method `{method}` not found; "
                               f"available: {', '.join(methods) or 'none'}")
        section, label = ref[method], f"{path.name}:{method}"
    out = {}
    for name, v in section["parameters"].items():
        if isinstance(v, Mapping):
            out[name] = {"value": _num(v.get("value")), "std": _num(v.get("std"))}
        else:
            out[name] = {"value": _num(v), "std": math.nan}
    if isinstance(section.get("R_diag"), Mapping):
        out["__R_diag__"] = {k: _num(v) for k, v in section["R_diag"].items()}
    return out, label, path


# --------------------------------------------------------------------------- numerics


def _autocorrelation(e: np.ndarray, max_lag: int) -> tuple[np.ndarray, int]:
    """Sample autocorrelation r_0..r_max_lag of a NaN-aware, de-meaned series."""
    ok = np.isfinite(e)
    n = int(ok.sum())
    if n < 3:
        return np.full(max_lag + 1, np.nan), n
    x = np.where(ok, e - e[ok].mean(), 0.0)
    c0 = float(np.dot(x, x))
    if c0 <= 0:
        return np.full(max_lag + 1, np.nan), n
    r = np.array([np.dot(x[: len(x) - k], x[k:]) / c0 for k in range(max_lag + 1)])
    return r, n


def _ljung_box(r: np.ndarray, n: int, h: int) -> tuple[float, int, float]:
    """Ljung-Box statistic Q = n(n+2) Σ_{k=1}^h r_k²/(n-k), dof h, p-value (χ²)."""
    from scipy.stats import chi2

    if n <= h + 1 or not np.all(np.isfinite(r[1:h + 1])):
        return math.nan, h, math.nan
    k = np.arange(1, h + 1)
    q = float(n * (n + 2) * np.sum(r[1:h + 1] ** 2 / (n - k)))
    return q, h, float(chi2.sf(q, h))


def _welch(e: np.ndarray, fs: float) -> tuple[np.ndarray, np.ndarray]:
    from scipy.signal import welch

    ok = np.isfinite(e)
    x = np.where(ok, e - (e[ok].mean() if ok.any() else 0.0), 0.0)
    nper = int(min(256, max(8, len(x) // 4)))
    if len(x) < 8:
        return np.array([]), np.array([])
    f, p = welch(x, fs=fs, nperseg=nper)
    return f[1:], p[1:]


# --------------------------------------------------------------------------- figures


def new_figure(width: float, height: float):
    """A matplotlib Figure of ``width`` x ``height`` inches at ``FIG_DPI``, on the Agg canvas
    (no pyplot state)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), dpi=FIG_DPI)
    FigureCanvasAgg(fig)
    return fig


#: longest description drawn in a figure title (the HTML shows it whole)
FIGURE_TEXT_CHARS = 160


def _short(text: str) -> str:
    """``text`` cut to :data:`FIGURE_TEXT_CHARS` for a figure title: a 145-KB description
    took minutes to lay out, once per record (red team, session 48)."""
    text = " ".join(str(text).split())
    return text if len(text) <= FIGURE_TEXT_CHARS else text[:FIGURE_TEXT_CHARS - 1] + "…"


def png_data_uri(fig) -> str:
    """Figure -> palette PNG data URI (quantised: ~4x smaller than RGBA, same look)."""
    from PIL import Image

    canvas = fig.canvas
    canvas.draw()
    img = Image.frombuffer("RGBA", canvas.get_width_height(), canvas.buffer_rgba(), "raw",
                           "RGBA", 0, 1).convert("RGB")
    img = img.quantize(colors=96, method=Image.Quantize.FASTOCTREE, dither=Image.Dither.NONE)
    buf = io.BytesIO()
    img.save(buf, format="png", optimize=False, compress_level=6)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def _unit_label(quantity: str, unit: str | None) -> str:
    return f"{quantity} ({unit})" if unit and unit != "1" else (
        f"{quantity} (–)" if unit == "1" else quantity)


def _style(key: str, **override) -> dict:
    s = dict(SIGNAL_STYLE[key])
    s.update(override)
    return {("linewidth" if k == "lw" else "linestyle" if k == "ls" else "markersize" if k == "ms"
             else k): v for k, v in s.items()}


def _rate_unit(unit: str | None) -> str:
    """Unit of a time derivative: m/s -> m/s², rad -> rad/s, 1 -> 1/s."""
    if not unit or unit == "1":
        return "1/s"
    if unit.endswith("/s"):
        return unit + "²"
    return f"{unit}/s"


def _output_figure(t, sig, name, unit, desc) -> str:
    fig = new_figure(10.0, 5.2)
    ax1, ax2 = fig.subplots(2, 1, sharex=True, gridspec_kw={"height_ratios": [2.2, 1]})
    fig.subplots_adjust(left=0.09, right=0.985, top=0.87, bottom=0.1, hspace=0.08)
    for key in ("meas", "smooth", "sim", "pred"):
        y = sig.get(f"{name}_{key}")
        if y is not None:
            ax1.plot(t, y, **_style(key))
    ax1.set_ylabel(_unit_label(name, unit))
    fig.text(0.09, 0.985, f"Output {name}" + (f" — {_short(desc)}" if desc else ""), fontsize=11,
             parse_math=False,
             va="top", ha="left")
    ax1.legend(loc="lower right", bbox_to_anchor=(1.0, 1.0), fontsize=8, ncols=4, frameon=False,
               borderaxespad=0.2)
    ax1.grid(alpha=0.3)
    meas = sig.get(f"{name}_meas")
    for key, label in _RESIDUALS:
        y = sig.get(f"{name}_{key}")
        if meas is not None and y is not None:
            ax2.plot(t, meas - y, **_style(key, label=label, lw=0.9))
    ax2.axhline(0.0, color="0.5", lw=0.6)
    ax2.set_ylabel(_unit_label("residual", unit))
    ax2.set_xlabel("time (s)")
    ax2.legend(loc="upper right", fontsize=8, ncols=2, framealpha=0.8)
    ax2.grid(alpha=0.3)
    return png_data_uri(fig)


def _state_figure(t, sig, name, unit, desc) -> str:
    fig = new_figure(10.0, 4.6)
    ax1, ax2 = fig.subplots(2, 1, sharex=True)
    fig.subplots_adjust(left=0.09, right=0.985, top=0.86, bottom=0.11, hspace=0.1)
    mu = sig.get(f"{name}_mu")
    sd = sig.get(f"{name}_mu_std")
    if mu is not None:
        ax1.plot(t, mu, **_style("smooth", label="smoother mean μ"))
        if sd is not None and np.any(np.isfinite(sd)):
            ax1.fill_between(t, mu - 2 * sd, mu + 2 * sd, color=SIGNAL_STYLE["smooth"]["color"],
                             alpha=0.2, lw=0, label="μ ± 2σ")
    ax1.set_ylabel(_unit_label(name, unit))
    fig.text(0.09, 0.985, f"State {name}" + (f" — {_short(desc)}" if desc else ""), fontsize=11,
             parse_math=False,
             va="top", ha="left")
    ax1.legend(loc="lower right", bbox_to_anchor=(1.0, 1.0), fontsize=8, ncols=2,
               frameon=False, borderaxespad=0.2)
    ax1.grid(alpha=0.3)
    fd = sig.get(f"{name}_dot_fd")
    dr = sig.get(f"{name}_drift")
    dunit = _rate_unit(unit)
    if fd is not None:
        ax2.plot(t, fd, **_style("smooth", label="finite difference (μₖ₊₁ − μₖ)/T", lw=1.0))
    if dr is not None:
        ax2.plot(t, dr, **_style("drift"))
    ax2.set_ylabel(_unit_label(f"d{name}/dt", dunit))
    ax2.set_xlabel("time (s)")
    ax2.legend(loc="upper right", fontsize=8, ncols=2, framealpha=0.8)
    ax2.grid(alpha=0.3)
    return png_data_uri(fig)


def _diagnostics_figure(name, unit, acfs, spectra, lags) -> str:
    fig = new_figure(10.0, 3.4)
    axa, axb = fig.subplots(1, 2)
    fig.subplots_adjust(left=0.085, right=0.985, top=0.9, bottom=0.15, wspace=0.25)
    for key, label in _RESIDUALS:
        r, n = acfs[key]
        if np.any(np.isfinite(r)):
            off = -0.15 if key == "smooth" else 0.15
            axa.vlines(lags[1:] + off, 0, r[1:], color=SIGNAL_STYLE[key]["color"], lw=1.6,
                       label=label.split(" (")[0])
    n = max(acfs["pred"][1], acfs["smooth"][1], 1)
    band = 1.96 / math.sqrt(n)
    axa.axhspan(-band, band, color="0.6", alpha=0.25, lw=0, label=f"95 % band ±1.96/√N (N={n})")
    axa.axhline(0.0, color="0.3", lw=0.6)
    rmax = max([float(np.nanmax(np.abs(acfs[k][0][1:]))) for k in acfs
                if np.any(np.isfinite(acfs[k][0][1:]))] or [0.0])
    lim = max(2.5 * band, 1.15 * rmax)
    axa.set_ylim(-lim, lim)
    axa.set_xlim(0, lags[-1] + 1)
    axa.set_xlabel("lag (samples; lag 0 = 1 not shown)")
    axa.set_ylabel("autocorrelation (–)")
    axa.set_title(f"{name}: residual autocorrelation", fontsize=10, loc="left")
    axa.legend(fontsize=7, loc="upper right")
    axa.grid(alpha=0.3)
    for key, label in _RESIDUALS:
        f, p = spectra[key]
        if len(f) and np.any(p > 0):
            axb.semilogy(f, p, color=SIGNAL_STYLE[key]["color"], lw=1.1,
                         ls=SIGNAL_STYLE[key]["ls"], label=label.split(" (")[0])
    u2 = f"({unit})²/Hz" if unit and unit != "1" else "1/Hz"
    axb.set_xlabel("frequency (Hz)")
    axb.set_ylabel(f"PSD ({u2})")
    axb.set_title(f"{name}: residual spectrum (Welch)", fontsize=10, loc="left")
    axb.legend(fontsize=7, loc="upper right", framealpha=0.8)
    axb.grid(alpha=0.3, which="both")
    return png_data_uri(fig)


def _correlation_figure(names: Sequence[str], c: np.ndarray) -> str:
    n = len(names)
    size = min(11.0, max(4.5, 0.5 * n + 2.0))
    fig = new_figure(size + 1.2, size)
    ax = fig.subplots()
    fig.subplots_adjust(left=0.14, right=0.98, top=0.93, bottom=0.14)
    im = ax.imshow(c, cmap="RdBu_r", vmin=-1.0, vmax=1.0)
    ax.set_xticks(range(n), names, rotation=90, fontsize=8)
    ax.set_yticks(range(n), names, fontsize=8)
    if n <= 20:
        for i in range(n):
            for j in range(n):
                v = c[i, j]
                if np.isfinite(v):
                    strong = i != j and abs(v) > STRONG_CORRELATION
                    ax.text(j, i, f"{v:.2f}", ha="center", va="center", fontsize=6.5,
                            color="white" if abs(v) > 0.6 else "black",
                            fontweight="bold" if strong else "normal")
    for i in range(n):
        for j in range(n):
            if i != j and np.isfinite(c[i, j]) and abs(c[i, j]) > STRONG_CORRELATION:
                ax.add_patch(_rect(j, i))
    ax.set_title(f"Parameter correlation (boxed: |r| > {STRONG_CORRELATION})", fontsize=10,
                 loc="left")
    cb = fig.colorbar(im, ax=ax, shrink=0.8)
    cb.set_label("correlation coefficient r (–)")
    return png_data_uri(fig)


def _rect(x, y):
    from matplotlib.patches import Rectangle

    return Rectangle((x - 0.5, y - 0.5), 1, 1, fill=False, ec="gold", lw=2.2)


def _latex_name(name: str) -> str:
    """A declared name as LaTeX, as the equations' right-hand sides show it: a Greek name as
    its letter, one letter in italics, several upright (``\\mathrm{side}``, not the product
    s·i·d·e), digits or ``_rest`` as a subscript (``beta_m`` -> ``\\beta_{\\mathrm{m}}``)."""
    base, sep, sub = name.partition("_")
    if sep and base and sub and re.fullmatch(r"\w+", sub):
        return f"{_latex_name(base)}_{{\\mathrm{{{sub.replace('_', ',')}}}}}"
    if name in _GREEK:
        return "\\" + name
    m = re.match(r"^([A-Za-z]+?)(\d+)$", name)
    if m:
        return f"\\mathrm{{{m.group(1)}}}_{{{m.group(2)}}}"
    return f"\\mathrm{{{name}}}" if len(name) > 1 else name


_VERBATIM_ARG = {"begin", "end", "mathrm", "text", "operatorname", "mathit", "mathbf", "mathsf"}
_TEX_TOKEN = re.compile(r"\\[A-Za-z]+|[A-Za-z]+|\{|\}|\s+|.")


def _readable_tex(tex: str) -> str:
    """Upright multi-letter identifiers (``CD`` -> ``\\mathrm{CD}``) and thin spaces
    between juxtaposed factors, so ``CD SBYM \\bar{q}`` does not read as one word."""
    toks = _TEX_TOKEN.findall(tex)
    out: list[str] = []
    i = 0
    while i < len(toks):
        tok = toks[i]
        if tok.startswith("\\") and tok[1:] in _VERBATIM_ARG and i + 1 < len(toks) and toks[i + 1] == "{":
            depth, j = 0, i + 1
            while j < len(toks):
                depth += toks[j] == "{"
                depth -= toks[j] == "}"
                j += 1
                if depth == 0:
                    break
            out.append("".join(toks[i:j]))
            i = j
            continue
        if tok.isalpha() and len(tok) > 1:
            tok = f"\\mathrm{{{tok}}}"
        elif tok.isspace():
            prev = out[-1][-1:] if out else ""
            nxt = toks[i + 1][:1] if i + 1 < len(toks) else ""
            tok = "\\," if (prev.isalnum() or prev in "})") and (nxt.isalnum() or nxt == "\\") \
                and not (i + 1 < len(toks) and toks[i + 1] in ("\\right", "\\end")) else " "
        out.append(tok)
        i += 1
    return "".join(out)


def _mathtext_svg(tex: str) -> str:
    from matplotlib.font_manager import FontProperties
    from matplotlib.mathtext import math_to_image

    buf = io.BytesIO()
    math_to_image(f"${tex}$", buf, prop=FontProperties(size=13), dpi=FIG_DPI, format="svg")
    return "data:image/svg+xml;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


#: longest equation (LaTeX characters) typeset with mathtext, and the most characters
#: typeset in one report: matplotlib's parser took ~25 s for a 20000-character equation (a
#: hostile results.json made `vsidgen report` run for minutes); longer ones are shown as
#: their LaTeX source. The shipped models' longest equation has a few hundred characters.
MAX_TYPESET_CHARS = 4000
MAX_TYPESET_TOTAL = 60000


def _equation(lhs: str, rhs: str, *, budget: list | None = None) -> dict:
    """Typeset ``lhs = rhs`` with mathtext (SVG data URI); fall back to LaTeX source.
    ``budget``: a one-element list with the characters left to typeset in this report."""
    tex = rhs if "=" in rhs else f"{lhs} = {rhs}"
    item = {"tex": tex, "img": None, "error": None}
    left = budget[0] if budget is not None else MAX_TYPESET_TOTAL
    if len(tex) > MAX_TYPESET_CHARS or len(tex) > left:
        item["error"] = (f"too long to typeset ({len(tex)} characters; at most {MAX_TYPESET_CHARS} "
                         f"per equation and {MAX_TYPESET_TOTAL} per report): shown as LaTeX source")
        return item
    if budget is not None:
        budget[0] -= len(tex)
    for candidate in (f"{lhs} = {_readable_tex(rhs)}" if "=" not in rhs else tex, tex):
        try:
            item["img"] = _mathtext_svg(candidate)
            item["error"] = None
            # the LaTeX shown (alt text) is the one typeset: multi-letter names upright there
            # too (`\mathrm{side}`, not the italic product s·i·d·e)
            item["tex"] = candidate
            break
        except Exception as err:  # mathtext supports a subset of LaTeX: show the source instead
            item["error"] = str(err).splitlines()[0] if str(err) else type(err).__name__
    return item


def _equations(latex: Mapping | None) -> list[dict]:
    if not isinstance(latex, Mapping):
        return []
    groups = []
    budget = [MAX_TYPESET_TOTAL]
    for key, title, lhs in (("definitions", "Definitions", lambda n: _latex_name(n)),
                            ("drift", "State equations (drift)",
                             lambda n: f"\\dot{{{_latex_name(n)}}}"),
                            ("observations", "Observation equations",
                             # an output named with its own subscript (`beta_m`) as written;
                             # else the measured quantity's name with a subscript m
                             lambda n: _latex_name(n) if "_" in n.strip("_")
                             else f"{_latex_name(n)}_{{\\mathrm{{m}}}}")):
        eqs = latex.get(key)
        if isinstance(eqs, Mapping) and eqs:
            groups.append({"title": title, "eqs": [
                {"name": n, **_equation(lhs(n), str(e), budget=budget)} for n, e in eqs.items()]})
    return groups


# --------------------------------------------------------------------------- sections


def _fmt(v, digits: int = 4) -> str:
    v = _num(v)
    if not math.isfinite(v):
        return "—"
    if v == 0:
        return "0"
    if abs(v) >= 1e5 or abs(v) < 1e-3:
        return f"{v:.{digits - 1}e}"
    return f"{v:.{digits}g}"


def _parameters(res: dict, ref: dict) -> list[dict]:
    rows = []
    for name, p in res["parameters"].items():
        if not isinstance(p, Mapping):
            raise VsidgenError(f"results.json: error: parameter `{name}` is not an object")
        est, se = _num(p.get("estimate")), _num(p.get("std_error"))
        fixed = bool(p.get("fixed", False))
        lo, hi = _num(p.get("lower")), _num(p.get("upper"))
        bounds = "fixed" if fixed else (
            "" if not (math.isfinite(lo) or math.isfinite(hi)) else
            f"[{_fmt(lo) if math.isfinite(lo) else '−∞'}, {_fmt(hi) if math.isfinite(hi) else '∞'}]")
        at_bound = (not fixed) and ((math.isfinite(lo) and abs(est - lo) <= 1e-6 * max(1, abs(lo)))
                                    or (math.isfinite(hi) and abs(est - hi) <= 1e-6 * max(1, abs(hi))))
        refs = []
        spec_ref = _num(p.get("reference"))
        if math.isfinite(spec_ref):
            refs.append(("spec", spec_ref, math.nan))
        if name in ref:
            refs.append(("file", ref[name]["value"], ref[name]["std"]))
        ref_val = refs[-1][1] if refs else math.nan
        ref_std = refs[-1][2] if refs else math.nan
        diff = (est - ref_val) / se if (math.isfinite(ref_val) and math.isfinite(se) and se > 0) \
            else math.nan
        rel = abs(se / est) * 100 if (math.isfinite(se) and est != 0) else math.nan
        rows.append({
            "name": name, "unit": p.get("unit") or "", "description": p.get("description") or "",
            "estimate": _fmt(est, 6), "std_error": _fmt(se, 3),
            "rel_std": (f"{rel:.3g} %" if math.isfinite(rel) else "—"),
            "rel_large": math.isfinite(rel) and rel > 50,
            "bounds": bounds, "fixed": fixed, "at_bound": at_bound,
            "ref_value": _fmt(ref_val, 6), "ref_std": _fmt(ref_std, 3),
            "ref_source": ", ".join(s for s, _, _ in refs),
            "diff": (f"{diff:+.2f}" if math.isfinite(diff) else "—"),
            "diff_large": math.isfinite(diff) and abs(diff) > 3,
        })
    return rows


def _correlation(res: dict) -> tuple[str | None, list[dict]]:
    corr = res.get("correlation")
    if not isinstance(corr, Mapping) or not corr.get("names"):
        return None, []
    names = [str(n) for n in corr["names"]]
    try:
        c = np.array([[_num(x) for x in row] for row in corr.get("matrix", [])], dtype=float)
    except TypeError:
        raise VsidgenError("results.json: error: `correlation.matrix` is not a matrix") from None
    if c.shape != (len(names), len(names)):
        raise VsidgenError(f"results.json: error: `correlation.matrix` has shape {c.shape}, "
                           f"expected {len(names)}×{len(names)}")
    pairs = []
    for i in range(len(names)):
        for j in range(i):
            if np.isfinite(c[i, j]) and abs(c[i, j]) > STRONG_CORRELATION:
                pairs.append({"a": names[j], "b": names[i], "r": f"{c[i, j]:+.3f}"})
    pairs.sort(key=lambda d: -abs(float(d["r"])))
    return _correlation_figure(names, c), pairs


def _noise(res: dict, ref: dict, units_out: dict, units_state: dict) -> dict:
    noise = res.get("noise") if isinstance(res.get("noise"), Mapping) else {}
    meas = noise.get("measurement_std") or {}
    floor = noise.get("measurement_floor") or {}
    proc = noise.get("process_std") or {}
    r_ref = ref.get("__R_diag__", {})
    mrows = []
    for o, v in meas.items():
        s, f = _num(v), _num(floor.get(o))
        rr = _num(r_ref.get(o))
        mrows.append({"name": o, "unit": units_out.get(o) or "", "std": _fmt(s),
                      "floor": _fmt(f), "at_floor": math.isfinite(f) and math.isfinite(s)
                      and s <= f * 1.001 and f > 0,
                      "ref": _fmt(math.sqrt(rr)) if math.isfinite(rr) and rr >= 0 else "—"})
    prows = []
    lim = res.get("deterministic_limit") if isinstance(res.get("deterministic_limit"), Mapping) else {}
    degen = set(lim.get("states") or ()) - set(res.get("deterministic_states") or ())
    for x, v in proc.items():
        u = units_state.get(x)
        prows.append({"name": x, "unit": (f"{u}/√s" if u and u != "1" else "1/√s"),
                      "std": _fmt(v), "note": ("degenerate: no independent part (G_ii = 0), a "
                                               "combination of the earlier states' noise"
                                               if x in degen else "")})
    for x in res.get("deterministic_states") or ():
        if x in proc:
            continue
        u = units_state.get(x)
        note = "deterministic (no process noise)"
        if lim:
            note += (": exact limit reached" if lim.get("reached") else ": limit NOT reached (see warnings)")
        prows.append({"name": x, "unit": (f"{u}/√s" if u and u != "1" else "1/√s"), "std": "0", "note": note})
    return {"measurement": mrows, "process": prows, "has_ref": bool(r_ref)}


def _metrics_table(m: Mapping, names: Iterable[str]) -> list[dict]:
    rows = []
    for o in names:
        row = {"name": o, "cells": []}
        for crit, _ in _CRITERIA:
            d = (m.get(crit) or {}).get(o) or {}
            fp = d.get("fit_percent")
            row["cells"].append({"rms": _fmt(d.get("rms")), "theil": _fmt(d.get("theil"), 3),
                                 "r2": _fmt(d.get("r2"), 4),
                                 "fit": "—" if fp is None or not math.isfinite(_num(fp))
                                 else f"{_num(fp):.1f} %"})
        rows.append(row)
    return rows


def _record_rows(records: Mapping) -> dict:
    """The records of results.json for the data-records table, their sample period and
    duration to 6 significant digits (0.020000000000002335 s, the mean step of float time
    stamps, reads 0.02); other fields as they are."""
    rows = {}
    for kind, recs in records.items():
        if not isinstance(recs, list):
            rows[kind] = recs
            continue
        rows[kind] = [{**r, **{k: _fmt(r[k], 6) for k in ("dt", "duration_s")
                               if r.get(k) is not None}}
                      if isinstance(r, Mapping) else r for r in recs]
    return rows


def _status_text(status, converged: bool) -> str:
    """The fit's status after the converged / not converged tag: without the leading
    "converged: " that the tag already says ("converged converged: Newton decrement ...")."""
    text = str(status or "")
    word = "converged:" if converged else "not converged:"
    return text[len(word):].lstrip() if text.lower().startswith(word) else text


def _record_section(res: dict, results_dir: pathlib.Path, rec: Mapping, kind: str,
                    outputs: list[dict], states: list[dict]) -> dict:
    name = str(rec.get("name", ""))
    sig_file = (res.get("signals") or {}).get(name)
    rid = re.sub(r"[^A-Za-z0-9_\-]", "_", f"{kind}-{name}")
    sec = {"name": name, "id": rid, "kind": kind, "outputs": [], "states": [], "whiteness": [],
           "metrics": [], "derivative": [], "missing": None,
           "n_samples": rec.get("n_samples"), "dt": _fmt(rec.get("dt"), 6),
           "duration": _fmt(rec.get("duration_s"), 6), "path": rec.get("path") or ""}
    m = ((res.get("metrics") or {}).get(kind) or {}).get(name) or {}
    sec["metrics"] = _metrics_table(m, [o["name"] for o in outputs])
    der = m.get("derivative") or {}
    sec["derivative"] = [{"name": s["name"], "rms": _fmt((der.get(s["name"]) or {}).get("rms")),
                          "theil": _fmt((der.get(s["name"]) or {}).get("theil"), 3),
                          "r2": _fmt((der.get(s["name"]) or {}).get("r2"), 4),
                          "unit": _rate_unit(s["unit"])}
                         for s in states if der.get(s["name"])]
    if not sig_file:
        sec["missing"] = "no signals file recorded for this record in results.json"
        return sec
    sig = _read_signals(contained_file(results_dir, sig_file, what="signals file"))
    t = sig["t_s"]
    dt = _num(rec.get("dt"))
    if not (math.isfinite(dt) and dt > 0):
        d = np.diff(t)
        dt = float(np.median(d)) if len(d) else 1.0
    n = len(t)
    max_lag = int(max(1, min(40, n // 4)))
    h = int(max(1, min(20, n // 5)))
    lags = np.arange(max_lag + 1)
    for o in outputs:
        on, unit = o["name"], o["unit"]
        if f"{on}_meas" not in sig:
            continue
        fig = _output_figure(t, sig, on, unit, o["description"])
        acfs, spectra = {}, {}
        meas = sig[f"{on}_meas"]
        for key, label in _RESIDUALS:
            other = sig.get(f"{on}_{key}")
            e = meas - other if other is not None else np.full(n, np.nan)
            acfs[key] = _autocorrelation(e, max_lag)
            spectra[key] = _welch(e, 1.0 / dt)
            r, nn = acfs[key]
            q, dof, p = _ljung_box(r, nn, h)
            band = 1.96 / math.sqrt(max(nn, 1))
            outside = int(np.sum(np.abs(r[1:]) > band)) if np.any(np.isfinite(r)) else 0
            sec["whiteness"].append({
                "output": on, "residual": label, "q": _fmt(q), "dof": dof, "p": _fmt(p, 3),
                "outside": f"{outside}/{max_lag}",
                "white": (None if not math.isfinite(p) else bool(p > 0.05))})
        diag = _diagnostics_figure(on, unit, acfs, spectra, lags)
        sec["outputs"].append({"name": on, "unit": unit, "figure": fig, "diagnostics": diag})
    for s in states:
        if f"{s['name']}_mu" not in sig:
            continue
        sec["states"].append({"name": s["name"], "unit": s["unit"],
                              "figure": _state_figure(t, sig, s["name"], s["unit"],
                                                      s["description"])})
    sec["lb_lags"] = h
    return sec


def _vars(items) -> list[dict]:
    out = []
    for v in items or []:
        if isinstance(v, Mapping) and "name" in v:
            out.append({"name": str(v["name"]), "unit": v.get("unit") or "",
                        "description": v.get("description") or ""})
    return out


def _versions(res: dict) -> list[tuple[str, str]]:
    import matplotlib
    import scipy

    import vsidgen

    out = [("vsidgen (fit)", str(res.get("vsidgen_version", "unknown")))]
    extra = res.get("versions")
    if isinstance(extra, Mapping):
        out += [(f"{k} (fit)", str(v)) for k, v in extra.items()]
    out += [("vsidgen (report)", vsidgen.__version__), ("python (report)", platform.python_version()),
            ("numpy (report)", np.__version__), ("scipy (report)", scipy.__version__),
            ("matplotlib (report)", matplotlib.__version__)]
    return out


# --------------------------------------------------------------------------- public API


def write_report(results_dir, *, out=None, reference=None, title: str | None = None,
                 extra_sections: Sequence[tuple[str, str]] | None = None,
                 display_dir: str | os.PathLike | None = None,
                 overwrite: bool = False) -> pathlib.Path:
    """Render a fit's results directory into one self-contained HTML file.

    Args:
        results_dir: directory written by ``vsidgen fit`` (holds ``results.json``
            and the ``signals_<record>.csv`` files).
        out: output file (default ``results_dir/report.html``); written
            atomically (temporary file in the same directory, then ``os.replace``).
        reference: optional reference-values JSON, ``PATH`` or ``PATH:method``
            (e.g. ``shared/reference/hfb320_reference.json:oem``). Without a method
            the ``fem`` section is used when present, else ``oem``. A file with a
            top-level ``parameters`` mapping ``{name: {value, std}}`` also works.
            Reference values in ``results.json`` (``parameters[*].reference``) are
            always shown; a reference file takes precedence for the difference column.
        title: page title (default ``"vsidgen report: <spec name>"``).
        extra_sections: ``(title, html)`` pairs appended as extra sections (e.g. the
            discrepancy analysis); ``html`` is inserted verbatim (trusted).
        display_dir: the directory named in the footer (default ``results_dir``;
            ``vsidgen fit`` passes its final ``--out`` while it writes a temporary one).
        overwrite: replace an existing ``out`` that vsidgen did not write (one listed in the
            results directory's manifest is replaced anyway, and a report written into the
            results directory is listed there, so ``vsidgen report`` may replace it later).

    Only files inside ``results_dir`` are read (:func:`contained_file`); the page's
    one inline script is allowed by its SHA-256 hash in the Content-Security-Policy
    (no ``'unsafe-inline'`` scripts).

    Returns:
        The path of the written report.

    Raises:
        VsidgenError: missing or corrupt results directory, signals file or reference.
    """
    import jinja2
    from markupsafe import Markup

    from ..atomic import add_to_manifest, read_manifest

    results_dir = pathlib.Path(results_dir)
    res = read_results(results_dir)
    ref, ref_label, _ = parse_reference(reference)
    out_path = pathlib.Path(out) if out is not None else results_dir / "report.html"
    in_dir = results_dir.is_dir() and out_path.parent.resolve() == results_dir.resolve()
    if os.path.lexists(out_path) and not overwrite:
        manifest = read_manifest(results_dir) if in_dir else None
        if manifest is None or out_path.name not in manifest["files"]:
            raise VsidgenError(f"{out_path}: error: exists and was not written by vsidgen (not "
                               f"listed in the manifest of {results_dir}); pass overwrite "
                               "(--overwrite) to replace it or choose another output file")

    outputs = _vars(res["model"].get("outputs"))
    states = _vars(res["model"].get("states"))
    inputs = _vars(res["model"].get("inputs"))
    units_out = {o["name"]: o["unit"] for o in outputs}
    units_state = {s["name"]: s["unit"] for s in states}

    records = res["records"]
    sections = []
    for kind, heading in (("estimation", "Estimation data"), ("validation", "Validation data")):
        recs = [r for r in (records.get(kind) or []) if isinstance(r, Mapping)]
        if not recs:
            continue
        sections.append({"kind": kind, "heading": heading, "records": [
            _record_section(res, results_dir, r, kind, outputs, states) for r in recs]})

    corr_fig, strong_pairs = _correlation(res)
    warnings = [w if isinstance(w, Mapping) else {"code": "warning", "message": str(w)}
                for w in (res.get("warnings") or [])]
    spec = res["spec"]
    method = res.get("method") if isinstance(res.get("method"), Mapping) else {}
    val = res.get("validation") if isinstance(res.get("validation"), Mapping) else {}
    ctx = {
        "title": title or f"vsidgen report: {spec.get('name', 'unnamed model')}",
        "spec": spec, "method": method,
        "records": _record_rows(records),
        "converged": bool(res.get("converged", False)),
        "status": _status_text(res.get("status", ""), bool(res.get("converged", False))),
        "iterations": res.get("iterations"),
        "wall_time": _fmt(res.get("wall_time_s"), 3), "elbo": _fmt(res.get("elbo"), 8),
        "validation_elbo": _fmt(val.get("elbo"), 8),
        "validation_converged": val.get("converged", True) is not False,
        "validation_elbo_own_noise": _fmt(val.get("elbo_own_noise"), 8)
        if val.get("elbo_own_noise") is not None else None,
        "validation_own_noise_converged": val.get("own_noise_converged", True) is not False,
        "validation_status": str(val.get("status") or ""),
        "versions": _versions(res),
        "warnings": warnings,
        "std_reliable": bool(res.get("std_errors_reliable", True)),
        "std_issues": [i for i in (res.get("std_error_issues") or []) if isinstance(i, Mapping)],
        "parameters": _parameters(res, ref), "reference_label": ref_label,
        "has_reference": bool(ref) or any(
            math.isfinite(_num((p or {}).get("reference"))) for p in res["parameters"].values()
            if isinstance(p, Mapping)),
        "correlation_figure": corr_fig, "strong_pairs": strong_pairs,
        "strong_threshold": STRONG_CORRELATION,
        "equations": _equations(res["model"].get("equations_latex")),
        "noise": _noise(res, ref, units_out, units_state),
        "sections": sections, "outputs": outputs, "states": states, "inputs": inputs,
        "criteria": _CRITERIA, "style": SIGNAL_STYLE,
        "extra_sections": [(str(t), Markup(h)) for t, h in (extra_sections or [])],
        "generated": _dt.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M:%S %Z"),
        "results_dir": str(display_dir if display_dir is not None else results_dir),
    }
    n_fig = (1 if corr_fig else 0) + sum(
        2 * len(r["outputs"]) + len(r["states"]) for s in sections for r in s["records"])
    ctx["n_figures"] = n_fig

    tdir = _templates_dir()
    if not (tdir / "report.html.j2").is_file():
        raise VsidgenError(f"{tdir / 'report.html.j2'}: error: report template not found "
                           "(broken installation?)")
    env = jinja2.Environment(loader=jinja2.FileSystemLoader(str(tdir)), autoescape=True,
                             undefined=jinja2.StrictUndefined, trim_blocks=True,
                             lstrip_blocks=True)
    try:
        script = env.get_template("report_check.js.j2").render()
        ctx["check_script"] = Markup(script.replace("</", "<\\/"))
        ctx["script_hash"] = "sha256-" + base64.b64encode(
            hashlib.sha256(str(ctx["check_script"]).encode("utf-8")).digest()).decode("ascii")
        html = env.get_template("report.html.j2").render(**ctx)
    except jinja2.TemplateError as err:
        raise VsidgenError(f"{tdir / 'report.html.j2'}: error: cannot render report "
                           f"template: {err}") from None

    try:
        write_text_atomic(out_path, html)
        if in_dir:
            add_to_manifest(results_dir, [out_path.name])
    except OSError as err:
        raise VsidgenError(f"{out_path}: error: cannot write report: {err}") from None
    return out_path
