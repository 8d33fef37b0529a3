"""The forward model: a programmed cut's expected torque and force (daemon/physics/expected.py)."""

import math

import pytest

from millsense.daemon.physics.expected import ProgrammedCut, cut_feed_per_tooth_mm, expected_load
from millsense.daemon.physics.milling import SB40_TABLE2, cutting_coefficients, engagement_angles_rad, average_chip_thickness_mm

R_MM, FLUTES = 8.0, 4


def _load(cut, rpm=1000.0, override=100.0):
    return expected_load(cut, tool_radius_mm=R_MM, flutes=FLUTES, material=SB40_TABLE2, spindle_rpm=rpm, override_pct=override)


@pytest.mark.parametrize("mode, ae_mm", [("slot", 16.0), ("down", 4.0), ("up", 6.0)])
def test_the_expected_power_is_the_specific_energy_times_the_removal_rate(mode, ae_mm):
    """T·ω = K_s(t_a)·a_e·a_p·v_f: what the cut removes, at [D] eq. 9's specific energy — not eq. 7 restated."""
    rpm, fz, ap = 900.0, 0.08, 3.0
    load = _load(ProgrammedCut(ae_mm, ap, mode, feed_per_tooth_mm=fz), rpm=rpm)
    entry, exit_ = engagement_angles_rad(ae_mm / R_MM, mode)
    ks, _, _ = cutting_coefficients(average_chip_thickness_mm(fz, entry, exit_), SB40_TABLE2)
    feed_mm_s = fz * FLUTES * rpm / 60.0
    power_w = float(ks) * ae_mm * ap * feed_mm_s * 1e-3
    assert load.torque_nm * rpm * 2.0 * math.pi / 60.0 == pytest.approx(power_w, rel=1e-9)
    assert load.force_n > load.torque_nm / (R_MM * 1e-3)   # C_f > 1: the radial component adds


def test_a_feed_rate_and_its_feed_per_tooth_expect_the_same_load_and_both_follow_the_override():
    rpm = 1200.0
    per_tooth = ProgrammedCut(16.0, 2.0, "slot", feed_per_tooth_mm=0.05)
    per_minute = ProgrammedCut(16.0, 2.0, "slot", feed_mm_min=0.05 * FLUTES * rpm)
    assert _load(per_tooth, rpm) == pytest.approx(_load(per_minute, rpm))
    assert cut_feed_per_tooth_mm(per_tooth, rpm, FLUTES, 50.0) == pytest.approx(0.025)
    assert cut_feed_per_tooth_mm(per_minute, 2 * rpm, FLUTES, 100.0) == pytest.approx(0.025)   # G94: faster spindle, thinner chip
    assert _load(per_tooth, rpm, 50.0).torque_nm < _load(per_tooth, rpm).torque_nm


@pytest.mark.parametrize("override", [None, 0.0, -5.0, math.nan])
def test_an_unknown_override_expects_nothing(override):
    assert _load(ProgrammedCut(16.0, 2.0, "slot", feed_per_tooth_mm=0.05), override=override) is None


def test_a_stopped_spindle_or_a_cut_without_feed_expects_nothing():
    assert _load(ProgrammedCut(16.0, 2.0, "slot", feed_mm_min=200.0), rpm=0.0) is None
    assert _load(ProgrammedCut(16.0, 2.0, "slot")) is None
    assert _load(ProgrammedCut(20.0, 2.0, "down", feed_per_tooth_mm=0.05)) is None   # ae beyond the diameter
