"""Resultant cutting force from cutting torque ([P] §2.2, eqs. 14–18).

For one tooth in cut, ``F_T = K_s·a·S_t·sin φ`` and ``F_R = r₁·F_T`` (eq. 14), so the
in-plane resultant is ``√(1 + r₁²)·F_T`` at every instant (eq. 17) and ``T_c = R·F_T``
(eq. 16). Hence eq. (18): ``F_res = C_f·T_c/R``, with F_res the revolution mean of
the instantaneous |(F_x, F_y)|. [P] fitted C_f = 1.03–1.11 (mean 1.075);
``cf_model`` gives it from r₁(t_a) of [D] eq. (9) instead. That factor is exact
only while one tooth at a time is in cut (a 2-flute slot); with overlapping teeth
the true mean resultant is smaller.
"""

from __future__ import annotations

import math

import numpy as np

from millsense.daemon.physics.milling import Material
from millsense.daemon.physics.numbers import sqrt, values


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
