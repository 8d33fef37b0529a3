"""A synthetic source with the Plant's interface: a deterministic int16 ramp.

Sample with device index ``k`` has, on channel ``c``, the count
``(k + 1000 * c) mod 65536`` read as int16.  Because the value is a function of
the index alone, a reader can check every sample it receives ("each arrives once,
in order, with the right value") without a copy of the generator.
"""

from __future__ import annotations

import numpy as np

from millsense.drivers.protocol import Channel, ChannelKind, Descriptor

RAMP_CHANNELS = (
    Channel(ChannelKind.VOLTAGE, "v_uv"),
    Channel(ChannelKind.VOLTAGE, "v_vw"),
    Channel(ChannelKind.VOLTAGE, "v_wu"),
    Channel(ChannelKind.CURRENT, "i_u"),
    Channel(ChannelKind.CURRENT, "i_v"),
    Channel(ChannelKind.CURRENT, "i_w"),
    Channel(ChannelKind.SPEED, "sp_rpm"),
    Channel(ChannelKind.ENCODER, "sp_enc"),
)
CHANNEL_STEP = 1000


def ramp_counts(first_index: int, n: int, channels: int) -> np.ndarray:
    """The ramp's (n, C) int16 counts for indices first_index .. first_index + n - 1."""
    k = (first_index + np.arange(n, dtype=np.int64))[:, None] + CHANNEL_STEP * np.arange(channels)
    return (k % 65536).astype(np.uint16).view(np.int16)


class RampPlant:
    """Same surface as ``sim.Plant`` (descriptor, step, feed_hold, truth)."""

    description = "synthetic int16 ramp, value = (index + 1000*channel) mod 2^16 (contract tests)"

    def __init__(self, *, sample_rate_hz: int = 1000, start_index: int = 0) -> None:
        self.descriptor = Descriptor(sample_rate_hz, RAMP_CHANNELS)
        self.sample_rate_hz = sample_rate_hz
        self.duration_s = float("inf")
        self.feed_hold = False
        self.truth = None
        self._next = start_index

    def history(self, first_index: int, n: int) -> np.ndarray:
        """Samples from before the start, so a device started mid-count has a full ring."""
        return ramp_counts(first_index, n, len(RAMP_CHANNELS))

    def step(self, n: int) -> np.ndarray:
        out = ramp_counts(self._next, n, len(RAMP_CHANNELS))
        self._next += n
        return out
