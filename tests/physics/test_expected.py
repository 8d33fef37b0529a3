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
    ks, r1, _ = cutting_coefficients(average_chip_thickness_mm(fz, entry, exit_), SB40_TABLE2)
    one_tooth_n = math.sqrt(1.0 + float(r1) ** 2) * load.torque_nm / (R_MM * 1e-3)    # [P] eq. 17 per tooth
    assert 0.0 < load.force_n <= one_tooth_n * (1.0 + 1e-9)   # teeth add as vectors: never more than eq. 17


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


# The plant's own slices (sim/cutting.py, every edge element's (F_x, F_y) added): the forward force of a
# programmed cut against the plant's revolution mean |(F_x, F_y)| and its torque, at the same chip. The
# plant takes K_s, r_1 at the average chip as [D] eq. 7 does, so the torque agrees to the quadrature and
# the force to η's table (tests/physics/test_resultant.py, 0.1 %) and the plant's axial slicing (its
# helix lag in 20+ steps: well under 0.05 % at these lags).
PLANT_FORCE_REL = 1.5e-3


def _plant_mean(tool, material, mode, ae_mm, ap_mm, fz_mm):
    import numpy as np

    from millsense.sim.cutting import CutGeometry, cutting_forces

    xp = np.array([-1000.0, 1000.0])
    geom = CutGeometry(tool, material, mode, xp, np.array([ap_mm, ap_mm]), xp, np.array([ae_mm, ae_mm]), ap_mm)
    n = 4096
    theta = np.arange(n) * (2.0 * math.pi / n)
    f = cutting_forces(geom, theta, np.zeros(n), np.full(n, fz_mm), np.ones(tool.flutes), 2.0 * math.pi / n)
    return float(f["ft_n"].mean()) * tool.radius_mm * 1e-3, float(np.hypot(f["fx_n"], f["fy_n"]).mean())


@pytest.mark.parametrize("tool_name, mode, ae_ratio, ap_mm, fz_mm", [
    ("D", "slot", 2.0, 3.0, 0.06),      # 4 flutes: two teeth always in cut, η = π/4
    ("F", "slot", 2.0, 6.0, 0.05),      # 3 flutes, 35° helix
    ("P", "slot", 2.0, 12.0, 0.15),     # 2 flutes: the helix alone
    ("D", "down", 1.5, 10.0, 0.1),
    ("D", "up", 0.5, 16.0, 0.2),
    ("F", "down", 0.25, 8.0, 0.04),
    ("P", "up", 1.0, 5.0, 0.12),
])
def test_the_forward_force_is_the_plants_resultant(tool_name, mode, ae_ratio, ap_mm, fz_mm):
    from millsense.daemon.physics.milling import Material
    from millsense.sim.machine import MATERIALS, TOOL_D, TOOL_F, TOOL_P

    tool = {"D": TOOL_D, "F": TOOL_F, "P": TOOL_P}[tool_name]
    plant = MATERIALS["SS41"]
    material = Material(plant.ks, plant.ks_exp, plant.r1, plant.r1_exp, plant.r2, plant.r2_exp)
    ae_mm = ae_ratio * tool.radius_mm
    rpm = 1200.0
    load = expected_load(ProgrammedCut(ae_mm, ap_mm, mode, feed_per_tooth_mm=fz_mm), tool_radius_mm=tool.radius_mm,
                         flutes=tool.flutes, material=material, spindle_rpm=rpm, override_pct=100.0,
                         helix_deg=tool.helix_deg)
    torque_nm, force_n = _plant_mean(tool, plant, mode, ae_mm, ap_mm, fz_mm)
    assert load.torque_nm == pytest.approx(torque_nm, rel=1e-6)
    assert load.force_n == pytest.approx(force_n, rel=PLANT_FORCE_REL)


def test_an_unknown_helix_expects_the_straight_flutes_force_the_largest():
    """helix_deg None: ψ = 0, the upper bound of η (physics/resultant.py)."""
    cut = ProgrammedCut(16.0, 12.0, "slot", feed_per_tooth_mm=0.08)
    args = dict(tool_radius_mm=R_MM, flutes=3, material=SB40_TABLE2, spindle_rpm=1000.0, override_pct=100.0)
    straight = expected_load(cut, **args)
    helical = expected_load(cut, helix_deg=35.0, **args)
    assert straight.torque_nm == helical.torque_nm
    assert straight.force_n > helical.force_n
