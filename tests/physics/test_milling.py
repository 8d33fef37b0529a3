"""[D] eqs. (7)–(10), (12): closed-form averages against the paper's formulas and a brute-force model."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from millsense.daemon.physics.milling import (
    SB40_TABLE2,
    average_chip_thickness_mm,
    average_forces_n,
    cutting_coefficients,
    engagement_angles_rad,
    force_ratio_fx,
    force_ratio_fxt,
    load_scale,
)
from tests.physics.instant_model import instantaneous_forces

pytestmark = pytest.mark.quick

M = SB40_TABLE2


def paper_down_milling(r_r, t_c, n_flutes):
    """[D] eq. (7) as printed (down milling), with tan β = 1 (it cancels) and K R_a = K_s t_c d_a."""
    phi_r = np.arccos(r_r - 1.0)
    phi_n = 2.0 * np.pi / n_flutes
    c_r = r_r / phi_n
    a_r = (r_r**2 - 2.0 * r_r) / (2.0 * phi_n)
    b_r = ((r_r - 1.0) * np.sqrt(2.0 * r_r - r_r**2) - phi_r + np.pi) / (2.0 * phi_n)
    t_a = t_c * r_r / (np.pi - phi_r)  # eq. (8) as printed
    return a_r, b_r, c_r, t_a


def test_engagement_angles_per_mode():
    r = np.array([0.5, 1.0, 2.0])
    entry, exit_ = engagement_angles_rad(r, "down")
    np.testing.assert_allclose(entry, [np.arccos(-0.5), np.pi / 2, 0.0])
    np.testing.assert_allclose(exit_, np.pi)
    entry, exit_ = engagement_angles_rad(r, "up")
    np.testing.assert_allclose(entry, 0.0)
    np.testing.assert_allclose(exit_, [np.arccos(0.5), np.pi / 2, np.pi])
    entry, exit_ = engagement_angles_rad(r, "slot")
    np.testing.assert_allclose(entry, 0.0)
    np.testing.assert_allclose(exit_, np.pi)


def test_radial_ratio_outside_domain_is_nan_and_bad_mode_raises():
    f = average_forces_n(np.array([-0.1, 0.0, 2.5]), 1.0, 0.1, 8.0, 4, M, "down")
    assert np.all(np.isnan(f.tangential_n))
    with pytest.raises(ValueError, match="climb"):
        force_ratio_fx(1.0, 0.1, M, "climb")


def test_chip_thickness_matches_eq8_forms():
    t_c = 0.2
    entry, exit_ = engagement_angles_rad(0.6, "down")
    _, _, _, t_a_paper = paper_down_milling(0.6, t_c, 4)
    assert float(average_chip_thickness_mm(t_c, entry, exit_)) == pytest.approx(t_a_paper, rel=1e-12)
    entry, exit_ = engagement_angles_rad(2.0, "slot")
    assert float(average_chip_thickness_mm(t_c, entry, exit_)) == pytest.approx(2 * t_c / np.pi, rel=1e-12)


def test_coefficients_use_their_own_exponents():
    ks, r1, r2 = cutting_coefficients(0.1, M)
    assert float(ks) == pytest.approx(646.08 * 0.1**-0.4362)
    assert float(r1) == pytest.approx(0.2201 * 0.1**-0.2667)
    assert float(r2) == pytest.approx(0.1244 * 0.1**0.1702)


@settings(max_examples=60, deadline=None)
@given(r_r=st.floats(0.01, 2.0), t_c=st.floats(0.01, 0.7), flutes=st.integers(1, 8))
def test_down_milling_equals_the_papers_printed_eq7(r_r, t_c, flutes):
    a_r, b_r, c_r, t_a = paper_down_milling(r_r, t_c, flutes)
    ks, r1, r2 = cutting_coefficients(t_a, M)
    k_ra = float(ks) * t_c * 5.0  # K·R_a with tan β = 1, d_a = 5 mm
    f = average_forces_n(r_r, 5.0 / 8.0, t_c, 8.0, flutes, M, "down")
    np.testing.assert_allclose(f.tangential_n, k_ra * c_r, rtol=1e-9)
    np.testing.assert_allclose(f.x_n, k_ra * (a_r + r1 * b_r), rtol=1e-9, atol=1e-9 * k_ra)
    np.testing.assert_allclose(f.y_n, k_ra * (-b_r + r1 * a_r), rtol=1e-9, atol=1e-9 * k_ra)
    np.testing.assert_allclose(f.z_n, k_ra * r2 * c_r, rtol=1e-9)


@pytest.mark.parametrize(
    "mode, r_r, flutes, helix_deg, axial_mm",
    [
        ("down", 0.25, 4, 30.0, 16.0),
        ("down", 1.3, 4, 45.0, 6.0),
        ("up", 0.5, 2, 30.0, 10.0),
        ("up", 1.7, 3, 0.0, 5.0),
        ("slot", 2.0, 2, 30.0, 3.0),
    ],
)
def test_averages_equal_brute_force_instantaneous_model(mode, r_r, flutes, helix_deg, axial_mm):
    t_c, radius = 0.15, 8.0
    entry, exit_ = (float(x) for x in engagement_angles_rad(r_r, mode))
    ks, r1, _ = (float(x) for x in cutting_coefficients(average_chip_thickness_mm(t_c, entry, exit_), M))
    f_t, f_x, f_y = instantaneous_forces(
        entry_rad=entry, exit_rad=exit_, feed_per_tooth_mm=t_c, axial_depth_mm=axial_mm,
        tool_radius_mm=radius, flutes=flutes, helix_deg=helix_deg, ks_n_mm2=ks, r1=r1,
        angles=4000, slices=100,
    )
    avg = average_forces_n(r_r, axial_mm / radius, t_c, radius, flutes, M, mode)
    scale = float(avg.tangential_n)
    # The brute force samples the in-cut indicator on a 4000-point grid: error ~ 1e-3.
    assert f_t.mean() == pytest.approx(scale, rel=2e-3)
    assert f_x.mean() == pytest.approx(float(avg.x_n), abs=2e-3 * scale)
    assert f_y.mean() == pytest.approx(float(avg.y_n), abs=2e-3 * scale)


@settings(max_examples=60, deadline=None)
@given(
    r_r=st.floats(0.01, 2.0), t_c=st.floats(0.01, 0.7), axial_mm=st.floats(0.1, 30.0),
    radius_mm=st.floats(1.0, 25.0), flutes=st.integers(1, 8), rpm=st.floats(100, 20000),
    mode=st.sampled_from(["down", "up"]),
)
def test_power_balance_specific_energy_times_removal_rate(r_r, t_c, axial_mm, radius_mm, flutes, rpm, mode):
    """F_at·R·ω = K_s·d_a·d_r·(feed rate): the spindle does the cutting work."""
    f = average_forces_n(r_r / 1.0, axial_mm / radius_mm, t_c, radius_mm, flutes, M, mode)
    entry, exit_ = engagement_angles_rad(r_r, mode)
    ks = float(cutting_coefficients(average_chip_thickness_mm(t_c, entry, exit_), M)[0])
    omega = rpm * 2 * np.pi / 60
    power_w = float(f.tangential_n) * radius_mm * 1e-3 * omega
    feed_mm_s = flutes * t_c * rpm / 60
    removal_mm3_s = axial_mm * r_r * radius_mm * feed_mm_s
    assert power_w == pytest.approx(ks * removal_mm3_s * 1e-3, rel=1e-9)  # N/mm² · mm³/s = mJ/s


def test_slot_ratios_reduce_to_r1():
    """Slot: a = 0, b = π/2, c = 2 → f_x = r₁/√(1+r₁²), f_xt = r₁·π/4."""
    t_c = 0.1
    r1 = float(cutting_coefficients(2 * t_c / np.pi, M)[1])
    assert float(force_ratio_fx(2.0, t_c, M, "slot")) == pytest.approx(r1 / np.sqrt(1 + r1**2), rel=1e-12)
    assert float(force_ratio_fxt(2.0, t_c, M, "slot")) == pytest.approx(r1 * np.pi / 4, rel=1e-12)
    assert float(force_ratio_fx(2.0, t_c, M, "down")) == pytest.approx(float(force_ratio_fx(2.0, t_c, M, "slot")))


def test_fxt_strictly_increasing_in_down_milling():
    r = np.geomspace(1e-3, 2.0, 3000)
    for t_c in (0.01, 0.05, 0.1042, 0.3, 0.7):
        assert np.all(np.diff(force_ratio_fxt(r, t_c, M, "down")) > 0)


def test_fx_turns_over_at_small_immersion_in_down_milling():
    r = np.geomspace(1e-3, 2.0, 3000)
    for t_c in (0.01, 0.1042, 0.7):
        f = force_ratio_fx(r, t_c, M, "down")
        turn = r[np.argmin(f)]
        assert 0.005 < turn < 0.03
        assert np.all(np.diff(f[r > turn * 1.01]) > 0)


@settings(max_examples=60, deadline=None)
@given(r_r=st.floats(0.01, 2.0), t_c=st.floats(0.01, 0.5), override_pct=st.floats(10.0, 200.0),
       mode=st.sampled_from(["down", "up", "slot"]))
def test_load_scale_is_eq7_at_the_overridden_feed_over_the_programmed_one(r_r, t_c, override_pct, mode):
    """The override scales t_c; eq. 7 with K_s(t_a) of eq. 9 gives the load's ratio u^(1 + p) ([D] eq. 8)."""
    u = override_pct / 100.0
    at_programmed = float(average_forces_n(r_r, 0.5, t_c, 8.0, 4, M, mode).tangential_n)
    at_override = float(average_forces_n(r_r, 0.5, t_c * u, 8.0, 4, M, mode).tangential_n)
    assert load_scale(override_pct, 1.0 + M.ks_exp) == pytest.approx(at_override / at_programmed, rel=1e-9)


@pytest.mark.parametrize("override_pct", [100.0, None, 0.0, -5.0, float("nan")])
def test_load_scale_takes_the_load_as_it_is_at_or_without_a_sensible_override(override_pct):
    assert load_scale(override_pct, 0.56) == 1.0
