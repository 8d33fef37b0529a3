"""The cutting model against closed forms integrated by hand (not against the daemon)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from millsense.sim.cutting import CutGeometry, cutting_forces, tooth_chip_factors
from millsense.sim.machine import MATERIALS, Material, Tool

pytestmark = pytest.mark.quick

FLAT = Material("flat", 2000.0, 0.0, 0.3, 0.0, 0.2, 0.0)  # constant coefficients: K_s, r1, r2 exact


def _geom(tool, material, mode, depth_mm, radial_mm):
    return CutGeometry(tool, material, mode, np.array([-1000.0, 1000.0]), np.array([depth_mm, depth_mm]),
                       np.array([-1000.0, 1000.0]), np.array([radial_mm, radial_mm]), depth_mm)


def _rev_mean(geom, tc_mm, flutes, n=7200, factors=None):
    theta = (np.arange(n) + 0.5) * 2 * math.pi / n
    f = cutting_forces(geom, theta, np.zeros(n), np.full(n, tc_mm),
                       tooth_chip_factors(flutes) if factors is None else factors)
    return {k: v.mean() for k, v in f.items()}, f


def test_slot_one_tooth_matches_hand_integral():
    """One tooth over [0, π]: mean F_t = K_s·t_c·a/π, F_x = r1·K_s·t_c·a/4, F_y = −K_s·t_c·a/4 (no helix)."""
    tool = Tool(20.0, 1, 1e-4)
    tc, a = 0.15, 3.0
    mean, f = _rev_mean(_geom(tool, FLAT, "slot", a, 20.0), tc, 1)
    ksa = FLAT.ks * tc * a
    assert mean["ft_n"] == pytest.approx(ksa / math.pi, rel=1e-3)
    assert mean["fx_n"] == pytest.approx(FLAT.r1 * ksa / 4, rel=1e-3)
    assert mean["fy_n"] == pytest.approx(-ksa / 4, rel=1e-3)
    assert mean["fz_n"] == pytest.approx(FLAT.r2 * ksa / math.pi, rel=1e-3)
    # one tooth in cut at a time: |F| = sqrt(1 + r1²)·F_t at every instant ([P] eq. 17)
    np.testing.assert_allclose(np.hypot(f["fx_n"], f["fy_n"]), math.sqrt(1 + FLAT.r1**2) * f["ft_n"], rtol=1e-9,
                               atol=1e-9)


def _eq7(material, tool, tc, d_a, d_r):
    """[D] eq. (7) for down milling, written out here (tan β cancels)."""
    r = tool.radius_mm
    rr = d_r / r
    phi_n = 2 * math.pi / tool.flutes
    phi_r = math.acos(rr - 1)
    ta = tc * rr / (math.pi - phi_r)
    ks, r1 = material.ks * ta**material.ks_exp, material.r1 * ta**material.r1_exp
    k_over_tan = ks * r * tc  # K·tan β
    ra = d_a / r
    c_r = rr / phi_n
    a_r = (rr**2 - 2 * rr) / (2 * phi_n)
    b_r = ((rr - 1) * math.sqrt(2 * rr - rr**2) - phi_r + math.pi) / (2 * phi_n)
    return {"ft_n": k_over_tan * ra * c_r, "fx_n": k_over_tan * ra * (a_r + r1 * b_r),
            "fy_n": k_over_tan * ra * (-b_r + r1 * a_r)}


@pytest.mark.parametrize("d_r", [1.0, 3.0, 6.0])
def test_down_milling_averages_match_eq7_for_any_helix(d_r):
    """Averages per tooth period do not depend on the helix ([D] §2) and equal eq. (7)."""
    sb40 = MATERIALS["SB40"]
    expected = None
    for helix in (10.0, 30.0, 45.0):
        tool = Tool(16.0, 4, helix)
        mean, _ = _rev_mean(_geom(tool, sb40, "down", 8.0, d_r), 0.1042, 4)
        ref = _eq7(sb40, tool, 0.1042, 8.0, d_r)
        for k in ("ft_n", "fx_n", "fy_n"):
            assert mean[k] == pytest.approx(ref[k], rel=2e-3, abs=0.05), (helix, k)
        if expected is None:
            expected = mean
        for k in ("ft_n", "fx_n", "fy_n", "fz_n"):
            assert mean[k] == pytest.approx(expected[k], rel=2e-3, abs=0.05)


def test_specific_energy_balance():
    """Cutting power = K_s × material removal rate ([D] §2 sanity check)."""
    tool = Tool(20.0, 2, 30.0)
    sm45c = MATERIALS["SM45C"]
    tc, a = 0.1667, 2.0
    mean, _ = _rev_mean(_geom(tool, sm45c, "slot", a, 20.0), tc, 2)
    ks = sm45c.ks * (2 * tc / math.pi) ** sm45c.ks_exp  # slot: t_a = 2t_c/π
    omega = 2 * math.pi  # 1 rev/s: feed = N·t_c mm/s
    power = mean["ft_n"] * tool.radius_mm / 1000 * omega
    mrr_mm3_s = a * tool.diameter_mm * tool.flutes * tc
    assert power == pytest.approx(ks * mrr_mm3_s / 1000, rel=1e-3)


def test_chip_factors_broken_teeth():
    np.testing.assert_array_equal(tooth_chip_factors(2), [1, 1])
    np.testing.assert_array_equal(tooth_chip_factors(2, (1,)), [2, 0])
    np.testing.assert_array_equal(tooth_chip_factors(4, (1, 2)), [3, 0, 0, 1])
    np.testing.assert_array_equal(tooth_chip_factors(3, (0, 1, 2)), [0, 0, 0])


def test_broken_flute_keeps_removal_but_one_tooth_cuts():
    """After a breakage the survivor removes both chips: same removal rate, so mean torque
    changes only by K_s(2·t_a)/K_s(t_a) = 2^ks_exp; and one force pulse per revolution."""
    tool = Tool(20.0, 2, 30.0)
    ss41 = MATERIALS["SS41"]
    geom = _geom(tool, ss41, "slot", 3.0, 20.0)
    sound, fs = _rev_mean(geom, 0.125, 2)
    broken, fb = _rev_mean(geom, 0.125, 2, factors=tooth_chip_factors(2, (1,)))
    assert broken["ft_n"] / sound["ft_n"] == pytest.approx(2**ss41.ks_exp, rel=2e-3)
    spec_s = np.abs(np.fft.rfft(fs["ft_n"]))
    spec_b = np.abs(np.fft.rfft(fb["ft_n"]))
    assert spec_s[1] < 1e-6 * spec_s[2]  # sound tool: tooth frequency only (2 per rev)
    assert spec_b[1] > 0.3 * spec_b[2]  # broken: once per revolution


def test_entering_a_step_is_gradual():
    """The depth is taken at the cutting edge: entering a 1->3 mm step takes one radius of travel."""
    tool = Tool(20.0, 2, 30.0)
    geom = CutGeometry(tool, FLAT, "slot", np.array([0.0, 50.0, 50.000001, 100.0]), np.array([1.0, 1.0, 3.0, 3.0]),
                       np.array([0.0, 1.0]), np.array([20.0, 20.0]), 3.0)
    n = 3600
    theta = (np.arange(n) + 0.5) * 2 * math.pi / n
    means = []
    for s in (38.0, 40.5, 45.0, 49.5, 50.5):
        f = cutting_forces(geom, theta, np.full(n, s), np.full(n, 0.1), tooth_chip_factors(2))
        means.append(f["ft_n"].mean())
    assert means[1] > means[0] * 1.01  # leading edge past the wall: deeper chips begin
    assert means[0] < means[2] < means[3] < means[4]
    assert means[4] == pytest.approx(3 * means[0], rel=1e-3)
