"""The independent simulator of benchmarks/independent (no vsidgen code) against exact and
textbook references: linear response (scipy.signal.lsim on a much finer grid), a pure
transport delay, level-flight trim, Dryden spectrum and variance, vane kinematics."""

import math
import pathlib
import sys

import numpy as np
import pytest
from scipy import signal

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "benchmarks" / "independent"))
import sim  # noqa: E402


@pytest.mark.parametrize("effect,mag", [("none", 0.0), ("phugoid", 1.0)])
def test_linear_longitudinal_matches_lsim(effect, mag):
    cols, _ = sim.simulate_sp(effect=effect, magnitude=mag, duration=12.0, gust_sigma_bg=0.0,
                              clean=True)
    A, B = sim.sp_matrices(effect, mag)
    C = np.array([[0, 1.0, 0, 0], [0, 0, 1.0, 0]])
    t_fine = np.arange(0, 12.0 + 1e-9, 1e-4)
    u = sim.sp_elevator()(t_fine)
    _, y, _ = signal.lsim((A, B[:, None], C, np.zeros((2, 1))), u, t_fine)
    k = np.round(cols["t_s"] / 1e-4).astype(int)
    for j, name in enumerate(("alpha_rad", "q_radps")):
        ref = y[k, j]
        assert np.max(np.abs(cols[name] - ref)) < 1e-5 * np.max(np.abs(ref))


def test_transport_delay_is_an_exact_shift():
    base, _ = sim.simulate_sp(duration=20.0, gust_sigma_bg=0.0, clean=True)
    late, _ = sim.simulate_sp(effect="de_delay", magnitude=0.12, duration=20.0,
                              gust_sigma_bg=0.0, clean=True)
    # 0.12 s = 3 samples of 0.04 s; the record starts at rest, the maneuver at 2 s
    for name in ("alpha_rad", "q_radps"):
        np.testing.assert_allclose(late[name][3:], base[name][:-3], atol=1e-12)
    np.testing.assert_array_equal(late["de_rad"], base["de_rad"])  # the recorded command


def test_hfb_trim_is_an_equilibrium():
    cols, truth = sim.simulate_hfb(duration=10.0, de_amp=0.0, gust_sigma_bg=0.0, clean=True)
    assert 0.05 < truth["trim"]["alpha"] < 0.2
    for name in ("v_mps", "alpha_rad", "theta_rad", "q_radps", "ax_mps2", "az_mps2"):
        assert np.ptp(cols[name]) < 1e-8 * max(1.0, np.max(np.abs(cols[name])))
    # level flight: vertical specific force balances weight, θ = α
    a = truth["trim"]["alpha"]
    assert cols["az_mps2"][0] * math.cos(a) - cols["ax_mps2"][0] * math.sin(a) == \
        pytest.approx(-sim.G0, rel=1e-9)
    assert cols["theta_rad"][0] == pytest.approx(a, abs=1e-12)


def test_dryden_variance_and_spectrum():
    sigma, L, V, step = 1.5, 50.0, 100.0, 0.01
    rng = np.random.default_rng(3)
    w = sim.dryden_series(rng, 400_000, step, sigma, L, V)
    assert np.var(w) == pytest.approx(sigma**2, rel=0.05)
    f, p_hz = signal.welch(w, fs=1 / step, nperseg=4096)
    omega = 2 * np.pi * f
    phi = p_hz / (2 * np.pi)           # one-sided, per rad/s
    theory = sim.dryden_psd(omega, sigma, L, V)
    for lo, hi in ((0.05, 0.2), (0.2, 0.8), (0.8, 3.0), (3.0, 10.0)):
        sel = (f >= lo) & (f < hi)
        assert np.mean(phi[sel]) == pytest.approx(np.mean(theory[sel]), rel=0.1)
    # ∫Φ dω = σ²
    grid = np.linspace(0, 2000, 2_000_001)
    assert np.trapezoid(sim.dryden_psd(grid, sigma, L, V), grid) == pytest.approx(
        sigma**2, rel=2e-3)


def test_vane_kinematics_small_angles():
    V, x = 100.0, 8.0
    alpha = np.linspace(-0.02, 0.02, 7)
    q = np.linspace(-0.05, 0.05, 7)
    u, w = V * np.cos(alpha), V * np.sin(alpha)
    exact = sim.vane_angle(w, u, q, x)
    small = alpha - x * q / V
    assert np.max(np.abs(exact - small)) < 3e-5          # second order in α and x q/V
    assert np.max(np.abs(exact - small)) > 0             # full kinematics, not the linear form
    # larger angles: first order in x q/V with the exact factor ∂atan2(w, u)/∂w = cos α / V
    alpha = np.linspace(-0.1, 0.3, 9)
    u, w = V * np.cos(alpha), V * np.sin(alpha)
    first = alpha - x * q[0] / V * np.cos(alpha)
    assert np.max(np.abs(sim.vane_angle(w, u, q[0], x) - first)) < 2 * (x * q[0] / V) ** 2


def test_vane_and_accelerometer_offsets_in_simulated_records():
    kw = dict(duration=20.0, gust_sigma_bg=0.0, clean=True)
    base, _ = sim.simulate_hfb(**kw)
    vane, _ = sim.simulate_hfb(effect="alpha_vane", magnitude=10.0, **kw)
    acc, _ = sim.simulate_hfb(effect="az_position", magnitude=5.0, **kw)
    d = vane["alpha_rad"] - base["alpha_rad"]
    lin = -10.0 * base["q_radps"] / base["v_mps"]
    assert np.max(np.abs(d - lin)) < 0.02 * np.max(np.abs(lin))
    np.testing.assert_allclose(acc["az_mps2"] - base["az_mps2"], -5.0 * base["qdot_radps2"],
                               atol=1e-12)
    np.testing.assert_allclose(acc["ax_mps2"] - base["ax_mps2"], -5.0 * base["q_radps"] ** 2,
                               atol=1e-12)
    lat0, _ = sim.simulate_lat(duration=15.0, gust_sigma_bg=0.0, clean=True)
    lat1, _ = sim.simulate_lat(effect="beta_vane", magnitude=6.0, duration=15.0,
                               gust_sigma_bg=0.0, clean=True)
    lin = 6.0 * lat0["r_radps"] / 100.0
    assert np.max(np.abs(lat1["beta_rad"] - lat0["beta_rad"] - lin)) < 0.02 * np.max(np.abs(lin))


def _lat_lsim(t, da_surface, dr_surface):
    """The linear lateral model of sim.LAT driven by the given surface signals on the fine grid
    ``t`` (scipy.signal.lsim): states (β, p, r, φ)."""
    c, V0 = sim.LAT, sim.LAT["V0"]
    A = np.array([[c["YB"], c["YP"], c["YR"] - 1.0, sim.G0 / V0],
                  [c["LB"], c["LP"], c["LR"], 0.0],
                  [c["NB"], c["NP"], c["NR"], 0.0],
                  [0.0, 1.0, 0.0, 0.0]])
    B = np.array([[0.0, c["YDR"]], [c["LDA"], c["LDR"]], [c["NDA"], c["NDR"]], [0.0, 0.0]])
    _, y, _ = signal.lsim((A, B, np.eye(4), np.zeros((4, 2))),
                          np.column_stack([da_surface, dr_surface]), t)
    return y


def test_lateral_effects_against_independent_references():
    """The lateral effects: an accelerometer ahead of the CG adds x·ṙ (ṙ checked against a
    central difference of the recorded r); an aileron transport delay and a rudder lag are
    compared with the linear model (scipy.signal.lsim on a 0.1-ms grid) driven by the delayed
    aileron command and by the rudder command through a first-order filter (the surfaces are
    not recorded); a p-gyro bias moves p alone."""
    kw = dict(duration=20.0, gust_sigma_bg=0.0, clean=True)
    base, _ = sim.simulate_lat(**kw)
    acc, _ = sim.simulate_lat(effect="ay_position", magnitude=4.0, **kw)
    dt = base["t_s"][1] - base["t_s"][0]
    rdot_fd = np.gradient(base["r_radps"], dt)
    d = acc["ay_mps2"] - base["ay_mps2"]
    assert np.max(np.abs(d - 4.0 * rdot_fd)) < 0.05 * np.max(np.abs(d))
    for name in ("beta_rad", "p_radps", "r_radps", "phi_rad"):
        np.testing.assert_array_equal(acc[name], base[name])

    bias, _ = sim.simulate_lat(effect="p_bias", magnitude=0.002, **kw)
    np.testing.assert_allclose(bias["p_radps"] - base["p_radps"], 0.002, atol=1e-15)
    for name in ("beta_rad", "r_radps", "phi_rad", "ay_mps2"):
        np.testing.assert_array_equal(bias[name], base[name])

    t_fine = np.arange(0.0, 20.0 + 1e-9, 1e-4)
    da = sim.doublet(2.0, 1.0, 0.03) + sim.m3211(16.0, 0.6, -0.7 * 0.03)
    dr = sim.m3211(7.0, 0.8, 0.03) + sim.doublet(23.0, 1.0, -0.03)
    tau = 0.15
    _, dr_surface, _ = signal.lsim(([1.0], [tau, 1.0]), dr(t_fine), t_fine)
    cases = {"none": (da(t_fine), dr(t_fine)), "da_delay": (da(t_fine - 0.12), dr(t_fine)),
             "dr_lag": (da(t_fine), dr_surface)}
    for effect, (a, r) in cases.items():
        rec, _ = sim.simulate_lat(effect=effect, magnitude={"none": 0.0, "da_delay": 0.12,
                                                            "dr_lag": tau}[effect], **kw)
        np.testing.assert_array_equal(rec["da_rad"], base["da_rad"])   # the recorded commands
        np.testing.assert_array_equal(rec["dr_rad"], base["dr_rad"])
        y = _lat_lsim(t_fine, a, r)
        k = np.round(rec["t_s"] / 1e-4).astype(int)
        for j, name in enumerate(("beta_rad", "p_radps", "r_radps", "phi_rad")):
            ref = y[k, j]
            assert np.max(np.abs(rec[name] - ref)) < 1e-4 * np.max(np.abs(ref)), (effect, name)
        if effect != "none":
            assert np.max(np.abs(rec["p_radps"] - base["p_radps"])) > 0.05 * np.max(
                np.abs(base["p_radps"])), effect
