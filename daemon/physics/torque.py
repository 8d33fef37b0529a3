"""Cutting torque at the spindle from air-gap power ([P] eqs. 10–13, 20).

[P] eq. (13), with the friction terms referred to the spindle, and (beyond
[P], which assumes a steady speed) the rotating masses' share while the speed
changes:

    T_c = P_g/ω_sp − T_f' − B'·ω_sp − J·dω_sp/dt,   T_f' = T_f·g,   B' = B_m·g² + B_sp,
    J = J_rotor·g² + J_spindle   (per gear, referred to the spindle)

Per revolution the J term is the change of kinetic energy over the revolution
divided by the angle turned (`inertia_torque_nm`).

``P_g/ω_sp`` stands for ``T_e·g`` with ``T_e = P_g/ω_s ≈ P_g/ω_m`` (eqs. 10, 12).
Eq. (10) is exact with the synchronous speed ω_s; eq. (12) drops the slip
(< 5 %). When the electrical frequency is measured, ``power_omega_rad_s`` =
ω_s referred to the spindle removes that slip error.

Gear ratio g = ω_motor/ω_spindle; all speeds in rad/s.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence

import numpy as np

from millsense.daemon.physics.numbers import positive_or_nan, values


def cutting_torque_nm(p_gap_w, spindle_omega_rad_s, friction_torque_nm, viscous_nms, power_omega_rad_s=None):
    """Cutting torque at the spindle, N·m ([P] eq. 13); nan where the dividing speed is not > 0.

    ``power_omega_rad_s``: the speed P_g is divided by (default ω_sp; pass
    ``synchronous_spindle_omega_rad_s(f_e, ...)`` for eq. 10's exact ω_s).
    """
    omega_sp = values(spindle_omega_rad_s)
    omega_p = omega_sp if power_omega_rad_s is None else values(power_omega_rad_s)
    return values(p_gap_w) / positive_or_nan(omega_p) - friction_torque_nm - viscous_nms * omega_sp


def inertia_torque_nm(inertia_kgm2, omega_start_rad_s, omega_end_rad_s, duration_s, omega_mean_rad_s):
    """Torque that went into the rotating masses over an interval, N·m (the J·dω/dt of eq. 13 with inertia).

    Over a revolution the exact form is the change of kinetic energy per radian
    turned: ``½J(ω_end² − ω_start²)/(Δt·ω̄)`` — the mean power into the masses
    divided by the speed the air-gap power is divided by. With ω_start, ω_end =
    ω̄ ∓ Δω/2 it is ``J·Δω/Δt``. Negative while slowing down: the masses give
    energy back, to the cut or to friction. nan where ω̄ or Δt is not > 0.
    """
    w0, w1 = values(omega_start_rad_s), values(omega_end_rad_s)
    energy_j = 0.5 * values(inertia_kgm2) * (w1 * w1 - w0 * w0)
    return energy_j / (positive_or_nan(values(duration_s)) * positive_or_nan(values(omega_mean_rad_s)))


def synchronous_spindle_omega_rad_s(electrical_frequency_hz, pole_pairs: int, gear_ratio: float):
    """Synchronous speed referred to the spindle, rad/s: ``2π·f_e/pole_pairs/g`` ([P] eq. 5)."""
    return 2.0 * np.pi * values(electrical_frequency_hz) / pole_pairs / gear_ratio


def torque_sigma_nm(power_sigma_w, spindle_omega_rad_s):
    """Torque uncertainty from power noise, N·m: static sensitivity ΔP_g/ΔT_c = ω_sp ([P] eq. 20).

    Worst at low spindle speed: the same watt of noise is more torque.
    """
    return values(power_sigma_w) / positive_or_nan(values(spindle_omega_rad_s))


def rpm_to_rad_s(rpm):
    """Speed in rev/min to rad/s."""
    return np.asarray(rpm, dtype=float) * (2.0 * np.pi / 60.0)


def select_gear(
    spindle_rpm: float,
    max_spindle_rpm: Sequence[float],
    ratios: Sequence[float],
    motor_to_spindle_ratio: float | None = None,
) -> int:
    """Index of the engaged gear.

    With a measured motor/spindle speed ratio (motor-speed channel, or f_e and the
    pole pairs): the gear whose ratio is nearest in log — the only certain way, since
    both gears can run at the change-over speed. Otherwise by spindle speed: the
    gear with the lowest ``max_spindle_rpm`` ≥ |rpm|, or the highest if above all.
    """
    if len(max_spindle_rpm) != len(ratios) or not ratios:
        raise ValueError("select_gear: need one max_spindle_rpm per gear ratio, at least one gear")
    # plain floats: this runs once a revolution in the live daemon, on a handful of gears
    if motor_to_spindle_ratio is not None and math.isfinite(motor_to_spindle_ratio) and motor_to_spindle_ratio > 0:
        quotients = [float(r) / motor_to_spindle_ratio for r in ratios]
        distance = [abs(math.log(q)) if q > 0.0 else math.inf for q in quotients]   # underflow: as numpy's -inf
        return distance.index(min(distance))   # the first of equals, as argmin
    maxima = [float(m) for m in max_spindle_rpm]
    order = sorted(range(len(maxima)), key=maxima.__getitem__)   # stable
    speed = abs(spindle_rpm)
    return next((k for k in order if maxima[k] >= speed), order[-1])


@functools.lru_cache(maxsize=16)
def _gear_table(max_spindle_rpm: tuple[float, ...], ratios: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The gears' constants `select_gears` needs, once per gearbox: (order by max speed, the maxima in that
    order, the ratios). A revolution's gear is chosen every revolution."""
    if len(max_spindle_rpm) != len(ratios) or not ratios:
        raise ValueError("select_gears: need one max_spindle_rpm per gear ratio, at least one gear")
    maxima = np.asarray(max_spindle_rpm, dtype=float)
    order = np.argsort(maxima, kind="stable")
    table = (order, maxima[order], np.asarray(ratios, dtype=float))
    for a in table:
        a.flags.writeable = False   # shared between calls
    return table


def select_gears(spindle_rpm, max_spindle_rpm: Sequence[float], ratios: Sequence[float], motor_to_spindle_ratio=None):
    """``select_gear`` over arrays of revolutions: (R,) gear indices.

    Where a measured motor/spindle ratio is finite and > 0 (nan elsewhere), the gear
    nearest in log ratio; else the lowest ``max_spindle_rpm`` ≥ |rpm|, or the highest.
    """
    order, sorted_max, ratio_arr = _gear_table(tuple(max_spindle_rpm), tuple(ratios))
    rpm = np.abs(np.atleast_1d(np.asarray(spindle_rpm, dtype=float)))
    # the first gear in max-speed order whose maximum is ≥ |rpm| (a nan speed sorts past all: the highest)
    by_speed = order[np.minimum(np.searchsorted(sorted_max, rpm), len(order) - 1)]
    if motor_to_spindle_ratio is None:
        return by_speed
    measured = np.atleast_1d(np.asarray(motor_to_spindle_ratio, dtype=float))
    ok = np.isfinite(measured) & (measured > 0)
    # clipped into a range that cannot overflow the quotient; the nearest gear in log ratio stays the same
    measured = np.clip(np.where(ok, measured, 1.0), 1e-12, 1e12)
    distance = np.abs(np.log(ratio_arr[None, :] / measured[:, None]))
    return np.where(ok, distance.argmin(axis=1), by_speed)
