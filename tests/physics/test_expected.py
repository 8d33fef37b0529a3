"""The forward model: a programmed cut's expected torque and force (daemon/physics/expected.py)."""

import math
from dataclasses import replace

import numpy as np
import pytest

from millsense.daemon.physics.expected import ProgrammedCut, cut_feed_per_tooth_mm, expected_load
from millsense.daemon.physics.milling import SB40_TABLE2, cutting_coefficients, engagement_angles_rad, average_chip_thickness_mm
from millsense.daemon.physics.resultant import local_exponents
from millsense.sim.cut_effects import NONE

R_MM, FLUTES = 8.0, 4
ETA_TABLE_REL = 1e-3   # physics/resultant.py's table against a fine quadrature (tests/physics/test_resultant.py)


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
    # teeth add as vectors: never more than the sum of the elements' magnitudes, Σ|dF| = Σ w·√(1 + ρ²)·dz
    # (resultant.py R1a: w = sin^(1+p) φ, ρ = κ·r₁(t_a)·sin^q φ; with p = q = 0 it is [P] eq. 17's √(1 + r₁²))
    p, q = local_exponents(SB40_TABLE2.ks_exp, SB40_TABLE2.r1_exp)
    phi = float(entry) + (np.arange(200000) + 0.5) * (float(exit_) - float(entry)) / 200000
    w = np.sin(phi) ** (1.0 + p)
    rho = float(r1) * np.sin(phi) ** q * w.sum() / (w * np.sin(phi) ** q).sum()
    magnitudes_n = (w * np.sqrt(1.0 + rho**2)).sum() / w.sum() * load.torque_nm / (R_MM * 1e-3)
    assert 0.0 < load.force_n <= magnitudes_n * (1.0 + ETA_TABLE_REL)     # η's table: its interpolation


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
# programmed cut against the plant's revolution mean |(F_x, F_y)| and its torque, at the same chip. Without
# effects the plant takes K_s, r_1 at the average chip as [D] eq. 7 does, so the torque agrees to the
# quadrature. The force's C_f = F/F_T against the plant with Kienzle's law at the instantaneous chip and
# nothing else (LOCAL_LAW: no edge forces, runout or deflection, the clamp h_min below every chip cut here),
# which is resultant.py's (R1a): to η's table (tests/physics/test_resultant.py, 0.1 %), the plant's axial
# slicing (its helix lag in 20+ steps: well under 0.05 % at these lags) and its radial law fitted on a slot
# where (R1a) keeps [D] eq. 9's mean ratio in each cut (0.02 % in bench/force_accuracy.py's up cuts).
PLANT_FORCE_REL = 1.5e-3
LOCAL_LAW = replace(NONE, size_effect=True, min_chip_mm=1e-6)


def _plant_mean(tool, material, mode, ae_mm, ap_mm, fz_mm, effects=None):
    import numpy as np

    from millsense.sim.cutting import CutGeometry, cutting_forces

    xp = np.array([-1000.0, 1000.0])
    geom = CutGeometry(tool, material, mode, xp, np.array([ap_mm, ap_mm]), xp, np.array([ae_mm, ae_mm]), ap_mm,
                       effects=effects)
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
    torque_nm, _ = _plant_mean(tool, plant, mode, ae_mm, ap_mm, fz_mm)
    assert load.torque_nm == pytest.approx(torque_nm, rel=1e-6)
    local_torque_nm, local_force_n = _plant_mean(tool, plant, mode, ae_mm, ap_mm, fz_mm, LOCAL_LAW)
    assert load.force_n / load.torque_nm == pytest.approx(local_force_n / local_torque_nm, rel=PLANT_FORCE_REL)


def test_an_unknown_helix_expects_the_straight_flutes_force_the_largest():
    """helix_deg None: ψ = 0, the upper bound of η (physics/resultant.py)."""
    cut = ProgrammedCut(16.0, 12.0, "slot", feed_per_tooth_mm=0.08)
    args = dict(tool_radius_mm=R_MM, flutes=3, material=SB40_TABLE2, spindle_rpm=1000.0, override_pct=100.0)
    straight = expected_load(cut, **args)
    helical = expected_load(cut, helix_deg=35.0, **args)
    assert straight.torque_nm == helical.torque_nm
    assert straight.force_n > helical.force_n
