"""Induction motor, steady-state per-phase model driven sample by sample (delta winding).

From motor torque T_e and motor speed ω_m (both slow: the drive's torque lag
filters them) the motor is solved as a quasi-static circuit at every internal
sample:

- slip proportional to torque, ``s = s_rated·T_e/T_rated``; ``ω_s = ω_m/(1−s)``
  ([P] eq. 5), electrical frequency ``f_e = p·ω_s/2π``;
- V/f line voltage up to the base frequency, constant above;
- magnetising current ``I_m`` lagging the phase voltage by 90°, constant up to
  base frequency and ∝ 1/f above (field weakening: flux ∝ V/f);
- in-phase current ``I_p`` from the power balance of one phase
  ``3·V·I_p = P_g + 3·R_s·(I_p² + I_m²)`` with ``P_g = T_e·ω_s`` ([P] eqs. 10-12),
  the smaller root of the quadratic;
- delta winding: phase voltage = line voltage; phase currents
  ``i_uv = √2(I_p cos θ + I_m sin θ)`` and cyclic; line currents
  ``i_u = i_uv − i_wu`` (√3 × phase, lagging 30°).

Iron and stray losses are not modelled here: they are inside the gearbox
friction (see ``machine.py``).
"""

from __future__ import annotations

import math

import numpy as np

from millsense.sim.machine import Motor

SQRT2 = math.sqrt(2.0)
C120 = math.cos(2 * math.pi / 3)
S120 = math.sin(2 * math.pi / 3)


def slip(motor: Motor, torque_nm: np.ndarray) -> np.ndarray:
    return motor.rated_slip * np.asarray(torque_nm) / motor.rated_torque_nm


def synchronous_speed_rad_s(motor: Motor, motor_speed_rad_s: np.ndarray, torque_nm: np.ndarray) -> np.ndarray:
    """ω_s = ω_m/(1 − s), [P] eq. (5)."""
    return np.asarray(motor_speed_rad_s) / (1.0 - slip(motor, torque_nm))


def electrical_hz(motor: Motor, sync_speed_rad_s: np.ndarray) -> np.ndarray:
    return motor.pole_pairs * np.asarray(sync_speed_rad_s) / (2 * math.pi)


def phase_voltage_rms(motor: Motor, f_e_hz: np.ndarray) -> np.ndarray:
    """V/f below base frequency, rated above (delta: phase voltage = line voltage)."""
    return motor.rated_line_voltage_v * np.minimum(1.0, np.abs(f_e_hz) / motor.base_frequency_hz)


def magnetising_current_rms(motor: Motor, f_e_hz: np.ndarray) -> np.ndarray:
    return motor.magnetising_current_a * np.minimum(1.0, motor.base_frequency_hz / np.maximum(np.abs(f_e_hz), 1e-3))


def in_phase_current_rms(
    motor: Motor, airgap_power_w: np.ndarray, v_phase_rms: np.ndarray, i_mag_rms: np.ndarray
) -> np.ndarray:
    """Smaller root of 3R·I² − 3V·I + (P_g + 3R·I_m²) = 0 (input = air gap + stator copper)."""
    r = motor.stator_resistance_ohm
    v = np.maximum(v_phase_rms, 1e-6)
    c = airgap_power_w + 3 * r * i_mag_rms**2
    disc = np.maximum(9 * v**2 - 12 * r * c, 0.0)
    return (3 * v - np.sqrt(disc)) / (6 * r)


def motor_waveforms(
    motor: Motor, torque_nm: np.ndarray, motor_speed_rad_s: np.ndarray, dt_s: float, theta_e0_rad: float
) -> tuple[dict[str, np.ndarray], float]:
    """Line voltages, line currents and the quantities behind them at each instant.

    The electrical angle is integrated from f_e so its phase is continuous across
    blocks; returns the waveforms and the angle to start the next block with."""
    w_s = synchronous_speed_rad_s(motor, motor_speed_rad_s, torque_nm)
    f_e = electrical_hz(motor, w_s)
    w_e = 2 * math.pi * f_e
    theta = theta_e0_rad + dt_s * np.concatenate(([0.0], np.cumsum(w_e[:-1])))
    theta_next = float((theta[-1] + dt_s * w_e[-1]) % (2 * math.pi))
    v = phase_voltage_rms(motor, f_e)
    i_m = magnetising_current_rms(motor, f_e)
    p_g = np.asarray(torque_nm) * w_s  # air-gap power, [P] eq. (12)
    i_p = in_phase_current_rms(motor, p_g, v, i_m)
    c, s = np.cos(theta), np.sin(theta)
    # phase sequence uv, vw, wu: each lags the one before by 120°
    c_vw, s_vw = c * C120 + s * S120, s * C120 - c * S120
    c_wu, s_wu = c * C120 - s * S120, s * C120 + c * S120
    a_v = SQRT2 * v
    a_p, a_m = SQRT2 * i_p, SQRT2 * i_m
    i_uv = a_p * c + a_m * s
    i_vw = a_p * c_vw + a_m * s_vw
    i_wu = a_p * c_wu + a_m * s_wu
    out = {
        "v_uv": a_v * c,
        "v_vw": a_v * c_vw,
        "v_wu": a_v * c_wu,
        "i_u": i_uv - i_wu,
        "i_v": i_vw - i_uv,
        "i_w": i_wu - i_vw,
        "i_uv": i_uv,
        "i_vw": i_vw,
        "i_wu": i_wu,
        "airgap_w": p_g,
        "f_e_hz": f_e,
        "sync_rad_s": w_s,
        "theta_e_rad": theta,
    }
    return out, theta_next
