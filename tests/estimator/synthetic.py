"""Balanced three-phase waveforms with a known air-gap power, written here from first principles.

Independent of both the simulator and `daemon.physics`: line-to-line voltages
and line currents of a balanced machine, passed through a Butterworth filter's
gain and phase at f_e (same for V and I), quantised to the DAQ's counts. The
true input power is `√3·V_ll·I_l·cos φ`, the copper loss `3·R·I_ph²` with
`I_ph = I_l/√3` for delta, `I_l` for wye.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from millsense.drivers.protocol import Channel, ChannelKind, Descriptor

SCALE = {"v": 0.02, "i": 0.002, "sp_rpm": 0.1}
CHANNELS = (
    (ChannelKind.VOLTAGE, "v_uv"), (ChannelKind.VOLTAGE, "v_vw"), (ChannelKind.VOLTAGE, "v_wu"),
    (ChannelKind.CURRENT, "i_u"), (ChannelKind.CURRENT, "i_v"), (ChannelKind.CURRENT, "i_w"),
    (ChannelKind.SPEED, "sp_rpm"), (ChannelKind.ENCODER, "sp_enc"),
)


@dataclass(frozen=True)
class Machine:
    spindle_rpm: float = 600.0
    gear_ratio: float = 4.81
    pole_pairs: int = 2
    slip: float = 0.02
    v_ll_rms: float = 180.0
    i_line_rms: float = 12.0
    power_factor_angle_rad: float = 0.6
    winding: str = "delta"
    stator_resistance_ohm: float = 0.349
    cutoff_hz: float = 200.0
    order: int = 2
    sample_rate_hz: float = 1000.0

    @property
    def f_e_hz(self) -> float:
        """Electrical frequency: synchronous speed = motor speed / (1 - slip)."""
        return self.pole_pairs * self.gear_ratio * self.spindle_rpm / 60.0 / (1.0 - self.slip)

    @property
    def p_in_w(self) -> float:
        return math.sqrt(3.0) * self.v_ll_rms * self.i_line_rms * math.cos(self.power_factor_angle_rad)

    @property
    def p_cu_w(self) -> float:
        i_ph = self.i_line_rms / math.sqrt(3.0) if self.winding == "delta" else self.i_line_rms
        return 3.0 * self.stator_resistance_ohm * i_ph**2

    def torque_nm(self, friction_nm: float, viscous_nms: float) -> float:
        """[P] eq. (13) with the exact synchronous speed of eq. (10), referred to the spindle."""
        omega_sync_spindle = 2 * math.pi * self.f_e_hz / self.pole_pairs / self.gear_ratio
        omega = 2 * math.pi * self.spindle_rpm / 60.0
        return (self.p_in_w - self.p_cu_w) / omega_sync_spindle - friction_nm - viscous_nms * omega


def descriptor(channels=CHANNELS, rate: int = 1000) -> Descriptor:
    return Descriptor(rate, tuple(Channel(k, n) for k, n in channels))


def counts(m: Machine, n: int, channels=CHANNELS, start_angle_rev: float = 0.0) -> np.ndarray:
    """(n, C) int16 raw counts of the machine running steadily for n samples."""
    t = np.arange(n) / m.sample_rate_hz
    w = 2 * math.pi * m.f_e_hz
    if m.cutoff_hz > 0:
        s = 1j * m.f_e_hz / m.cutoff_hz
        h = 1.0 / (s * s + math.sqrt(2.0) * s + 1.0) if m.order == 2 else 1.0 / (1.0 + s)
    else:
        h = 1.0 + 0j
    gain, lag = abs(h), np.angle(h)
    v_pk = m.v_ll_rms * math.sqrt(2) * gain
    i_pk = m.i_line_rms * math.sqrt(2) * gain
    phase_v = [w * t + lag + math.pi / 6 - k * 2 * math.pi / 3 for k in range(3)]   # v_uv leads v_u by 30°
    phase_i = [w * t + lag - m.power_factor_angle_rad - k * 2 * math.pi / 3 for k in range(3)]
    signal = {
        "v_uv": v_pk * np.cos(phase_v[0]) / SCALE["v"],
        "v_vw": v_pk * np.cos(phase_v[1]) / SCALE["v"],
        "v_wu": v_pk * np.cos(phase_v[2]) / SCALE["v"],
        "i_u": i_pk * np.cos(phase_i[0]) / SCALE["i"],
        "i_v": i_pk * np.cos(phase_i[1]) / SCALE["i"],
        "i_w": i_pk * np.cos(phase_i[2]) / SCALE["i"],
        "sp_rpm": np.full(n, m.spindle_rpm / SCALE["sp_rpm"]),
    }
    angle = start_angle_rev + m.spindle_rpm / 60.0 * t
    enc = np.round(angle * 4096).astype(np.int64)
    signal["sp_enc"] = (enc + 32768) % 65536 - 32768
    return np.column_stack([np.round(signal[name]) for _, name in channels]).astype(np.int16)
