"""Turns the device's samples and replies into wire bytes, with injected faults.

Faults are for tests of the reader: ``corrupt_fraction`` flips one byte in that
fraction of frames (each one is written to the status log, so a test knows which
samples it must count as lost), ``garbage_bps`` puts random bytes between frames.
"""

from __future__ import annotations

import numpy as np

from millsense.drivers.protocol import (
    MAX_SAMPLES_PER_FRAME,
    Context,
    Samples,
    Status,
    encode_context,
    encode_descriptor,
    encode_sample_frames,
    encode_samples,
    encode_status,
)


class WireEmitter:
    def __init__(
        self,
        device,
        *,
        per_frame: int = 10,
        corrupt_fraction: float = 0.0,
        garbage_bps: float = 0.0,
        seed: int = 0,
        descriptor_period_s: float = 1.0,
    ) -> None:
        if not 0.0 <= corrupt_fraction <= 1.0:
            raise ValueError("corrupt fraction must be within 0..1")
        if not 1 <= per_frame <= MAX_SAMPLES_PER_FRAME:
            raise ValueError(f"samples per frame must be within 1..{MAX_SAMPLES_PER_FRAME}")
        self.device = device
        self.per_frame = per_frame
        self.corrupt_fraction = corrupt_fraction
        self.garbage_bps = garbage_bps
        self.rng = np.random.default_rng(seed + 7919)
        self.descriptor_period_s = descriptor_period_s
        self._next_descriptor = -1.0
        self._last_garbage_time: float | None = None
        self.corrupted_frames = 0

    def block(self, first_index: int, counts: np.ndarray, now: float) -> bytes:
        """The device's last produced block on the wire, as `DeviceModel.stream_items` orders it: SAMPLES
        frames, each CONTEXT of the part program just before the sample it holds for, and a STATUS after each
        frame in which the CNC's applied override moved (version 2: the host learns of it where it happened,
        however large the block)."""
        parts = []
        for item in self.device.stream_items(first_index, counts, frame=self.per_frame):
            if isinstance(item, Samples):
                parts.append(self.samples(item.first_index, item.counts, now))
            elif isinstance(item, Status):
                parts.append(self.status(now, item))
            else:
                parts.append(self.context(now, item))
        return b"".join(parts)

    def _maybe_corrupt(self, frame: bytes, now: float, kind: str, **fields) -> bytes:
        if self.corrupt_fraction <= 0 or self.rng.random() >= self.corrupt_fraction:
            return frame
        pos = int(self.rng.integers(0, len(frame)))
        flip = int(self.rng.integers(1, 256))
        out = bytearray(frame)
        out[pos] ^= flip
        self.corrupted_frames += 1
        self.device.log.write("corrupt", now, frame_type=kind, byte=pos, **fields)
        return bytes(out)

    def descriptor(self, now: float) -> bytes:
        """The DESCRIPTOR, and on version 2 the CONTEXT with it (both at start, once a second, on request)."""
        self._next_descriptor = now + self.descriptor_period_s
        return self._maybe_corrupt(encode_descriptor(self.device.descriptor), now, "descriptor") + self.context(now)

    def context(self, now: float, ctx: Context | None = None) -> bytes:
        """A CONTEXT frame: `ctx`, else the CNC's now (version 2); b"" on version 1."""
        ctx = self.device.context() if ctx is None else ctx
        if ctx is None:
            return b""
        return self._maybe_corrupt(encode_context(ctx), now, "context")

    def status(self, now: float, status: Status | None = None) -> bytes:
        """A STATUS frame: `status`, else the device's now."""
        return self._maybe_corrupt(encode_status(self.device.status() if status is None else status), now, "status")

    def periodic(self, now: float) -> bytes:
        """The once-a-second descriptor when due, and garbage for the time passed."""
        out = b""
        if now >= self._next_descriptor:
            out += self.descriptor(now)
        if self.garbage_bps > 0:
            if self._last_garbage_time is None:
                self._last_garbage_time = now
            n = int((now - self._last_garbage_time) * self.garbage_bps)
            if n > 0:
                self._last_garbage_time += n / self.garbage_bps
                out += self.rng.bytes(n)
        return out

    def samples(self, first_index: int, counts: np.ndarray, now: float) -> bytes:
        """SAMPLES frames of `per_frame` samples."""
        n = len(counts)
        if n == 0:
            return b""
        if self.corrupt_fraction <= 0:
            return encode_sample_frames(first_index, counts, self.per_frame)
        parts = []
        for a in range(0, n, self.per_frame):
            chunk = counts[a : a + self.per_frame]
            first = (first_index + a) % (1 << 32)
            frame = encode_samples(first, chunk)
            parts.append(self._maybe_corrupt(frame, now, "samples", first_index=first, samples=len(chunk)))
        return b"".join(parts)
