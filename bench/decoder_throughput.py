"""Decoder throughput: samples/s of 8 channels through StreamDecoder on one core.

Prints one line per case: frames of S=10 and S=1 samples, clean and with 1 % of
the frames corrupted (one flipped byte each), fed in 64 KiB chunks.
Run: python bench/decoder_throughput.py
"""

from __future__ import annotations

import time

import numpy as np

from millsense.drivers.protocol import (
    Channel,
    ChannelKind,
    Descriptor,
    StreamDecoder,
    encode_descriptor,
    encode_sample_frames,
)

CHANNELS = 8
N_SAMPLES = 400_000
CHUNK = 65536


def make_stream(per_frame: int, corrupt_fraction: float, rng) -> tuple[bytes, int]:
    desc = Descriptor(1000, tuple(Channel(ChannelKind.CURRENT, f"c{i}") for i in range(CHANNELS)))
    counts = rng.integers(-32768, 32768, size=(N_SAMPLES, CHANNELS)).astype(np.int16)
    body = bytearray(encode_sample_frames(0, counts, per_frame))
    flen = 7 + 6 + 2 * CHANNELS * per_frame
    n_frames = N_SAMPLES // per_frame
    bad = rng.choice(n_frames, size=int(n_frames * corrupt_fraction), replace=False)
    for i in bad:
        body[i * flen + int(rng.integers(0, flen))] ^= 0x5A
    return encode_descriptor(desc) + bytes(body), len(bad)


def run(per_frame: int, corrupt_fraction: float) -> None:
    rng = np.random.default_rng(0)
    data, n_bad = make_stream(per_frame, corrupt_fraction, rng)
    best = 0.0
    for _ in range(3):
        dec = StreamDecoder()
        t0 = time.perf_counter()
        for a in range(0, len(data), CHUNK):
            dec.feed(data[a : a + CHUNK])
        dt = time.perf_counter() - t0
        best = max(best, dec.stats.samples / dt)
    print(
        f"S={per_frame:<3d} corrupt={corrupt_fraction:4.0%}  {best / 1e6:6.2f} M samples/s "
        f"({CHANNELS} ch, {dec.stats.samples} delivered, {n_bad} frames corrupted, bad_crc={dec.stats.bad_crc})"
    )


if __name__ == "__main__":
    for per_frame in (10, 1):
        for frac in (0.0, 0.01):
            run(per_frame, frac)
