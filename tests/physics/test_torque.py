"""[P] eqs. (10)–(13), (20): torque from air-gap power, gear choice, sensitivity."""

from __future__ import annotations

import numpy as np
import pytest

from millsense.daemon.physics.torque import (
    cutting_torque_nm,
    rpm_to_rad_s,
    select_gear,
    synchronous_spindle_omega_rad_s,
    torque_sigma_nm,
)

pytestmark = pytest.mark.quick

# [P] Table 2, "high ratio" gear (≤ 900 rpm, g = 4.81).
T_F, B_V, G = 2.6629, 0.0400, 4.81


def test_eq13_on_p_table2_numbers():
    omega = 600 * 2 * np.pi / 60  # 62.83 rad/s
    # An air cut's air-gap power is exactly the friction power: T_c = 0.
    p_friction = (T_F + B_V * omega) * omega
    assert float(cutting_torque_nm(p_friction, omega, T_F, B_V)) == pytest.approx(0.0, abs=1e-12)
    # 1 kW more at the air gap is 1000/ω more torque at the spindle.
    assert float(cutting_torque_nm(p_friction + 1000.0, omega, T_F, B_V)) == pytest.approx(1000.0 / omega)


def test_eq13_vectorised_and_zero_speed_is_nan():
    t = cutting_torque_nm(np.array([500.0, 500.0]), np.array([0.0, 50.0]), T_F, B_V)
    assert np.isnan(t[0]) and np.isfinite(t[1])


def test_synchronous_speed_removes_slip_error():
    """T_e = P_g/ω_s exactly (eq. 10); dividing by the slipping rotor speed over-reads by 1/(1−s)."""
    omega_sp = 600 * 2 * np.pi / 60
    slip = 0.03
    f_e = omega_sp * G / (1 - slip) * 2 / (2 * np.pi)  # 2 pole pairs, synchronous above the rotor
    omega_sync = synchronous_spindle_omega_rad_s(f_e, 2, G)
    assert float(omega_sync) == pytest.approx(omega_sp / (1 - slip))
    t_true = 20.0
    p_gap = (t_true + T_F + B_V * omega_sp) * omega_sync  # air-gap power carries torque at ω_s
    assert float(cutting_torque_nm(p_gap, omega_sp, T_F, B_V, power_omega_rad_s=omega_sync)) == pytest.approx(t_true)
    biased = float(cutting_torque_nm(p_gap, omega_sp, T_F, B_V))
    assert biased > t_true * 1.02


def test_torque_sigma_is_power_sigma_over_speed():
    assert float(torque_sigma_nm(10.0, 20.0)) == pytest.approx(0.5)
    s = torque_sigma_nm(10.0, rpm_to_rad_s(np.array([300.0, 2500.0])))
    assert s[0] > s[1]
    assert np.isnan(torque_sigma_nm(10.0, 0.0))


MAX_RPM, RATIOS = [900.0, 4500.0], [4.81, 1.157]


@pytest.mark.parametrize("rpm, expected", [(300, 0), (900, 0), (901, 1), (2500, 1), (6000, 1), (-600, 0)])
def test_select_gear_by_spindle_speed(rpm, expected):
    assert select_gear(rpm, MAX_RPM, RATIOS) == expected


def test_select_gear_by_speed_ignores_listing_order():
    assert select_gear(600, MAX_RPM[::-1], RATIOS[::-1]) == 1


def test_select_gear_by_measured_ratio_wins_at_changeover():
    # At 900 rpm both gears can be engaged; the measured ratio decides.
    assert select_gear(900, MAX_RPM, RATIOS, motor_to_spindle_ratio=1.16) == 1
    assert select_gear(900, MAX_RPM, RATIOS, motor_to_spindle_ratio=4.7) == 0
    assert select_gear(900, MAX_RPM, RATIOS, motor_to_spindle_ratio=float("nan")) == 0
    with pytest.raises(ValueError):
        select_gear(900, [900.0], RATIOS)


def test_select_gear_on_floats_takes_any_finite_ratio():
    """A quotient that underflows to 0 is infinitely far in log (numpy's -inf), not a math domain error."""
    assert select_gear(100, [900.0, 6000.0], [1e-30, 1.0], motor_to_spindle_ratio=1e300) == 1
    assert select_gear(100, [900.0, 6000.0], [1.0, 1e-30], motor_to_spindle_ratio=1e300) == 0


def test_inertia_torque_is_the_change_of_kinetic_energy_per_radian():
    """½J(ω1² − ω0²) over a revolution of Δt = 2π/ω̄ turned into torque: J·Δω/Δt when ω̄ is the midpoint."""
    from millsense.daemon.physics.torque import inertia_torque_nm

    j, w0, w1 = 1.5, 60.0, 64.0
    wm = (w0 + w1) / 2
    dt = 2 * np.pi / wm
    energy = 0.5 * j * (w1**2 - w0**2)
    assert inertia_torque_nm(j, w0, w1, dt, wm) == pytest.approx(energy / (2 * np.pi))
    assert inertia_torque_nm(j, w0, w1, dt, wm) == pytest.approx(j * (w1 - w0) / dt)
    assert inertia_torque_nm(j, w1, w0, dt, wm) == pytest.approx(-j * (w1 - w0) / dt)   # slowing: given back
    assert np.isnan(inertia_torque_nm(j, w0, w1, 0.0, wm)) and np.isnan(inertia_torque_nm(j, 0.0, 0.0, dt, 0.0))
