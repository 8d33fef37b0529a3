"""Resultant cutting force from cutting torque ([P] §2.2, eqs. 14–18).

For one tooth in cut, ``F_T = K_s·a·S_t·sin φ`` and ``F_R = r₁·F_T`` (eq. 14), so the
in-plane resultant is ``√(1 + r₁²)·F_T`` at every instant (eq. 17) and ``T_c = R·F_T``
(eq. 16). Hence eq. (18): ``F_res = C_f·T_c/R``, with F_res the revolution mean of
the instantaneous |(F_x, F_y)|. [P] fitted C_f = 1.03–1.11 (mean 1.075);
``cf_model`` gives it from r₁(t_a) of [D] eq. (9) instead. That factor is exact
only while one tooth at a time is in cut (a 2-flute slot, straight flutes); with
overlapping teeth the forces add as vectors and the true mean resultant is
smaller by the overlap factor η of ``resultant.py`` (its eq. R2), which takes each
tooth's force at its instantaneous chip (Kienzle's law with [D] eq. 9's exponents,
R1a). ``engaged_cf`` is the one function the estimator (``cf = "model"``, ``"auto"``)
and the forward model (``expected.py``) take C_f from: η·√(1 + r₁(t_a)²).
"""

from __future__ import annotations

import math

import numpy as np

from millsense.daemon.physics import validity
from millsense.daemon.physics.edge import edge_cf, has_edge
from millsense.daemon.physics.milling import NP, SCALAR, Material, chip_xp, engagement_xp
from millsense.daemon.physics.numbers import sqrt, values
from millsense.daemon.physics.resultant import helix_lag_rad, local_exponents, mirror_r1, overlap_factor

# [P] §4.2: the mean C_f of its trial cuts (a φ20 2-flute slot, where η ≈ 1: it stands for √(1 + r₁²)).
P_MEAN_CF = 1.075


def tangential_force_n(torque_nm, tool_radius_mm):
    """Mean tangential force, N: ``F_T = T_c/R`` ([P] eq. 16), R in metres."""
    return values(torque_nm) / (values(tool_radius_mm) * 1e-3)


def resultant_force_n(torque_nm, tool_radius_mm, cf):
    """Mean in-plane resultant force, N: ``F_res = C_f·T_c/R`` ([P] eq. 18), R in metres."""
    return values(cf) * tangential_force_n(torque_nm, tool_radius_mm)


def resultant_force_magnitudes_n(torque_nm, tool_radius_mm: float, cf, noise_nm):
    """Each revolution's |F_res| of eq. (18), N (a float or an array of revolutions): never negative;
    nan where eq. (18) does not apply, else ``C_f·max(T_c, 0)/R`` ([P] eq. 18).

    Eq. (18) turns a cutting torque, which is never below zero, into a force. An
    estimate below zero is either noise around an air cut (within ``noise_nm``:
    the force is 0 within it, clamped) or a revolution in which the drive takes
    energy back from the spindle — after a crash the speed overshoots and the
    drive brakes it, or a speed drop whose J·dω/dt is not compensated. Then
    ``P_g/ω`` says nothing about a cutting force, and a number (negative, or a
    clamped 0 that reads "no force") would mislead: nan (published as null).
    """
    torque = values(torque_nm)
    if isinstance(torque, float):   # one revolution
        return math.nan if torque < -noise_nm else resultant_force_n(max(torque, 0.0), tool_radius_mm, cf)
    applies = ~(torque < -np.asarray(noise_nm, dtype=float))
    return np.where(applies, resultant_force_n(np.maximum(torque, 0.0), tool_radius_mm, cf), np.nan)


def cf_model(average_chip_thickness_mm, r1, r1_exp):
    """C_f = √(1 + r₁²) with r₁ = k₁·t_a^p₁ ([P] eq. 17 with [D] eq. 9)."""
    r1_t = r1 * values(average_chip_thickness_mm) ** r1_exp
    return sqrt(1.0 + r1_t**2)


def slot_cf(feed_per_tooth_mm, material: Material):
    """C_f of a slot cut: t_a = 2·t_c/π ([D] eq. 8 over [0, π])."""
    t_a = 2.0 * np.asarray(feed_per_tooth_mm, dtype=float) / np.pi
    return cf_model(t_a, material.r1, material.r1_exp)


def engaged_cf(mode: str, flutes: int, tool_radius_mm: float, helix_deg: float | None, feed_per_tooth_mm,
               radial_depth_mm, axial_depth_mm, material: Material, fallback_cf: float | None = None):
    """C_f of the engaged teeth, ``η·√(1 + r₁(t_a)²)`` ([P] eq. 17 with [D] eqs. 8–9 and resultant.py's R2):
    a float for one revolution (floats in), else an array.

    - engagement [θ₁, θ₂]: the mode and ``radial_depth_mm`` (a slot: the diameter, whatever is given),
      [D] Table 1; unknown (None/nan, or outside (0, 2R]): no η;
    - ψ = d_a·tan β/R from ``axial_depth_mm`` and the helix; either unknown: ψ = 0, the straight-flute
      value, the largest η the cut can have (resultant.py): an over-estimate, never an under-estimate;
    - r₁(t_a) only inside the chip model's range (validity.feed_status); outside it no √(1 + r₁²);
    - η of each tooth's force at its instantaneous chip (resultant.py R1a) with the material's exponents
      (``local_exponents``), read at r₁(t_a), its sign turned for up milling (``mirror_r1``).

    ``fallback_cf`` None (``cf = "model"``): nan wherever a part is missing. A number (``cf = "auto"``,
    [P]'s 1.075): it stands for √(1 + r₁²) where the chip is unknown (η·fallback), and for the whole C_f
    where the engagement is (eq. 18 as before).
    """
    if isinstance(feed_per_tooth_mm, float) and not isinstance(radial_depth_mm, np.ndarray) \
            and not isinstance(axial_depth_mm, np.ndarray):
        return _engaged_cf_one(mode, flutes, tool_radius_mm, helix_deg, feed_per_tooth_mm, radial_depth_mm,
                               axial_depth_mm, material, fallback_cf)
    t_c = np.asarray(feed_per_tooth_mm, dtype=float)
    n = t_c.shape
    radial = np.full(n, 2.0 * tool_radius_mm) if mode == "slot" else _column(radial_depth_mm, n)
    ratio = radial / tool_radius_mm
    known = np.isfinite(ratio) & (ratio > 0.0) & (ratio <= 2.0)
    p, q = local_exponents(material.ks_exp, material.r1_exp)
    with np.errstate(invalid="ignore", divide="ignore"):
        entry, exit_ = engagement_xp(NP, np.where(known, ratio, 1.0), mode)
        low, high = validity.feed_masks(t_c, tool_radius_mm)
        chip_ok = known & np.isfinite(t_c) & (t_c > 0) & ~low & ~high
        t_a = chip_xp(NP, np.where(chip_ok, t_c, 1.0), entry, exit_)                               # [D] eq. 8
        chip_ok &= np.isfinite(t_a) & (t_a > 0)
        r1 = np.where(chip_ok, material.r1 * np.where(chip_ok, t_a, 1.0) ** material.r1_exp, np.nan)  # [D] eq. 9
        single = sqrt(1.0 + r1**2)                                                                 # [P] eq. 17
        r1_eta = np.where(chip_ok, r1, _fallback_r1(fallback_cf))
        lag = helix_lag_rad(_column(axial_depth_mm, n), helix_deg, tool_radius_mm)
        eta = np.where(known, overlap_factor(flutes, exit_ - entry, lag, mirror_r1(mode, r1_eta), p, q), np.nan)
    out = eta * single if fallback_cf is None else np.where(known, eta * np.where(chip_ok, single, fallback_cf),
                                                           fallback_cf)
    if has_edge(material) and chip_ok.any():   # the material's edge forces taken out of its law (edge.py, E3)
        out = np.array(out, dtype=float)
        axial = _column(axial_depth_mm, n)
        for i in zip(*np.nonzero(chip_ok)):
            split = edge_cf(mode, flutes, tool_radius_mm, helix_deg, float(t_c[i]), float(radial[i]),
                            float(axial[i]), material)
            if split is not None:
                out[i] = split
    return out


def _fallback_r1(fallback_cf: float | None) -> float:
    """The r₁ a fallback C_f stands for (C_f = √(1 + r₁²)); 0 where it is none or at most 1."""
    if fallback_cf is None or not fallback_cf > 1.0:
        return 0.0
    return math.sqrt(fallback_cf * fallback_cf - 1.0)


def _column(x, shape) -> np.ndarray:
    if x is None:
        return np.full(shape, np.nan)
    return np.broadcast_to(np.asarray(x, dtype=float), shape)


def _engaged_cf_one(mode, flutes, tool_radius_mm, helix_deg, t_c, radial_mm, axial_mm, material, fallback_cf):
    """`engaged_cf` of one revolution on Python floats (the live path)."""
    ratio = 2.0 if mode == "slot" else (math.nan if radial_mm is None else float(radial_mm) / tool_radius_mm)
    if not 0.0 < ratio <= 2.0:
        return math.nan if fallback_cf is None else fallback_cf
    entry, exit_ = engagement_xp(SCALAR, ratio, mode)
    lag = helix_lag_rad(None if axial_mm is None else float(axial_mm), helix_deg, tool_radius_mm)
    p, q = local_exponents(material.ks_exp, material.r1_exp)
    r1 = math.nan
    if math.isfinite(t_c) and t_c > 0 and validity.feed_status(t_c, tool_radius_mm) is None:
        t_a = chip_xp(SCALAR, t_c, entry, exit_)                                                    # [D] eq. 8
        if math.isfinite(t_a) and t_a > 0:
            r1 = material.r1 * t_a**material.r1_exp                                                 # [D] eq. 9
    if math.isnan(r1):
        if fallback_cf is None:
            return math.nan
        return overlap_factor(flutes, exit_ - entry, lag, mirror_r1(mode, _fallback_r1(fallback_cf)), p, q) * fallback_cf
    if has_edge(material):   # the material's edge forces taken out of its law (edge.py, E3)
        split = edge_cf(mode, flutes, tool_radius_mm, helix_deg, t_c, ratio * tool_radius_mm,
                        None if axial_mm is None else float(axial_mm), material)
        if split is not None:
            return split
    return overlap_factor(flutes, exit_ - entry, lag, mirror_r1(mode, r1), p, q) * math.sqrt(1.0 + r1 * r1)  # R2, 17
