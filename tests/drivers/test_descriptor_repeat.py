"""The decoder's shortcut for a DESCRIPTOR repeated byte for byte (the DAQ sends one a second):
frames and counters exactly as the full path gives them, for good, corrupt and changed repeats,
whatever the read sizes."""

from __future__ import annotations

import numpy as np
import pytest

from millsense.drivers.protocol import (
    Channel,
    ChannelKind,
    Descriptor,
    StreamDecoder,
    encode_descriptor,
    encode_sample_frames,
)

pytestmark = pytest.mark.quick

A = Descriptor(1000, tuple(Channel(ChannelKind.CURRENT, f"ch{i}") for i in range(4)))
B = Descriptor(1000, tuple(Channel(ChannelKind.VOLTAGE, f"v{i}") for i in range(4)))   # same shape, other channels


class _NoShortcut(StreamDecoder):
    """The full path for every DESCRIPTOR: the shortcut's cache is never filled."""

    def __setattr__(self, name, value):
        super().__setattr__(name, None if name == "_last_descriptor" else value)


def _stream() -> bytes:
    rng = np.random.default_rng(3)
    parts, index = [], 0
    desc_a = encode_descriptor(A)
    corrupt_crc = desc_a[:-1] + bytes([desc_a[-1] ^ 0x01])
    corrupt_body = desc_a[:12] + bytes([desc_a[12] ^ 0x40]) + desc_a[13:]
    for k, desc in enumerate([desc_a, desc_a, corrupt_crc, desc_a, corrupt_body, encode_descriptor(B), desc_a,
                              desc_a[:7], desc_a]):
        parts.append(desc)
        n = 10 * (k + 3)
        parts.append(encode_sample_frames(index, rng.integers(-3000, 3000, (n, 4)).astype(np.int16)))
        index += n
    return b"".join(parts)


def _decode(decoder: StreamDecoder, data: bytes, chunk: int) -> tuple[list, dict]:
    frames = []
    for i in range(0, len(data), chunk):
        frames += decoder.feed(data[i:i + chunk])
    out = [(type(f).__name__, f if isinstance(f, Descriptor) else (f.first_index, f.counts.tolist())) for f in frames]
    return out, decoder.stats.as_dict()


@pytest.mark.parametrize("chunk", [1 << 20, 1, 7, 64, 173, 1000])
def test_repeats_decode_as_the_full_path(chunk):
    data = _stream()
    got, stats = _decode(StreamDecoder(), data, chunk)
    want, want_stats = _decode(_NoShortcut(), data, chunk)
    assert got == want
    assert stats == want_stats
    # the stream is meant to exercise both: refused repeats and a change of descriptor
    assert stats["bad_crc"] >= 2
    assert [f for kind, f in got if kind == "Descriptor"].count(B) == 1


def test_the_shortcut_is_taken():
    d = StreamDecoder()
    first = d.feed(encode_descriptor(A))[0]
    again = d.feed(encode_descriptor(A))[0]
    assert again is first          # the parsed descriptor reused, not parsed again
    assert d.stats.frames == 2
