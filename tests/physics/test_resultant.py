"""The engaged teeth's forces added as vectors (daemon/physics/resultant.py, eqs. R1–R3).

Checked three ways: against an independent brute-force model that sums every slice's (F_x, F_y)
(tests/physics/instant_model.py, no closed form); the table against a fine quadrature over the
whole range the table serves; and the properties the physics gives (η = 1 with one straight tooth
in cut, π/4 in a slot with 4 flutes, never above 1, never above the straight-flute value, up and
down milling mirror images).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from millsense.daemon.physics import resultant
from millsense.daemon.physics.resultant import exact_overlap_factor, helix_lag_rad, overlap_factor
from tests.physics.instant_model import instantaneous_forces

pytestmark = pytest.mark.quick

FINE = 32                 # Gauss points on each smooth piece for the reference quadrature
# the table's bilinear interpolation (π/48 in span, π/24 in lag) and its 6-point Gauss pieces against
# FINE: the grid holds the kinks at multiples of π/2, π/3, π/4; 0.1 % is 1/20 of the 2 % force budget
ETA_TABLE_REL = 1e-3


def brute_eta(flutes, entry, exit_, helix_deg, axial_mm, radius_mm=8.0):
    """mean |(F_x, F_y)| / (√(1 + r₁²)·mean F_t) of the brute-force slices (r₁ = 0.4, any K_s)."""
    r1 = 0.4
    f_t, f_x, f_y = instantaneous_forces(
        entry_rad=entry, exit_rad=exit_, feed_per_tooth_mm=0.1, axial_depth_mm=axial_mm, tool_radius_mm=radius_mm,
        flutes=flutes, helix_deg=helix_deg, ks_n_mm2=1000.0, r1=r1, angles=3600, slices=300)
    return float(np.mean(np.hypot(f_x, f_y)) / np.mean(f_t) / math.sqrt(1 + r1 * r1))


@pytest.mark.parametrize("flutes, entry, exit_, helix_deg, axial_mm", [
    (4, 0.0, math.pi, 30.0, 6.0),                       # 4-flute slot
    (3, 0.0, math.pi, 35.0, 10.0),                      # 3-flute slot, long helix
    (2, 0.0, math.pi, 30.0, 12.0),                      # 2-flute slot: the helix alone
    (4, math.acos(0.5), math.pi, 30.0, 16.0),           # down, R_r = 1.5
    (4, 0.0, math.acos(0.25), 45.0, 8.0),               # up, R_r = 0.75
    (6, math.acos(-0.5), math.pi, 40.0, 4.0),           # down, R_r = 0.5
])
def test_the_quadrature_matches_brute_force_slices(flutes, entry, exit_, helix_deg, axial_mm):
    lag = axial_mm * math.tan(math.radians(helix_deg)) / 8.0
    got = float(exact_overlap_factor(flutes, entry, exit_, lag, nodes=FINE))
    # the slices' own discretisation: 300 slices over the lag, 3600 angles a revolution
    assert got == pytest.approx(brute_eta(flutes, entry, exit_, helix_deg, axial_mm), rel=5e-4)


@pytest.mark.parametrize("flutes", [1, 2, 3, 4, 5, 6, 8])
def test_the_table_holds_the_quadrature_over_its_whole_range(flutes):
    rng = np.random.default_rng(flutes)
    span = np.concatenate([rng.uniform(0.02, math.pi, 200), [math.pi] * 20, [math.pi / 2] * 10])
    lag = np.concatenate([rng.uniform(0.0, resultant.LAG_MAX_RAD, 200), rng.uniform(0, 3, 30)])
    want = exact_overlap_factor(flutes, math.pi - span, math.pi, lag, nodes=FINE)
    got = overlap_factor(flutes, span, lag)
    assert np.max(np.abs(got / want - 1.0)) <= ETA_TABLE_REL
    one = [overlap_factor(flutes, float(s), float(p)) for s, p in zip(span[:40], lag[:40])]
    np.testing.assert_allclose(one, got[:40], rtol=1e-12)          # the float path is the array path
    beyond = overlap_factor(flutes, 2.0, resultant.LAG_MAX_RAD + 1.0)
    assert beyond == pytest.approx(float(exact_overlap_factor(flutes, math.pi - 2.0, math.pi,
                                                              resultant.LAG_MAX_RAD + 1.0)), rel=1e-12)


def test_what_the_physics_says_of_eta():
    # one straight tooth in cut at a time: exactly eq. (17)
    assert float(exact_overlap_factor(2, 0.0, math.pi, 0.0, nodes=FINE)) == pytest.approx(1.0, abs=1e-12)
    assert overlap_factor(2, math.pi, 0.0) == pytest.approx(1.0, abs=1e-9)    # 6-point pieces
    # 4 flutes in a slot: two teeth π/2 apart at every instant, |H| constant = π/4 of the tangential sum
    for lag in (0.0, 0.3, 1.1, 2.5):
        assert overlap_factor(4, math.pi, lag) == pytest.approx(math.pi / 4, rel=1e-9)
    rng = np.random.default_rng(3)
    span, lag = rng.uniform(0.05, math.pi, 300), rng.uniform(0.0, 6.0, 300)
    for flutes in (2, 3, 4, 6):
        up = exact_overlap_factor(flutes, 0.0, span, lag, nodes=12)
        down = exact_overlap_factor(flutes, math.pi - span, math.pi, lag, nodes=12)
        np.testing.assert_allclose(up, down, rtol=1e-9)            # mirror images
        straight = exact_overlap_factor(flutes, math.pi - span, math.pi, 0.0, nodes=12)
        assert np.all(down <= 1.0 + 1e-12)                          # triangle inequality
        assert np.all(down <= straight + 2e-3)                      # ψ = 0 bounds it (quadrature of a jump)


def test_the_helix_lag_and_what_is_unknown():
    assert helix_lag_rad(3.0, 30.0, 10.0) == pytest.approx(3.0 * math.tan(math.radians(30.0)) / 10.0)
    assert helix_lag_rad(3.0, None, 10.0) == 0.0
    assert helix_lag_rad(None, 30.0, 10.0) == 0.0
    assert helix_lag_rad(math.nan, 30.0, 10.0) == 0.0
    np.testing.assert_allclose(helix_lag_rad(np.array([2.0, np.nan]), 45.0, 4.0), [0.5, 0.0])
    assert math.isnan(overlap_factor(4, 0.0, 0.1))
    assert math.isnan(overlap_factor(4, 1.0, -0.1))
