"""Stator power, copper loss and air-gap power of the spindle motor ([P] §2.1, eq. 11).

[P] = Choi, Kim, Lee, Chu, *Cutting Force Estimation Using Spindle Motor Power*.
Eq. (11) writes ``P_g = V_sᵀI_s − I_sᵀR_sI_s`` with phase quantities; the DAQ
measures line-to-line voltages and line currents, so the input power is taken
in its 3-wire forms (exact for delta and wye alike) and only the copper loss
needs the winding to get phase currents.

The DAQ's analog anti-alias filter attenuates voltage and current alike at the
electrical frequency, so both measured powers are low by |H(f_e)|² (physics.md
§1); ``air_gap_power_w`` divides it out. ``electrical_frequency_hz`` measures f_e
from the voltages.

All functions take numpy arrays (or scalars) of samples and broadcast.
"""

from __future__ import annotations

import numpy as np

from millsense.daemon.physics.numbers import values

WINDINGS = ("delta", "wye")
_SQRT3 = np.sqrt(3.0)


def third_line_current_a(i_a, i_b):
    """The third line current of a 3-wire machine: i_u + i_v + i_w = 0 (Kirchhoff)."""
    return -(np.asarray(i_a) + np.asarray(i_b))


def phase_currents_a(i_u, i_v, i_w, winding: str):
    """Phase (winding) currents from line currents.

    wye: the line currents themselves. delta ([P] §4.1, FANUC motor): with no
    circulating current ``i_uv = (i_u − i_v)/3`` and cyclic — in sinusoidal steady
    state the line current is √3 × the phase current, lagging by π/6.
    """
    i_u, i_v, i_w = (np.asarray(x, dtype=float) for x in (i_u, i_v, i_w))
    if winding == "wye":
        return i_u, i_v, i_w
    if winding == "delta":
        return (i_u - i_v) / 3.0, (i_v - i_w) / 3.0, (i_w - i_u) / 3.0
    raise ValueError(f"winding {winding!r} is not one of {', '.join(WINDINGS)}")


def input_power_two_wattmeter_w(v_uv, v_vw, i_u, i_v):
    """Instantaneous input power, W: ``p = v_uw·i_u + v_vw·i_v`` with ``v_uw = v_uv + v_vw``.

    The two-wattmeter form (W as common point) of ``V_sᵀI_s`` in [P] eq. (11):
    exact for any 3-wire load, delta or wye.
    """
    v_uv, v_vw = np.asarray(v_uv, dtype=float), np.asarray(v_vw, dtype=float)
    return (v_uv + v_vw) * np.asarray(i_u) + v_vw * np.asarray(i_v)


def input_power_symmetric_w(v_uv, v_vw, v_wu, i_u, i_v, i_w):
    """Instantaneous input power, W, using all six channels:

        p = (v_uv·(i_u − i_v) + v_vw·(i_v − i_w) + v_wu·(i_w − i_u)) / 3

    Equal to ``Σ v_k·i_k`` whenever ``Σ i = 0`` (3-wire), and it averages the
    errors of every sensor instead of leaning on two.
    """
    v_uv, v_vw, v_wu = (np.asarray(x, dtype=float) for x in (v_uv, v_vw, v_wu))
    i_u, i_v, i_w = (np.asarray(x, dtype=float) for x in (i_u, i_v, i_w))
    return (v_uv * (i_u - i_v) + v_vw * (i_v - i_w) + v_wu * (i_w - i_u)) / 3.0


def copper_loss_w(i_u, i_v, i_w, winding: str, stator_resistance_ohm: float):
    """Stator copper loss, W: ``I_sᵀR_sI_s = R_s·Σ i_phase²`` ([P] eq. 11), R_s per phase."""
    phases = phase_currents_a(i_u, i_v, i_w, winding)
    return stator_resistance_ohm * (phases[0] ** 2 + phases[1] ** 2 + phases[2] ** 2)


def butterworth_power_gain(frequency_hz, cutoff_hz: float, order: int):
    """|H(f)|² of an n-th order Butterworth low-pass: ``1/(1 + (f/f_c)^(2n))``; cutoff 0 = no filter.

    2nd order at 200 Hz: 0.992 at 60 Hz, 0.788 at 144 Hz (900 rpm × 4.81, 2 pole pairs).
    """
    f = values(frequency_hz)
    if cutoff_hz == 0:
        return 1.0 if isinstance(f, float) else np.ones_like(f)
    if cutoff_hz < 0 or order < 1:
        raise ValueError(f"filter cutoff {cutoff_hz} Hz must be >= 0 and order {order} >= 1")
    return 1.0 / (1.0 + (f / cutoff_hz) ** (2 * order))


def air_gap_power_w(p_in_w, p_cu_w, filter_power_gain=1.0):
    """Air-gap (rotor input) power, W ([P] eq. 11): ``P_g = (p_in − p_cu)/|H|²``.

    Both measured powers come through the anti-alias filter and are low by the same
    |H(f_e)|², so one division restores them.
    """
    return (values(p_in_w) - values(p_cu_w)) / values(filter_power_gain)


def clarke_alpha_beta_v(v_uv, v_vw, v_wu):
    """Clarke (α, β) components of the line-voltage space vector, V.

    ``α = (2v_uv − v_vw − v_wu)/3``, ``β = (v_vw − v_wu)/√3``: the vector turns at
    +2πf_e for the u-v-w sequence; a common-mode error cancels.
    """
    v_uv, v_vw, v_wu = (np.asarray(x, dtype=float) for x in (v_uv, v_vw, v_wu))
    return (2.0 * v_uv - v_vw - v_wu) / 3.0, (v_vw - v_wu) / _SQRT3


def _angle_rad(vector):
    """Unwrapped angle of a complex space-vector series."""
    return np.unwrap(np.angle(vector))


def _space_vector(v_uv, v_vw, v_wu):
    alpha, beta = clarke_alpha_beta_v(v_uv, v_vw, v_wu)
    return alpha + 1j * beta


def _slope_hz(angle_rad, sample_rate_hz: float) -> float:
    """Least-squares slope of an angle series, in Hz (signed)."""
    t_s = np.arange(angle_rad.size) / sample_rate_hz
    return float(np.polyfit(t_s, angle_rad, 1)[0] / (2.0 * np.pi))


def _remove_offset(vector, sample_rate_hz: float, passes: int = 2):
    """Subtract the DAQ offset: the vector's mean over a whole number of cycles.

    An offset shifts the circle off the origin and makes the angle wobble once per
    cycle; the mean over whole cycles is the offset alone. The cycle length comes
    from a first slope estimate, refined ``passes`` times. Under one cycle: unchanged.
    """
    corrected = vector
    for _ in range(passes):
        f_hz = abs(_slope_hz(_angle_rad(corrected), sample_rate_hz))
        if not f_hz > 0.0:
            break
        whole = int(round(np.floor(vector.size * f_hz / sample_rate_hz) * sample_rate_hz / f_hz))
        if whole < 2:
            break
        corrected = vector - vector[:whole].mean()
    return corrected


def electrical_angle_rad(v_uv, v_vw, v_wu, sample_rate_hz: float | None = None):
    """Unwrapped angle of the line-voltage space vector, rad.

    With ``sample_rate_hz`` the DAQ offset is first removed (see ``electrical_frequency_hz``).
    """
    vector = _space_vector(v_uv, v_vw, v_wu)
    if sample_rate_hz is not None:
        vector = _remove_offset(vector, sample_rate_hz)
    return _angle_rad(vector)


def electrical_frequency_hz(v_uv, v_vw, v_wu, sample_rate_hz: float, min_amplitude_v: float = 1.0, min_samples: int = 8) -> float:
    """Electrical frequency f_e, Hz (≥ 0), from the line voltages; nan if not measurable.

    Least-squares slope of the unwrapped Clarke angle against time: every sample
    votes, so white noise averages out (a zero-crossing counter would jitter by
    whole samples). A common-mode error cancels in the Clarke transform; an offset
    on one channel is removed as the mean over whole cycles. Needs f_e below half
    the sample rate. nan with fewer than ``min_samples`` samples or an rms
    space-vector amplitude under ``min_amplitude_v`` (drive off: the angle of
    noise means nothing).
    """
    vector = _space_vector(v_uv, v_vw, v_wu)
    if vector.size < max(min_samples, 2):
        return float("nan")
    vector = _remove_offset(vector, sample_rate_hz)
    if np.sqrt(np.mean(np.abs(vector) ** 2)) < min_amplitude_v:
        return float("nan")
    return abs(_slope_hz(_angle_rad(vector), sample_rate_hz))
