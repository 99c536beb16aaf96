"""User-facing messages a new user found misleading (session 46).

1. `dr` used in an equation, mapped under `data.inputs` but not declared under `inputs:`:
   "unknown symbol `dr`, did you mean `Ldr`?" sent them to a parameter named after it.
2. The report showed the sample period 0.020000000000002335 s and the duration
   19.94000000000233 s, "converged converged: ...", the output `beta_m` as beta_mm and a
   definition `side` as the italic product s·i·d·e in its LaTeX.
3. diagnose's progress lines: "refitting 7 candidates" then 1/7, 2/8; "the time limit ends
   the round in 662 s" then "about 110 s left in this round"; the second member of a family
   task announced as started after it had been refitted ("ends the round in 1 s"); a delay
   profile started after the round's refit deadline.
"""

from __future__ import annotations

import io
import json
import pathlib
import subprocess
import sys
import time
import types

import pytest

from vsidgen.errors import SpecError
from vsidgen.spec import compile_spec

ROOT = pathlib.Path(__file__).resolve().parent.parent
TOTTER = ROOT / "specs" / "totter_lat.yaml"
RUDDER = "  dr: {unit: rad, description: rudder deflection}\n"


def _spec_without_rudder_input(tmp_path, *, keep_map: bool) -> pathlib.Path:
    text = TOTTER.read_text()
    assert RUDDER in text and "    dr: dr_rad\n" in text
    text = text.replace(RUDDER, "", 1)
    if not keep_map:
        text = text.replace("    dr: dr_rad\n", "", 1)
    path = tmp_path / "m2.yaml"
    path.write_text(text)
    return path


# ----------------------------------------------------------------------- 1. missing input


def test_an_input_mapped_in_the_data_but_not_declared_is_to_be_declared(tmp_path):
    path = _spec_without_rudder_input(tmp_path, keep_map=True)
    with pytest.raises(SpecError) as ei:
        compile_spec(path)
    err = ei.value
    assert err.message == "unknown symbol `dr`"
    assert "did you mean" not in err.hint and "Ldr" not in err.hint
    assert "declare `dr` under `inputs:`" in err.hint and "data.inputs" in err.hint
    assert "dr_rad" in err.hint


def test_check_command_says_declare_the_input(tmp_path):
    path = _spec_without_rudder_input(tmp_path, keep_map=True)
    proc = subprocess.run([sys.executable, "-m", "vsidgen", "check", str(path)],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode != 0
    assert "unknown symbol `dr`" in proc.stderr
    assert "declare `dr` under `inputs:`" in proc.stderr and "`Ldr`" not in proc.stderr


def test_a_name_parameters_are_named_after_looks_like_an_undeclared_variable(tmp_path):
    path = _spec_without_rudder_input(tmp_path, keep_map=False)
    with pytest.raises(SpecError) as ei:
        compile_spec(path)
    hint = ei.value.hint
    assert "did you mean" not in hint
    assert "undeclared variable" in hint and "`inputs:`" in hint and "`states:`" in hint
    assert "`Cldr`" in hint and "`Cndr`" in hint      # why it looks like one


def test_a_typo_keeps_its_did_you_mean_and_an_output_is_named_as_one(tmp_path):
    text = TOTTER.read_text()
    assert "  Cl: Clb*beta + " in text and "  phi: p + tan(theta0)*r" in text
    (tmp_path / "t.yaml").write_text(text.replace("  Cl: Clb*beta + ", "  Cl: Clbeta*beta + "))
    with pytest.raises(SpecError) as ei:
        compile_spec(tmp_path / "t.yaml")
    assert ei.value.hint == "did you mean `Clb`?"
    (tmp_path / "o.yaml").write_text(text.replace("  phi: p + tan(theta0)*r",
                                                  "  phi: ay + tan(theta0)*r"))
    with pytest.raises(SpecError) as ei:
        compile_spec(tmp_path / "o.yaml")
    assert ei.value.message == "unknown symbol `ay`" and "`ay` is an output" in ei.value.hint


# ----------------------------------------------------------------------- 2. report text


def test_report_rounds_the_sample_period_and_says_converged_once(tmp_path):
    from report_fixture import write_results_dir

    from vsidgen.report import write_report

    d = write_results_dir(tmp_path / "fit", validation=False, warnings=False, n_samples=998,
                          dt=0.02, n_outputs=1)
    res = json.loads((d / "results.json").read_text())
    for r in res["records"]["estimation"]:
        r["dt"], r["duration_s"] = 0.020000000000002335, 19.94000000000233
    assert res["status"].startswith("converged: ")
    (d / "results.json").write_text(json.dumps(res))
    src = write_report(d).read_text()
    assert "0.020000000000002335" not in src and "19.94000000000233" not in src
    assert '<td class="num">0.02</td><td class="num">19.94</td>' in src
    assert "T = 0.02 s, 19.94 s" in src
    assert "</span> converged:" not in src
    assert '<span class="tag ok">converged</span> gradient norm' in src


def test_report_latex_names_outputs_and_multi_letter_names_once_and_upright():
    from vsidgen.report.html import _equations

    groups = _equations({"definitions": {"side": r"Y_{0} + Yb \beta"},
                         "drift": {"beta": r"side - r", "phi": "p"},
                         "observations": {"beta_m": r"\beta", "ay_m": r"V_{0} side",
                                          "q": "q"}})
    tex = {(g["title"].split()[0], e["name"]): e["tex"] for g in groups for e in g["eqs"]}
    assert tex["Definitions", "side"].startswith(r"\mathrm{side} = ")
    assert tex["Observation", "beta_m"] == r"\beta_{\mathrm{m}} = \beta"     # not beta_mm
    assert tex["Observation", "ay_m"].startswith(r"\mathrm{ay}_{\mathrm{m}} = ")
    assert r"\mathrm{side}" in tex["Observation", "ay_m"]       # as the definition's name
    assert r"\mathrm{side}" in tex["State", "beta"] and tex["State", "beta"].startswith(r"\dot{\beta}")
    assert tex["Observation", "q"] == r"q_{\mathrm{m}} = q"     # a bare name gets its m
    assert all(e["img"] for g in groups for e in g["eqs"])


# ----------------------------------------------------------------------- 3. diagnose progress


def test_time_left_always_names_the_time_limit_next_to_the_estimate():
    from vsidgen.progress import DiagnoseProgress

    p = DiagnoseProgress(io.StringIO(), live=False)
    first = p.refitting(1, 1, 8, "a", limit_left=662.0)
    assert "(1/8; time left: after the first refit; the time limit ends the round in 662 s)" \
        in first
    time.sleep(0.02)
    second = p.refitting(1, 2, 8, "b", limit_left=646.0)
    assert "s left in this round; the time limit ends the round in 646 s" in second
    fam = p.refitting(1, 3, 8, "c + d", limit_left=640.0, n=2)
    assert "refitting c + d (3–4/8;" in fam


class _Clock:
    def __init__(self):
        self.t = 1000.0

    def __call__(self):
        return self.t


class _Engine:
    """Serial engine (as vsidgen.engine's): no task starts at or after the deadline; a
    family task's members come back together; ``advance`` moves the clock per task."""

    def __init__(self, clock, log, advance):
        self.clock, self.log, self.advance = clock, log, advance

    def run(self, fn, tasks, *, deadline=None, on_done=None):
        from vsidgen.discrepancy.family import FAMILY_KEY
        from vsidgen.engine import TaskOutcome, TaskStatus

        out = []
        for key, members in tasks:
            if deadline is not None and self.clock() >= deadline:
                oc = TaskOutcome(key, TaskStatus.CANCELLED, error="time limit reached")
            else:
                self.log.append(("refit", key))
                self.clock.t += self.advance.get(key, 1.0)
                if key.startswith(FAMILY_KEY):
                    oc = TaskOutcome(key, TaskStatus.DONE, value=[
                        TaskOutcome(k, TaskStatus.DONE, value=(None, []), wall_s=1.0)
                        for k in members])
                else:
                    oc = TaskOutcome(key, TaskStatus.DONE, value=(None, []), wall_s=1.0)
            out.append(oc)
            if on_done is not None:
                on_done(oc)
        return out


def _round(monkeypatch, keys, profiled, families, *, limit_s=None, advance=None):
    """Run search._refit_round on a fake engine with the real progress lines; returns
    (progress lines, engine/profile log, cut keys)."""
    from vsidgen.discrepancy import search
    from vsidgen.progress import DiagnoseProgress

    clock, log, lines = _Clock(), [], []
    monkeypatch.setattr(search, "time", types.SimpleNamespace(
        monotonic=clock, perf_counter=time.perf_counter, time=time.time))
    trial = types.SimpleNamespace(state=types.SimpleNamespace(elbo=1.0, fit=None),
                                  statistic=2.0, refit=types.SimpleNamespace(compile_s=0.0),
                                  candidate=types.SimpleNamespace(info={}))

    def delay_trial(c, *a, **kw):
        log.append(("profile", c.key))
        clock.t += 1.0
        return types.SimpleNamespace(state=None, refit=None, to_json=lambda: {"key": c.key})

    monkeypatch.setattr(search, "delay_trial", delay_trial)
    monkeypatch.setattr(search, "_trial_of", lambda *a: trial)
    monkeypatch.setattr(search, "_undecided_json", lambda t: {})
    monkeypatch.setattr(search, "_checkpoint", lambda *a, **k: None)
    monkeypatch.setattr(search, "conv_label", lambda fit: "converged")

    cands = [types.SimpleNamespace(key=k, info={}) for k in keys]
    by_key = {c.key: (i, 1.0, c, None) for i, c in enumerate(cands)}
    in_family = {k for ks in families.values() for k in ks}
    tasks = [(k, tuple(families[k])) for k in families] + [
        (c.key, ()) for i, c in enumerate(cands) if i not in profiled and c.key not in in_family]
    deadline = None if limit_s is None else clock() + limit_s
    plan = search._RoundPlan([(1.0, None, c, None) for c in cands],
                             [pathlib.Path(f"{k}.yaml") for k in keys], profiled, {}, tasks,
                             by_key, families={k: tuple(v) for k, v in families.items()},
                             deadline=deadline)
    progress = DiagnoseProgress(io.StringIO(), live=False)
    run = types.SimpleNamespace(progress=progress, engine=_Engine(clock, log, advance or {}),
                                say=lines.append, gen=None, max_iter=10, alpha=0.01)
    st = types.SimpleNamespace(unfinished={"pending": list(keys), "refitted": []})
    current = types.SimpleNamespace(model=types.SimpleNamespace(name="m"))
    _, cut = search._refit_round(run, st, 2, plan, current)
    return [ln for ln in lines if ln.startswith("round 2: refitting")
            or ln.startswith("round 2: profiling")], log, cut


def test_refit_lines_count_refits_and_delay_profiles_alike_and_a_family_once(monkeypatch):
    """1/7 then 2/8 (the delay profile counted from the second line on), and the family's
    second member announced after the family task had refitted it."""
    from vsidgen.discrepancy.family import FAMILY_KEY

    keys = ["s1", "s2", "lag", "delay_c", "delay_t", "s3"]
    fam = FAMILY_KEY + "lag+delay_c"
    lines, log, cut = _round(monkeypatch, keys, [4], {fam: ["lag", "delay_c"]}, limit_s=900.0)
    assert cut == []
    assert [ln.split(" (")[0] for ln in lines] == [
        "round 2: refitting s1", "round 2: refitting s2",
        "round 2: refitting lag + delay_c",
        "round 2: profiling the delay of delay_t over a grid", "round 2: refitting s3"]
    counts = [ln.split(" (", 1)[1].split(";")[0] for ln in lines]
    assert counts == ["1/6", "2/6", "3–4/6", "5/6", "6/6"]
    assert all("the time limit ends the round in" in ln for ln in lines)
    assert log == [("refit", "s1"), ("refit", "s2"), ("refit", fam), ("profile", "delay_t"),
                   ("refit", "s3")]


def test_nothing_is_announced_or_started_after_the_rounds_refit_deadline(monkeypatch):
    """After the refit that used up the round's time, no "refitting …" line (the engine starts
    no refit then) and no delay profile is started (it was, with 1 s left, and cut)."""
    lines, log, cut = _round(monkeypatch, ["s1", "delay_t", "s2"], [1], {}, limit_s=10.0,
                             advance={"s1": 15.0})
    assert log == [("refit", "s1")]
    assert cut == ["delay_t", "s2"]
    assert len(lines) == 1 and lines[0].startswith("round 2: refitting s1 (1/3;")


def test_a_unit_warning_for_an_added_term_points_at_the_add_terms_entry(tmp_path):
    """A child spec adding `Yr*r` (Yr declared in 1/s) to a parent's definition was warned at
    the parent's line, quoting an expression without the term (session 46, a new user); the
    warning now names the child's `add_terms` entry."""
    from vsidgen.spec import compile_spec

    parent = tmp_path / "base.yaml"
    parent.write_text("name: base\nstates:\n  beta: {unit: rad}\n  r: {unit: rad/s}\n"
                      "inputs:\n  dr: {unit: rad}\noutputs:\n  b_m: {unit: rad}\n"
                      "parameters:\n  Yb: {unit: 1/s}\n  Y0: {unit: 1/s}\n  Nb: {unit: 1/s^2}\n"
                      "  Ndr: {unit: 1/s^2}\n"
                      "definitions:\n  side: Yb*beta + Y0\n"
                      "drift:\n  beta: side - r\n  r: Nb*beta + Ndr*dr\n"
                      "observations:\n  b_m: beta\n"
                      "data:\n  time: t\n  inputs: {dr: dr}\n  outputs: {b_m: b}\n")
    child = tmp_path / "child.yaml"
    child.write_text("extends: base.yaml\nname: child\nparameters:\n  Yr: {unit: 1/s}\n"
                     "add_terms:\n  definitions:\n    side: Yr*r\n")
    got = [w for w in compile_spec(child).warnings if w.code == "units"]
    assert len(got) == 1, [w.message for w in got]
    w = got[0]
    assert pathlib.Path(w.path).name == "child.yaml" and w.line == 7, (w.path, w.line)
    assert "`Yr*r`" in w.message and "add_terms" in w.message
