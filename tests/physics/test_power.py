"""[P] §2.1, eq. (11): stator power, copper loss, filter gain, electrical frequency."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import signal

from millsense.daemon.physics.power import (
    air_gap_power_w,
    butterworth_power_gain,
    copper_loss_w,
    electrical_angle_rad,
    electrical_frequency_hz,
    input_power_symmetric_w,
    input_power_two_wattmeter_w,
    phase_currents_a,
    third_line_current_a,
)

pytestmark = pytest.mark.quick

FS_HZ = 1000.0
SHIFT = 2.0 * np.pi / 3.0


def balanced_machine(v_phase, i_phase, phi, f_hz, t_s, winding, theta0=0.3):
    """A balanced machine built from its windings: phase voltage amplitude ``v_phase``,
    phase current amplitude ``i_phase`` lagging by ``phi``.

    Returns (line-to-line voltages, line currents, phase currents), each a list of 3.
    Wye: windings between line and star point, line current = phase current.
    Delta: windings between lines (u-v, v-w, w-u), line current i_u = i_uv − i_wu.
    """
    w = 2 * np.pi * f_hz
    v_ph = [v_phase * np.cos(w * t_s + theta0 - k * SHIFT) for k in range(3)]
    i_ph = [i_phase * np.cos(w * t_s + theta0 - phi - k * SHIFT) for k in range(3)]
    if winding == "wye":
        v_line = [v_ph[k] - v_ph[(k + 1) % 3] for k in range(3)]
        i_line = i_ph
    else:
        v_line = v_ph
        i_line = [i_ph[k] - i_ph[(k + 2) % 3] for k in range(3)]
    return v_line, i_line, i_ph


def test_third_current_and_phase_currents():
    i_u, i_v = np.array([1.0, -2.0]), np.array([0.5, 3.0])
    i_w = third_line_current_a(i_u, i_v)
    np.testing.assert_allclose(i_u + i_v + i_w, 0.0)
    np.testing.assert_allclose(phase_currents_a(i_u, i_v, i_w, "wye"), [i_u, i_v, i_w])
    i_uv, i_vw, i_wu = phase_currents_a(i_u, i_v, i_w, "delta")
    # Kirchhoff at the delta's corners gives the line currents back.
    np.testing.assert_allclose(i_uv - i_wu, i_u)
    np.testing.assert_allclose(i_vw - i_uv, i_v)
    np.testing.assert_allclose(i_uv + i_vw + i_wu, 0.0, atol=1e-15)
    with pytest.raises(ValueError, match="star"):
        phase_currents_a(i_u, i_v, i_w, "star")


def test_delta_phase_current_is_line_over_sqrt3_leading_30_degrees():
    t = np.arange(2000) / 50_000
    _, (i_u, i_v, i_w), _ = balanced_machine(400.0, 10.0 / np.sqrt(3), 0.0, 50.0, t, "delta")
    assert np.max(np.abs(i_u)) == pytest.approx(10.0, rel=1e-3)
    i_uv, _, _ = phase_currents_a(i_u, i_v, i_w, "delta")
    assert np.max(np.abs(i_uv)) == pytest.approx(10.0 / np.sqrt(3), rel=1e-3)
    # i_u = i_uv − i_wu lags i_uv by 30°: i_uv peaks 30° earlier than i_u.
    phasor = lambda x: np.sum(x * np.exp(-2j * np.pi * 50.0 * t))  # noqa: E731 - two whole cycles
    lead_deg = np.degrees(np.angle(phasor(i_uv) / phasor(i_u)))
    assert lead_deg == pytest.approx(30.0, abs=1e-6)


@settings(max_examples=60, deadline=None)
@given(
    v_phase=st.floats(10, 500), i_phase=st.floats(0.1, 100), phi=st.floats(-1.4, 1.4),
    f_hz=st.floats(5, 150), cycles=st.integers(1, 20), winding=st.sampled_from(["delta", "wye"]),
)
def test_power_forms_equal_sqrt3_vi_cos_phi(v_phase, i_phase, phi, f_hz, cycles, winding):
    n = 400 * cycles
    t = np.arange(n) * (cycles / f_hz / n)  # whole cycles, 400 points each
    (v_uv, v_vw, v_wu), (i_u, i_v, i_w), i_ph = balanced_machine(v_phase, i_phase, phi, f_hz, t, winding)
    v_ll_rms, i_line_rms = np.sqrt(np.mean(v_uv**2)), np.sqrt(np.mean(i_u**2))
    expected = np.sqrt(3) * v_ll_rms * i_line_rms * np.cos(phi)
    assert expected == pytest.approx(3 * v_phase * i_phase / 2 * np.cos(phi), rel=1e-9, abs=1e-9 * v_phase * i_phase)
    two = input_power_two_wattmeter_w(v_uv, v_vw, i_u, i_v)
    sym = input_power_symmetric_w(v_uv, v_vw, v_wu, i_u, i_v, i_w)
    scale = v_phase * i_phase
    # Balanced three-phase power is constant sample by sample, not only on average.
    np.testing.assert_allclose(two, expected, atol=1e-9 * scale)
    np.testing.assert_allclose(sym, expected, atol=1e-9 * scale)
    # ... and the phase currents recovered from the line currents are the windings' own.
    np.testing.assert_allclose(phase_currents_a(i_u, i_v, i_w, winding), i_ph, atol=1e-9 * i_phase)


def test_two_wattmeter_equals_sum_of_phase_powers_for_unbalanced_wye():
    rng = np.random.default_rng(3)
    v_n = rng.normal(size=(3, 500)) * 100  # arbitrary potentials of u, v, w
    i_u, i_v = rng.normal(size=(2, 500))
    i_w = third_line_current_a(i_u, i_v)
    v_uv, v_vw, v_wu = v_n[0] - v_n[1], v_n[1] - v_n[2], v_n[2] - v_n[0]
    truth = v_n[0] * i_u + v_n[1] * i_v + v_n[2] * i_w
    np.testing.assert_allclose(input_power_two_wattmeter_w(v_uv, v_vw, i_u, i_v), truth, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(input_power_symmetric_w(v_uv, v_vw, v_wu, i_u, i_v, i_w), truth, rtol=1e-12, atol=1e-9)


@pytest.mark.parametrize("winding", ["delta", "wye"])
def test_copper_loss_is_three_phase_i_squared_r(winding):
    t = np.arange(1000) / 50_000  # one cycle of 50 Hz
    _, (i_u, i_v, i_w), _ = balanced_machine(230.0, 20.0, 0.4, 50.0, t, winding)
    p_cu = copper_loss_w(i_u, i_v, i_w, winding, 0.349)
    np.testing.assert_allclose(p_cu, 3 * 0.349 * (20.0 / np.sqrt(2)) ** 2, rtol=1e-9)


def test_butterworth_gain_matches_scipy_and_physics_md_numbers():
    b, a = signal.butter(2, 2 * np.pi * 200.0, analog=True)
    f = np.array([0.0, 60.0, 144.0, 200.0, 400.0])
    _, h = signal.freqs(b, a, worN=2 * np.pi * f)
    np.testing.assert_allclose(butterworth_power_gain(f, 200.0, 2), np.abs(h) ** 2, rtol=1e-9)
    # physics.md §1: 0.8 % low at 60 Hz, 21 % low at 144 Hz (900 rpm × 4.81, 2 pole pairs).
    f_e = 900 / 60 * 4.81 * 2
    assert f_e == pytest.approx(144.3, abs=0.1)
    assert 1 - float(butterworth_power_gain(60.0, 200.0, 2)) == pytest.approx(0.008, abs=0.0005)
    assert 1 - float(butterworth_power_gain(f_e, 200.0, 2)) == pytest.approx(0.21, abs=0.005)
    np.testing.assert_array_equal(butterworth_power_gain(f, 0.0, 2), 1.0)
    with pytest.raises(ValueError):
        butterworth_power_gain(f, -1.0, 2)


@pytest.mark.parametrize("f_e_hz", [60.0, 144.3])
def test_filter_correction_restores_power_through_an_analog_butterworth(f_e_hz):
    """Continuous 2nd-order 200 Hz Butterworth on all six channels (lsim at 50 kHz), sampled at 1 kHz."""
    b, a = signal.butter(2, 2 * np.pi * 200.0, analog=True)
    fs_sim = 50_000
    t = np.arange(int(0.4 * fs_sim)) / fs_sim
    (v_uv, v_vw, v_wu), (i_u, i_v, i_w), _ = balanced_machine(300.0, 15.0, 0.5, f_e_hz, t, "delta")
    filt = [signal.lsim((b, a), x, t)[1] for x in (v_uv, v_vw, v_wu, i_u, i_v, i_w)]
    keep = slice(int(0.2 * fs_sim), None, fs_sim // 1000)  # after the transient, 1 kHz
    fv_uv, fv_vw, fv_wu, fi_u, fi_v, fi_w = (x[keep] for x in filt)
    r_s = 0.349
    p_in = input_power_symmetric_w(fv_uv, fv_vw, fv_wu, fi_u, fi_v, fi_w)
    p_cu = copper_loss_w(fi_u, fi_v, fi_w, "delta", r_s)
    truth = np.mean(input_power_symmetric_w(v_uv, v_vw, v_wu, i_u, i_v, i_w) - copper_loss_w(i_u, i_v, i_w, "delta", r_s))
    f_meas = electrical_frequency_hz(fv_uv, fv_vw, fv_wu, 1000.0)
    gain = butterworth_power_gain(f_meas, 200.0, 2)
    uncorrected = np.mean(air_gap_power_w(p_in, p_cu))
    corrected = np.mean(air_gap_power_w(p_in, p_cu, gain))
    assert corrected == pytest.approx(truth, rel=1e-3)
    assert uncorrected == pytest.approx(truth * float(gain), rel=1e-3)


@settings(max_examples=40, deadline=None)
@given(
    f_hz=st.floats(5, 200), v_ll=st.floats(20, 400), noise_frac=st.floats(0, 0.1),
    offset_frac=st.floats(-0.3, 0.3), seconds=st.floats(0.1, 0.5), theta0=st.floats(0, 6.28),
    reverse=st.booleans(),
)
def test_electrical_frequency_from_noisy_offset_voltages(f_hz, v_ll, noise_frac, offset_frac, seconds, theta0, reverse):
    rng = np.random.default_rng(int(f_hz * 1000))
    seconds = max(seconds, 2.0 / f_hz)  # the offset is removed over whole cycles: at least two
    t = np.arange(int(seconds * FS_HZ)) / FS_HZ
    sign = -1.0 if reverse else 1.0
    v = [v_ll * np.cos(sign * 2 * np.pi * f_hz * t + theta0 - k * SHIFT) for k in range(3)]
    v = [x + noise_frac * v_ll * rng.normal(size=t.size) for x in v]
    v[0] = v[0] + offset_frac * v_ll  # a DAQ offset on one channel
    est = electrical_frequency_hz(*v, FS_HZ)
    # Noise on the angle is ~noise_frac rad per sample; the LSQ slope error scales as σ·√12/(T·√n).
    tol_hz = 0.02 + 5 * noise_frac * np.sqrt(12) / (2 * np.pi * seconds * np.sqrt(t.size))
    assert est == pytest.approx(f_hz, abs=tol_hz)


def test_electrical_frequency_nan_when_not_measurable():
    t = np.arange(500) / FS_HZ
    v = [0.1 * np.cos(2 * np.pi * 50 * t - k * SHIFT) for k in range(3)]
    assert np.isnan(electrical_frequency_hz(*v, FS_HZ))  # 0.1 V: drive off
    big = [x * 1000 for x in v]
    assert np.isnan(electrical_frequency_hz(*(x[:3] for x in big), FS_HZ))  # 3 samples
    assert electrical_frequency_hz(*big, FS_HZ) == pytest.approx(50.0, abs=1e-6)


def test_electrical_angle_advances_2pi_per_cycle():
    t = np.arange(1000) / FS_HZ
    v = [300 * np.cos(2 * np.pi * 25 * t - k * SHIFT) for k in range(3)]
    angle = electrical_angle_rad(*v, FS_HZ)
    assert angle[-1] - angle[0] == pytest.approx(2 * np.pi * 25 * t[-1], rel=1e-9)
