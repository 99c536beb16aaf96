"""The report's "where" table shows, beside the residual tests of locate, the exact score test
of the round-1 screen per target, so that a sensor error the smoother absorbs (residual tests
clean, score test strong) is not shown as "no mismatch" next to a candidate ranked first.
(Session 47: a new user's lateral model had "bias p=1, scale p=0.33" on p_m while
sensor_scale:p_m scored −log10 p 80.5 in the screen.)"""

import re

from vsidgen.discrepancy.findings import _screen_leads, report_section


def _ev(flagged=False):
    return {"flagged": flagged, "systematic_share": 0.0, "windows": [],
            "bias": {"p": 1.0}, "scale": {"p": 0.33}, "lag_s": 0.0}


def _cand(key, target, mlp):
    return {"key": key, "target": target,
            "score_test": {"statistic": 1.0, "dof": 1, "minus_log10_p": mlp}}


def _doc():
    screen = [_cand("sensor_bias:p_m", "output:p_m", 2.0),
              _cand("sensor_scale:p_m", "output:p_m", 80.5),
              _cand("missing_derivative:p:r", "drift:p", 4.0),
              _cand("coefficient_derivative:side:r", "definition:side", 157.0),
              {"key": "locate_only:q", "target": "output:q_m", "score_test": None},
              _cand("nan:x", "output:r_m", float("nan"))]
    loc = {"states": {"p": {"flagged": True, "systematic_share": 0.29, "windows": [],
                            "top_regressors": [{"name": "udot:da", "p": 1e-19}]}},
           "outputs": {"p_m": _ev(), "r_m": _ev()}}
    return {"conclusion": "x", "findings": [], "locate": loc,
            "rounds": [{"round": 1, "screen": screen, "trials": []}]}


def _rows(html):
    table = html[html.index("Where the base"):html.index("</table>")]
    return [re.sub(r"<[^>]+>", "|", r) for r in table.split("<tr>")[2:]]


def test_each_target_gets_its_strongest_score_test():
    leads = _screen_leads(_doc())
    assert leads == {"definition:side": "coefficient_derivative:side:r, −log₁₀ p 157",
                     "output:p_m": "sensor_scale:p_m, −log₁₀ p 80.5",
                     "drift:p": "missing_derivative:p:r, −log₁₀ p 4"}
    assert list(leads)[0] == "definition:side"     # strongest first


def test_report_table_puts_the_score_test_beside_the_residual_tests():
    rows = _rows(report_section(_doc()))
    p_m = next(r for r in rows if "output p_m" in r)
    assert "scale p=0.33" in p_m and "sensor_scale:p_m, −log₁₀ p 80.5" in p_m
    assert "missing_derivative:p:r" in next(r for r in rows if "equation p" in r)
    assert "—" in next(r for r in rows if "output r_m" in r)     # NaN statistic not shown
    # targets without a residual test (definitions, inputs) get their own row
    assert any("definition side" in r and "157" in r for r in rows)


def test_no_screen_no_score_column_values():
    doc = _doc()
    doc["rounds"] = []
    assert _screen_leads(doc) == {}
    rows = _rows(report_section(doc))
    assert all("−log₁₀" not in r for r in rows)
