"""The generated HFB-320 model equals an independent hand-written implementation.

The reference below is typed from Jategaonkar's test case 4 (xdot_TC04_hfb_lon.m,
obs_TC04_hfb_lon.m) in plain numpy, sharing no code with the spec compiler.
"""

import pathlib

import jax
import numpy as np
import pytest

jax.config.update("jax_enable_x64", True)

from vsidgen.model import load_model  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parents[1]

G0, SBYM, SCBYIY, FEIYLT = 9.80665, 4.02800e-3, 8.00270e-4, -7.01530e-6
V0, RM, SIGMAT, RHO, CBARH = 104.67, 7472.0, 0.0524, 0.792, 1.215


def hand_drift(x, u, p):
    V, al, th, q = x
    de, fe = u
    CD0, CDV, CDAL, CL0, CLV, CLAL, CM0, CMV, CMAL, CMQ, CMDE = p
    qbar = 0.5 * RHO * V**2
    CD = CD0 + CDV * V / V0 + CDAL * al
    CL = CL0 + CLV * V / V0 + CLAL * al
    Cm = CM0 + CMV * V / V0 + CMAL * al + CMQ * q * CBARH / V0 + CMDE * de
    Vdot = -SBYM * qbar * CD + fe * np.cos(al + SIGMAT) / RM + G0 * np.sin(al - th)
    aldot = (-SBYM * qbar / V * CL - fe * np.sin(al + SIGMAT) / (RM * V) + q
             + G0 * np.cos(al - th) / V)
    qdot = SCBYIY * qbar * Cm + FEIYLT * fe
    return np.array([Vdot, aldot, q, qdot])


def hand_output(x, u, p):
    V, al, th, q = x
    de, fe = u
    CD0, CDV, CDAL, CL0, CLV, CLAL, CM0, CMV, CMAL, CMQ, CMDE = p
    qbar = 0.5 * RHO * V**2
    CD = CD0 + CDV * V / V0 + CDAL * al
    CL = CL0 + CLV * V / V0 + CLAL * al
    Cm = CM0 + CMV * V / V0 + CMAL * al + CMQ * q * CBARH / V0 + CMDE * de
    CX = CL * np.sin(al) - CD * np.cos(al)
    CZ = -CL * np.cos(al) - CD * np.sin(al)
    return np.array([
        V, al, th, q,
        SCBYIY * qbar * Cm + FEIYLT * fe,
        qbar * SBYM * CX + fe * np.cos(SIGMAT) / RM,
        qbar * SBYM * CZ - fe * np.sin(SIGMAT) / RM,
    ])


@pytest.fixture(scope="module")
def model():
    return load_model(ROOT / "specs" / "hfb320.yaml", generated_dir=ROOT / "generated")


def _random_points(n, seed=0):
    rng = np.random.default_rng(seed)
    xs = np.column_stack([rng.uniform(60, 150, n), rng.uniform(-0.3, 0.4, n),
                          rng.uniform(-0.5, 0.5, n), rng.uniform(-0.3, 0.3, n)])
    us = np.column_stack([rng.uniform(-0.1, 0.1, n), rng.uniform(5e3, 2e4, n)])
    ps = rng.normal(0.0, 2.0, (n, 11))
    return xs, us, ps


def test_names_follow_textbook(model):
    assert model.parameter_names == ("CD0", "CDV", "CDAL", "CL0", "CLV", "CLAL",
                                     "CM0", "CMV", "CMAL", "CMQ", "CMDE")
    assert model.state_names == ("V", "alpha", "theta", "q")
    assert model.input_names == ("de", "thrust")
    assert model.output_names == ("V", "alpha", "theta", "q", "qdot", "ax", "az")


def test_drift_and_output_equal_hand_written(model):
    xs, us, ps = _random_points(200)
    for x, u, p in zip(xs, us, ps):
        np.testing.assert_allclose(np.asarray(model.drift(x, u, p)), hand_drift(x, u, p),
                                   rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(np.asarray(model.output(x, u, p)), hand_output(x, u, p),
                                   rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("fname,hand,arg", [
    ("drift_jac_x", hand_drift, 0), ("drift_jac_u", hand_drift, 1), ("drift_jac_p", hand_drift, 2),
    ("output_jac_x", hand_output, 0), ("output_jac_u", hand_output, 1), ("output_jac_p", hand_output, 2),
])
def test_generated_jacobians(model, fname, hand, arg):
    gen = getattr(model.module, fname)
    base = model.drift if hand is hand_drift else model.output
    xs, us, ps = _random_points(20, seed=1)
    for x, u, p in zip(xs, us, ps):
        args = [x, u, p]
        J = np.asarray(gen(*args))
        J_ad = np.asarray(jax.jacfwd(base, argnums=arg)(*args))
        np.testing.assert_allclose(J, J_ad, rtol=1e-10, atol=1e-10)
        # central finite differences of the independent hand-written model
        v = np.asarray(args[arg], dtype=float)
        J_fd = np.empty_like(J)
        for i in range(v.size):
            h = 1e-6 * max(1.0, abs(v[i]))
            vp, vm = v.copy(), v.copy()
            vp[i] += h
            vm[i] -= h
            ap, am = list(args), list(args)
            ap[arg], am[arg] = vp, vm
            J_fd[:, i] = (hand(*ap) - hand(*am)) / (2 * h)
        np.testing.assert_allclose(J, J_fd, rtol=1e-5, atol=1e-6 * np.abs(J).max())
