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


# Kienzle's law at the instantaneous chip (R1a): SS41's exponents (the first-part programs' material) and
# [D] Table 2's SB40
SS41_PQ = (-0.42, -0.27)
SB40_PQ = (-0.4362, -0.2667)


def _mean_ratio(entry, exit_, p, q, fz=0.1, r1=0.3, points=400000):
    """The cut's mean radial over mean tangential force of the brute-force slices' law, by a midpoint sum."""
    phi = entry + (np.arange(points) + 0.5) * (exit_ - entry) / points
    h = fz * np.sin(phi)
    return float(r1 * (h ** (1 + p + q)).sum() / (h ** (1 + p)).sum())


@pytest.mark.parametrize("flutes, entry, exit_, helix_deg, axial_mm", [
    (4, 0.0, math.pi, 30.0, 6.0),                       # 4-flute slot
    (3, 0.0, math.pi, 35.0, 10.0),                      # 3-flute slot, long helix
    (3, 0.0, math.pi, 0.0, 10.0),                       # 3-flute slot, straight flutes
    (4, math.acos(0.5), math.pi, 30.0, 16.0),           # down, R_r = 1.5
    (4, 0.0, math.acos(0.25), 45.0, 8.0),               # up, R_r = 0.75: the mirror image takes −r₁
    (3, 0.0, math.acos(0.625), 35.0, 6.0),              # up, R_r = 0.375
])
def test_the_local_law_matches_brute_force_slices(flutes, entry, exit_, helix_deg, axial_mm):
    """C_f of slices with dF_t ∝ h^(1+p), dF_r ∝ h^q·dF_t against η(R2)·√(1 + r₁²), r₁ the slices' mean ratio."""
    p, q = SS41_PQ
    f_t, f_x, f_y = instantaneous_forces(
        entry_rad=entry, exit_rad=exit_, feed_per_tooth_mm=0.1, axial_depth_mm=axial_mm, tool_radius_mm=8.0,
        flutes=flutes, helix_deg=helix_deg, ks_n_mm2=1000.0, r1=0.3, angles=3600, slices=300, size_exp=p, r1_exp=q)
    brute_cf = float(np.mean(np.hypot(f_x, f_y)) / np.mean(f_t))
    r1 = _mean_ratio(entry, exit_, p, q)
    lag = axial_mm * math.tan(math.radians(helix_deg)) / 8.0
    got = float(exact_overlap_factor(flutes, entry, exit_, lag, nodes=FINE, r1=r1, size_exp=p, r1_exp=q))
    assert got * math.sqrt(1 + r1 * r1) == pytest.approx(brute_cf, rel=5e-4)
    # the table, built for down milling, reads up milling as its mirror image with −r₁
    mode = "up" if entry == 0.0 and exit_ < math.pi else "down"
    table = overlap_factor(flutes, exit_ - entry, lag, resultant.mirror_r1(mode, r1), p, q)
    assert table == pytest.approx(got, rel=ETA_TABLE_REL)
    # and [D]'s average law (p = q = 0) is off by far more than that in the slots: the test tells them apart
    if flutes > 2 and exit_ - entry == math.pi:
        old = float(exact_overlap_factor(flutes, entry, exit_, lag, nodes=FINE, r1=r1))
        assert abs(old / got - 1.0) > 0.01


@pytest.mark.parametrize("exponents", [SS41_PQ, SB40_PQ])
@pytest.mark.parametrize("flutes", [2, 3, 4, 6])
def test_the_table_holds_the_local_law_quadrature(flutes, exponents):
    p, q = exponents
    rng = np.random.default_rng(10 + flutes)
    span = np.concatenate([rng.uniform(0.02, math.pi, 150), [math.pi] * 20])
    lag = np.concatenate([rng.uniform(0.0, resultant.LAG_MAX_RAD, 150), rng.uniform(0, 3, 10), [0.0] * 10])
    r1 = rng.uniform(-resultant.R1_MAX, resultant.R1_MAX, span.size)
    want = exact_overlap_factor(flutes, math.pi - span, math.pi, lag, nodes=FINE, r1=r1, size_exp=p, r1_exp=q)
    got = overlap_factor(flutes, span, lag, r1, p, q)
    assert np.max(np.abs(got / want - 1.0)) <= ETA_TABLE_REL
    one = [overlap_factor(flutes, float(s), float(g), float(r), p, q) for s, g, r in zip(span[:40], lag[:40], r1[:40])]
    np.testing.assert_allclose(one, got[:40], rtol=1e-12)          # the float path is the array path
    beyond = overlap_factor(flutes, 2.0, 0.5, resultant.R1_MAX + 0.5, p, q)
    assert beyond == pytest.approx(float(exact_overlap_factor(flutes, math.pi - 2.0, math.pi, 0.5,
                                                              r1=resultant.R1_MAX + 0.5, size_exp=p, r1_exp=q)))


def test_up_milling_is_down_milling_with_the_other_sign_of_r1():
    p, q = SS41_PQ
    rng = np.random.default_rng(5)
    span, lag, r1 = rng.uniform(0.05, math.pi, 200), rng.uniform(0.0, 6.0, 200), rng.uniform(0.1, 1.5, 200)
    for flutes in (2, 3, 4):
        up = exact_overlap_factor(flutes, 0.0, span, lag, nodes=FINE, r1=r1, size_exp=p, r1_exp=q)
        down = exact_overlap_factor(flutes, math.pi - span, math.pi, lag, nodes=FINE, r1=-r1, size_exp=p, r1_exp=q)
        np.testing.assert_allclose(up, down, rtol=2e-5)           # FINE's own error with p < 0 (not mirrored)
        same_sign = exact_overlap_factor(flutes, math.pi - span, math.pi, lag, nodes=FINE, r1=r1, size_exp=p,
                                         r1_exp=q)
        assert np.max(np.abs(same_sign / up - 1.0)) > 0.005     # with q ≠ 0 the sign matters
    assert resultant.mirror_r1("up", 0.4) == -0.4 and resultant.mirror_r1("down", 0.4) == 0.4
    assert resultant.mirror_r1("slot", 0.4) == 0.4


def test_a_law_without_a_finite_force_falls_back_to_the_average_law():
    assert resultant.local_exponents(-0.42, -0.27) == (-0.42, -0.27)
    assert resultant.local_exponents(-1.0, 0.0) == (0.0, 0.0)       # 1 + p = 0: no chip in the tooth force
    assert resultant.local_exponents(-0.6, -0.5) == (0.0, 0.0)      # 1 + p + q ≤ 0: ρ·w unbounded at h → 0
    assert resultant.local_exponents(math.nan, 0.1) == (0.0, 0.0)
    # S_m against its closed form and scipy's adaptive quadrature
    from scipy.integrate import quad

    phi = np.linspace(0.0, math.pi, 37)
    np.testing.assert_allclose(resultant.sin_power_integral(1.0, phi), 1 - np.cos(phi), atol=1e-15)
    for m in (0.58, 1.31, 1.58):
        want = [quad(lambda t: math.sin(t) ** m, 0.0, x, epsabs=1e-13, epsrel=1e-12)[0] for x in phi]
        # the table's first interval holds t^m at 0 (16-point Gauss: ~5e-10 for m = 0.58), nothing η would see
        np.testing.assert_allclose(resultant.sin_power_integral(m, phi), want, rtol=1e-9, atol=1e-9)


def test_an_unknown_helix_still_bounds_the_force_from_above_with_the_local_law():
    """ψ = 0 (helix or axial depth unknown) takes the straight-flute η, the largest the cut can have: the
    estimate errs high, never low (physics.md §5)."""
    p, q = SS41_PQ
    rng = np.random.default_rng(8)
    span, lag, r1 = rng.uniform(0.05, math.pi, 400), rng.uniform(0.0, 6.0, 400), rng.uniform(-1.5, 1.5, 400)
    for flutes in (2, 3, 4, 6):
        helical = exact_overlap_factor(flutes, math.pi - span, math.pi, lag, nodes=16, r1=r1, size_exp=p, r1_exp=q)
        straight = exact_overlap_factor(flutes, math.pi - span, math.pi, 0.0, nodes=16, r1=r1, size_exp=p, r1_exp=q)
        assert np.all(helical <= straight * (1.0 + 1e-4))        # the 16-point quadrature of a jump at ψ = 0


def test_the_daemon_computes_only_the_cells_a_cut_reads_once_each_and_as_the_whole_table_has_them():
    """The daemon never builds the whole table (0.3-0.75 s a flute count and material, in every daemon, replay
    and test that starts one): a cut's first revolution computes the four cells it reads, later revolutions
    none, and the values are the whole table's, on the float path (live) and the array path (replay)."""
    p, q = resultant.local_exponents(-0.4362, -0.2667)
    key = (3, p, q)
    resultant._TABLES.pop(key, None)
    span, lag, r1 = 2.0, 0.7, 0.45
    first = overlap_factor(3, span, lag, r1, p, q)
    cells = resultant._TABLES[key].done
    assert cells.sum() == 4
    again = overlap_factor(3, span, lag, r1, p, q)
    assert again == first and resultant._TABLES[key].done.sum() == 4
    whole = resultant.overlap_table(3, p, q)
    spans, lags, rs = np.array([2.0, 0.3, 3.1]), np.array([0.7, 0.0, 5.0]), np.array([0.45, -0.3, 1.2])
    many = overlap_factor(3, spans, lags, rs, p, q)
    resultant._TABLES[key] = _whole(key, whole)
    assert overlap_factor(3, span, lag, r1, p, q) == pytest.approx(first, abs=1e-12)
    assert overlap_factor(3, spans, lags, rs, p, q) == pytest.approx(many, abs=1e-12)
    resultant._TABLES.pop(key, None)


def _whole(key, table):
    lazy = resultant._Lazy(key)
    lazy.table[:] = table
    lazy.done[:] = True
    return lazy
