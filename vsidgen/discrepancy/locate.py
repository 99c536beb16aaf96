"""Locate model/data mismatches from the evaluation signals of one fit (pure numpy).

State equations (CTSM's idea, with the variational smoother in place of the
extended Kalman smoother): the *equation error*

.. math:: e_k = \\frac{\\mu_{k+1} - \\mu_k}{T} - f(\\mu_k, u_k, \\hat θ)

is the smoothed process-noise increment :math:`G \\hat w_k/\\sqrt T`. For a
correct model it carries turbulence only; a deficient equation shows

* a large share of variance of :math:`e` *explained* by a candidate regressor
  :math:`r` (a state, an input, a square, a product, a break ``max(α − α_b, 0)``,
  an input rate :math:`\\dot u`, a flow-angle rate :math:`\\dot α`): the correlation
  :math:`ρ(e, r)` is tested with the effective sample size
  :math:`n_{eff} = n / (1 + 2\\sum_k ρ_e(k) ρ_r(k))` (Bartlett) so that coloured
  errors do not fake significance, Bonferroni-corrected over the regressors;
* a large normalised process-noise intensity :math:`ν = σ_G \\sqrt{τ}/\\mathrm{std}(x)`
  with :math:`τ` the record length (how far the noise alone would move the state,
  relative to its excursion) and a large low-frequency share of :math:`e`
  (deterministic structure is slow, turbulence is broadband).

Output channels: the smoother residual :math:`y - h(μ)` and the one-step
prediction residual (innovation) are tested for a mean offset (sensor bias),
correlation with the channel itself (scale factor), with the angular rates and
accelerations (sensor position offset) and with the channel's rate (time skew,
confirmed by the lag of the cross-correlation of measured and smoothed output).

Windows: moving RMS of the normalised residual against a χ² bound; flight
condition: residual RMS per angle-of-attack (or first-state) quantile bin.

Everything returned is a frozen dataclass with a ``to_json()``; nothing here
runs a fit.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from scipy import stats

from .base import roles_of
from .pvalues import chi2_log10sf

#: locate significance level (Bonferroni-corrected within a target) for "flagged"
ALPHA_LOCATE = 1e-3
_LN10 = math.log(10.0)


# ---------------------------------------------------------------------------
# inputs
# ---------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class LocateRecord:
    """The per-record arrays locate needs (from :class:`vsidgen.evaluation.Signals` + the record)."""

    name: str
    t: np.ndarray          # (N,)
    u: np.ndarray          # (N, nu)
    y_meas: np.ndarray     # (N, ny)
    y_smooth: np.ndarray   # (N, ny)
    y_pred: np.ndarray     # (N, ny)
    y_sim: np.ndarray      # (N, ny)
    x_smooth: np.ndarray   # (N, nx)
    xdot_fd: np.ndarray    # (N-1, nx)
    f_smooth: np.ndarray   # (N-1, nx)

    @classmethod
    def from_signals(cls, signals, u) -> "LocateRecord":
        s = signals
        return cls(name=s.record, t=np.asarray(s.t, float), u=np.asarray(u, float).reshape(len(s.t), -1),
                   y_meas=np.asarray(s.y_meas, float), y_smooth=np.asarray(s.y_smooth, float),
                   y_pred=np.asarray(s.y_pred, float), y_sim=np.asarray(s.y_sim, float),
                   x_smooth=np.asarray(s.x_smooth, float), xdot_fd=np.asarray(s.xdot_fd, float),
                   f_smooth=np.asarray(s.f_smooth, float))


# ---------------------------------------------------------------------------
# outputs
# ---------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class RegressorStat:
    """Correlation test of a residual against one regressor."""

    name: str
    corr: float
    coef: float            # least-squares coefficient of the residual on the regressor
    p: float               # two-sided p-value with the effective sample size
    n_eff: float
    share: float           # share of residual variance explained (corr²)
    log10p: float = math.nan   # log10 p computed without underflow (t.logsf); nan: log10(p)

    def log10_p(self) -> float:
        """log10 of the p-value, exact also where ``p`` underflows to 0 (ranks strong effects)."""
        if math.isfinite(self.log10p):
            return float(self.log10p)
        return math.log10(min(1.0, max(float(self.p), 1e-300))) if math.isfinite(self.p) else 0.0

    def with_factor(self, k: float) -> "RegressorStat":
        """The same test with its p-value multiplied by ``k`` (capped at 1), exactly in logs."""
        lg = min(0.0, self.log10_p() + math.log10(k))
        return dataclasses.replace(self, p=min(1.0, k * self.p), log10p=lg)

    def to_json(self) -> dict:
        return {k: _num(v) for k, v in dataclasses.asdict(self).items()}


@dataclasses.dataclass(frozen=True)
class Window:
    """A time window where the normalised residual is systematically large."""

    record: str
    t0: float
    t1: float
    rms_ratio: float                 # moving RMS / noise level
    condition: Mapping[str, Any]     # {name: [min, mean, max]} of flow angles/inputs in the window

    def to_json(self) -> dict:
        return {"record": self.record, "t0": _num(self.t0), "t1": _num(self.t1),
                "rms_ratio": _num(self.rms_ratio),
                "condition": {k: [_num(x) for x in v] for k, v in self.condition.items()}}


@dataclasses.dataclass(frozen=True)
class StateEvidence:
    """Locate statistics of one state equation."""

    state: str
    n: int
    rms: float                      # RMS of the equation error e
    noise_level: float              # σ_G/√T, the white-noise level expected from the process noise
    process_std: float | None
    intensity: float                # normalised process-noise intensity ν
    lowfreq_ratio: float            # low-frequency power share of e / share for white noise
    ljung_box_p: float
    systematic_share: float         # R² of e on the stepwise-selected regressors
    selected: tuple[str, ...]       # those regressors
    regressors: tuple[RegressorStat, ...]   # sorted by p (best first)
    flagged: bool
    windows: tuple[Window, ...]
    condition_bins: Mapping[str, Any]

    def best(self) -> RegressorStat | None:
        return self.regressors[0] if self.regressors else None

    def regressor(self, name: str) -> RegressorStat | None:
        for r in self.regressors:
            if r.name == name:
                return r
        return None

    def to_json(self) -> dict:
        return {"state": self.state, "n": self.n, "rms": _num(self.rms),
                "noise_level": _num(self.noise_level), "process_std": _num(self.process_std),
                "intensity": _num(self.intensity), "lowfreq_ratio": _num(self.lowfreq_ratio),
                "ljung_box_p": _num(self.ljung_box_p),
                "systematic_share": _num(self.systematic_share), "selected": list(self.selected),
                "top_regressors": [r.to_json() for r in self.regressors[:5]],
                "flagged": self.flagged, "windows": [w.to_json() for w in self.windows],
                "condition_bins": _jsonable(self.condition_bins)}


@dataclasses.dataclass(frozen=True)
class OutputEvidence:
    """Locate statistics of one output channel."""

    output: str
    n: int
    rms_smooth: float
    rms_pred: float
    rms_sim: float
    noise_std: float | None
    bias: RegressorStat             # regressor "1": coef = mean offset
    scale: RegressorStat            # regressor = the channel itself: coef = scale error
    rate: RegressorStat | None      # regressor = the channel's rate: coef = time skew [s]
    lag_s: float                    # lag maximising the cross-correlation of y_meas and y_smooth
    offsets: tuple[RegressorStat, ...]   # against angular rates / accelerations
    systematic_share: float
    flagged: bool
    windows: tuple[Window, ...]
    whiteness_p: float = 1.0        # Ljung–Box p of the one-step prediction residual (innovation)
    whiteness_log10p: float = 0.0   # its log10, exact where the p-value underflows

    def regressor(self, name: str) -> RegressorStat | None:
        for r in (self.bias, self.scale, self.rate, *self.offsets):
            if r is not None and r.name == name:
                return r
        return None

    def to_json(self) -> dict:
        return {"output": self.output, "n": self.n, "rms_smooth": _num(self.rms_smooth),
                "rms_pred": _num(self.rms_pred), "rms_sim": _num(self.rms_sim),
                "noise_std": _num(self.noise_std), "bias": self.bias.to_json(),
                "scale": self.scale.to_json(),
                "rate": None if self.rate is None else self.rate.to_json(),
                "lag_s": _num(self.lag_s), "offsets": [r.to_json() for r in self.offsets],
                "systematic_share": _num(self.systematic_share), "flagged": self.flagged,
                "whiteness_p": _num(self.whiteness_p),
                "whiteness_log10p": _num(self.whiteness_log10p),
                "windows": [w.to_json() for w in self.windows]}


@dataclasses.dataclass(frozen=True)
class Evidence:
    """Everything locate found, per state equation and per output channel."""

    states: Mapping[str, StateEvidence]
    outputs: Mapping[str, OutputEvidence]
    dt: float
    alpha: float = ALPHA_LOCATE

    def flagged_states(self) -> list[str]:
        return [s for s, ev in self.states.items() if ev.flagged]

    def flagged_outputs(self) -> list[str]:
        return [o for o, ev in self.outputs.items() if ev.flagged]

    def state_score(self, state: str, regressor: str) -> float:
        """−log10 of the Bonferroni-corrected p of ``regressor`` in the ``state`` equation."""
        ev = self.states.get(state)
        if ev is None:
            return 0.0
        r = ev.regressor(regressor)
        if r is None:
            return 0.0
        return _score(r.log10_p(), len(ev.regressors))

    def output_score(self, output: str, regressor: str) -> float:
        ev = self.outputs.get(output)
        if ev is None:
            return 0.0
        r = ev.regressor(regressor)
        if r is None:
            return 0.0
        return _score(r.log10_p(), 3 + len(ev.offsets))

    def colored_score(self, state: str | None = None) -> float:
        """Support for unexplained coloured structure (missing dynamics, wind).

        The one-step prediction residuals (innovations) of the steady-state Kalman
        filter are white for a correct model; their Ljung–Box test (Bonferroni over
        the outputs) is weighed down by the share a single equation-error regressor
        already explains (then a deterministic term is the better explanation).
        """
        if not self.outputs:
            return 0.0
        lg = min(ev.whiteness_log10p for ev in self.outputs.values())
        explained = 0.0
        for s, ev in self.states.items():
            if state is None or s == state:
                b = ev.best()
                if b is not None and b.p * len(ev.regressors) < self.alpha:
                    explained = max(explained, b.share)
        for ev in self.outputs.values():
            if ev.flagged:
                explained = max(explained, ev.systematic_share)
        # a fallback explanation: half weight against a specific deterministic one
        return float(0.5 * _score(lg, len(self.outputs)) * (1.0 - explained) ** 2)

    def summary(self) -> str:
        lines = []
        for s, ev in self.states.items():
            b = ev.best()
            lines.append(f"state {s}: {'FLAGGED' if ev.flagged else 'ok'}; systematic share "
                         f"{ev.systematic_share:.0%}; best regressor "
                         f"{b.name if b else '-'} (p={b.p if b else float('nan'):.2g}); "
                         f"noise intensity {ev.intensity:.3g}")
        for o, ev in self.outputs.items():
            lines.append(f"output {o}: {'FLAGGED' if ev.flagged else 'ok'}; bias p={ev.bias.p:.2g}, "
                         f"scale p={ev.scale.p:.2g}, lag {ev.lag_s:+.3g} s, "
                         f"innovation whiteness p={ev.whiteness_p:.2g}")
        return "\n".join(lines)

    def to_json(self) -> dict:
        return {"alpha": self.alpha, "dt": _num(self.dt),
                "flagged_states": self.flagged_states(), "flagged_outputs": self.flagged_outputs(),
                "states": {k: v.to_json() for k, v in self.states.items()},
                "outputs": {k: v.to_json() for k, v in self.outputs.items()}}


# ---------------------------------------------------------------------------
# statistics helpers
# ---------------------------------------------------------------------------

def _num(v):
    if v is None:
        return None
    try:
        f = float(v)
    except (TypeError, ValueError):
        return v
    return f if math.isfinite(f) else None


def _jsonable(obj):
    if isinstance(obj, Mapping):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, (np.floating, float, int, np.integer)):
        return _num(obj)
    return obj


def _score(log10p: float, m: int | float = 1) -> float:
    """−log10 of the Bonferroni-corrected p-value ``min(1, m·p)``, computed from log10 p so
    that it does not saturate where p underflows: strong effects keep their order."""
    if not math.isfinite(log10p):
        return 0.0
    return float(max(0.0, -(log10p + math.log10(max(m, 1)))))


def _t_log10p(tstat: float, df: float) -> float:
    """log10 of the two-sided Student-t p-value ``2·sf(|t|)``, without underflow.

    ``2·sf(|t|) = I_x(ν/2, 1/2)`` with ``x = ν/(ν + t²)`` (regularised incomplete beta), and
    ``I_x(a, b) = x^a (1−x)^b ₂F₁(a+b, 1; a+1; x) / (a B(a, b))`` (DLMF 8.17.8), evaluated in
    logs where scipy's ``logsf`` underflows to −∞.
    """
    from scipy import special

    lg = stats.t.logsf(abs(tstat), df)
    if math.isfinite(lg):
        return float((math.log(2.0) + lg) / _LN10)
    a, b = 0.5 * df, 0.5
    x = df / (df + tstat * tstat)
    ln = (a * math.log(x) + b * math.log1p(-x) - math.log(a) - special.betaln(a, b)
          + math.log(special.hyp2f1(a + b, 1.0, a + 1.0, x)))
    return float(ln / _LN10)


def _acf(x: np.ndarray, nlags: int) -> np.ndarray:
    x = x - x.mean()
    d = float(x @ x)
    if d <= 0:
        return np.zeros(nlags + 1)
    n = len(x)
    f = np.fft.rfft(x, 2 * n)
    ac = np.fft.irfft(f * np.conj(f))[: nlags + 1] / d
    return ac


def _segments_acf(x: np.ndarray, seg: Sequence[slice], nlags: int) -> np.ndarray:
    acc = np.zeros(nlags + 1)
    w = 0.0
    for s in seg:
        xs = x[s]
        if len(xs) > nlags + 2:
            acc += _acf(xs, nlags) * len(xs)
            w += len(xs)
    return acc / w if w > 0 else acc


def corr_test(e: np.ndarray, r: np.ndarray, seg: Sequence[slice] | None = None, *,
              name: str = "", nlags: int | None = None) -> RegressorStat:
    """Correlation of residual ``e`` with regressor ``r`` and its p-value (effective sample size).

    ``r`` is centred unless it is constant (the bias regressor "1": then the test
    is the mean-offset t-test with the same effective sample size).
    """
    e = np.asarray(e, float)
    r = np.asarray(r, float)
    ok = np.isfinite(e) & np.isfinite(r)
    n = int(ok.sum())
    if seg is None:
        seg = [slice(0, len(e))]
    if n < 5:
        return RegressorStat(name, 0.0, 0.0, 1.0, float(n), 0.0)
    e0 = np.where(ok, e, 0.0)
    r0 = np.where(ok, r, 0.0)
    K = nlags or int(min(50, max(5, n // 10)))
    const = np.ptp(r[ok]) <= 1e-12 * max(1.0, abs(r[ok]).max())
    if const:
        m = e0[ok].mean()
        sd = e0[ok].std()
        rho = _segments_acf(np.where(ok, e0 - m, 0.0), seg, K)
        n_eff = n / max(1.0, 1 + 2 * np.sum(rho[1:] * (1 - np.arange(1, K + 1) / n)))
        n_eff = float(np.clip(n_eff, 3.0, n))
        tstat = m / (sd / math.sqrt(n_eff)) if sd > 0 else 0.0
        p = 2 * stats.t.sf(abs(tstat), df=max(1.0, n_eff - 1))
        share = m * m / (m * m + sd * sd) if sd > 0 or m != 0 else 0.0
        return RegressorStat(name, float(np.sign(m) * math.sqrt(share)), float(m), float(p),
                             n_eff, float(share),
                             min(0.0, _t_log10p(tstat, max(1.0, n_eff - 1))))
    ec = np.where(ok, e0 - e0[ok].mean(), 0.0)
    rc = np.where(ok, r0 - r0[ok].mean(), 0.0)
    se, sr = math.sqrt(ec @ ec), math.sqrt(rc @ rc)
    if se <= 0 or sr <= 0:
        return RegressorStat(name, 0.0, 0.0, 1.0, float(n), 0.0)
    c = float(ec @ rc / (se * sr))
    coef = float(ec @ rc / (rc @ rc))
    rho_e = _segments_acf(ec, seg, K)
    rho_r = _segments_acf(rc, seg, K)
    n_eff = n / max(1.0, 1 + 2 * np.sum(rho_e[1:] * rho_r[1:]))
    n_eff = float(np.clip(n_eff, 4.0, n))
    c2 = min(c * c, 1 - 1e-15)
    tstat = math.sqrt(c2 * (n_eff - 2) / (1 - c2))
    p = 2 * stats.t.sf(tstat, df=n_eff - 2)
    return RegressorStat(name, c, coef, float(p), n_eff, float(c * c),
                         min(0.0, _t_log10p(tstat, n_eff - 2)))


def ljung_box(e: np.ndarray, seg: Sequence[slice], nlags: int = 20) -> float:
    """Ljung–Box p-value of ``e`` (see :func:`ljung_box_log10p`)."""
    return float(10.0 ** ljung_box_log10p(e, seg, nlags))


def ljung_box_log10p(e: np.ndarray, seg: Sequence[slice], nlags: int = 20) -> float:
    """log10 of the Ljung–Box p-value ``Q = n(n+2) Σ_k ρ_k²/(n−k) ~ χ²(nlags)``, exact in logs."""
    n = int(np.isfinite(e).sum())
    if n < nlags + 5:
        return 0.0
    e = np.where(np.isfinite(e), e - np.nanmean(e), 0.0)
    rho = _segments_acf(e, seg, nlags)
    k = np.arange(1, nlags + 1)
    q = n * (n + 2) * np.sum(rho[1:] ** 2 / (n - k))
    return float(min(0.0, chi2_log10sf(q, nlags)))


def lowfreq_ratio(e: np.ndarray, seg: Sequence[slice], frac: float = 0.1) -> float:
    """Share of power of ``e`` below ``frac`` × Nyquist, divided by ``frac`` (1 for white noise)."""
    num = den = 0.0
    for s in seg:
        x = e[s]
        x = x[np.isfinite(x)]
        if len(x) < 16:
            continue
        x = x - x.mean()
        P = np.abs(np.fft.rfft(x)) ** 2
        P = P[1:]
        m = max(1, int(round(frac * len(P))))
        num += P[:m].sum()
        den += P.sum()
    if den <= 0:
        return float("nan")
    return float(num / den / frac)


def xcorr_lag(a: np.ndarray, b: np.ndarray, dt: float, max_lag: int = 25) -> float:
    """Lag (s) by which ``a`` lags ``b`` (a(t) ≈ b(t − lag)), sub-sample by parabolic peak fit."""
    ok = np.isfinite(a) & np.isfinite(b)
    a = np.where(ok, a - a[ok].mean(), 0.0)
    b = np.where(ok, b - b[ok].mean(), 0.0)
    n = len(a)
    max_lag = min(max_lag, n // 4)
    if max_lag < 1 or not np.any(a) or not np.any(b):
        return 0.0
    lags = np.arange(-max_lag, max_lag + 1)
    c = np.array([np.dot(a[max(0, k):n + min(0, k)], b[max(0, -k):n - max(0, k)]) for k in lags])
    i = int(np.argmax(c))
    frac = 0.0
    if 0 < i < len(c) - 1:
        den = c[i - 1] - 2 * c[i] + c[i + 1]
        if den < 0:
            frac = 0.5 * (c[i - 1] - c[i + 1]) / den
    return float((lags[i] + frac) * dt)


def _windows(res: np.ndarray, level: float, t: np.ndarray, rec_name: str,
             cond: Mapping[str, np.ndarray], dt: float, *, width_s: float = 1.0,
             alpha: float = ALPHA_LOCATE, max_windows: int = 5) -> list[Window]:
    n = len(res)
    w = int(max(8, min(n // 4, round(width_s / dt)))) if n >= 32 else 0
    if w == 0 or not np.isfinite(level) or level <= 0:
        return []
    z2 = np.where(np.isfinite(res), (res / level) ** 2, 0.0)
    cs = np.concatenate([[0.0], np.cumsum(z2)])
    ms = (cs[w:] - cs[:-w]) / w                                  # moving mean square, n-w+1
    bound = stats.chi2.ppf(1 - alpha / max(1, n / w), w) / w
    hot = ms > bound
    out = []
    i = 0
    while i < len(hot):
        if hot[i]:
            j = i
            while j + 1 < len(hot) and hot[j + 1]:
                j += 1
            a, b = i, min(n - 1, j + w - 1)
            condition = {k: [float(np.nanmin(v[a:b + 1])), float(np.nanmean(v[a:b + 1])),
                             float(np.nanmax(v[a:b + 1]))] for k, v in cond.items()}
            out.append(Window(rec_name, float(t[a]), float(t[b]),
                              float(math.sqrt(ms[i:j + 1].max())), condition))
            i = j + 1
        else:
            i += 1
    out.sort(key=lambda wi: -wi.rms_ratio)
    return out[:max_windows]


def _robust_level(x: np.ndarray) -> float:
    x = x[np.isfinite(x)]
    if len(x) == 0:
        return float("nan")
    return float(1.4826 * np.median(np.abs(x - np.median(x))))


# ---------------------------------------------------------------------------
# regressor library for state equations
# ---------------------------------------------------------------------------

def state_roles(state_names: Sequence[str],
                roles: Mapping[str, str] | None = None) -> dict[str, str]:
    """``{state: role}`` (α, β, p, q, r, V...): ``roles`` when given (the model's, which also
    reads descriptions: :meth:`.base.ModelInfo.state_roles`), else from the names alone."""
    if roles is not None:
        return {s: roles[s] for s in state_names if s in roles}
    return roles_of(state_names)


def state_regressors(state_names: Sequence[str], input_names: Sequence[str],
                     X: np.ndarray, U: np.ndarray, Xdot: np.ndarray, Udot: np.ndarray,
                     *, dt: float | None = None, seg: Sequence[slice] | None = None,
                     roles: Mapping[str, str] | None = None) -> dict[str, np.ndarray]:
    """Candidate regressors for the equation errors (names are used by the catalogue).

    ``x:<s>``, ``u:<i>``: linear; ``sq:<v>``: square of a flow angle or input; ``cube:<β>``:
    cube of the sideslip angle;
    ``prod:<a>*<b>``: flow angle × other state/input; ``hinge:<v>:<b>``:
    ``max(v − b, 0)`` at the 70th/85th percentile (and ``max(b − v, 0)`` at the
    15th/30th as ``hingelo``); ``udot:<i>``: input rate (time delay / actuator lag);
    ``xdot:<a>``: flow-angle rate (unsteady aerodynamics; through the downwash-lag filter of
    :func:`downwash_tau` when ``dt`` and ``seg`` are given); ``lp:<v>``: ``v`` through a
    first-order low-pass of time constant :data:`LOWPASS_TAU` (a missing slow mode).
    ``roles`` (:func:`state_roles`) says which states are flow angles.
    """
    roles = state_roles(state_names, roles)

    def _is_flow_angle(name: str) -> bool:
        return roles.get(name) in ("alpha", "beta")

    reg: dict[str, np.ndarray] = {}
    for j, s in enumerate(state_names):
        reg[f"x:{s}"] = X[:, j]
    for j, i in enumerate(input_names):
        reg[f"u:{i}"] = U[:, j]
    nonlin = [(s, X[:, j]) for j, s in enumerate(state_names) if _is_flow_angle(s)]
    nonlin += [(i, U[:, j]) for j, i in enumerate(input_names)]
    for v, col in nonlin:
        if np.ptp(col) <= 0:
            continue
        reg[f"sq:{v}"] = col ** 2
        if roles.get(v) == "beta":
            reg[f"cube:{v}"] = col ** 3      # odd in sideslip (a symmetric aircraft)
        for kind, b in break_points(col):
            reg[f"{kind}:{v}:{b:.6g}"] = (np.maximum(col - b, 0.0) if kind == "hinge"
                                          else np.maximum(b - col, 0.0))
    for j, s in enumerate(state_names):
        if not _is_flow_angle(s):
            continue
        for k, o in enumerate(state_names):
            if o != s:
                reg[f"prod:{s}*{o}"] = X[:, j] * X[:, k]
        for k, i in enumerate(input_names):
            reg[f"prod:{s}*{i}"] = X[:, j] * U[:, k]
    for j, i in enumerate(input_names):
        if np.ptp(U[:, j]) > 0:
            reg[f"udot:{i}"] = Udot[:, j]
    for j, s in enumerate(state_names):
        if _is_flow_angle(s):
            if seg is not None and dt:
                # what the unsteady-aerodynamics candidate adds: the flow-angle rate through
                # the downwash lag, (a − a_l)/τ_l with a_l = a low-passed by τ_l
                tl = downwash_tau(dt)
                reg[f"xdot:{s}"] = (X[:, j] - lowpass(X[:, j], dt, tl, seg, from_first=True)) / tl
            else:
                reg[f"xdot:{s}"] = Xdot[:, j]
    if seg is not None and dt:
        for j, s in enumerate(state_names):
            reg[f"lp:{s}"] = lowpass(X[:, j], dt, LOWPASS_TAU, seg)
        for j, i in enumerate(input_names):
            if np.ptp(U[:, j]) > 0:
                reg[f"lp:{i}"] = lowpass(U[:, j], dt, LOWPASS_TAU, seg)
                # signature of a short lag/delay of the input: lowpass(u, 3T) − u
                reg[f"lag:{i}"] = lowpass(U[:, j], dt, 3 * dt, seg) - U[:, j]
        sp = speed_proxy(state_names, X, dt, seg, roles=roles)
        if sp is not None:
            reg[SPEED_REGRESSOR] = sp
    return reg


#: locate regressor of the speed (phugoid) motion a short-period model leaves out
SPEED_REGRESSOR = "speed:kin"

def speed_proxy(state_names: Sequence[str], X: np.ndarray, dt: float,
                seg: Sequence[slice], *, roles: Mapping[str, str] | None = None
                ) -> np.ndarray | None:
    """Shape of the airspeed perturbation a short-period model leaves out, from kinematics.

    Along the flight path gravity changes the speed as ``ΔV̇ = −g Δγ`` (plus drag and thrust
    terms), and the flight-path angle is ``γ = θ − α`` with ``θ̇ = q``. Per segment:
    ``θ_k = Σ_{i<k} q_i T``, ``Δγ = γ − mean(γ)`` (the trim path angle is unknown),
    ``ΔV_k ∝ −Σ_{i<k} Δγ_i T`` minus its mean (the scale ``g`` and the sign do not matter to a
    correlation). Returns None unless the model has an angle-of-attack state, a pitch rate
    ``q`` and no speed state (a state in the role V, or named ``u``); roles as in
    :func:`state_roles`.
    """
    roles = state_roles(state_names, roles)
    by_role = {r: s for s, r in roles.items()}
    if "V" in by_role or any(s.lower() == "u" for s in state_names):
        return None
    if "alpha" not in by_role or "q" not in by_role:
        return None
    ja, jq = state_names.index(by_role["alpha"]), state_names.index(by_role["q"])
    out = np.zeros(X.shape[0])
    for s in seg:
        a, q = X[s, ja], X[s, jq]
        if len(a) < 3 or not (np.all(np.isfinite(a)) and np.all(np.isfinite(q))):
            continue
        theta = np.concatenate([[0.0], np.cumsum(q[:-1]) * dt])
        gam = theta - a
        gam = gam - gam.mean()
        dv = -np.concatenate([[0.0], np.cumsum(gam[:-1]) * dt])
        out[s] = dv - dv.mean()
    return out if np.ptp(out) > 0 else None


#: time constant (s) of the low-passed regressors ``lp:<v>`` (signature of a missing slow mode)
LOWPASS_TAU = 2.0


def downwash_tau(dt: float | None) -> float:
    """Time constant (s) of the downwash-lag filter of the unsteady-aerodynamics candidate
    (and of its locate regressor ``xdot:<angle>``): four samples, at least 0.1 s."""
    return max(0.1, 4 * (dt or 0.025))


def lowpass(x: np.ndarray, dt: float, tau: float, seg: Sequence[slice], *,
            from_first: bool = False) -> np.ndarray:
    """First-order low-pass ``z' = (x − z)/τ`` (exact discretisation), restarted per segment
    at 0 (a mode excited from rest) or, with ``from_first``, at the segment's first value
    (a lag of the signal itself)."""
    a = math.exp(-dt / tau)
    out = np.empty_like(x)
    for s in seg:
        xs = x[s]
        if len(xs) == 0:
            continue
        z = float(xs[0]) if from_first and np.isfinite(xs[0]) else 0.0
        o = np.empty_like(xs)
        for k, v in enumerate(xs):
            o[k] = z
            z = a * z + (1 - a) * v
        out[s] = o
    return out


#: share of the samples at one exact value that makes it a rest value of the variable
ATOM_SHARE = 0.05
#: fewest samples off the rest values for a break to be placed
MIN_MOVING = 20


def break_points(col: np.ndarray) -> list[tuple[str, float]]:
    """Break points tried for ``max(v − b, 0)`` ("hinge") and ``max(b − v, 0)`` ("hingelo"):
    percentiles of the values the variable moves through.

    A value it rests at (a control at trim between manoeuvres: an atom holding at least
    :data:`ATOM_SHARE` of the samples) is left out first: a break there puts the kink of
    ``max(v − b, 0)`` under many samples at once, so the ELBO is not differentiable in ``b``
    and the break's refit cannot converge (session 47: an independent lateral record's
    rudder at 0 gave ``hinge:dr:0`` and ``hingelo:dr:0``, both NOT converged on every case)."""
    col = np.asarray(col, float)
    col = col[np.isfinite(col)]
    if len(col) == 0 or np.ptp(col) <= 0:
        return []
    values, counts = np.unique(col, return_counts=True)
    atoms = values[counts >= ATOM_SHARE * len(col)]
    if len(atoms):
        col = col[~np.isin(col, atoms)]
        if len(col) < MIN_MOVING or np.ptp(col) <= 0:
            return []
    out = [("hinge", float(f"{np.percentile(col, q):.6g}")) for q in (70, 85)]
    out += [("hingelo", float(f"{np.percentile(col, q):.6g}")) for q in (15, 30)]
    return out


def _ols_share(e: np.ndarray, cols: list[np.ndarray]) -> float:
    ok = np.isfinite(e)
    if not cols or ok.sum() < len(cols) + 3:
        return 0.0
    A = np.column_stack([np.ones(ok.sum())] + [c[ok] for c in cols])
    y = e[ok]
    coef, *_ = np.linalg.lstsq(A, y, rcond=None)
    r = y - A @ coef
    v = np.var(y)
    return float(max(0.0, 1 - np.var(r) / v)) if v > 0 else 0.0


def _stepwise(e, reg: Mapping[str, np.ndarray], seg, alpha: float, max_terms: int = 3):
    chosen: list[str] = []
    resid = e.copy()
    for _ in range(max_terms):
        best = None
        for k, r in reg.items():
            if k in chosen:
                continue
            st = corr_test(resid, r, seg, name=k)
            if best is None or st.log10_p() < best.log10_p():
                best = st
        if best is None or best.p * len(reg) >= alpha:
            break
        chosen.append(best.name)
        ok = np.isfinite(e)
        A = np.column_stack([np.ones(ok.sum())] + [reg[c][ok] for c in chosen])
        coef, *_ = np.linalg.lstsq(A, e[ok], rcond=None)
        resid = np.full_like(e, np.nan)
        resid[ok] = e[ok] - A @ coef
    return tuple(chosen), _ols_share(e, [reg[c] for c in chosen])


# ---------------------------------------------------------------------------
# main entry
# ---------------------------------------------------------------------------

def _concat(records: Sequence[LocateRecord], attr: str, trim: bool = False):
    arrs = []
    for r in records:
        a = np.asarray(getattr(r, attr), float)
        arrs.append(a[:-1] if trim else a)
    return np.concatenate(arrs, axis=0)


def _segments(lengths: Sequence[int]) -> list[slice]:
    out, i = [], 0
    for n in lengths:
        out.append(slice(i, i + n))
        i += n
    return out


def _rate(y: np.ndarray, dt: float, seg) -> np.ndarray:
    out = np.full_like(y, np.nan)
    for s in seg:
        ys = y[s]
        if len(ys) >= 3:
            out[s] = np.gradient(ys, dt, axis=0)
    return out


class _Partial:
    """Projection onto the orthogonal complement of ``[1, Z]`` (NaN rows ignored).

    ``r ↦ r − P r`` with ``P`` the least-squares projection on the constant and the
    columns of ``Z`` (an orthonormal basis from the SVD, rank-truncated), so that a
    regressor is tested only for what the existing terms of the equation cannot
    absorb (the added-variable / partial-correlation test of stepwise regression).
    """

    def __init__(self, Z: np.ndarray | None, n: int):
        cols = [np.ones(n)]
        if Z is not None and np.size(Z):
            Z = np.asarray(Z, float).reshape(n, -1)
            cols += [Z[:, j] for j in range(Z.shape[1])]
        A = np.column_stack(cols)
        self.ok = np.all(np.isfinite(A), axis=1)
        A = A[self.ok]
        scale = np.sqrt(np.mean(A ** 2, axis=0))
        A = A[:, scale > 0] / scale[scale > 0]
        u, sv, _ = np.linalg.svd(A, full_matrices=False)
        keep = sv > 1e-9 * sv[0] if len(sv) else np.zeros(0, bool)
        self.Q = u[:, keep]

    def __call__(self, r: np.ndarray) -> np.ndarray | None:
        """``r`` with its projection removed; ``None`` when (almost) nothing is left."""
        r = np.asarray(r, float)
        ok = self.ok & np.isfinite(r)
        if ok.sum() < 5:
            return None
        out = np.full_like(r, np.nan)
        rr = np.where(ok, r, 0.0)[self.ok]
        res = rr - self.Q @ (self.Q.T @ rr)
        v0 = np.var(r[ok])
        if v0 <= 0 or np.var(res) <= PARTIAL_TOL * v0:
            return None
        out[self.ok] = res
        out[~np.isfinite(r)] = np.nan
        return out


#: a regressor whose variance left after partialling is below this share of its own
#: variance is absorbed by the existing terms of the equation (not testable there)
PARTIAL_TOL = 1e-6


def locate(records: Sequence[LocateRecord], *, state_names: Sequence[str],
           input_names: Sequence[str], output_names: Sequence[str],
           process_std: Mapping[str, float] | None = None,
           measurement_std: Mapping[str, float] | None = None,
           alpha: float = ALPHA_LOCATE, min_share: float = 0.02,
           window_s: float = 1.0,
           nuisance: Mapping[str, np.ndarray] | None = None,
           roles: Mapping[str, str] | None = None,
           kinematics: Mapping[str, frozenset[str]] | None = None) -> Evidence:
    """Locate mismatches; see the module docstring for the statistics.

    Args:
        records: per-record signals of the fit (at least one).
        state_names, input_names, output_names: model names in array-column order.
        process_std: estimated process-noise std per state (state unit/√s).
        measurement_std: estimated measurement-noise std per output.
        alpha: significance for flagging (after Bonferroni within each target).
        min_share: minimum share of residual variance a structure must explain to be flagged.
        window_s: width of the moving-RMS window.
        nuisance: per state, the directions its existing terms can already move the
            drift, an ``(n, k)`` array aligned with the equation errors (records
            concatenated, last sample of each dropped), e.g. the sensitivities
            ``∂f_s/∂θ_j`` of the free parameters along the smoothed path. Every
            regressor and the equation error are then tested as *partial*
            correlations given them (added-variable test): a term collinear with
            the model's own terms (``α̇ ≈ Z_α α + q + Z_δ δ`` against ``M_α, M_q,
            M_δ``) is tested for the part the refit could not absorb. ``None``:
            plain correlations.
        roles: ``{state: role}`` (α, β, p, q, r, V: :meth:`.base.ModelInfo.state_roles`,
            which reads the states' descriptions too); ``None``: recognised by name.
        kinematics: ``{state: variables}`` for the equations that are exact geometry
            (``φ̇ = p + tanθ (q sinφ + r cosφ)``, ``θ̇ = q``): their errors are tested only
            against the constant and the linear terms of the named variables (the rates of
            the equation's dimension), since no aerodynamic, nonlinear or input term acts
            on an attitude directly; an error there points at the sensors or the timing of
            those rates (:func:`.catalogue.kinematic_rates`). ``None``: every regressor.
    """
    roles = state_roles(state_names, roles)
    process_std = dict(process_std or {})
    measurement_std = dict(measurement_std or {})
    if not records:
        raise ValueError("locate needs at least one record")
    dt = float(np.median(np.concatenate([np.diff(r.t) for r in records])))
    states = _state_evidence(records, state_names, input_names, process_std, dt, alpha=alpha,
                             min_share=min_share, window_s=window_s, nuisance=nuisance,
                             roles=roles, kinematics=dict(kinematics or {}))
    outputs = _output_evidence(records, state_names, input_names, output_names, measurement_std, dt,
                               alpha=alpha, min_share=min_share, window_s=window_s, roles=roles)
    return Evidence(states, outputs, dt, alpha)


def _state_evidence(records, state_names, input_names, process_std, dt, *, alpha, min_share, window_s,
                    nuisance, roles, kinematics=None) -> dict[str, StateEvidence]:
    """Per state equation: the equation error e = ẋ_fd − f(x̂) (records concatenated, last sample of
    each dropped) tested against every state regressor (partial correlations given ``nuisance``),
    stepwise selection, whiteness and low-frequency share, and its windows of excess error."""
    seg_s = _segments([len(r.t) - 1 for r in records])
    X = _concat(records, "x_smooth", trim=True)
    U = _concat(records, "u", trim=True)
    E = _concat(records, "xdot_fd") - _concat(records, "f_smooth")
    Xdot = _concat(records, "xdot_fd")
    Udot = np.concatenate([np.diff(np.asarray(r.u, float), axis=0) / dt for r in records], axis=0)
    tt = _concat(records, "t", trim=True)
    reg = state_regressors(state_names, input_names, X, U, Xdot, Udot, dt=dt, seg=seg_s,
                           roles=roles)
    cond_src = {s: X[:, j] for j, s in enumerate(state_names)
                if roles.get(s) in ("alpha", "beta")}
    cond_src.update({i: U[:, j] for j, i in enumerate(input_names)})
    bin_var = next((s for s in state_names if roles.get(s) == "alpha"),
                   next(iter(cond_src), None))
    total_time = sum(float(r.t[-1] - r.t[0]) for r in records)
    states: dict[str, StateEvidence] = {}
    for j, s in enumerate(state_names):
        e = E[:, j]
        rms = float(np.sqrt(np.nanmean(e ** 2)))
        g = process_std.get(s)
        level = g / math.sqrt(dt) if g is not None and g > 0 else _robust_level(e)
        own = {k: v for k, v in reg.items() if k != f"xdot:{s}"}
        if kinematics and s in kinematics:
            own = {k: v for k, v in own.items()
                   if k.split(":", 1)[0] in ("x", "u") and k.split(":", 1)[1] in kinematics[s]
                   and k != f"x:{s}"}
        e_t = e
        if nuisance is not None and nuisance.get(s) is not None:
            part = _Partial(nuisance[s], len(e))
            e_t = part(e)
            if e_t is None:
                e_t = e
            own = {k: r for k, r in ((k, part(v)) for k, v in own.items()) if r is not None}
        # the constant "1" (a missing trim term) is tested on the equation error itself: a
        # mean offset, which partialling on [1, Z] would remove
        tests = sorted([*(corr_test(e_t, v, seg_s, name=k) for k, v in own.items()),
                        corr_test(e, np.ones_like(e), seg_s, name="1")],
                       key=lambda r: r.log10_p())
        lb = ljung_box(e, seg_s)
        lf = lowfreq_ratio(e, seg_s)
        sx = float(np.nanstd(X[:, j]))
        intensity = (g * math.sqrt(max(total_time, dt)) / sx) if (g and sx > 0) else float("nan")
        selected, share = _stepwise(e_t, own, seg_s, alpha)
        flagged = bool(selected) and share >= min_share
        wins = []
        for rec, sg in zip(records, seg_s):
            wins += _windows(e[sg], _robust_level(e) if not np.isfinite(level) else level,
                             tt[sg], rec.name, {k: v[sg] for k, v in cond_src.items()}, dt,
                             width_s=window_s, alpha=alpha)
        bins = _condition_bins(e, X[:, state_names.index(bin_var)] if bin_var in state_names
                               else cond_src.get(bin_var), bin_var)
        states[s] = StateEvidence(s, int(np.isfinite(e).sum()), rms, float(level), g,
                                  float(intensity), lf, lb, float(share), selected,
                                  tuple(tests), flagged, tuple(wins[:5]), bins)
    return states


def _output_evidence(records, state_names, input_names, output_names, measurement_std, dt, *, alpha,
                     min_share, window_s, roles) -> dict[str, OutputEvidence]:
    """Per output: the smoothed and predicted residuals tested for a bias, a scale error, a rate
    term and rate/acceleration offsets of the rate states (:func:`_output_tests`), a lag, and
    windows of the simulation residual."""
    seg_o = _segments([len(r.t) for r in records])
    Ym = _concat(records, "y_meas")
    Ys = _concat(records, "y_smooth")
    Yp = _concat(records, "y_pred")
    Yi = _concat(records, "y_sim")
    Xs = _concat(records, "x_smooth")
    t_o = _concat(records, "t")
    Xs_dot = _rate(Xs, dt, seg_o)
    Ys_dot = _rate(Ys, dt, seg_o)
    rates = [(s, j) for j, s in enumerate(state_names) if roles.get(s) in ("p", "q", "r")]
    ocond = {s: Xs[:, j] for j, s in enumerate(state_names) if roles.get(s) in ("alpha", "beta")}
    ocond.update({i: np.concatenate([np.asarray(r.u, float)[:, j] for r in records])
                  for j, i in enumerate(input_names)})
    outputs: dict[str, OutputEvidence] = {}
    for j, o in enumerate(output_names):
        ys = Ys[:, j]
        res_s = Ym[:, j] - ys
        res_p = Ym[:, j] - Yp[:, j]
        bias, scale, rate, offs, regs = _output_tests(res_s, res_p, ys, Ys_dot[:, j], Xs, Xs_dot, rates, seg_o)
        lag = float(np.mean([xcorr_lag(Ym[sg, j], ys[sg], dt) for sg in seg_o]))
        m = 3 + len(offs)
        tests = [t_ for t_ in (bias, scale, rate, *offs) if t_ is not None]
        sig = [t_ for t_ in tests if t_.p * m < alpha]
        share = max((t_.share for t_ in sig), default=0.0)
        sigma = measurement_std.get(o)
        level = sigma if sigma else _robust_level(res_s)
        wins = []
        for rec, sg in zip(records, seg_o):
            wins += _windows(Ym[sg, j] - Yi[sg, j], level, t_o[sg], rec.name,
                             {k: v[sg] for k, v in ocond.items()}, dt, width_s=window_s,
                             alpha=alpha)
        outputs[o] = OutputEvidence(
            o, int(np.isfinite(res_s).sum()), _rms(res_s), _rms(res_p), _rms(Ym[:, j] - Yi[:, j]),
            sigma, bias, scale, rate, lag, tuple(offs), float(share),
            bool(sig) and share >= min_share, tuple(wins[:5]),
            10.0 ** (wl := ljung_box_log10p(
                _remove(res_p, [regs[t_.name] for t_ in sig if t_.name in regs]), seg_o)), wl)
    return outputs


def _output_tests(res_s, res_p, ys, ys_dot, Xs, Xs_dot, rates, seg_o):
    """One output's regressor tests: each regressor against the smoothed and the predicted
    residual, the more significant kept with a factor 2 (two looks). Returns (bias, scale, rate
    (None when ŷ is constant), [rate:s, accel:s per rate state], {name: regressor})."""

    def test(name, r):
        a = corr_test(res_s, r, seg_o, name=name)
        b = corr_test(res_p, r, seg_o, name=name)
        st = a if a.log10_p() <= b.log10_p() else b
        return st.with_factor(2.0)

    regs = {"bias": np.ones_like(ys), "scale": ys, "rate": ys_dot}
    regs.update({f"rate:{s}": Xs[:, k] for s, k in rates})
    regs.update({f"accel:{s}": Xs_dot[:, k] for s, k in rates})
    bias = test("bias", np.ones_like(ys))
    scale = test("scale", ys)
    rate = test("rate", ys_dot) if np.nanstd(ys_dot) > 0 else None
    offs = []
    for s, k in rates:
        offs.append(test(f"rate:{s}", Xs[:, k]))
        offs.append(test(f"accel:{s}", Xs_dot[:, k]))
    return bias, scale, rate, offs, regs


def _remove(e: np.ndarray, cols: list[np.ndarray]) -> np.ndarray:
    """``e`` minus its least-squares fit on ``cols`` (NaN-aware)."""
    if not cols:
        return e
    ok = np.isfinite(e)
    for c in cols:
        ok &= np.isfinite(c)
    if ok.sum() <= len(cols) + 2:
        return e
    A = np.column_stack([c[ok] for c in cols])
    coef, *_ = np.linalg.lstsq(A, e[ok], rcond=None)
    out = np.full_like(e, np.nan)
    out[ok] = e[ok] - A @ coef
    return out


def _rms(x):
    return float(np.sqrt(np.nanmean(np.asarray(x, float) ** 2)))


def _condition_bins(e, v, name, nbins: int = 4) -> dict:
    if v is None or name is None or np.nanstd(v) <= 0:
        return {}
    edges = np.nanpercentile(v, np.linspace(0, 100, nbins + 1))
    out = []
    for a, b in zip(edges[:-1], edges[1:]):
        m = (v >= a) & (v <= b) & np.isfinite(e)
        out.append({"range": [float(a), float(b)], "rms": _rms(e[m]) if m.any() else None})
    r = [b["rms"] for b in out if b["rms"]]
    return {"variable": name, "bins": out,
            "max_over_min": (max(r) / min(r)) if r and min(r) > 0 else None}
