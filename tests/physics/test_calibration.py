"""[P] §4.2 least squares: friction per gear (eq. 13) and C_f (eq. 18)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from millsense.daemon.physics.calibration import fit_cf, fit_friction


@settings(max_examples=50, deadline=None)
@given(
    t_f=st.floats(0.0, 10.0), b=st.floats(0.0, 0.1), n=st.integers(2, 40),
    w_lo=st.floats(5.0, 100.0), span=st.floats(5.0, 200.0), seed=st.integers(0, 2**16),
)
def test_friction_fit_recovers_a_known_line(t_f, b, n, w_lo, span, seed):
    rng = np.random.default_rng(seed)
    omega = np.sort(rng.uniform(w_lo, w_lo + span, n))
    omega[0], omega[-1] = w_lo, w_lo + span  # at least two distinct speeds
    fit = fit_friction(omega, t_f + b * omega)
    assert fit.friction_torque_nm == pytest.approx(t_f, abs=1e-8)
    assert fit.viscous_nms == pytest.approx(b, abs=1e-9)
    assert fit.samples == n
    np.testing.assert_allclose(fit.residuals_nm, 0.0, atol=1e-8)


def test_friction_fit_on_noisy_air_cuts_and_trial_cuts():
    """P_g/ω − T_c from air cuts (T_c = 0) and dynamometer trial cuts together."""
    rng = np.random.default_rng(7)
    omega = np.repeat(np.array([300, 500, 700, 900]) * 2 * np.pi / 60, 25)
    t_c = np.where(np.arange(omega.size) % 2 == 0, 0.0, rng.uniform(2, 20, omega.size))
    p_gap = (t_c + 2.6629 + 0.0400 * omega) * omega + rng.normal(0, 5.0, omega.size)
    fit = fit_friction(omega, p_gap / omega - t_c)
    assert fit.friction_torque_nm == pytest.approx(2.6629, abs=0.05)
    assert fit.viscous_nms == pytest.approx(0.0400, abs=0.001)
    assert 0.5 < fit.r2 <= 1.0
    assert fit.residuals_nm.shape == omega.shape


def test_friction_fit_rejects_one_speed_and_bad_input():
    with pytest.raises(ValueError, match="two or more distinct"):
        fit_friction([50.0, 50.0, 50.0], [3.0, 3.1, 2.9])
    with pytest.raises(ValueError, match="pair up"):
        fit_friction([50.0, 60.0], [3.0])
    with pytest.raises(ValueError, match="nan"):
        fit_friction([50.0, np.nan], [3.0, 3.1])


def test_cf_fit_through_origin():
    torque = np.array([2.0, 5.0, 8.0, 12.0])
    radius_mm = 10.0
    force = 1.075 * torque / 0.010
    fit = fit_cf(force, torque, radius_mm)
    assert fit.cf == pytest.approx(1.075)
    assert fit.r2 == pytest.approx(1.0)
    noisy = fit_cf(force * np.array([1.02, 0.98, 1.01, 0.99]), torque, radius_mm)
    assert noisy.cf == pytest.approx(1.075, rel=0.02)
    assert noisy.residuals_n.shape == (4,)
    with pytest.raises(ValueError, match="non-zero"):
        fit_cf([0.0, 0.0], [0.0, 0.0], radius_mm)


def test_inertia_fit_recovers_j_and_refuses_a_capture_without_speed_change():
    from millsense.daemon.physics.calibration import fit_inertia

    rng = np.random.default_rng(4)
    accel = np.concatenate([np.zeros(40), rng.choice([-1.0, 1.0], 12) * rng.uniform(10.0, 45.0, 12)])
    torque = 1.47 * accel + rng.normal(0.0, 0.4, accel.size)      # noise of the speed reading's rise
    fit = fit_inertia(accel, torque)
    assert abs(fit.inertia_kgm2 - 1.47) < 4 * fit.sigma_kgm2 and fit.sigma_kgm2 < 0.02
    assert fit.changing == 12 and fit.samples == accel.size
    with pytest.raises(ValueError, match="no speed change"):
        fit_inertia(rng.normal(0.0, 0.6, 50), rng.normal(0.0, 0.4, 50))
