"""The catalogue's missing trim (constant) term, ``trim_term``: ``f_s += D`` for a state
equation without a free constant.

* It is offered exactly where a user's linear model written in absolute variables has no
  constant (the textbook ATTAS short period has ``Z0`` and ``M0``: nothing; with ``M0``
  deleted as a new user would write it: the q equation only; never a kinematic state).
* Its score statistic on a record from an independent numpy simulation (a one-state model
  trimmed away from zero) equals Rao's statistic of an exact Kalman filter written in
  jax.numpy (tests/test_score_states.py's references).
* Marked slow and flight: the real ATTAS record ``attas_elv1`` fitted without ``M0`` —
  diagnose names the q equation's trim term first and estimates it near the textbook's
  output-error ``M0`` (../shared/reference/attas_sp_reference.json).
"""

from __future__ import annotations

import json
import pathlib

import pytest
from test_score_states import _kf_bias, screen_against_kalman, simulate_lin1

from vsidgen.discrepancy.base import model_info, propose
from vsidgen.discrepancy.catalogue import has_constant_term

ROOT = pathlib.Path(__file__).resolve().parents[1]
ATTAS = ROOT / "specs" / "attas_sp.yaml"
HFB = ROOT / "specs" / "hfb320.yaml"


def _without_m0(tmp_path) -> pathlib.Path:
    """specs/attas_sp.yaml with M0 deleted the way a user edits it (parameter and term)."""
    lines = [ln for ln in ATTAS.read_text().splitlines() if not ln.strip().startswith("M0:")]
    text = "\n".join(lines).replace("q: M0 + MAL*alpha", "q: MAL*alpha")
    text = text.replace("name: attas_sp\n", "name: attas_sp_no_m0\n")
    assert "M0" not in text
    p = tmp_path / "attas_sp_no_m0.yaml"
    p.write_text(text + "\n")
    return p


def _trim_keys(spec) -> list[str]:
    return sorted(c.key for c in propose(model_info(spec, dt=0.04)) if c.effect == "trim_term")


def test_trim_term_only_where_an_equation_has_no_free_constant(tmp_path):
    assert _trim_keys(ATTAS) == []
    no_m0 = _without_m0(tmp_path)
    assert _trim_keys(no_m0) == ["trim_term:q"]
    info = model_info(no_m0, dt=0.04)
    assert has_constant_term(info, "alpha") and not has_constant_term(info, "q")
    c = next(c for c in propose(info) if c.key == "trim_term:q")
    (p,) = c.parameters
    assert p.initial == 0.0 and p.unit == "(rad/s)/s" and c.add_terms == {"drift": {"q": p.name}}
    # HFB-320: θ̇ = q is kinematics (no trim force); its aerodynamic states have no free
    # additive constant (CL0 etc. are scaled by the dynamic pressure)
    assert _trim_keys(HFB) == ["trim_term:V", "trim_term:all", "trim_term:alpha", "trim_term:q"]


def test_all_trim_terms_together_for_a_model_without_any(tmp_path):
    """A model linearised about zero instead of its trim point lacks every constant: one
    candidate adds them all (its spec compiles; at zero it is the user's model)."""
    from vsidgen.spec import compile_spec

    user = ROOT / "benchmarks" / "users" / "tu144_mine.yaml"
    info = model_info(user, dt=0.03125)
    assert _trim_keys(user) == ["trim_term:all", "trim_term:alpha", "trim_term:q"]
    c = next(c for c in propose(info) if c.key == "trim_term:all")
    assert c.target == "drift:alpha+q" and len(c.parameters) == 2 and c.n_free == 2
    p = tmp_path / "all.yaml"
    p.write_text(c.spec_yaml(user, name="tu144_trims", candidate_path=p, info=info))
    sym = compile_spec(p)
    base = compile_spec(user)
    for i, (a, b) in enumerate(zip(sym.drift_expanded(), base.drift_expanded())):
        (new,) = {s.name for s in a.free_symbols} - {s.name for s in b.free_symbols}
        assert new.startswith("D_TRIM_")
        assert (a - b).free_symbols == {next(s for s in a.free_symbols if s.name == new)}


def test_trim_term_score_statistic_against_kalman_filter(tmp_path):
    """x′ = −1.2 x + 2 u + 0.08 (independent numpy simulation, 10 substeps per sample),
    fitted with the constant left out: the screen's statistic of ``trim_term:x`` against an
    exact Kalman filter's Rao statistic at the null maximum-likelihood estimate."""
    t, u, y = simulate_lin1(23, trim=0.08)
    res, ref = screen_against_kalman(tmp_path, t, u, y, "trim_term:x",
                                     lambda p, c: _kf_bias(p, u, y, 0.0, c))
    print("trim_term:x score statistic", res.statistic, "Kalman-filter reference", ref)
    assert res.dof == 1 and 10.0 < ref < 5000.0, (res, ref)
    # measured: 24.878 against 24.742
    assert res.statistic == pytest.approx(ref, rel=0.02), (res.statistic, ref)


@pytest.mark.slow
@pytest.mark.flight
def test_attas_without_m0_names_the_trim_term(flight_data_dir, tmp_path):
    """attas_elv1 (validation attas_elv2) with the textbook spec less M0. Measured
    2026-11-28: trim_term:q first, 2ΔELBO 1767, D_TRIM_q 0.4698 ± 0.0047 (rad/s)/s against
    the output-error M0 0.4752 ± 0.0014; ELBO 7375.18 = the textbook spec's 7375.17."""
    from vsidgen.discrepancy import search

    ref = json.loads((ROOT.parent / "shared" / "reference" / "attas_sp_reference.json")
                     .read_text()) if (ROOT.parent / "shared" / "reference").is_dir() else None
    out = tmp_path / "diag"
    search.run_diagnose(_without_m0(tmp_path), [flight_data_dir / "attas_elv1.csv"],
                        validate=[flight_data_dir / "attas_elv2.csv"], out=out, max_rounds=1,
                        max_candidates=3, numerics=False, workers=1)
    doc = json.loads((out / "findings.json").read_text())
    first = doc["findings"][0]
    assert first["key"] == "trim_term:q", [f["key"] for f in doc["findings"]]
    (est,) = first["parameters"].values()
    m0 = ref["oem"]["parameters"]["M0"]["value"] if ref else 0.475234
    assert abs(est["estimate"] - m0) < 0.05 * abs(m0), (est, m0)


@pytest.mark.slow
@pytest.mark.flight
def test_a_users_model_without_trim_terms_gets_them_all(flight_data_dir, tmp_path):
    """benchmarks/users/tu144_mine.yaml (short period in absolute α, δe without constants) on
    tu144_lon_f20_4f (validation f20_4d). Measured 2026-11-28: trim_term:all screened first
    (−log10 p 132) and accepted, 2ΔELBO 1022; D_TRIM_alpha 0.0573 ± 0.0014 rad/s and D_TRIM_q
    0.1152 ± 0.0074 rad/s² against the textbook spec's Z0 0.0579 ± 0.0007 and M0
    0.1155 ± 0.0066 on the same record; an 'elevator lag' of 5.0 s (2ΔELBO 3022) beyond its
    label's range, not accepted."""
    from vsidgen.discrepancy import search

    out = tmp_path / "diag"
    search.run_diagnose(ROOT / "benchmarks" / "users" / "tu144_mine.yaml",
                        [flight_data_dir / "tu144_lon_f20_4f.csv"],
                        validate=[flight_data_dir / "tu144_lon_f20_4d.csv"], out=out,
                        max_rounds=1, workers=1)
    doc = json.loads((out / "findings.json").read_text())
    first = doc["findings"][0]
    assert first["key"] == "trim_term:all", [f["key"] for f in doc["findings"]]
    est = {k: v["estimate"] for k, v in first["parameters"].items()}
    assert abs(est["D_TRIM_alpha"] - 0.0579) < 0.005 and abs(est["D_TRIM_q"] - 0.1155) < 0.02

