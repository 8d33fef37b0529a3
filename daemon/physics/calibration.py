"""Least-squares calibration of friction and C_f ([P] §4.2, Table 2; eq. 13, eq. 18).

Friction, per gear: with the cutting torque known (0 in an air cut, a
dynamometer's value in a trial cut), eq. (13) rearranges into a straight line in
the spindle speed,

    P_g/ω_sp − T_c = T_f' + B'·ω_sp,

fitted by linear least squares on ``[1, ω_sp]``. At least two distinct speeds are
needed for a line. C_f: eq. (18) is a line through the origin, ``F_res = C_f·(T_c/R)``.

Inertia, per gear (beyond [P], whose eq. 13 assumes a steady speed): in an air
cut whose speed changes, what the friction line leaves over is the rotating
masses' share, ``P_g/ω_sp − T_f' − B'·ω_sp = J·dω_sp/dt``, per revolution
``J·Δω/Δt`` — a line through the origin in the revolution's acceleration, fitted
by least squares. Only revolutions that speed up or slow down tell anything
about J; a capture without them cannot fit it.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from millsense.daemon.physics.force import tangential_force_n


class FrictionFit(NamedTuple):
    friction_torque_nm: float  # T_f', referred to the spindle
    viscous_nms: float  # B', N·m·s/rad, referred to the spindle
    r2: float  # coefficient of determination (nan if the load does not vary)
    residuals_nm: np.ndarray  # measured − fitted load torque, per sample
    samples: int


class InertiaFit(NamedTuple):
    inertia_kgm2: float  # J referred to the spindle
    sigma_kgm2: float  # standard error of J
    r2: float  # uncentred: share of the left-over torque the J·α line explains
    residuals_nm: np.ndarray
    samples: int  # revolutions in the fit
    changing: int  # of which with |α| at or over the minimum


class CfFit(NamedTuple):
    cf: float
    residuals_n: np.ndarray  # measured − fitted resultant force, per sample
    r2: float
    samples: int


def _finite_pair(x, y, what: str) -> tuple[np.ndarray, np.ndarray]:
    x, y = np.asarray(x, dtype=float).ravel(), np.asarray(y, dtype=float).ravel()
    if x.shape != y.shape:
        raise ValueError(f"{what}: {x.size} speeds/torques but {y.size} values; they must pair up")
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
        raise ValueError(f"{what}: inputs contain nan or inf")
    return x, y


def _r2(y: np.ndarray, residuals: np.ndarray) -> float:
    ss_tot = float(np.sum((y - y.mean()) ** 2))
    return 1.0 - float(np.sum(residuals**2)) / ss_tot if ss_tot > 0.0 else float("nan")


def fit_friction(spindle_omega_rad_s, load_torque_nm) -> FrictionFit:
    """T_f' and B' from ``load_torque_nm = P_g/ω_sp − T_c`` at several spindle speeds ([P] eq. 13).

    Raises ValueError unless there are at least two distinct speeds (relative spread > 1e-6).
    """
    omega, load = _finite_pair(spindle_omega_rad_s, load_torque_nm, "fit_friction")
    if omega.size < 2 or np.ptp(omega) <= 1e-6 * max(float(np.max(np.abs(omega))), 1e-12):
        raise ValueError("fit_friction: needs samples at two or more distinct spindle speeds to fit T_f' + B'·ω")
    design = np.column_stack([np.ones_like(omega), omega])
    (t_f, b), *_ = np.linalg.lstsq(design, load, rcond=None)
    residuals = load - design @ np.array([t_f, b])
    return FrictionFit(float(t_f), float(b), _r2(load, residuals), residuals, int(omega.size))


def fit_inertia(accel_rad_s2, inertia_torque_nm, min_accel_rad_s2: float = 5.0, min_changing: int = 3) -> InertiaFit:
    """J from ``inertia_torque_nm ≈ J·accel_rad_s2`` per revolution, least squares through the origin.

    ``inertia_torque_nm``: P_g/ω_sp less the friction line (T_c = 0, an air cut).
    Raises ValueError when fewer than ``min_changing`` revolutions change speed at
    ``min_accel_rad_s2`` or more (above the speed reading's noise, ~0.6 rad/s² at
    900 rpm): the fit would be noise. A negative or poorly determined J is the
    caller's to judge (sigma_kgm2).
    """
    accel, torque = _finite_pair(accel_rad_s2, inertia_torque_nm, "fit_inertia")
    changing = int(np.count_nonzero(np.abs(accel) >= min_accel_rad_s2))
    if changing < min_changing:
        raise ValueError(f"fit_inertia: {changing} revolutions change speed by {min_accel_rad_s2:g} rad/s² or more, "
                         f"{min_changing} needed: the capture has no speed change to fit J to")
    sxx = float(np.dot(accel, accel))
    j = float(np.dot(accel, torque)) / sxx
    residuals = torque - j * accel
    dof = max(accel.size - 1, 1)
    sigma = float(np.sqrt(float(np.dot(residuals, residuals)) / dof / sxx))
    syy = float(np.dot(torque, torque))
    r2 = 1.0 - float(np.dot(residuals, residuals)) / syy if syy > 0.0 else float("nan")
    return InertiaFit(j, sigma, r2, residuals, int(accel.size), changing)


def fit_cf(mean_resultant_force_n, torque_nm, tool_radius_mm: float) -> CfFit:
    """C_f of eq. (18) by least squares through the origin: ``F_res ≈ C_f·T_c/R``.

    r² is the usual centred one (1 − SS_res/SS_tot), nan when the forces do not vary.
    """
    force, torque = _finite_pair(mean_resultant_force_n, torque_nm, "fit_cf")
    x = tangential_force_n(torque, tool_radius_mm)
    sxx = float(np.dot(x, x))
    if sxx <= 0.0:
        raise ValueError("fit_cf: needs at least one revolution with non-zero cutting torque")
    cf = float(np.dot(x, force)) / sxx
    residuals = force - cf * x
    return CfFit(cf, residuals, _r2(force, residuals), int(force.size))
