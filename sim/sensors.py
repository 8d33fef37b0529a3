"""The simulated DAQ front end: sensor noise and offsets, the analog anti-alias
filter, sampling and int16 quantisation (docs/architecture.md, "Simulated sensors").

The filter is [P]'s 200 Hz analog low-pass, taken as a 2nd-order Butterworth and
emulated at the internal rate by the bilinear transform with the cut-off
pre-warped (so its gain at 200 Hz is exact and the gain at the electrical
frequency is within 0.1 % of the analog one).  Noise is white at the internal
rate: behind the filter most of it is removed, with ``filter_cutoff_hz=0`` it
aliases into the 1 kHz samples undiminished, as on a real DAQ without one.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from millsense.drivers.protocol import Channel, ChannelKind
from millsense.sim.lti import BlockFilter, butterworth_lowpass

ENCODER_COUNTS_PER_REV = 4096
INT16_MIN, INT16_MAX = -32768, 32767


@dataclass(frozen=True)
class SensorSpec:
    name: str
    kind: ChannelKind
    scale: float  # physical unit per count
    noise_sigma: float  # broadband, physical units, white at the internal rate
    max_offset: float  # |offset| bound, fixed per seed (uniform)


BASE_SENSORS = (
    SensorSpec("v_uv", ChannelKind.VOLTAGE, 0.02, 0.5, 0.2),
    SensorSpec("v_vw", ChannelKind.VOLTAGE, 0.02, 0.5, 0.2),
    SensorSpec("v_wu", ChannelKind.VOLTAGE, 0.02, 0.5, 0.2),
    SensorSpec("i_u", ChannelKind.CURRENT, 0.002, 0.05, 0.05),
    SensorSpec("i_v", ChannelKind.CURRENT, 0.002, 0.05, 0.05),
    SensorSpec("i_w", ChannelKind.CURRENT, 0.002, 0.05, 0.05),
    SensorSpec("sp_rpm", ChannelKind.SPEED, 0.1, 0.5, 0.2),
    SensorSpec("sp_enc", ChannelKind.ENCODER, 1.0, 0.0, 0.0),
)
OPTIONAL_SENSORS = (
    SensorSpec("mot_rpm", ChannelKind.SPEED, 0.2, 1.0, 0.5),
    SensorSpec("ix_feed", ChannelKind.FEED_CURRENT, 0.001, 0.01, 0.005),
    SensorSpec("fx_rate", ChannelKind.FEED_RATE, 0.1, 0.5, 0.0),
    SensorSpec("fx", ChannelKind.FORCE, 0.5, 2.0, 1.0),
    SensorSpec("fy", ChannelKind.FORCE, 0.5, 2.0, 1.0),
    SensorSpec("fz", ChannelKind.FORCE, 0.5, 2.0, 1.0),
)
ALL_SENSORS = {s.name: s for s in BASE_SENSORS + OPTIONAL_SENSORS}


def channel_scales() -> dict[str, dict]:
    """Every channel the simulator can send: kind, scale (unit per count), offset in counts."""
    out: dict[str, dict] = {}
    for s in BASE_SENSORS + OPTIONAL_SENSORS:
        if s.kind == ChannelKind.ENCODER:
            out[s.name] = {"kind": s.kind.name.lower(), "counts_per_rev": ENCODER_COUNTS_PER_REV}
        else:
            out[s.name] = {"kind": s.kind.name.lower(), "scale": s.scale, "offset": 0}
    return out


def select_sensors(extra) -> tuple[SensorSpec, ...]:
    """Base channels plus the optional ones asked for (True = all, names = those)."""
    if extra is None or extra is False:
        names: list[str] = []
    elif extra is True:
        names = [s.name for s in OPTIONAL_SENSORS]
    else:
        names = list(extra)
        unknown = [n for n in names if n not in ALL_SENSORS or ALL_SENSORS[n] in BASE_SENSORS]
        if unknown:
            optional = ", ".join(s.name for s in OPTIONAL_SENSORS)
            raise ValueError(f"unknown optional channel(s) {', '.join(unknown)} (choose from {optional})")
    chosen = [s for s in OPTIONAL_SENSORS if s.name in names]
    return BASE_SENSORS + tuple(chosen)


def descriptor_channels(sensors: tuple[SensorSpec, ...]) -> tuple[Channel, ...]:
    return tuple(Channel(s.kind, s.name) for s in sensors)


class AntiAliasFilter:
    """Butterworth low-pass per channel (2nd order unless asked), state carried across blocks: scipy's
    ``butter`` + ``sosfilt`` computed with numpy alone (sim/lti.py; scipy.signal's import costs 0.8 CPU s a
    process)."""

    def __init__(self, cutoff_hz: float, internal_rate_hz: float, channels: int, order: int = 2) -> None:
        self.cutoff_hz = float(cutoff_hz)
        self._run = None
        if self.cutoff_hz > 0:
            if self.cutoff_hz >= internal_rate_hz / 2:
                raise ValueError(f"filter cut-off {cutoff_hz} Hz must be below {internal_rate_hz / 2} Hz")
            # the bilinear transform with the cut-off pre-warped (scipy's digital butter)
            self._run = BlockFilter(butterworth_lowpass(order, self.cutoff_hz, internal_rate_hz), channels)

    def prime(self, x0: np.ndarray) -> None:
        """Start in steady state for a constant input x0 (C,)."""
        if self._run is not None:
            self._run.prime(x0)

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """x: (C, n) at the internal rate."""
        if self._run is None:
            return x
        return self._run(x)


def analog_gain(cutoff_hz: float, f_hz: np.ndarray, order: int = 2) -> np.ndarray:
    """|H(f)| of the analog Butterworth the filter stands for."""
    if cutoff_hz <= 0:
        return np.ones_like(np.asarray(f_hz, dtype=float))
    return 1.0 / np.sqrt(1.0 + (np.asarray(f_hz, dtype=float) / cutoff_hz) ** (2 * order))


def quantise(values: np.ndarray, scale: float) -> np.ndarray:
    """Round to counts and saturate at the int16 limits, like the A/D converter."""
    counts = np.rint(np.asarray(values) / scale)
    return np.clip(counts, INT16_MIN, INT16_MAX).astype(np.int16)


def encoder_counts(theta_rad: np.ndarray, turns: np.ndarray) -> np.ndarray:
    """Low 16 bits of the 4096-count encoder for angle θ (rad, within the turn) plus whole turns."""
    total = turns.astype(np.int64) * ENCODER_COUNTS_PER_REV + np.floor(
        theta_rad * (ENCODER_COUNTS_PER_REV / (2 * np.pi))
    ).astype(np.int64)
    return (total & 0xFFFF).astype(np.uint16).view(np.int16)


class SensorFaults:
    """A DAQ front end gone wrong, around any sample source (a `Plant`, the ramp): for fault tests.

    What a shop sees on real machines, written from the sensor's side, knowing
    nothing of how the daemon judges it:

    - `pin` {channel: count}: a stuck sensor or a broken ADC input, every sample
      the same count;
    - `current_gain` K: a hall sensor of the wrong rating, K times as many
      counts per ampere as the datasheet says (with K large the int16 rails
      clip the currents);
    - `clip_currents` C: hall sensors saturating at ±C counts;
    - `descriptor_rate_hz`: a DAQ that announces another rate than it samples at
      (the samples keep coming at the true rate);
    - `from_s`: the sample faults (pin, gain, clip) begin this far into the run, as a
      sensor that fails mid-cut (a cable torn off, a connector shaken loose).

    Everything else (feed hold, truth, history, duration) is the source's.
    """

    def __init__(self, source, *, pin: dict[str, int] | None = None, current_gain: float | None = None,
                 clip_currents: int | None = None, descriptor_rate_hz: int | None = None,
                 from_s: float = 0.0) -> None:
        object.__setattr__(self, "_source", source)
        desc = source.descriptor
        names = [ch.name for ch in desc.channels]
        pin = dict(pin or {})
        unknown = [n for n in pin if n not in names]
        if unknown:
            raise ValueError(f"cannot pin {', '.join(unknown)}: the DAQ sends {', '.join(names)}")
        for name, count in pin.items():
            if not INT16_MIN <= int(count) <= INT16_MAX:
                raise ValueError(f"pin {name}={count}: a count is {INT16_MIN}..{INT16_MAX}")
        if clip_currents is not None and not 0 < int(clip_currents) <= INT16_MAX:
            raise ValueError(f"clip-currents {clip_currents}: counts 1..{INT16_MAX}")
        if current_gain is not None and not current_gain > 0:
            raise ValueError(f"current gain {current_gain}: must be > 0")
        currents = [k for k, ch in enumerate(desc.channels) if ChannelKind(ch.kind) == ChannelKind.CURRENT]
        state = {
            "_pin": [(names.index(n), int(c)) for n, c in pin.items()],
            "_currents": np.array(currents, dtype=np.intp),
            "_gain": None if current_gain is None else float(current_gain),
            "_clip": None if clip_currents is None else int(clip_currents),
            "descriptor": desc if descriptor_rate_hz is None else replace(desc, sample_rate_hz=int(descriptor_rate_hz)),
            "sample_rate_hz": desc.sample_rate_hz,   # the rate the samples really come at
            "_from_sample": max(0, round(float(from_s) * desc.sample_rate_hz)),
            "_produced": 0,
        }
        for key, value in state.items():
            object.__setattr__(self, key, value)

    def step(self, n: int) -> np.ndarray:
        counts = np.array(self._source.step(n), dtype=np.int16)
        first = self._produced
        object.__setattr__(self, "_produced", first + n)
        skip = min(n, max(0, self._from_sample - first))  # samples before the fault begins stay sound
        self._spoil(counts[skip:])
        return counts

    def _spoil(self, counts: np.ndarray) -> None:
        cur = self._currents
        if len(cur) and (self._gain is not None or self._clip is not None):
            x = counts[:, cur].astype(np.float64)
            if self._gain is not None:
                x = np.rint(x * self._gain)
            top = self._clip if self._clip is not None else INT16_MAX
            bottom = -self._clip if self._clip is not None else INT16_MIN
            counts[:, cur] = np.clip(x, bottom, top).astype(np.int16)
        for col, count in self._pin:
            counts[:, col] = count

    def __getattr__(self, name):
        return getattr(self._source, name)

    def __setattr__(self, name, value):
        setattr(self._source, name, value)   # feed_hold from the device goes to the machine
