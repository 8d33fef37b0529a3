"""Capture files decode with the real stream decoder into exactly the plant's samples."""

from __future__ import annotations

import json

import numpy as np
import pytest

from millsense.drivers.protocol import Descriptor, Samples, StreamDecoder
from millsense.sim import Plant, write_capture

pytestmark = pytest.mark.quick


def test_capture_round_trip(tmp_path):
    cap, truth = tmp_path / "c.bin", tmp_path / "t.jsonl"
    n = write_capture("fig6", cap, truth, seed=5, per_frame=7, duration_s=2.5)
    assert n == 2500
    dec = StreamDecoder()
    frames = []
    data = cap.read_bytes()
    for i in range(0, len(data), 4093):  # arbitrary read sizes, as from a pipe
        frames += dec.feed(data[i:i + 4093])
    descriptors = [f for f in frames if isinstance(f, Descriptor)]
    samples = [f for f in frames if isinstance(f, Samples)]
    assert len(descriptors) == 3  # at start and once a second
    assert isinstance(frames[0], Descriptor)
    plant = Plant("fig6", seed=5)
    assert descriptors[0] == plant.descriptor
    assert samples[0].first_index == 0
    got = np.concatenate([s.counts for s in samples])
    idx = np.concatenate([s.first_index + np.arange(len(s.counts)) for s in samples])
    np.testing.assert_array_equal(idx, np.arange(2500))
    np.testing.assert_array_equal(got, plant.step(2500))
    assert dec.stats.bad_crc == 0 and dec.stats.dropped_bytes == 0
    lines = [json.loads(x) for x in truth.read_text().splitlines()]
    assert lines == list(plant.truth) and len(lines) in (24, 25)  # 600 rpm: the 25th ends right at 2.5 s
