"""``findings.json`` and the diagnose report section (HTML with embedded plots).

findings.json (keys in this order)::

    {"vsidgen_version", "spec", "records": {"estimation": [...], "validation": [...]},
     "options": {...}, "conclusion": "plain words",
     "numerics": null | {"kind": "modelling_numerics", "current", "trials": [...],
                         "adopted": null | {"setting", "recommendation", "statistic", ...}},
     "noise_model": null | {"kind": "noise_model", "current", "trials": [...],
                            "adopted": null | {"alternative", "recommendation", "statistic",
                                               "dof", "correlations", "explanation", ...},
                            "significant_not_adopted": null | {"statistic_lower_bound",
                                               "threshold", "dof", "stop_reason", ...}},
     "noise_gust": null | {"kind": "noise_gust", "test", "gusts": [{"velocity", "gust_state",
                                               "correlation_time", "definitions", ...}],
                           "trials": [...], "adopted": null | {"recommendation", "statistic",
                                               "threshold", "dof", "explanation", ...},
                           "checked": absent | {"round", "key", "statistic_without_gust",
                                               "threshold", "statistic_with_gust", "outcome":
                                               "gust_not_significant" | "significant_with_gust"
                                               | "explained_by_gust" | "undecided_with_gust",
                                               ...}},
     "findings": [                      # ranked: order of acceptance (most significant first)
        {"rank": 1, "effect": "missing_derivative", "title": "...",
         "explanation": "plain words", "target": "drift:q",
         "added_terms": {"drift": {"q": "D_q_q*q"}, ...},
         "parameters": {"D_q_q": {"estimate", "std_error", "unit", "at_acceptance"}},
         "evidence": {"elbo_before", "elbo_after", "statistic", "dof", "p_value",
                      "threshold", "alpha", "n_candidates", "test": "...",
                      "validation_elbo_before", "validation_elbo_after",
                      "metrics_before", "metrics_after", "locate": {...}},
         "spec": "DIR/candidates/r1_...yaml"}],
     "final_spec": "path", "base": {"elbo", "metrics"}, "final": {"elbo", "metrics"},
     "locate": {evidence of the base fit}, "rounds": [...],
     "unfinished_round": null | {"round", "base_spec", "base_elbo", "base_val_elbo", "n_candidates",
                                 "refitted": [trial...], "pending": [key...],
                                 "screen": [the round's ranking, as rounds[].screen]},
     "stop": {"reason": "completed" | "time_limit" | "interrupted" | "running",
              "time_limit_s"},
     "reference": null | {"held": bool, "states": [...], "elbo_limit", "elbo_held",
                          "held_converged": bool, "note"?}  (states without process noise:
                          the fit every refit is compared with),
     "report": "diagnose.html", "wall_time_s": ...}
"""

from __future__ import annotations

import html
import math
import pathlib
from collections.abc import Sequence

import numpy as np

from ..atomic import write_text_atomic
from ..estimator.results import StdErrorIssue
from ..report import new_figure, png_data_uri
from ..report import dumps, finite_or_none as _f
from .base import LINEAR_TERM_EFFECTS, NONLINEAR_TERM_EFFECTS, hold_lag, same_physics


def metrics_summary(st) -> dict:
    """Compact RMS metrics of a fitted state: {record: {kind: {channel: rms}}}."""
    out = {}
    for s in st.signals:
        out[s.record] = {kind: {ch: _f(m.get("rms")) for ch, m in (s.metrics.get(kind) or {}).items()}
                         for kind in ("prediction", "simulation", "smoother", "derivative")}
    return out


def _target_metrics(m: dict, target: str) -> dict:
    kind, name = target.split(":", 1)
    out = {}
    for rec, d in m.items():
        if kind == "output":
            out[rec] = {k: d.get(k, {}).get(name) for k in ("prediction", "simulation", "smoother")}
        elif kind == "drift":
            out[rec] = {"derivative": d.get("derivative", {}).get(name)}
        else:
            out[rec] = {"prediction": d.get("prediction", {}), "simulation": d.get("simulation", {})}
    return out


def _params(c, st) -> dict:
    names = list(st.model.parameter_names)
    out = {}
    delay = (c.info or {}).get("delay")
    if delay:  # a profiled transport delay: not a model parameter (the input is shifted)
        out[delay["name"]] = {"estimate": _f(delay["estimate"]), "std_error": _f(delay["std_error"]),
                              "unit": "s", "fixed": False,
                              "description": f"transport delay of {c.info['input']} (profiled)",
                              "spec_value": _f(delay.get("spec_value", delay["estimate"])),
                              "hold_lag": _f(delay.get("hold_lag", 0.0)),
                              "input_hold": delay.get("input_hold")}
    near = {n for f in getattr(st.fit, "std_error_flags", ()) or ()
            if f.issue is StdErrorIssue.AT_BOUND for n in f.parameters}
    lag = (c.info or {}).get("filter") in ("lag", "pade")
    for k, p in enumerate(c.parameters):
        if p.name not in names:
            continue
        i = names.index(p.name)
        # a refit stopped at a kink of the ELBO has no valid curvature there: its finding
        # says "without standard errors", so none is given (it printed ± from the indefinite
        # Hessian beside that sentence; session 44)
        at_kink = bool((c.info or {}).get("stopped_at_kink"))
        se = st.fit.std_errors[i] if not (p.fixed or at_kink) else None
        est = float(st.fit.theta[i])
        ent = {"estimate": _f(est), "std_error": _f(se), "unit": p.unit,
               "fixed": bool(p.fixed), "description": p.description}
        if p.name in near:
            # within 1.96 s.e. of a bound: the Gaussian interval is not valid there
            gaps = [(abs(est - b), side, b) for side, b in (("lower", p.lower), ("upper", p.upper))
                    if b is not None]
            if gaps:
                _, side, b = min(gaps)
                ent["near_bound"] = {"side": side, "bound": _f(b)}
        if lag and k == 0:
            # a lag of an input the model holds over each sample acts on an input already
            # delayed by the hold (half a sample, delay.hold_lag): to first order in s,
            # e^{-sT/2}/(1 + sτ̂) = 1/(1 + s(τ̂ + T/2)), so the physical time constant is τ̂ + T/2
            # (a Padé delay likewise: e^{-sT/2}·e^{-sτ̂} = e^{-s(τ̂ + T/2)})
            hl = hold_lag(st.model, float(np.median([r.dt for r in st.records])))
            ent.update(estimate=_f(est + hl), spec_value=_f(est), hold_lag=_f(hl),
                       input_hold=getattr(st.model, "input_hold", "zoh") or "zoh")
        out[p.name] = ent
    return out


def _records(st) -> dict:
    def info(r):
        return {"name": r.name, "path": None if r.path is None else str(r.path),
                "n_samples": int(len(r.t)), "dt": float(r.dt)}
    return {"estimation": [info(r) for r in st.records],
            "validation": [info(r) for r in st.vrecords]}


def _capital(text: str) -> str:
    return text[:1].upper() + text[1:]


_FLOW_ANGLES = ("alpha", "beta")
_INPUT_FILTERS = ("actuator_lag", "transport_delay", "control_delay")
_DERIVATIVES = {"coefficient_derivative", "output_derivative", "missing_derivative"}


def _channel(target: str) -> str:
    return target.split(":", 1)[-1]


def _mps(unit: str | None) -> float | None:
    """Metres per second of one ``unit`` of a speed (``spec.units.coherent``), or None when
    the unit is not a speed the unit parser knows."""
    from ..errors import SpecError
    from ..spec.units import coherent

    try:
        factor, shown = coherent(unit or "")
    except (SpecError, ValueError):
        return None
    return factor if shown.replace(" ", "") == "m/s" else None


def equivalent_vane(c, st, params: dict) -> dict | None:
    """A time skew τ of a flow angle read as a vane position: ``x = τ·V̄`` metres ahead of the
    centre of gravity, or None for any other finding.

    A vane x ahead of the CG reads ``α − x·q/V`` (``β + x·r/V``); a channel late by τ reads
    ``α − τ·α̇``. Where ``α̇ ≈ q`` (a short-period record flown near one airspeed) the two
    are the same to first order with ``x = τ·V``, so the late channel can be a vane on a
    nose boom (the ATTAS α channel: τ = 0.1005 ± 0.0011 s at 128.5 m/s, x = 12.9 m, against
    the noseboom's 13.08 m). V̄ is the mean of the model's own airspeed (a state's smoothed
    mean, or an input) in m/s, else the records' airspeed column or the constants file's trim
    speed (:func:`.flightconst.flight_conditions_of`); the aircraft constants' noseboom
    position is given beside it when the constants file has one. An airspeed the model holds
    as a constant has no declared unit here, so it is not used.
    """
    from .base import info_from_model
    from .catalogue import airspeed_name
    from .flightconst import flight_conditions_of

    if c.effect != "time_skew" or c.target_kind != "output":
        return None
    tau = next((v for v in params.values() if v.get("unit") == "s" and not v.get("fixed")), None)
    if tau is None or tau.get("estimate") is None:
        return None
    info = info_from_model(st.model)
    kind = info.output_roles.get(c.target_name)
    if kind not in _FLOW_ANGLES:
        return None
    name = airspeed_name(info)
    # the records' airspeed column or the constants file's trim speed (when the model has no
    # airspeed of its own), and the sensor positions of the constants file
    fc = flight_conditions_of(info, st.records)
    v_bar, source = None, None
    scale = _mps(info.unit(name)) if name else None
    if name in st.model.state_names and scale is not None:
        j = st.model.state_names.index(name)
        x = np.concatenate([np.asarray(sig.x_smooth, float)[:, j] for sig in st.signals])
        v_bar, source = float(np.mean(x)) * scale, f"mean of the model's {name}"
    elif name in st.model.input_names and scale is not None:
        j = st.model.input_names.index(name)
        u = np.concatenate([np.asarray(r.u, float)[:, j] for r in st.records])
        v_bar, source = float(np.nanmean(u)) * scale, f"mean of the input {name}"
    elif fc.airspeed is not None:
        v_bar, source = fc.airspeed.value, fc.airspeed.source
    if v_bar is None or not np.isfinite(v_bar) or v_bar <= 0:
        return None
    se = tau.get("std_error")
    out = {"x_m": _f(tau["estimate"] * v_bar),
           "std_error_m": None if se is None else _f(se * v_bar),
           "airspeed_mps": _f(v_bar), "airspeed_source": source,
           "flow_angle": kind}
    nose = fc.sensors.get("noseboom")
    if nose is not None:
        out["constants_noseboom_x_m"] = _f(nose[0])
    return out


def equivalent_vane_text(channel: str, ev: dict) -> str:
    """The sentence of :func:`equivalent_vane` for a finding's explanation."""
    se = f" ± {ev['std_error_m']:.2g}" if ev.get("std_error_m") is not None else ""
    kind = ev.get("flow_angle") or channel
    reads = f"{channel} − x·q/V" if kind == "alpha" else f"{channel} + x·r/V"
    text = (f" Read as a vane instead: a vane x ahead of the centre of gravity reads "
            f"{reads}, the same to first order as this skew with x = τ·V̄ = "
            f"{ev['x_m']:.3g}{se} m (V̄ = {ev['airspeed_mps']:.4g} m/s, {ev['airspeed_source']})")
    if ev.get("constants_noseboom_x_m") is not None:
        text += (f"; the aircraft constants put the noseboom at x = "
                 f"{ev['constants_noseboom_x_m']:.4g} m")
    return text + ". A record at another airspeed separates the two."


def statistic_text(d: dict) -> str:
    """A finding's or an alternative's 2ΔELBO for text: the test statistic (against the
    candidate's own nesting point) and, where it differs, the gain over the current model by
    which the round ranks alternatives (``statistic_vs_current``, search.Trial.comparison)."""
    own = d.get("statistic")
    cmp_ = d.get("statistic_vs_current")
    if own is None:
        return "—"
    if cmp_ is None or abs(cmp_ - own) < 0.05:
        return f"{own:.4g}"
    return f"{own:.4g}; {cmp_:.4g} over the current model"


def vuong_text(a: dict) -> str:
    """An alternative's Vuong test against the finding, for text ("" without one)."""
    v = a.get("vuong")
    if not v:
        return ""
    return (f"; Vuong z = {v['z']:.2g}, p = {v['p_value']:.2g}: one-step predictions "
            f"{v['loglik_difference']:+.3g} nats over {v['n']} samples")


#: ELBO difference (nats) within which two converged refits with as many parameters reach the
#: same optimum: twice the estimator's convergence tolerance (half the Newton decrement
#: below 1e-3 nats at each)
TIE_NATS = 2e-3

#: what separates two refits that tie exactly (:func:`exact_tie`)
EQUIVALENT_TEXT = (
    "nothing in records of this kind: the two refits reach the same ELBO, so within this model "
    "they are one re-parameterisation of each other (its free parameters take up the "
    "difference) at every airspeed and manoeuvre it describes; only knowledge from outside "
    "the data separates them: the sensor's installed position, or fixing the parameters that "
    "absorb the difference at independent (wind-tunnel, handbook) values")


def exact_tie(best, alt) -> bool:
    """Whether two refits of a round are one model in two parameterisations: both converged,
    as many added parameters, and ELBOs within :data:`TIE_NATS`. An independent lateral
    record (session 47) tied a β vane 6 m ahead of the CG and a lateral accelerometer 5.5 m
    *behind* it to 1e-4 nats: with free Y_p, Y_r, Y_δa the vane term x·r/V is the accelerometer
    term −x·ṙ, and "another airspeed" (the pair's usual separation) does not separate them
    in a model whose derivatives are fitted per record."""
    a, b = getattr(best, "state", None), getattr(alt, "state", None)
    if a is None or b is None or not (a.fit.converged and b.fit.converged):
        return False
    if getattr(best, "dof", None) != getattr(alt, "dof", None):
        return False
    return abs(float(a.elbo) - float(b.elbo)) <= TIE_NATS


def separating_experiment(effect: str, target: str, other_effect: str, other_target: str) -> str:
    """What data would separate two explanations of one mismatch (plain words, for a finding
    whose alternative the data could not rule out).

    The physics of the pair decides: a vane's error ``x·q/V`` changes with airspeed while a
    time skew ``τ·ẏ`` does not; a first-order lag attenuates and its phase saturates at 90°
    while a pure delay keeps the amplitude and its phase grows linearly with frequency; a
    bias is constant while a scale error grows with the channel's value; a generic slow
    mode and the speed (phugoid) dynamics differ in period, damping and the airspeed
    channel; a gust state differs between records while a physical term repeats; two forms
    of one effect on one target differ away from the conditions of the record; a vane's
    position error scales with 1/V while an accelerometer's lever-arm term does not; a flow-angle
    vane's position and a rate derivative of a force coefficient are, in a linear model, one
    re-parameterisation at every airspeed (the vane term ``x·r/V`` read as the state moves a
    ``Y_β x/V`` rate term into ``Y`` and ``L_β x/V``, ``N_β x/V`` into the moment equations'
    rate derivatives) except for ``x·ṙ/V`` in the flow angle's equation: only large angular
    accelerations or an independent flow-angle reference separate them. Any
    other pair (one effect on two channels included): a manoeuvre that excites the two
    targets differently.
    """
    pair = {effect, other_effect}
    ch, och = _channel(target), _channel(other_target)
    same_channel = ch == och
    if pair == {"sensor_position", "time_skew"} and same_channel:
        if ch in _FLOW_ANGLES:
            return (f"a record at another airspeed: a {ch} vane ahead of the centre of gravity "
                    f"reads {ch} − x·(rate)/V, an error that shrinks as the airspeed grows, "
                    f"while a time skew τ·d({ch})/dt does not depend on the airspeed")
        return (f"a manoeuvre whose angular acceleration and {ch} rate differ in shape (a "
                f"short sharp pulse next to a slow doublet): a sensor position error follows "
                f"the angular rates and accelerations, a time skew follows d({ch})/dt")
    if pair == {"control_delay", "transport_delay"} and same_channel:
        return (f"nothing at these bandwidths: both are the same time delay of {ch}, as a "
                f"first-order Padé state and as the input shifted by τ — a much faster {ch} "
                f"input would show the Padé form's phase saturating at 180° where a pure "
                f"delay's keeps growing in proportion to the frequency (both keep the "
                f"amplitude)")
    if len(pair) == 2 and pair <= set(_INPUT_FILTERS) and same_channel:
        return (f"a faster {ch} input (a sharp step or a doublet of shorter period): a "
                f"first-order lag attenuates fast inputs and its phase saturates at 90°, a "
                f"pure delay keeps the amplitude and its phase grows in proportion to the "
                f"frequency")
    if pair == {"sensor_bias", "sensor_scale"} and same_channel:
        return (f"a record at another trim (another mean {ch}): a bias stays the same, a "
                f"scale-factor error grows with the value of {ch}")
    if "speed_dynamics" in pair and "missing_dynamics" in pair:
        return ("a longer record that excites the speed (a thrust step, or an elevator pulse "
                "followed by one or two phugoid periods hands-off) with the airspeed "
                "recorded: a generic slow mode and the speed dynamics then differ in period, "
                "damping and the airspeed channel")
    if "unmodelled_wind" in pair:
        return ("a second record of the same manoeuvre (another flight through other "
                "turbulence): an unmodelled gust differs from record to record, a physical "
                "term repeats — validate both on it (--validate)")
    if pair == {"sensor_position"} and not same_channel and (ch in _FLOW_ANGLES) != (
            och in _FLOW_ANGLES):
        vane, acc = (ch, och) if ch in _FLOW_ANGLES else (och, ch)
        return (f"a record at another airspeed: a {vane} vane's position error x·(rate)/V "
                f"shrinks as the airspeed grows, while the {acc} sensor's lever-arm term "
                f"x·(angular acceleration) does not depend on the airspeed")
    if "sensor_position" in pair and pair & _DERIVATIVES:
        pos_ch = ch if effect == "sensor_position" else och
        if pos_ch in _FLOW_ANGLES:
            coef = och if effect == "sensor_position" else ch
            return (f"a manoeuvre with large angular accelerations (short, sharp pulses of the "
                    f"control that drives the rate), or a {pos_ch} reference independent of the "
                    f"vane (inertial velocities with a wind estimate, a second vane at another "
                    f"position, the boom length measured on the ground): in a linear model a "
                    f"{pos_ch} vane's error x·(rate)/V is the same as a rate derivative of "
                    f"{coef} with the moment equations' rate derivatives shifted, at every "
                    f"airspeed; only the vane's x·(angular acceleration)/V in d({pos_ch})/dt tells "
                    f"them apart")
    parts, oparts = set(ch.split("+")), set(och.split("+"))
    if effect == other_effect and not same_channel and (parts < oparts or oparts < parts):
        small, big = (parts, oparts) if parts < oparts else (oparts, parts)
        extra = ", ".join(sorted(big - small))
        return (f"more data of the same kind (a longer record, or further records fitted "
                f"together): the two forms are nested — the larger one adds the same term to "
                f"{extra} as well — and this record does not show whether {extra} needs it")
    if same_channel and pair & set(LINEAR_TERM_EFFECTS) and pair & set(NONLINEAR_TERM_EFFECTS):
        return (f"a record with larger excursions of the variable the two terms share: a linear "
                f"term and a nonlinear one (a square, a break) agree near the conditions of this "
                f"record and differ away from them")
    if effect == other_effect and same_channel:
        return (f"a record with larger excursions of the variables the two {effect} forms "
                f"use (they agree near the conditions of this record and differ away from "
                f"them)")
    if same_channel:
        return (f"a manoeuvre that excites {ch} with another input shape or with another "
                f"control, so that the two explanations predict different responses")
    return (f"a manoeuvre that excites {ch} and {och} differently (another input shape or "
            f"another control), so that the two explanations predict different responses")


def _keys_by_round(trials) -> list[str]:
    """Candidate keys of ``trials`` once each, in first-seen order, with the rounds they were
    refitted in when there are several (``"actuator_lag:de (rounds 1, 2)"``)."""
    rounds: dict = {}
    for t in trials:
        rs = rounds.setdefault(t["key"], [])
        if t.get("round") is not None and t["round"] not in rs:
            rs.append(t["round"])
    return [k if len(rs) < 2 else f"{k} (rounds {', '.join(str(r) for r in rs)})"
            for k, rs in rounds.items()]


def conclusion_text(findings: list, rounds: list, *, alpha: float, validated: bool,
                    final_spec, base_converged: bool = True, base_status: str = "",
                    numerics_adopted: bool = False) -> str:
    """The plain-words conclusion of findings.json (pure: findings and round records only;
    ``numerics_adopted``: a modelling-numerics setting or a noise model was adopted, so only
    the physics is kept when nothing else is found)."""
    if findings:
        conclusion = (f"{len(findings)} significant discrepanc{'y' if len(findings) == 1 else 'ies'}"
                      f" found: " + "; ".join(f"{f['effect']} on {f['target']}" for f in findings)
                      + f". Final augmented spec: {final_spec}.")
        for f in findings:
            hold = (f.get("added_terms") or {}).get("integrator")
            if hold:   # a delay profiled under both input holds changed the hold
                text = ", ".join(f"{k}: {v}" for k, v in hold.items())
                conclusion += (f" With {f['key']} modelled, the inputs are taken as "
                               f"`integrator: {{{text}}}` (this replaces the "
                               "setting of the numerics stage; the final spec carries it).")
            for cm in f.get("complementary") or ():
                conclusion += (f" {cm['key']}, not separated from {f['key']} in its round, was "
                               f"accepted on top of it in round {cm['accepted_in_round']}: the "
                               "two are complementary (both were missing), not alternatives.")
            if f["alternatives"]:
                conclusion += (f" {'AMBIGUOUS' if f['ambiguous'] else 'Form uncertain'}: "
                               f"{f['key']} (2ΔELBO = {statistic_text(f['evidence'])}) is not "
                               "clearly better than " + ", ".join(
                                   f"{a['key']} ({statistic_text(a)}{vuong_text(a)})"
                                   for a in f["alternatives"])
                               + " — the data do not separate these explanations; an engineer "
                                 "must judge the label. What would separate them: "
                               + "; ".join(f"from {a['key']}, {a['separated_by']}"
                                           for a in f["alternatives"] if a.get("separated_by"))
                               + ".")
    else:
        what = "physical discrepancy" if numerics_adopted else "discrepancy"
        kept = ("The model's physics is kept as it is (with the numerics or noise-model "
                "setting above)"
                if numerics_adopted else "The model is kept as it is")
        if any(r.get("reference") for r in rounds):
            kept = ("The model's equations are kept as they are, re-estimated at the better "
                    f"optimum described next (final spec: {final_spec})")
        if not rounds:
            # --max-rounds 0 (or a run stopped before its first round): nothing was tested,
            # so "no candidate improved the fit" would claim a search that did not happen
            conclusion = (f"No candidate effect was examined: no search round ran (--max-rounds "
                          f"0, or the run stopped before round 1). {kept}; run with "
                          "--max-rounds 1 or more to search for the physics it may leave out.")
        else:
            gusted = any((r.get("gust_check") or {}).get("outcome") == "explained_by_gust"
                         for r in rounds)
            conclusion = (f"No significant {what} found: no candidate effect improved the ELBO "
                          f"significantly (family-wise alpha = {alpha} per round, Holm-corrected)"
                          + (" and on the validation records" if validated else "")
                          + (" once the turbulence in the air-relative velocity is modelled"
                             if gusted else "")
                          + f". {kept}; the residual mismatch is consistent with "
                            "the estimated turbulence (process noise) and sensor noise.")
            undecided = [r for r in rounds
                         if (r.get("gust_check") or {}).get("outcome") == "undecided_with_gust"]
            if undecided:
                ch0 = undecided[-1]["gust_check"]
                conclusion = (f"INCONCLUSIVE: no effect was accepted, but round "
                              f"{ch0.get('round')}'s lead, {ch0.get('key')}, refitted on the "
                              "adopted gust model raised the ELBO beyond its threshold without "
                              "converging (above), so it can be neither accepted nor ruled out.")
    ch = (rounds[-1].get("gust_check") or {}) if rounds else {}
    if ch.get("outcome") == "explained_by_gust":
        # the run ended on the round whose lead the gust explained: its other significant
        # candidates were decided with white process noise and never refitted on the gust model
        others = [t["key"] for t in rounds[-1].get("trials") or []
                  if t.get("significant") and t.get("key") != ch.get("key")]
        if others:
            conclusion += (f" Also significant in round {ch.get('round')} with white process "
                           "noise and not re-tested on the adopted gust model (the run ended "
                           "with that round): " + ", ".join(others) + f"; rerun with "
                           f"--max-rounds {int(ch.get('round') or 1) + 1} or more (or a longer "
                           "--time-limit) to test them with the turbulence modelled.")
    for r in rounds:
        ref = r.get("reference")
        if ref:
            val = ""
            if ref.get("val_elbo") is not None and ref.get("val_elbo_before") is not None:
                val = (f"; validation ELBO {ref['val_elbo_before']:.6g} → {ref['val_elbo']:.6g}")
            conclusion += (f" In round {r.get('round')}, the current model itself reached a better "
                           f"optimum: ELBO {ref['elbo_before']:.6g} → {ref['elbo']:.6g}"
                           f" (+{ref['elbo'] - ref['elbo_before']:.4g} nats{val})"
                           + (f", found from the optimum of {ref['found_from']} with its new "
                              "terms removed" if ref.get("found_from") else "")
                           + "; the earlier fit had stopped in a local optimum, and every "
                             "statistic of that round is taken against the better one "
                             f"({ref['spec']}).")
    tried = [dict(t, round=r.get("round")) for r in rounds for t in r.get("trials", [])]
    val_rej = _keys_by_round([t for t in tried
                              if t.get("significant") and t.get("validation_ok") is False])
    # a refit named although it stopped short of convergence (search.stopped_short: its Λ a
    # lower bound) is a finding, not an unconverged rejection
    named = {(f.get("rank"), f["key"]) for f in findings}
    tried = [t for t in tried if (t.get("round"), t["key"]) not in named]
    # a refit refused under its label (a time constant beyond the label's range) is named as
    # such, and one decided as significant (stopped short of convergence with a
    # positive-definite Hessian, or at a kink) but refused by the validation records as
    # over-fitting: neither again as unconverged
    def unconverged(t) -> bool:
        return (t.get("converged") is False and t.get("verdict") != "beyond_range"
                and not (t.get("significant") and t.get("validation_ok") is False))

    unconv = [t["key"] for t in tried if unconverged(t)]
    strong = [t for t in tried if unconverged(t)
              and isinstance(t.get("statistic"), (int, float))
              and isinstance(t.get("threshold"), (int, float))
              and t["statistic"] > t["threshold"]]
    if not findings and strong:
        # an unconverged refit above its threshold is neither accepted nor ruled out: do not
        # call the mismatch turbulence
        conclusion = ("INCONCLUSIVE: no effect was accepted, but the refit of "
                      + ", ".join(f"{t['key']} (2ΔELBO = {t['statistic']:.4g} > threshold "
                                  f"{t['threshold']:.4g}, {t.get('status') or 'not converged'})"
                                  for t in strong)
                      + " raised the ELBO beyond its threshold without converging, so that effect "
                        "can be neither accepted nor ruled out; rerun with a larger --max-iter "
                        "(e.g. 500), restricted to it with --effects.")
        unconv = [k for k in unconv if k not in {t["key"] for t in strong}]
    failed = [t["key"] for t in tried if t.get("error")]
    if failed and not findings and len(failed) == len(tried):
        conclusion = ("INCONCLUSIVE: no refit produced a result (" + ", ".join(
            f"{t['key']}: {t['error']}" for t in tried if t.get("error"))
            + "), so nothing was tested.")
    elif failed:
        conclusion += (" Refits that failed (neither accepted nor ruled out): "
                       + ", ".join(failed) + ".")
    below = [t for t in tried if t.get("verdict") == "below_nesting_point"]
    if below:
        conclusion += (" Not tested (optimizer failure: the refit ended below the ELBO of its "
                       "nesting point, so it is neither evidence for nor against the effect): "
                       + ", ".join(f"{t['key']} (2ΔELBO = {t['statistic']:.4g})" for t in below)
                       + ".")
    noncausal = [t for t in tried if t.get("verdict") == "non_causal"]
    if noncausal:
        conclusion += (" Not accepted because the estimate is non-causal (the channel would read "
                       "before the motion; a sensor ahead of the CG reads early): "
                       + ", ".join(f"{t['key']} (2ΔELBO = {t['statistic']:.4g})"
                                   for t in noncausal) + ".")
    beyond = [t for t in tried if t.get("verdict") == "beyond_range"]
    if beyond:
        conclusion += (" Not accepted because a time constant ended at the upper end of the "
                       "range its label allows, or within 1.96 standard errors of it (the data "
                       "want a slower process than the label names: a missing mode, trim terms "
                       "or the speed dynamics, not an actuator or a delay): "
                       + ", ".join(f"{t['key']} (2ΔELBO = {t['statistic']:.4g})"
                                   for t in beyond) + ".")
    if val_rej:
        conclusion += (" Significant on the estimation records but rejected because the validation "
                       "ELBO (θ fixed, each validation record with its own noise and trim) did not improve "
                       "(over-fitting): " + ", ".join(val_rej) + ".")
    if unconv:
        unconv = _keys_by_round([t for t in tried if t["key"] in set(unconv)
                                 and unconverged(t)])
        conclusion += (" Not accepted because the refit did not converge (inconclusive for these "
                       "candidates): " + ", ".join(unconv) + ".")
    if not base_converged:
        # nothing about the model follows from an unconverged base: not "kept as it is", not
        # "consistent with the turbulence" (the run exits with status 1)
        tested = [t["key"] for t in tried if t.get("statistic") is not None]
        conclusion = ("INCONCLUSIVE: the base fit did not converge "
                      f"({base_status}); candidates are not accepted against an "
                      "unconverged base ELBO, and nothing about missing physics can be "
                      "concluded"
                      + (f" (refitted, not tested: {', '.join(tested)})" if tested else "")
                      + ". Make the base fit converge first (`vsidgen fit SPEC DATA "
                        "--max-iter 400`, initial values, or the spec's noise settings), then "
                        "run diagnose again.")
    return conclusion


def leading_refit(unfinished: dict | None, alpha: float) -> dict | None:
    """The unfinished round's refitted candidate with the largest statistic among those that
    converged to an ordinary verdict and are nominally significant (unadjusted p < ``alpha``;
    the round's Holm correction needs every candidate), or None. Not a finding: a pending
    candidate may explain the mismatch better, and validation decides only at the round's end.
    """
    best = None
    for t in (unfinished or {}).get("refitted", ()):
        stat, p = t.get("statistic"), t.get("p_value")
        if (not t.get("converged") or t.get("verdict") not in (None, "ordinary")
                or stat is None or p is None or not p < alpha):
            continue
        if best is None or stat > best["statistic"]:
            best = t
    return best


def stop_text(stop: dict | None, unfinished: dict | None, n_findings: int, *,
              alpha: float = 0.01) -> str:
    """Sentence put before the conclusion when the run did not complete (else "").

    With an unfinished round, it names the round's leading refit so far
    (:func:`leading_refit`), its validation ELBO against the current model's, and what
    would finish the round."""
    reason = (stop or {}).get("reason", "completed")
    if reason == "completed":
        return ""
    what = {"time_limit": f"STOPPED at the time limit ({(stop or {}).get('time_limit_s')} s)",
            "interrupted": "INTERRUPTED",
            "running": "RUNNING (checkpoint of a run in progress)"}.get(reason, reason.upper())
    part = (stop or {}).get("partial_round")
    if part:
        cut = list(part.get("not_refitted", ()))
        what += (f" after deciding round {part['round']} on the {part['refitted']} of "
                 f"{part['refitted'] + len(cut)} candidates it had refitted (not refitted, "
                 f"counted as not significant: {', '.join(cut)})")
    if unfinished is not None:
        done = len(unfinished.get("refitted", ()))
        pend = list(unfinished.get("pending", ()))
        what += (f" during round {unfinished['round']} ({done} of {done + len(pend)} candidates "
                 "refitted" + (f"; pending: {', '.join(pend)}" if pend else "")
                 + "; an unfinished round accepts nothing)")
        lead = leading_refit(unfinished, alpha)
        if lead is not None:
            val = ""
            # as the validation gate compares (search.validation_improved): each validation
            # record's own noise when both have it, else the estimation's noise
            v, v0 = lead.get("val_elbo_own_noise"), unfinished.get("base_val_elbo_own_noise")
            if v is None or v0 is None:
                v, v0 = lead.get("val_elbo"), unfinished.get("base_val_elbo")
            if v is not None and v0 is not None:
                v -= float((lead.get("refit") or {}).get("val_x0_entropy") or 0.0)
                val = (f", validation ELBO {v:.6g} against the current model's {v0:.6g}"
                       + (" (higher)" if v > v0 else " (not higher: it would be rejected)"))
            what += (f". Leading so far, not decided: {lead['key']} (2ΔELBO {lead['statistic']:.4g}"
                     f", unadjusted p {lead['p_value']:.2g}{val}); to decide the round, run "
                     "again with a longer --time-limit, or fewer candidates (--max-candidates, "
                     "--effects)")
        # refits that stopped before converging above the lead (or above the level when there
        # is none): their 2ΔELBO is the ELBO they had reached, not an optimum's, but the user
        # should not read the lead as the strongest evidence of the round (lat_p_bias_0.002_s1:
        # a roll-gyro bias at 2ΔELBO 175, unconverged, behind a "leading" wind at 11.6)
        floor = lead["statistic"] if lead is not None else None
        above = [r for r in unfinished.get("refitted", ())
                 if not r.get("converged") and r.get("verdict") in (None, "ordinary")
                 and isinstance(r.get("statistic"), (int, float))
                 and isinstance(r.get("p_value"), (int, float))
                 and (r["statistic"] > floor if floor is not None else r["p_value"] < alpha)]
        if above:
            what += ("; refitted without converging" + (" above it" if lead is not None else "")
                     + ": " + ", ".join(f"{r['key']} (2ΔELBO {r['statistic']:.4g} when it "
                                        "stopped; rerun with a larger --max-iter, restricted "
                                        "to it with --effects)"
                                        for r in sorted(above, key=lambda r: -r["statistic"])))
    if n_findings == 0:
        return what + ". No physical effect was accepted in the finished rounds. "
    return (what + f". {n_findings} effect{'s' if n_findings != 1 else ''} accepted in the "
            "finished rounds " + ("is" if n_findings == 1 else "are") + " kept below. ")


def estimate_text(name: str, ent: dict) -> str:
    est, se, unit = ent.get("estimate"), ent.get("std_error"), ent.get("unit")
    if est is None:
        return f"{name} = n/a"
    u = f" {unit}" if unit and unit != "1" else ""
    text = f"{name} = {est:.4g}" + (f" ± {se:.2g}" if se is not None else "") + u
    if ent.get("hold_lag"):
        text += (f" (spec value {ent['spec_value']:.4g}{u} + the input hold's "
                 f"{ent['hold_lag']:.4g}{u})")
    nb = ent.get("near_bound")
    if nb:
        text += (f" [near its {nb['side']} bound {nb['bound']:.4g}{u}: the ± interval is "
                 "not valid there]")
    at = ent.get("at_acceptance")
    if isinstance(at, (int, float)) and math.isfinite(at) and math.isfinite(est):
        # the estimate shown is the final model's; the test was made at the acceptance value
        # (an arm of +1.035 m accepted, −0.056 m once a later round's gust state was in)
        tol = 2.0 * se if se is not None and math.isfinite(se) else 0.1 * max(abs(at), abs(est))
        if abs(at - est) > tol:
            text += (f" (when accepted: {at:.4g}{u}; re-estimated with the later rounds' "
                     "terms)")
    return text


def summary_lines(document: dict, findings_path) -> list[str]:
    """The lines ``vsidgen diagnose`` prints, built only from the findings.json ``document``
    (one source of truth): per finding its test, estimates with units, explanation and
    alternatives; the last line is the document's ``conclusion`` and where it is written."""
    lines = []
    adopted = (document.get("numerics") or {}).get("adopted")
    if adopted:
        lines.append(f"0. modelling numerics (not physics): {adopted['recommendation']}: 2ΔELBO = "
                     f"{adopted['statistic']:.4g} > {adopted['threshold']:.4g}")
        lines.append(f"   {adopted['explanation']}")
    noise = (document.get("noise_model") or {}).get("adopted")
    if noise:
        lines.append(f"0. noise model (not physics): {noise['recommendation']}: 2ΔELBO = "
                     f"{noise['statistic']:.4g} > {noise['threshold']:.4g}")
        lines.append(f"   {noise['explanation']}")
    gust = (document.get("noise_gust") or {}).get("adopted")
    if gust:
        lines.append(f"0. noise model (not physics): {gust['recommendation']}: 2ΔELBO = "
                     f"{gust['statistic']:.4g} > {gust['threshold']:.4g}")
        lines.append(f"   {gust['explanation']}")
    unresolved = (document.get("noise_model") or {}).get("significant_not_adopted")
    if unresolved and not noise:
        lines.append(f"0. noise model UNRESOLVED (not physics): correlated process noise, 2ΔELBO ≥ "
                     f"{unresolved['statistic_lower_bound']:.4g} > {unresolved['threshold']:.4g}, "
                     f"refit stopped before its optimum ({unresolved.get('stop_reason')}); "
                     "the search used the diagonal noise")
    for f in sorted((document.get("findings") or []) + (document.get("noise_turbulence") or []),
                    key=lambda f: f["rank"]):
        ev = f["evidence"]
        lines.append(f"{f['rank']}. " + ("noise model (not physics): coloured turbulence, "
                                          if f.get("disturbance") else "")
                     + f"{f['effect']} on {f['target']}: 2ΔELBO = "
                     f"{ev['statistic']:.4g} > {ev['threshold']:.4g}")
        est = [estimate_text(k, v) for k, v in (f.get("parameters") or {}).items()
               if not v.get("fixed")]
        if est:
            lines.append("   " + "; ".join(est))
        lines.append(f"   {f['explanation']}")
        for a in f.get("alternatives") or []:
            word = "AMBIGUOUS" if f.get("ambiguous") else "form uncertain"
            how = ("exactly as well, the same model in another parameterisation"
                   if a.get("equivalent") else "nearly as well")
            lines.append(f"   {word}: {a['effect']} on {a['target']} explains it {how} "
                         f"(2ΔELBO = {statistic_text(a)})"
                         + (f"; to separate them: {a['separated_by']}"
                            if a.get("separated_by") else ""))
        for cm in f.get("complementary") or []:
            lines.append(f"   complementary: {cm['effect']} on {cm['target']} (not separated "
                         f"in round {f['rank']}) was accepted on top of it in round "
                         f"{cm['accepted_in_round']}")
    for r in document.get("noise_model_retests") or []:
        a = r.get("adopted")
        if a:
            lines.append(f"+ noise model re-tested after round {r['after_round']} (not physics): "
                         f"{a['recommendation']}: 2ΔELBO = {a['statistic']:.4g} > "
                         f"{a['threshold']:.4g}")
            lines.append(f"   {a['explanation']}")
    lines.append(f"{document['conclusion']} Findings in {findings_path}.")
    return lines


def _trial_table(first: str, rows, *, dof: bool) -> str:
    """HTML table of a before-physics stage's trials: ``rows`` of (escaped first cell, trial
    record with ``statistic``, ``dof``, ``threshold``, ``verdict``)."""
    e = html.escape
    head = (f"<tr><th>{first}</th><th>2ΔELBO</th>" + ("<th>dof</th>" if dof else "")
            + "<th>threshold</th><th>verdict</th></tr>")
    body = []
    for cell, t in rows:
        st = t.get("statistic")
        body.append(f"<tr><td>{cell}</td><td>{'n/a' if st is None else f'{st:.4g}'}</td>"
                    + (f"<td>{int(t['dof'])}</td>" if dof else "")
                    + f"<td>{(t.get('threshold') or 0):.4g}</td><td>{e(t['verdict'])}"
                    + (" (Rao's score statistic at the current fit; not refitted)"
                       if t.get("decided_by") == "score" else "") + "</td></tr>")
    return ("<table border='1' cellpadding='3' style='border-collapse:collapse;font-size:90%'>"
            + head + "".join("\n" + r for r in body) + "\n</table>")


def numerics_text(numerics: dict | None) -> str:
    """Sentence on the modelling-numerics stage put before the conclusion ("" when nothing
    was adopted)."""
    adopted = (numerics or {}).get("adopted")
    if not adopted:
        return ""
    return (f"MODELLING NUMERICS (not a physical effect): {adopted['recommendation']} "
            f"(2ΔELBO = {adopted['statistic']:.4g} > {adopted['threshold']:.4g} with no parameter "
            "added); the physical search below used it. ")


def noise_model_text(noise_model: dict | None) -> str:
    """Sentence on the noise-model stage put before the conclusion ("" when nothing was
    adopted and no alternative was significant)."""
    adopted = (noise_model or {}).get("adopted")
    unresolved = (noise_model or {}).get("significant_not_adopted")
    if not adopted and unresolved:
        low = [f"{s['state']} {s['share']:.2g}" for s in unresolved.get("independent_shares") or []
               if s.get("share") is not None]
        return ("NOISE MODEL UNRESOLVED: the process noise is correlated between the state "
                f"equations (2ΔELBO ≥ {unresolved['statistic_lower_bound']:.4g} > "
                f"{unresolved['threshold']:.4g}, chi2({unresolved['dof']}), from a refit that "
                f"stopped before its optimum: {unresolved.get('stop_reason')}), so the full "
                "factor was not adopted (share of each state's noise independent of the states "
                f"before it: {', '.join(low)}; near 0: one gust acting on several equations). "
                "The physical search below used "
                "the diagonal noise: a finding that couples these equations may be this "
                "correlation, not physics. ")
    if not adopted:
        return ""
    rho = ", ".join(f"ρ({c['states'][0]}, {c['states'][1]}) = {c['rho']:+.2f}"
                    for c in adopted.get("correlations") or [] if c.get("rho") is not None)
    return (f"NOISE MODEL (not a physical effect): the process noise is correlated between the "
            f"state equations ({rho}); {adopted['recommendation']} (2ΔELBO = "
            f"{adopted['statistic']:.4g} > {adopted['threshold']:.4g}, chi2({adopted['dof']})); "
            "the physical search below used it. ")


def turbulence_text(turbulence: Sequence[dict]) -> str:
    """Sentence on coloured turbulence accepted in a round (a gust state: a disturbance
    model, ``findings.json`` → ``noise_turbulence``), put before the conclusion."""
    out = []
    for f in turbulence or ():
        ev = f["evidence"]
        est = "; ".join(estimate_text(k, v) for k, v in (f.get("parameters") or {}).items()
                        if not v.get("fixed"))
        out.append(f"NOISE MODEL (not a physical effect), round {f['rank']}: the turbulence is "
                   f"coloured, not white — {f['key']} ({f['title']}; {est}; 2ΔELBO = "
                   f"{ev['statistic']:.4g} > {ev['threshold']:.4g}); the rounds after it used "
                   "it, and the final spec carries it. ")
    return "".join(out)


def noise_retest_text(retests: Sequence[dict]) -> str:
    """Sentences on the noise model re-tested after rounds that accepted an effect ("" when
    none adopted correlated noise or was significant without converging)."""
    out = []
    for r in retests or ():
        k = r.get("after_round")
        adopted, unresolved = r.get("adopted"), r.get("significant_not_adopted")
        if adopted:
            rho = ", ".join(f"ρ({c['states'][0]}, {c['states'][1]}) = {c['rho']:+.2f}"
                            for c in adopted.get("correlations") or [] if c.get("rho") is not None)
            out.append(f" NOISE MODEL re-tested after round {k}'s finding (not a physical "
                       f"effect): with that effect in the model the process noise is correlated "
                       f"between the state equations ({rho}; 2ΔELBO = {adopted['statistic']:.4g} "
                       f"> {adopted['threshold']:.4g}, chi2({adopted['dof']})), which the first "
                       f"test, on the model without it, did not show; "
                       f"{adopted['recommendation']} (in the final spec).")
        elif unresolved:
            out.append(f" NOISE MODEL UNRESOLVED after round {k}'s finding: correlated process "
                       f"noise 2ΔELBO ≥ {unresolved['statistic_lower_bound']:.4g} > "
                       f"{unresolved['threshold']:.4g} from a refit that stopped before its "
                       f"optimum ({unresolved.get('stop_reason')}); the final spec keeps the "
                       "diagonal noise.")
    return "".join(out)


def gust_check_text(noise_gust: dict | None) -> str:
    """Sentence on the air-relative gust tested as a rival of a round's lead
    (``noise_gust.checked``, :func:`.search._gust_check`); "" when it was not."""
    ch = (noise_gust or {}).get("checked")
    if not ch:
        return ""
    key, thr = ch["key"], ch.get("threshold")
    without = ch.get("statistic_without_gust")
    lam = ch.get("statistic_with_gust")
    lam_s = "not refitted (time limit)" if lam is None else f"2ΔELBO = {lam:.4g}"
    if ch.get("outcome") == "gust_not_significant":
        trial = (noise_gust.get("trials") or [{}])[0]
        st = trial.get("statistic")
        return (f"Turbulence in the air-relative velocity was tested as a rival explanation of "
                f"{key} and did not improve the fit significantly"
                + (f" (2ΔELBO = {st:.4g} ≤ {trial.get('threshold'):.4g})"
                   if isinstance(st, (int, float)) and isinstance(trial.get("threshold"),
                                                                  (int, float)) else "")
                + ". ")
    if ch.get("outcome") == "significant_with_gust":
        return (f"{key} stays significant with the gust ({lam_s} > {thr:.4g}; without it "
                f"{without:.4g}). ")
    if ch.get("outcome") == "undecided_with_gust":
        return (f"NOT ACCEPTED, UNDECIDED: {key} was significant with white process noise "
                f"(2ΔELBO = {without:.4g} > {thr:.4g}); refitted on the gust model it raised "
                f"the ELBO beyond the threshold (2ΔELBO ≥ {lam:.4g}) without converging, so it "
                "is neither accepted nor explained by the turbulence; rerun with a larger "
                f"--max-iter (e.g. 500), restricted to it with --effects. ")
    if ch.get("verdict_with_gust") == "below_nesting_point":
        return (f"NOT ACCEPTED: {key} was significant with white process noise (2ΔELBO = "
                f"{without:.4g} > {thr:.4g}); refitted on the gust model, it did not rise above "
                f"its nesting point ({lam_s}: an optimizer failure, flagged, not a test "
                "result): with the turbulence modelled the data give no evidence for it. ")
    if lam is None or ch.get("converged_with_gust") is False:
        return (f"NOT ACCEPTED: {key} was significant with white process noise (2ΔELBO = "
                f"{without:.4g} > {thr:.4g}); on the gust model its refit "
                + ("was not made (time limit)" if lam is None else
                   f"stayed at {lam_s} ≤ {thr:.4g} without converging")
                + ": with the turbulence modelled it is not shown. ")
    # converged, at or above its nesting point: below the threshold, or above it with a
    # verdict that refuses it under its label, or with a lower validation ELBO
    verdict = ch.get("verdict_with_gust")
    return (f"NOT ACCEPTED, explained by the turbulence: {key} was significant with white "
            f"process noise (2ΔELBO = {without:.4g} > {thr:.4g}) but not with the gust "
            f"({lam_s}" + (f" ≤ {thr:.4g}" if lam <= thr else "")
            + (f", verdict {verdict}" if verdict not in (None, "ordinary") else "")
            + (", validation ELBO lower" if ch.get("validation_ok_with_gust") is False else "")
            + "): the mismatch it absorbed is the turbulence the model's velocity state "
              "receives as a differentiated gust, not physics. ")


def noise_gust_text(noise_gust: dict | None) -> str:
    """Sentence on an adopted air-relative gust (:mod:`.gust`) put before the conclusion
    ("" when none was adopted), and on the lead it was tested against."""
    a = (noise_gust or {}).get("adopted")
    if not a:
        return gust_check_text(noise_gust)
    what = ", ".join(f"{g['velocity']} − {g['gust_state']}" for g in noise_gust.get("gusts") or [])
    return (f"NOISE MODEL (not a physical effect): the turbulence enters the air-relative "
            f"velocity ({what} in the flow-angle and airspeed definitions); "
            f"{a['recommendation']} (2ΔELBO = {a['statistic']:.4g} > {a['threshold']:.4g}, "
            f"chi2({a['dof']}) at alpha over the correlation times searched); "
            + (f"adopted when round {noise_gust['checked']['round']}'s lead was tested "
               "against it, and used from then on. " if noise_gust.get("checked")
               else "the physical search below used it. ")
            + gust_check_text(noise_gust))


def build_document(*, base, final, accepted, rounds, evidence, final_evidence, alpha, version,
                   wall_time_s, out, options, stop: dict | None = None,
                   unfinished_round: dict | None = None, numerics: dict | None = None,
                   noise_model: dict | None = None, noise_gust: dict | None = None,
                   noise_retests: Sequence[dict] = ()) -> dict:
    """The findings.json mapping (see the module docstring).

    ``stop``: {"reason": completed | time_limit | interrupted | running, "time_limit_s"};
    ``unfinished_round``: the round that was in progress (refitted trials, pending keys);
    ``numerics``: the modelling-numerics stage (:meth:`.numerics.NumericsResult.to_json`);
    ``noise_model``: the noise-model stage (:meth:`.noisemodel.NoiseModelResult.to_json`);
    ``noise_retests``: the same test after a round accepted an effect, each with its
    ``after_round``.
    """
    findings = []
    for rank, (trial, before, ev) in enumerate(accepted, start=1):
        c = trial.candidate
        after = trial.state
        params = _params(c, final)
        at_acc = _params(c, after)
        for k in params:
            params[k]["at_acceptance"] = at_acc.get(k, {}).get("estimate")
        mb, ma = metrics_summary(before), metrics_summary(after)
        locate_part = {}
        if c.target_kind == "drift" and c.target_name in ev.states:
            locate_part = ev.states[c.target_name].to_json()
        elif c.target_kind == "output" and c.target_name in ev.outputs:
            locate_part = ev.outputs[c.target_name].to_json()
        users = list((c.info or {}).get("users", ())) if c.target_kind == "definition" else []
        vane = equivalent_vane(c, final, params)
        findings.append({
            "rank": rank, "effect": c.effect, "title": _title(c.effect),
            "explanation": c.explanation + (equivalent_vane_text(c.target_name, vane)
                                            if vane else ""),
            "target": c.target, "key": c.key,
            "added_terms": c.added_terms(), "parameters": params,
            **({"users": users} if users else {}),
            **({"equivalent_vane": vane} if vane else {}),
            "evidence": {
                "test": "likelihood-ratio type: 2*(ELBO_after - ELBO_reference) vs chi2(dof), "
                        "Holm-corrected over the candidates of the round; ELBO_reference is "
                        "the candidate at its nesting point (= ELBO_before when no state is "
                        "added; see refit)",
                "elbo_reference": _f(trial.refit.elbo_ref) if trial.refit is not None else None,
                "statistic_vs_before": _f(trial.statistic_vs_base),
                "statistic_vs_current": _f(trial.comparison),
                "converged": bool(trial.converged),
                "refit": trial.refit.to_json() if trial.refit is not None else None,
                "elbo_before": _f(before.elbo), "elbo_after": _f(after.elbo),
                "statistic": _f(trial.statistic), "dof": trial.dof, "p_value": trial.p_value,
                "threshold": _f(trial.threshold), "alpha": alpha,
                "n_candidates": next((r["n_candidates"] for r in rounds
                                      if r["round"] == rank), None),
                "locate_score": _f(trial.score),
                "score_test": None if trial.screen is None else trial.screen.to_json(),
                "validation_elbo_before": _f(before.val_elbo),
                "validation_elbo_after": _f(after.val_elbo),
                "validation_elbo_own_noise_before": _f(before.val_elbo_own_noise),
                "validation_elbo_own_noise_after": _f(after.val_elbo_own_noise),
                "metrics_before": _target_metrics(mb, c.target),
                "metrics_after": _target_metrics(ma, c.target),
                "locate": locate_part,
                "delay_profile": (c.info or {}).get("profile_result"),
                "hold_comparison": (c.info or {}).get("hold_comparison")},
            **({"disturbance": True} if (c.info or {}).get("disturbance") else {}),
            "ambiguous": any(not same_physics(c, a.candidate) for a in trial.alternatives),
            "alternatives": [{**a.alternative_json(),
                              "same_physics": same_physics(c, a.candidate),
                              "equivalent": (tie := exact_tie(trial, a)),
                              "separated_by": EQUIVALENT_TEXT if tie else separating_experiment(
                                  c.effect, c.target, a.candidate.effect, a.candidate.target)}
                             for a in trial.alternatives],
            "spec": str(trial.spec_path)})
    complementary_findings(findings)
    # coloured turbulence (a gust state) is a model of the atmosphere: a noise-model finding
    turbulence = [f for f in findings if f.get("disturbance")]
    findings = [f for f in findings if not f.get("disturbance")]
    conclusion = conclusion_text(findings, rounds, alpha=alpha, validated=bool(base.vrecords),
                                 final_spec=final.spec_path,
                                 base_converged=bool(base.fit.converged),
                                 base_status=base.fit.status,
                                 numerics_adopted=bool((numerics or {}).get("adopted"))
                                 or bool((noise_model or {}).get("adopted"))
                                 or bool((noise_gust or {}).get("adopted"))
                                 or any(r.get("adopted") for r in noise_retests)
                                 or bool(turbulence))
    stopped = stop_text(stop, unfinished_round, len(findings), alpha=alpha)
    if stopped and not findings:
        conclusion = ("No effect accepted yet; the search did not finish, so this does not show "
                      "that the model is adequate.")
    conclusion = (stopped + numerics_text(numerics) + noise_model_text(noise_model)
                  + noise_gust_text(noise_gust) + turbulence_text(turbulence) + conclusion
                  + noise_retest_text(noise_retests))
    return {
        "vsidgen_version": version,
        "base_fit": {"converged": bool(base.fit.converged), "status": base.fit.status},
        "spec": {"name": base.model.name, "path": str(base.spec_path)},
        "records": _records(base), "options": options, "conclusion": conclusion,
        "numerics": numerics, "noise_model": noise_model, "noise_gust": noise_gust,
        "noise_model_retests": list(noise_retests), "noise_turbulence": turbulence,
        "findings": findings, "final_spec": str(final.spec_path),
        "base": {"elbo": _f(base.elbo), "validation_elbo": _f(base.val_elbo),
                 "validation_elbo_own_noise": _f(base.val_elbo_own_noise),
                 "metrics": metrics_summary(base)},
        "final": {"elbo": _f(final.elbo), "validation_elbo": _f(final.val_elbo),
                  "validation_elbo_own_noise": _f(final.val_elbo_own_noise),
                  "metrics": metrics_summary(final)},
        "locate": evidence.to_json(), "locate_final": final_evidence.to_json(),
        "rounds": rounds, "unfinished_round": unfinished_round,
        "stop": stop or {"reason": "completed", "time_limit_s": None},
        "report": "diagnose.html", "wall_time_s": _f(wall_time_s)}


def complementary_findings(findings: list) -> list:
    """Move out of each finding's alternatives those that a *later* round accepted on top of it
    — the same candidate, or one whose added terms include all of the alternative's (the
    constants of every equation include the q equation's) — in place; returns ``findings``.

    An alternative is a refit of the same round that the records do not separate from the
    finding (:func:`.search.alternatives_of`: Vuong's test, which also keeps one whose
    one-step predictions are significantly *better* while its ELBO is lower). When a later
    round accepts it with the finding already in the model, it raised the ELBO significantly
    beyond what the finding explains: the two are complementary (both missing), not two
    explanations of one mismatch. Such entries go to ``complementary`` (with the round that
    accepted them); ``ambiguous`` is recomputed from the alternatives left. (A new user's Twin
    Otter model without trim constants and without an a_z bias: the a_z bias, 2ΔELBO 3238,
    was reported AMBIGUOUS with the trim constants, 782, whose one-step predictions were better
    by 86 000 nats — both were missing.)"""
    def terms(added) -> set:
        return {(kind, name, str(expr).replace(" ", ""))
                for kind, group in (added or {}).items() if isinstance(group, dict)
                for name, expr in group.items()}

    def accepted_later(a, rank):
        """The round that accepted ``a`` itself, or every term it adds, after ``rank``."""
        mine = terms(a.get("added_terms"))
        for g in findings:
            if g["rank"] > rank and (g["key"] == a["key"]
                                     or (mine and mine <= terms(g.get("added_terms")))):
                return g["rank"]
        return None

    for f in findings:
        later = {a["key"]: accepted_later(a, f["rank"]) for a in f["alternatives"]}
        comp = [a for a in f["alternatives"] if later[a["key"]] is not None]
        if not comp:
            continue
        keys = {a["key"] for a in comp}
        f["alternatives"] = [a for a in f["alternatives"] if a["key"] not in keys]
        f["complementary"] = [{"key": a["key"], "effect": a["effect"], "target": a["target"],
                               "accepted_in_round": later[a["key"]],
                               "statistic_as_alternative": a.get("statistic"),
                               "vuong": a.get("vuong")} for a in comp]
        f["ambiguous"] = any(not a.get("same_physics", a["effect"] == f["effect"])
                             for a in f["alternatives"])
    return findings


def _title(effect_id: str) -> str:
    from .base import get_effect
    try:
        return get_effect(effect_id).title
    except Exception:  # noqa: BLE001
        return effect_id


def write_findings_json(out, doc) -> pathlib.Path:
    """Write ``out/findings.json`` only (atomically; the checkpoint after every refit)."""
    return write_text_atomic(pathlib.Path(out) / "findings.json", dumps(doc))


def write_findings(out, doc, *, base, final, accepted) -> pathlib.Path:
    """Write ``out/findings.json`` and ``out/diagnose.html``; returns the JSON path."""
    out = pathlib.Path(out)
    section = report_section(doc, base=base, final=final, accepted=accepted)
    page = ("<!DOCTYPE html><html><head><meta charset='utf-8'><title>vsidgen diagnose: "
            f"{html.escape(doc['spec']['name'])}</title></head><body>{section}</body></html>\n")
    write_text_atomic(out / "diagnose.html", page)
    return write_text_atomic(out / "findings.json", dumps(doc))


# ---------------------------------------------------------------------------
# report section
# ---------------------------------------------------------------------------

def _channels(finding, base) -> tuple[list[str], list[str]]:
    """(outputs, states) to plot for a finding."""
    kind, name = finding["target"].split(":", 1)
    outs, sts = [], []
    if kind == "output":
        outs.append(name)
    elif kind == "drift":
        sts.append(name)
        for o in base.model.output_names:
            sym = base.model.symbolic
            if sym is not None:
                i = base.model.output_names.index(o)
                e = sym.observations[i]
                if getattr(e, "name", None) == name:
                    outs.append(o)
    elif kind == "definition":
        # a coefficient: every equation and output that uses it (the finding's "users")
        users = finding.get("users") or ()
        sts = [u.split(":", 1)[1] for u in users if u.startswith("drift:")]
        outs = [u.split(":", 1)[1] for u in users if u.startswith("observations:")]
    else:
        sts = list(finding["added_terms"].get("drift", {}).keys())
    return outs, sts


def plot_finding(finding, base, final) -> str | None:
    """Before/after figure (PNG data URI) of the channels where the mismatch was found."""
    outs, sts = _channels(finding, base)
    rows = [("out", o) for o in outs if o in base.model.output_names] + \
           [("eq", s) for s in sts if s in base.model.state_names]
    if not rows:
        return None
    sb, sf = base.signals[0], final.signals[0]
    fig = new_figure(8, 2.4 * len(rows))
    axes = fig.subplots(len(rows), 1, squeeze=False)
    for ax, (kind, name) in zip(axes[:, 0], rows):
        if kind == "out":
            j = base.model.output_names.index(name)
            jf = final.model.output_names.index(name)
            ax.plot(sb.t, sb.y_meas[:, j], color="0.6", lw=1.0, label="measured")
            ax.plot(sb.t, sb.y_sim[:, j], color="tab:red", lw=1.0, label="simulation, base")
            ax.plot(sf.t, sf.y_sim[:, jf], color="tab:blue", lw=1.0, label="simulation, augmented")
            ax.set_ylabel(name)
        else:
            j = base.model.state_names.index(name)
            jf = final.model.state_names.index(name)
            eb = sb.xdot_fd[:, j] - sb.f_smooth[:, j]
            ef = sf.xdot_fd[:, jf] - sf.f_smooth[:, jf]
            ax.plot(sb.t[:-1], eb, color="tab:red", lw=0.8, label="equation error, base")
            ax.plot(sf.t[:-1], ef, color="tab:blue", lw=0.8, label="equation error, augmented")
            ax.set_ylabel(f"d({name})/dt − f")
        ax.legend(fontsize=7, loc="upper right")
        ax.grid(alpha=0.3)
    axes[-1, 0].set_xlabel("t [s]")
    fig.suptitle(f"{finding['effect']} on {finding['target']} ({sb.record})", fontsize=9)
    fig.tight_layout()
    return png_data_uri(fig)


_NOT_TESTED_TEXT = ("<b>Not tested</b>: the base fit did not converge, so a refit's gain would "
                    "measure the unfinished fit, not this setting.")


def _not_tested(stage: dict) -> bool:
    return all(t.get("verdict") == "not_tested_base_unconverged" for t in stage["trials"])


def _screen_leads(doc: dict) -> dict[str, str]:
    """Per target of round 1's score screen, its strongest score-tested candidate as text
    ("sensor_scale:p_m, −log₁₀ p 80.5"), strongest targets first; empty without a screen."""
    rounds = doc.get("rounds") or []
    best: dict[str, tuple[float, str]] = {}
    for c in (rounds[0].get("screen") or []) if rounds else []:
        st = c.get("score_test") or {}
        v = st.get("minus_log10_p")
        if not isinstance(v, (int, float)) or not math.isfinite(v) or not c.get("target"):
            continue
        if v > best.get(c["target"], (-math.inf, ""))[0]:
            best[c["target"]] = (float(v), str(c.get("key", "")))
    return {t: f"{k}, −log₁₀ p {v:.3g}"
            for t, (v, k) in sorted(best.items(), key=lambda kv: -kv[1][0])}


def report_section(doc: dict, *, base=None, final=None, accepted: Sequence = ()) -> str:
    """HTML section "Discrepancy diagnosis" for the report (findings table, text, plots)."""
    e = html.escape
    parts = ["<section id='diagnose'><h2>Discrepancy diagnosis</h2>",
             f"<p>{e(doc['conclusion'])}</p>"]
    num = doc.get("numerics") or {}
    if num.get("trials"):
        parts.append("<h3>Modelling numerics (tested before physics)</h3>"
                     f"<p>Current setting: <code>{e(num['current']['text'])}</code>. "
                     + (f"<b>{e(num['adopted']['explanation'])}</b>" if num.get("adopted")
                        else _NOT_TESTED_TEXT if _not_tested(num)
                        else "Kept: no other setting improved the fit significantly.")
                     + "</p>" + _trial_table("setting", [(f"<code>{e(t['setting']['text'])}</code>", t)
                                                       for t in num["trials"]], dof=False))
    nm = doc.get("noise_model") or {}
    if nm.get("trials"):
        parts.append("<h3>Noise model (tested before physics)</h3>"
                     f"<p>Current process noise: <code>structure: {e(nm['current']['structure'])}"
                     f"</code> on {e(', '.join(nm['current']['states']))}. "
                     + (f"<b>{e(nm['adopted']['explanation'])}</b>" if nm.get("adopted")
                        else _NOT_TESTED_TEXT if _not_tested(nm)
                        else f"<b>{e(noise_model_text(nm))}</b>"
                        if nm.get("significant_not_adopted")
                        else "Kept: the score test of correlated process noise at the "
                             "current fit is not significant, so it was not refitted."
                        if all(t.get("decided_by") == "score" for t in nm["trials"])
                        else "Kept: correlated process noise did not improve the fit "
                             "significantly.")
                     + "</p>" + _trial_table("alternative", [(e(t["alternative"]), t)
                                                           for t in nm["trials"]], dof=True))
    for r in doc.get("noise_model_retests") or []:
        if not r.get("trials"):
            continue
        k = r.get("after_round")
        parts.append(f"<h3>Noise model re-tested after round {e(str(k))} (its effect accepted)</h3>"
                     f"<p>Current process noise: <code>structure: "
                     f"{e(r['current']['structure'])}</code> on "
                     f"{e(', '.join(r['current']['states']))}. "
                     + (f"<b>{e(r['adopted']['explanation'])}</b>" if r.get("adopted")
                        else "<b>Not tested</b>: the current fit did not converge."
                        if _not_tested(r)
                        else f"<b>{e(noise_retest_text([r]))}</b>"
                        if r.get("significant_not_adopted")
                        else "Kept: with the accepted effect in the model, correlated process "
                             "noise is still not significant.")
                     + "</p>" + _trial_table("alternative", [(e(t["alternative"]), t)
                                                           for t in r["trials"]], dof=True))
    ng = doc.get("noise_gust") or {}
    if ng.get("trials"):
        gusts = "; ".join(f"{g['velocity']} − {g['gust_state']} in "
                          f"{', '.join(g['definitions'])}" for g in ng.get("gusts") or [])
        when = ("tested as a rival of the round's lead" if ng.get("checked")
                else "tested before physics")
        parts.append(f"<h3>Turbulence in the air-relative velocity ({when})</h3>"
                     f"<p>Gust tried: {e(gusts)}. "
                     + (f"<b>{e(ng['adopted']['explanation'])}</b>" if ng.get("adopted")
                        else "Kept: the gust did not improve the fit significantly.")
                     + (f" {e(gust_check_text(ng))}" if ng.get("checked") else "")
                     + "</p>" + _trial_table("alternative", [(e(t["alternative"]), t)
                                                           for t in ng["trials"]], dof=True))
    loc = doc.get("locate", {})
    if loc:
        lead = _screen_leads(doc)
        parts.append("<h3>Where the base model and the records disagree</h3>"
                     "<p>Two kinds of evidence per target. <i>Residual tests</i> correlate the "
                     "residuals of the base fit with regressors (state equations: the smoothed "
                     "path's finite differences against the drift; outputs: the smoothed and "
                     "predicted output residuals): they say <i>where</i> and <i>when</i>, but the "
                     "smoother moves the state path wherever the process noise lets it, so an "
                     "error on a state's own sensor can leave them clean. The <i>score test</i> "
                     "uses the ELBO's exact gradient and Hessian at the fit (round 1's screen of "
                     "the whole catalogue, its strongest candidate on that target shown, "
                     "−log₁₀ p unadjusted); it decides what is refitted.</p>"
                     "<table border='1' cellpadding='3' style='border-collapse:collapse;"
                     "font-size:90%'><tr><th>target</th><th>residual tests flag</th>"
                     "<th>systematic share</th><th>best regressor / test</th>"
                     "<th>windows (s)</th><th>strongest score test</th></tr>")
        for s, ev in loc.get("states", {}).items():
            top = (ev.get("top_regressors") or [{}])[0]
            wins = ", ".join(f"{w['t0']:.1f}–{w['t1']:.1f}" for w in ev.get("windows", [])
                             if w.get("t0") is not None)
            parts.append(f"<tr><td>equation {e(s)}</td><td>{'yes' if ev['flagged'] else 'no'}</td>"
                         f"<td>{(ev.get('systematic_share') or 0):.0%}</td>"
                         f"<td>{e(str(top.get('name', '')))} (p={top.get('p') or 0:.2g})</td>"
                         f"<td>{e(wins)}</td><td>{e(lead.pop(f'drift:{s}', '—'))}</td></tr>")
        for o, ev in loc.get("outputs", {}).items():
            wins = ", ".join(f"{w['t0']:.1f}–{w['t1']:.1f}" for w in ev.get("windows", [])
                             if w.get("t0") is not None)
            parts.append(f"<tr><td>output {e(o)}</td><td>{'yes' if ev['flagged'] else 'no'}</td>"
                         f"<td>{(ev.get('systematic_share') or 0):.0%}</td>"
                         f"<td>bias p={ev['bias']['p'] or 0:.2g}, scale p={ev['scale']['p'] or 0:.2g}, "
                         f"lag {ev.get('lag_s') or 0:+.3g} s</td><td>{e(wins)}</td>"
                         f"<td>{e(lead.pop(f'output:{o}', '—'))}</td></tr>")
        for target, text in lead.items():
            kind, _, name = target.partition(":")
            parts.append(f"<tr><td>{e(kind)} {e(name)}</td><td>—</td><td>—</td><td>—</td>"
                         f"<td>—</td><td>{e(text)}</td></tr>")
        parts.append("</table>")
    for f in sorted(doc["findings"] + (doc.get("noise_turbulence") or []),
                    key=lambda f: f["rank"]):
        ev = f["evidence"]
        parts.append(f"<h3>{e(str(f['rank']))}. "
                     + ("Noise model (not physics): " if f.get("disturbance") else "")
                     + f"{e(f['title'])} — {e(f['target'])}</h3>"
                     f"<p>{e(f['explanation'])}</p>")
        terms = "; ".join(f"{sect}: {k} += {v}" if isinstance(v, str) else f"{sect}: {k}"
                          for sect, d in f["added_terms"].items() for k, v in d.items())
        parts.append(f"<p><b>Added:</b> <code>{e(terms)}</code></p>")
        ptxt = ", ".join(estimate_text(k, p) for k, p in f["parameters"].items()
                         if p.get("estimate") is not None)
        parts.append(f"<p><b>Estimates:</b> {e(ptxt)}</p>")
        parts.append(f"<p><b>Evidence:</b> ELBO {ev['elbo_before']:.6g} → {ev['elbo_after']:.6g}; "
                     f"2ΔELBO = {ev['statistic']:.4g} &gt; χ²({e(str(ev['dof']))}) threshold "
                     f"{ev['threshold']:.4g} (α = {e(str(ev['alpha']))}, "
                     f"{e(str(ev['n_candidates']))} candidates, "
                     f"Holm)</p>")
        if f.get("alternatives"):
            parts.append("<p><b>" + ("Ambiguous" if f.get("ambiguous") else "Form uncertain")
                         + ":</b> not separated by the records: " + e(", ".join(
                             f"{a['key']} (2ΔELBO = {statistic_text(a)}{vuong_text(a)})"
                             for a in f["alternatives"])) + "</p>")
            seps = [a for a in f["alternatives"] if a.get("separated_by")]
            if seps:
                parts.append("<p><b>What would separate them:</b> " + e("; ".join(
                    f"from {a['key']}, {a['separated_by']}" for a in seps)) + ".</p>")
        if f.get("complementary"):
            parts.append("<p><b>Complementary:</b> " + e("; ".join(
                f"{cm['key']}, not separated in round {f['rank']}, accepted on top of it in "
                f"round {cm['accepted_in_round']}" for cm in f["complementary"]))
                + " — both were missing.</p>")
        if base is not None and final is not None:
            img = plot_finding(f, base, final)
            if img:
                parts.append(f"<img alt='before/after {e(f['target'])}' "
                             f"src='{img}'/>")
    rows = [(r["round"], t) for r in doc.get("rounds", []) for t in r.get("trials", [])]
    if rows:
        parts.append("<h3>Every candidate refitted</h3><table border='1' cellpadding='3'>"
                     "<tr><th>round</th><th>candidate</th><th>locate score</th>"
                     "<th>score test (dof)</th>"
                     "<th>2ΔELBO vs nested reference</th><th>threshold</th><th>converged</th>"
                     "<th>significant</th><th>validation</th><th>verdict</th></tr>")
        for rnd, t in rows:
            def num(v, fmt=".4g"):
                return "–" if v is None else format(v, fmt)
            conv = {True: "yes", False: "<b>no</b>", None: "–"}[t.get("converged")]
            val = {True: "holds", False: "<b>fails</b>", None: "–"}[t.get("validation_ok")]
            st = t.get("score_test") or {}
            sct = ("–" if st.get("statistic") is None
                   else f"{num(st.get('statistic'))} ({st.get('dof')})")
            parts.append(f"<tr><td>{rnd}</td><td>{e(t['key'])}</td><td>{num(t.get('score'), '.3g')}</td>"
                         f"<td>{sct}</td><td>{num(t.get('statistic'))}</td><td>{num(t.get('threshold'))}</td>"
                         f"<td>{conv}</td><td>{'yes' if t.get('significant') else 'no'}</td>"
                         f"<td>{val}</td><td>{e(t.get('verdict') or '–')}</td></tr>")
        parts.append("</table><p>An unconverged refit is never accepted (it enters the Holm "
                     "family with p = 1); nor is one with the verdict <i>below_nesting_point</i> "
                     "(an optimizer failure, not a rejection), <i>non_causal</i> (an estimate "
                     "impossible under its label) or <i>beyond_range</i> (a time constant at the "
                     "upper end of the range its label allows).</p>")
    parts.append("</section>")
    return "\n".join(parts)
