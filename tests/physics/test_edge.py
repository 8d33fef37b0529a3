"""C_f with the material's edge forces (daemon/physics/edge.py, eqs. E1–E4).

The quadrature (E2–E3) against the independent brute-force slices of tests/physics/instant_model.py, the chip
term and the edge term summed as vectors at every tool angle; the split (E1) and the chip term's exponents (E4)
against the law they come from; and with no edge coefficients nothing changes (resultant.py's η·√(1 + r₁²)).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from millsense.daemon.physics import edge
from millsense.daemon.physics.force import engaged_cf
from millsense.daemon.physics.milling import Material

pytestmark = pytest.mark.quick

STEEL = Material(580.0, -0.42, 0.22, -0.27, 0.12, 0.17)       # config/part-program.toml's SS41
EDGED = STEEL._replace(edge_t_n_mm=25.0, edge_r_n_mm=35.0)


def _brute_cf(flutes, entry, exit_, helix_deg, axial_mm, fz, material, radius_mm=4.0, angles=1440, slices=120):
    """mean |F| / mean F_t of brute-force slices (as tests/physics/instant_model.py: no closed form), each slice's
    force the chip's at the instant with the split's exponents and scales plus the edge's, constant along the
    engaged edge, added as vectors at every tool angle."""
    parts = edge.split(entry, exit_, fz, material)
    phi = np.arange(angles) * (2.0 * np.pi / angles)
    dz = axial_mm / slices
    lag = (np.arange(slices) + 0.5) * dz * np.tan(np.radians(helix_deg)) / radius_mm
    chip_t = np.zeros(angles)
    chip_r = np.zeros(angles)
    sums = {k: np.zeros(angles) for k in ("ct", "cr_x", "cr_y", "ct_x", "ct_y", "e_n", "e_x", "e_y", "er_x", "er_y")}
    for k in range(flutes):
        ang = np.mod(phi[:, None] + 2.0 * np.pi * k / flutes - lag[None, :], 2.0 * np.pi)
        inside = (ang >= entry) & (ang <= exit_)
        h = np.where(inside, fz * np.sin(ang), 0.0)
        hp = np.where(inside, np.maximum(h, 1e-300), 1.0)
        d_t = np.where(inside, hp**parts.size_exp * h * dz, 0.0)     # chip, tangential, unit scale
        d_r = hp**parts.r1_exp * d_t                                  # chip, radial, unit scale
        d_e = np.where(inside, dz, 0.0)                               # edge, per unit coefficient
        c, s_ = np.cos(ang), np.sin(ang)
        chip_t += d_t.sum(axis=1)
        chip_r += d_r.sum(axis=1)
        for name, v in (("ct_x", d_t * c), ("ct_y", -d_t * s_), ("cr_x", d_r * s_), ("cr_y", d_r * c),
                        ("e_n", d_e), ("e_x", d_e * c), ("e_y", -d_e * s_), ("er_x", d_e * s_), ("er_y", d_e * c)):
            sums[name] += v.sum(axis=1)
    kt = parts.chip_t / chip_t.mean()                     # the chip's tangential mean is T_c ...
    kr = parts.chip_r / (kt * chip_r.mean())              # ... its radial mean R_c
    ke = parts.edge_t / (material.edge_t_n_mm * sums["e_n"].mean())   # the edge's tangential mean is T_e
    fx = kt * (sums["ct_x"] + kr * sums["cr_x"]) + ke * (material.edge_t_n_mm * sums["e_x"]
                                                        + material.edge_r_n_mm * sums["er_x"])
    fy = kt * (sums["ct_y"] + kr * sums["cr_y"]) + ke * (material.edge_t_n_mm * sums["e_y"]
                                                        + material.edge_r_n_mm * sums["er_y"])
    return float(np.mean(np.hypot(fx, fy)) / (parts.chip_t + parts.edge_t))


@pytest.mark.parametrize("flutes, entry, exit_, helix_deg, axial_mm, fz", [
    (3, 0.0, math.pi, 30.0, 2.0, 0.04),                 # the φ8 3-flute slot at 0.04 mm a tooth (4101/3/70)
    (4, 0.0, math.pi, 30.0, 3.0, 0.05),                 # a 4-flute slot
    (4, math.pi - math.acos(0.75), math.pi, 30.0, 8.0, 0.06),   # a 4-flute down-milling cut, ae/D = 1/8
    (2, 0.0, math.acos(1 - 0.75), 30.0, 6.0, 0.08),     # a 2-flute up-milling cut, ae/D = 3/8
])
def test_the_quadrature_matches_brute_force_slices(flutes, entry, exit_, helix_deg, axial_mm, fz):
    lag = axial_mm * math.tan(math.radians(helix_deg)) / 4.0
    got = edge.split_cf(flutes, entry, exit_, lag, fz, EDGED)
    assert got == pytest.approx(_brute_cf(flutes, entry, exit_, helix_deg, axial_mm, fz, EDGED), rel=2e-3)


def test_the_split_keeps_the_law_and_the_chip_term_its_own_slope():
    """(E1): chip + edge is the law's mean; (E4): the chip term's exponents are its log-slopes (finite difference)."""
    entry, exit_ = 0.0, math.pi
    span = exit_ - entry

    def law(fz):
        t_a = 2.0 * fz / math.pi
        t = EDGED.ks * t_a ** EDGED.ks_exp * t_a * span / (2 * math.pi)
        return t, EDGED.r1 * t_a ** EDGED.r1_exp * t

    fz = 0.05
    parts = edge.split(entry, exit_, fz, EDGED)
    t, r = law(fz)
    assert parts.chip_t + parts.edge_t == pytest.approx(t, rel=1e-12)
    assert parts.chip_r + parts.edge_r == pytest.approx(r, rel=1e-12)
    assert parts.edge_t == pytest.approx(25.0 / 2.0) and parts.edge_r == pytest.approx(35.0 / 2.0)
    d = 1e-4
    (t1, r1), (t2, r2) = law(fz * (1 - d)), law(fz * (1 + d))
    slope_t = (math.log(t2 - parts.edge_t) - math.log(t1 - parts.edge_t)) / (math.log(1 + d) - math.log(1 - d))
    slope_r = (math.log(r2 - parts.edge_r) - math.log(r1 - parts.edge_r)) / (math.log(1 + d) - math.log(1 - d))
    assert 1.0 + parts.size_exp == pytest.approx(slope_t, abs=1e-3)
    assert 1.0 + parts.size_exp + parts.r1_exp == pytest.approx(slope_r, abs=2e-3)


def test_without_edge_coefficients_nothing_changes_and_an_edge_beyond_the_law_is_not_used():
    args = ("slot", 3, 4.0, 30.0, 0.04, 8.0, 2.0)
    assert not edge.has_edge(STEEL) and edge.has_edge(EDGED)
    plain = engaged_cf(*args, STEEL, 1.075)
    assert edge.split_cf(3, 0.0, math.pi, 0.0, 0.04, STEEL) == pytest.approx(
        engaged_cf("slot", 3, 4.0, None, 0.04, 8.0, 2.0, STEEL, 1.075), rel=2e-3)
    # the edge spread evenly over the arc cancels more between the teeth in cut: a smaller C_f in a 3-flute slot
    assert engaged_cf(*args, EDGED, 1.075) < plain
    huge = STEEL._replace(edge_t_n_mm=900.0, edge_r_n_mm=900.0)       # more than the whole law at this chip
    assert edge.split(0.0, math.pi, 0.04, huge) is None
    assert engaged_cf(*args, huge, 1.075) == plain                    # the chip-only C_f, as before
    # one revolution (floats) and a column (arrays) read the same
    col = engaged_cf("slot", 3, 4.0, 30.0, np.array([0.04, 0.05]), 8.0, 2.0, EDGED, 1.075)
    assert col[0] == pytest.approx(engaged_cf(*args, EDGED, 1.075), rel=1e-12)


def test_a_split_whose_chip_keeps_almost_no_radial_force_falls_back_not_nan():
    """Where the edge's radial term takes nearly all the law's radial force (R_c → 0), (E4)'s q_c runs to
    45–70 and the quadrature of sin^q_c φ gave nan, which `cf = "auto"` published as a null force. The split
    says nothing there: None, and the caller's chip-only C_f (a material fitted from a feed-drive test cut,
    r₁ 0.157·t_a^−0.284, with the round steel pair 25 / 35 N/mm; down milling, 4 flutes, φ16)."""
    fitted = Material(591.019, -0.452169, 0.157176, -0.283623, 0.1244, 0.1702, 25.0, 35.0)
    for fz, ae_mm in ((0.208, 0.24), (0.104, 0.96)):
        parts = edge.split(*edge.engagement_xp(edge.NP, np.asarray(ae_mm / 8.0), "down"), fz, fitted)
        assert parts is not None and parts.r1_exp > 40.0          # the degenerate split this is about
        assert edge.edge_cf("down", 4, 8.0, None, fz, ae_mm, 2.0, fitted) is None
        cf = engaged_cf("down", 4, 8.0, None, fz, ae_mm, 2.0, fitted, 1.075)
        assert math.isfinite(cf) and cf == engaged_cf("down", 4, 8.0, None, fz, ae_mm, 2.0,
                                                      fitted._replace(edge_t_n_mm=0.0, edge_r_n_mm=0.0), 1.075)


def _fxt_dense(r_r, fz, material, mode, points=200_000):
    """(E5) by a dense midpoint sum over the arc, the split clipped as split_fxt does: the reference."""
    from millsense.daemon.physics.milling import chip_xp, engagement_xp as engagement, NP as np_

    entry, exit_ = (float(v) for v in engagement(np_, np.asarray(r_r), mode))
    t_a = float(chip_xp(np_, fz, entry, exit_))
    t_hat = material.ks * t_a ** material.ks_exp * t_a
    r_hat = material.r1 * t_a ** material.r1_exp * t_hat
    chip_t, chip_r = max(t_hat - material.edge_t_n_mm, 0.0), max(r_hat - material.edge_r_n_mm, 0.0)
    phi = entry + (np.arange(points) + 0.5) * (exit_ - entry) / points
    sin = np.sin(phi)
    f_t = np.full_like(phi, t_hat - chip_t)
    f_r = np.full_like(phi, r_hat - chip_r)
    if chip_t > 0.0:
        w = sin ** ((1.0 + material.ks_exp) * t_hat / chip_t)
        f_t += chip_t * w / w.mean()
    if chip_r > 0.0:
        w = sin ** ((1.0 + material.ks_exp + material.r1_exp) * r_hat / chip_r)
        f_r += chip_r * w / w.mean()
    return float((f_t * np.cos(phi) + f_r * sin).mean() / f_t.mean())


@pytest.mark.parametrize("mode", ["down", "up"])
def test_split_fxt_is_e5_and_the_depth_inverts_it(mode):
    """(E5) by Gauss-Legendre against a dense sum, over immersions from thin chips (the edge beyond the law:
    the chip term clipped to 0) to full; [D]'s (a + r₁b)/c with no edge and constant coefficients; and the
    feed-drive depth's solver, which takes (E5) for a material with edge coefficients, gives R_r back."""
    from millsense.daemon.physics.depth import OK, radial_ratio_from_fxt
    from millsense.daemon.physics.milling import force_ratio_fxt

    sb40_edge = Material(646.08, -0.4362, 0.2201, -0.2667, 0.1244, 0.1702, 25.0, 35.0)
    ratios = (0.02, 0.05, 0.1, 0.25, 0.5, 0.9, 1.3, 1.8)
    for fz in (0.05, 0.104, 0.208):
        got = edge.split_fxt(np.array(ratios), fz, sb40_edge, mode)
        for r_r, value in zip(ratios, got):
            assert value == pytest.approx(_fxt_dense(r_r, fz, sb40_edge, mode), abs=2e-4), (r_r, fz)
    flat = Material(700.0, 0.0, 0.3, 0.0, 0.1, 0.0)
    assert edge.split_fxt(0.4, 0.1, flat, mode)[0] == pytest.approx(float(force_ratio_fxt(0.4, 0.1, flat, mode)),
                                                                  rel=1e-9)
    if mode == "down":                              # up milling's f_xt rises and falls: two roots, by design
        cell = edge.feed_cell(0.104)                # the solver builds (E5) on edge.py's feed grid
        assert cell != 0.104 and cell == pytest.approx(0.104, rel=edge.FEED_STEP)
        for r_r in (0.1, 0.25, 0.5, 0.9):
            target = float(edge.split_fxt(r_r, cell, sb40_edge, mode)[0])
            solved, status = radial_ratio_from_fxt(target, 0.104, sb40_edge, mode)
            assert status == OK and solved == pytest.approx(r_r, abs=1e-9)
            # at the exact feed the grid moves the root by well under 0.1 %
            exact = float(edge.split_fxt(r_r, 0.104, sb40_edge, mode)[0])
            assert radial_ratio_from_fxt(exact, 0.104, sb40_edge, mode)[0] == pytest.approx(r_r, rel=1e-3)
            plain = sb40_edge._replace(edge_t_n_mm=0.0, edge_r_n_mm=0.0)   # [D]'s eq. 12 reads it otherwise
            assert abs(radial_ratio_from_fxt(target, 0.104, plain, mode)[0] - r_r) > 0.05 * r_r
