"""Decoder throughput: samples/s of 8 channels through StreamDecoder on one core.

Prints one line per case: frames of S=10 and S=1 samples, clean and with 1 % of
the frames corrupted (one flipped byte each), fed in 64 KiB chunks. Then the live
case: one 10-sample frame of 9 channels per `feed` (what a 1 kHz DAQ sends every
10 ms), µs a frame, and the CRC of its 189-byte body: the compiled one
(crcmod-plus, what the decoder calls) against the byte-by-byte Python loop it
replaced and the position-table gather (baselines, same run), back to back and
paced 10 ms apart as the reader thread runs it (caches cold).
Run: python bench/decoder_throughput.py
"""

from __future__ import annotations

import time

import numpy as np

from millsense.drivers import protocol
from millsense.drivers.protocol import (
    Channel,
    ChannelKind,
    Descriptor,
    StreamDecoder,
    encode_descriptor,
    encode_sample_frames,
    encode_samples,
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


def crc_python_loop(data: bytes) -> int:
    """The reader's CRC before crcmod-plus (stop 19): a Python loop, one 256-entry table step a byte."""
    crc = 0xFFFF
    table = protocol._T1
    for b in data:
        crc = (crc >> 8) ^ table[(crc ^ b) & 0xFF]
    return crc


def crc_gather(data: bytes) -> int:
    """The position-table gather (`crc16_modbus_rows`) on one body."""
    return int(protocol.crc16_modbus_rows(np.frombuffer(data, np.uint8)[None, :])[0])


def paced_us(fn, items, gap_s: float = 0.01, n: int = 150) -> float:
    """Median µs of one call made every `gap_s` (the reader's pace: other work in between)."""
    times = []
    for x in items[:n]:
        t0 = time.perf_counter()
        fn(x)
        times.append(time.perf_counter() - t0)
        time.sleep(gap_s)
    return float(np.median(times)) * 1e6


def per_us(fn, items, repeat: int = 3) -> float:
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        for x in items:
            fn(x)
        best = min(best, (time.perf_counter() - t0) / len(items))
    return best * 1e6


def live_frames() -> None:
    rng = np.random.default_rng(1)
    desc = Descriptor(1000, tuple(Channel(ChannelKind.CURRENT, f"c{i}") for i in range(9)))
    frames = [encode_samples(10 * k, rng.integers(-2000, 2000, (10, 9)).astype(np.int16)) for k in range(5000)]
    dec = StreamDecoder()
    dec.feed(encode_descriptor(desc))
    t_frame = per_us(dec.feed, frames, repeat=1)
    bodies = [f[2:-2] for f in frames]
    assert all(protocol.crc16_modbus(b) == crc_python_loop(b) == crc_gather(b) for b in bodies[:100])
    print(f"one 10-sample frame of 9 channels a feed: {t_frame:5.1f} us a frame")
    for label, fn in (("compiled (crcmod-plus)", protocol.crc16_modbus), ("Python byte loop", crc_python_loop),
                      ("numpy gather", crc_gather)):
        print(f"  CRC of its {len(bodies[0])}-byte body, {label:22s}: back to back {per_us(fn, bodies):6.1f} us, "
              f"paced 10 ms apart {paced_us(fn, bodies):6.1f} us")


if __name__ == "__main__":
    for per_frame in (10, 1):
        for frac in (0.0, 0.01):
            run(per_frame, frac)
    live_frames()
