"""Electrical side of the plant against first principles: power balance, delta relations, slip."""

from __future__ import annotations

import math

import numpy as np
import pytest

from millsense.sim import Plant
from millsense.sim.machine import MCH10
from millsense.sim.motor import motor_waveforms

from .helpers import airgap_power_w, butterworth2_gain, electrical_hz, physical, steady_cut_revs

pytestmark = pytest.mark.quick

MOTOR = MCH10.motor


def _phase_amp(x: np.ndarray, theta: np.ndarray) -> complex:
    """Complex amplitude of x against the reference angle theta (least squares on cos, sin)."""
    a = np.column_stack([np.cos(theta), np.sin(theta)])
    c, s = np.linalg.lstsq(a, x, rcond=None)[0]
    return complex(c, -s)


def test_delta_line_current_is_sqrt3_phase_lagging_30_degrees():
    n = 20_000
    torque = np.full(n, 40.0)
    speed = np.full(n, 300.0)
    w, _ = motor_waveforms(MOTOR, torque, speed, 1e-4, 0.3)
    th = w["theta_e_rad"]
    for line, phase in (("i_u", "i_uv"), ("i_v", "i_vw"), ("i_w", "i_wu")):
        il, ip = _phase_amp(w[line], th), _phase_amp(w[phase], th)
        assert abs(il) == pytest.approx(math.sqrt(3) * abs(ip), rel=1e-9)
        assert math.degrees(np.angle(il / ip)) == pytest.approx(-30.0, abs=1e-6)
    np.testing.assert_allclose(w["i_u"] + w["i_v"] + w["i_w"], 0.0, atol=1e-9)
    np.testing.assert_allclose(w["v_uv"] + w["v_vw"] + w["v_wu"], 0.0, atol=1e-9)
    # phase sequence u-v-w: v_vw lags v_uv by 120°
    assert math.degrees(np.angle(_phase_amp(w["v_vw"], th) / _phase_amp(w["v_uv"], th))) == pytest.approx(-120, abs=1e-6)


def test_instantaneous_power_balance_of_the_motor_model():
    """Σ v_ph·i_ph − R_s·Σ i_ph² = T_e·ω_s (air gap), in steady state (no ripple for a balanced machine)."""
    n = 10_000
    for torque in (-30.0, 5.0, 90.0):
        w, _ = motor_waveforms(MOTOR, np.full(n, torque), np.full(n, 250.0), 1e-4, 0.0)
        p_in = w["v_uv"] * w["i_uv"] + w["v_vw"] * w["i_vw"] + w["v_wu"] * w["i_wu"]
        p_cu = MOTOR.stator_resistance_ohm * (w["i_uv"] ** 2 + w["i_vw"] ** 2 + w["i_wu"] ** 2)
        np.testing.assert_allclose(p_in - p_cu, torque * w["sync_rad_s"], rtol=1e-9)


def test_slip_and_electrical_frequency_consistent():
    """f_e = p·ω_m/(2π(1 − s)) with s ∝ torque; V/f below base frequency, constant above."""
    n = 100
    for torque, speed in ((0.0, 100.0), (97.0, 157.0), (60.0, 400.0)):
        w, _ = motor_waveforms(MOTOR, np.full(n, torque), np.full(n, speed), 1e-4, 0.0)
        s = 1 - MOTOR.pole_pairs * speed / (2 * math.pi * w["f_e_hz"][0])
        assert s == pytest.approx(MOTOR.rated_slip * torque / MOTOR.rated_torque_nm, abs=1e-12)
    lo, _ = motor_waveforms(MOTOR, np.zeros(40_000), np.full(40_000, 2 * math.pi * 10), 1e-4, 0.0)  # 20 Hz
    hi, _ = motor_waveforms(MOTOR, np.zeros(40_000), np.full(40_000, 2 * math.pi * 40), 1e-4, 0.0)  # 80 Hz
    assert np.sqrt(np.mean(lo["v_uv"] ** 2)) == pytest.approx(200 * 20 / 50, rel=2e-3)
    assert np.sqrt(np.mean(hi["v_uv"] ** 2)) == pytest.approx(200, rel=2e-3)


def test_plant_mean_power_balance_from_the_samples():
    """From the 1 kHz counts: (p_in − p_cu)/|H(f_e)|² = air-gap power in the truth, and
    = (T_cut + T_f' + B'·ω_sp)·ω_sp/(1 − s), s measured from f_e and the spindle speed."""
    plant = Plant("step", noise_scale=0.0)
    counts = plant.step(22_000)
    sig = physical(plant, counts)
    gear = plant.gear
    revs = [r for r in steady_cut_revs(plant.truth.revolutions()) if r["axial_depth_mm"] == 3.0]
    assert len(revs) > 10
    a, b = revs[0]["index_end"] + 1, revs[-1]["index_end"] + 1
    f_e = electrical_hz(sig["v_uv"][a:b])
    gain2 = butterworth2_gain(f_e, 200.0) ** 2
    p_g = airgap_power_w(sig, MOTOR.stator_resistance_ohm)[a:b].mean() / gain2
    truth_pg = np.mean([r["airgap_power_w"] for r in revs[1:]])
    assert p_g == pytest.approx(truth_pg, rel=5e-3)
    w_sp = np.mean([r["spindle_rpm"] for r in revs[1:]]) * 2 * math.pi / 60
    slip = 1 - MOTOR.pole_pairs * gear.ratio * w_sp / (2 * math.pi * f_e)
    torque = np.mean([r["torque_nm"] for r in revs[1:]])
    mech = (torque + gear.friction_torque_nm + gear.viscous_nms * w_sp) * w_sp / (1 - slip)
    assert p_g == pytest.approx(mech, rel=5e-3)
    assert 0 < slip < 0.005  # light cut: a fraction of the rated 2.5 %


def test_filter_gain_at_electrical_frequency():
    """The voltage amplitude seen behind the 200 Hz Butterworth is |H(f_e)| × the true one."""
    results = {}
    for cutoff in (0.0, 200.0):
        plant = Plant("aircut-low", noise_scale=0.0, filter_cutoff_hz=cutoff)
        sig = physical(plant, plant.step(15_000))
        v = sig["v_uv"][13_000:15_000]  # 750 rpm from 12 s: f_e ≈ 120 Hz, above base: 200 V rms
        results[cutoff] = (np.sqrt(np.mean(v**2)), electrical_hz(v))
    rms0, f_e = results[0.0]
    assert rms0 == pytest.approx(200.0, rel=1e-3)
    assert f_e == pytest.approx(MCH10.motor.pole_pairs * 750 * 4.81 / 60, rel=2e-3)
    assert results[200.0][0] / rms0 == pytest.approx(butterworth2_gain(f_e, 200.0), rel=2e-3)
