"""Average forces per tooth period in peripheral end milling ([D] §2, eqs. 4–10, 12).

[D] = Kim & Chung, *Real-Time Estimation of Radial and Axial Depth of Cuts in
End Milling Using the Cutting Forces*. The paper derives the averages for down
milling only; here the same integrals are taken over any engagement interval
``[θ₁, θ₂]`` so that up milling and slotting come out of one formula.

An axial slice of a flute meets every engagement angle once per revolution, so
the average over one tooth period ``φ_N = 2π/N`` of the total force is

    F_avg = (N/2π)·K_s·t_c·d_a · ∫_{θ₁}^{θ₂} (integrand of eq. 4) dθ

with the integrands ``sin θ`` (tangential), ``sin θ cos θ + r₁ sin²θ`` (x, feed)
and ``−sin²θ + r₁ sin θ cos θ`` (y, normal). This is eq. (7) with
``K·R_a·(tan β/φ_N) = K_s·t_c·d_a·N/2π``: the helix angle cancels from every
average. The three integrals are

    a = ∫ sin θ cos θ dθ = (cos 2θ₁ − cos 2θ₂)/4                  ([D] A_i)
    b = ∫ sin²θ dθ      = (θ₂ − θ₁)/2 − (sin 2θ₂ − sin 2θ₁)/4    ([D] B_i, typo fixed)
    c = ∫ sin θ dθ      = cos θ₁ − cos θ₂                         ([D] C_i)

For down milling (θ₁ = arccos(R_r − 1), θ₂ = π) they reduce to [D]'s A_r, B_r,
C_r of eq. (7) without the common factor ``tan β/φ_N``.

Every function takes numpy arrays or scalars and broadcasts; a radial ratio
outside (0, 2] gives nan. The ``*_xp`` kernels take the math
namespace as an argument so the root finder in ``depth.py`` can run the very
same formulas on Python floats (``math``), an order of magnitude faster than
numpy on scalars; ``engagement_xp`` and ``chip_xp`` are public, the estimator's
one-revolution path (``pipeline/per_revolution.py``) runs them too.
"""

from __future__ import annotations

import math
from types import SimpleNamespace
from typing import NamedTuple

import numpy as np

MODES = ("down", "up", "slot")

# Math namespaces with the same names, for the shared formula kernels.
NP = SimpleNamespace(cos=np.cos, sin=np.sin, sqrt=np.sqrt, arccos=np.arccos, pi=np.pi)
SCALAR = SimpleNamespace(cos=math.cos, sin=math.sin, sqrt=math.sqrt, arccos=math.acos, pi=math.pi)


class Material(NamedTuple):
    """Cutting-coefficient power laws of [D] eq. (9): ``k·t_a^p``, t_a in mm, K_s in N/mm²."""

    ks: float
    ks_exp: float
    r1: float
    r1_exp: float
    r2: float
    r2_exp: float
    # the edge (ploughing) force per mm of engaged edge, N/mm (edge.py): 0, the law taken as all chip
    edge_t_n_mm: float = 0.0
    edge_r_n_mm: float = 0.0


# [D] Table 2: SB40 steel, 4-flute φ16 HSS end mill, 600 rpm.
SB40_TABLE2 = Material(ks=646.08, ks_exp=-0.4362, r1=0.2201, r1_exp=-0.2667, r2=0.1244, r2_exp=0.1702)


class AverageForces(NamedTuple):
    """Average forces over one tooth period, N ([D] eq. 7): x = feed, y = normal, z = axial."""

    tangential_n: np.ndarray
    x_n: np.ndarray
    y_n: np.ndarray
    z_n: np.ndarray


def check_mode(mode: str) -> str:
    """Return ``mode`` if it is one of MODES, else raise a ValueError naming the choices."""
    if mode not in MODES:
        raise ValueError(f"milling mode {mode!r} is not one of {', '.join(MODES)}")
    return mode


def engagement_xp(xp, radial_ratio, mode: str):
    """Entry and exit angles (rad) of one tooth, [D] Table 1 generalised."""
    if mode == "down":  # enters at φ_r = arccos(R_r − 1), leaves at π
        return xp.arccos(radial_ratio - 1.0), xp.pi + 0.0 * radial_ratio
    if mode == "up":  # enters at 0, leaves at arccos(1 − R_r)
        return 0.0 * radial_ratio, xp.arccos(1.0 - radial_ratio)
    return 0.0 * radial_ratio, xp.pi + 0.0 * radial_ratio  # slot: R_r = 2, half a turn


def _integrals_xp(xp, phi_entry, phi_exit):
    """(a, b, c): the engagement integrals of eq. (4) over [θ₁, θ₂]."""
    a = (xp.cos(2.0 * phi_entry) - xp.cos(2.0 * phi_exit)) / 4.0
    b = (phi_exit - phi_entry) / 2.0 - (xp.sin(2.0 * phi_exit) - xp.sin(2.0 * phi_entry)) / 4.0
    c = xp.cos(phi_entry) - xp.cos(phi_exit)
    return a, b, c


def chip_xp(xp, feed_per_tooth_mm, phi_entry, phi_exit):
    """Average chip thickness, mm, eq. (8): mean of t_c·sin φ over the engagement."""
    return feed_per_tooth_mm * (xp.cos(phi_entry) - xp.cos(phi_exit)) / (phi_exit - phi_entry)


def _ratios_xp(xp, radial_ratio, feed_per_tooth_mm, material: Material, mode: str):
    """(f_x, f_xt) of eqs. (10) and (12) — the kernel shared with the root finder."""
    entry, exit_ = engagement_xp(xp, radial_ratio, mode)
    a, b, c = _integrals_xp(xp, entry, exit_)
    t_a = chip_xp(xp, feed_per_tooth_mm, entry, exit_)
    r1 = material.r1 * t_a**material.r1_exp  # eq. (9)
    feed = a + r1 * b
    f_x = feed / xp.sqrt((1.0 + r1 * r1) * (a * a + b * b))  # eq. (10)
    f_xt = feed / c  # eq. (12)
    return f_x, f_xt


def _tangential_per_axial_ratio_xp(xp, radial_ratio, feed_per_tooth_mm, tool_radius_mm, flutes, material: Material, mode: str):
    """F_at at R_a = 1, N: ``(N/2π)·K_s(t_a)·t_c·R·c`` (eq. 7 is linear in R_a)."""
    entry, exit_ = engagement_xp(xp, radial_ratio, mode)
    c = xp.cos(entry) - xp.cos(exit_)
    t_a = chip_xp(xp, feed_per_tooth_mm, entry, exit_)
    ks = material.ks * t_a**material.ks_exp  # eq. (9)
    return flutes / (2.0 * xp.pi) * ks * feed_per_tooth_mm * tool_radius_mm * c


def _valid_ratio(radial_ratio, mode: str) -> np.ndarray:
    """Radial ratio as float array, nan outside (0, 2]; slot is always 2."""
    r = np.asarray(radial_ratio, dtype=float)
    if mode == "slot":
        return np.full_like(r, 2.0)
    return np.where((r > 0.0) & (r <= 2.0), r, np.nan)


def engagement_angles_rad(radial_ratio, mode: str):
    """Entry and exit angle of a tooth (rad) for ``R_r = d_r/R`` ([D] Table 1, φ_A, φ_B).

    down: (arccos(R_r − 1), π); up: (0, arccos(1 − R_r)); slot: (0, π).
    """
    check_mode(mode)
    with np.errstate(invalid="ignore"):
        return engagement_xp(NP, _valid_ratio(radial_ratio, mode), mode)


def average_chip_thickness_mm(feed_per_tooth_mm, phi_entry_rad, phi_exit_rad):
    """Average chip thickness t_a, mm ([D] eq. 8): down milling gives t_c·R_r/(π − φ_r); nan if no engagement."""
    with np.errstate(invalid="ignore", divide="ignore"):
        return chip_xp(NP, np.asarray(feed_per_tooth_mm, dtype=float), phi_entry_rad, phi_exit_rad)


def cutting_coefficients(t_a_mm, material: Material):
    """(K_s in N/mm², r₁, r₂) at average chip thickness t_a ([D] eq. 9).

    Each coefficient has its own exponent (the paper prints p₁ for both K_s and r₁).
    """
    t_a = np.asarray(t_a_mm, dtype=float)
    return (
        material.ks * t_a**material.ks_exp,
        material.r1 * t_a**material.r1_exp,
        material.r2 * t_a**material.r2_exp,
    )


def average_forces_n(
    radial_ratio,
    axial_ratio,
    feed_per_tooth_mm,
    tool_radius_mm,
    flutes,
    material: Material,
    mode: str,
) -> AverageForces:
    """Average tangential, feed (x), normal (y) and axial (z) force, N ([D] eq. 7, any mode).

    ``F_avg = (N/2π)·K_s(t_a)·t_c·d_a·{c, a + r₁b, −b + r₁a, r₂c}``. The tangential
    average satisfies ``F_at·R·ω = K_s·d_a·d_r·(feed rate)``: specific energy × removal rate.
    """
    check_mode(mode)
    r_r = _valid_ratio(radial_ratio, mode)
    t_c = np.asarray(feed_per_tooth_mm, dtype=float)
    with np.errstate(invalid="ignore", divide="ignore"):
        entry, exit_ = engagement_xp(NP, r_r, mode)
        a, b, c = _integrals_xp(NP, entry, exit_)
        ks, r1, r2 = cutting_coefficients(chip_xp(NP, t_c, entry, exit_), material)
    axial_mm = np.asarray(axial_ratio, dtype=float) * np.asarray(tool_radius_mm, dtype=float)
    scale_n = np.asarray(flutes, dtype=float) / (2.0 * np.pi) * ks * t_c * axial_mm
    return AverageForces(
        tangential_n=scale_n * c,
        x_n=scale_n * (a + r1 * b),
        y_n=scale_n * (-b + r1 * a),
        z_n=scale_n * r2 * c,
    )


def force_ratio_fx(radial_ratio, feed_per_tooth_mm, material: Material, mode: str):
    """f_x = F_ax/√(F_ax² + F_ay²) ([D] eq. 10): independent of R_a and K_s."""
    check_mode(mode)
    with np.errstate(invalid="ignore", divide="ignore"):
        return _ratios_xp(NP, _valid_ratio(radial_ratio, mode), np.asarray(feed_per_tooth_mm, float), material, mode)[0]


def force_ratio_fxt(radial_ratio, feed_per_tooth_mm, material: Material, mode: str):
    """f_xt = F_ax/F_at ([D] eq. 12): feed-drive force over spindle tangential force."""
    check_mode(mode)
    with np.errstate(invalid="ignore", divide="ignore"):
        return _ratios_xp(NP, _valid_ratio(radial_ratio, mode), np.asarray(feed_per_tooth_mm, float), material, mode)[1]


def tangential_per_axial_ratio_n(radial_ratio, feed_per_tooth_mm, tool_radius_mm, flutes, material: Material, mode: str):
    """F_at / R_a, N: the tangential average at unit axial ratio (eq. 7 is linear in R_a)."""
    check_mode(mode)
    with np.errstate(invalid="ignore", divide="ignore"):
        return _tangential_per_axial_ratio_xp(
            NP, _valid_ratio(radial_ratio, mode), np.asarray(feed_per_tooth_mm, float),
            np.asarray(tool_radius_mm, float), np.asarray(flutes, float), material, mode,
        )


def load_scale(override_pct, gain: float) -> float:
    """How much a load at feed override `override_pct` (%) exceeds the same cut's load at the programmed feed.

    The load follows the feed per tooth as a power law, torque ~ t_c^(1+p) ([D] eq. 8: t_a ∝ t_c, so
    ``K_s(t_a)·t_c = k·t_a^p·t_c`` of eqs. 7 and 9), and the override u = `override_pct`/100 multiplies t_c:

        load(u) / load(1) = u^gain          gain = 1 + p, or `[afc] process_gain`

    One plain float (one revolution). Exactly 1.0 at 100 % (and without a report), so nothing changes for a
    machine that never moves the override. A nonsensical override (None, <= 0) counts as 100 %: the load is
    taken as it is.
    """
    if override_pct is None or not override_pct > 0.0 or override_pct == 100.0:
        return 1.0
    return (float(override_pct) / 100.0) ** gain
