"""A capture file -> (descriptor, SampleBlock) pairs, as a live driver would yield them.

A capture is the DAQ byte stream as it came off the wire (interfaces.md), so it
goes through the very `StreamDecoder` a live link uses. The 32-bit device index
is unwrapped into `seq` by the drivers' own `IndexTracker`: a forward jump is
lost samples, a backward jump (device restart) or a changed descriptor is a
discontinuity. Used by `calibrate` and the accuracy bench; reading is chunked
so a long capture never sits in memory twice.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

from millsense.drivers.base import IndexTracker, SampleBlock
from millsense.drivers.protocol import Descriptor, Samples, StreamDecoder

CHUNK_BYTES = 1 << 20


class CaptureError(Exception):
    """The capture cannot be used (unreadable, no descriptor, no samples)."""


def iter_capture_blocks(path: str | Path) -> Iterator[tuple[Descriptor, SampleBlock]]:
    """Yield (current descriptor, block) for every SAMPLES run in the capture."""
    decoder = StreamDecoder()
    tracker = IndexTracker()
    descriptor: Descriptor | None = None
    try:
        fh = open(path, "rb")  # noqa: SIM115 - closed below, chunks are yielded in between
    except OSError as exc:
        raise CaptureError(f"{path}: cannot read the capture ({exc.strerror or exc})") from exc
    with fh:
        while True:
            data = fh.read(CHUNK_BYTES)
            if not data:
                break
            for frame in decoder.feed(data):
                if isinstance(frame, Descriptor):
                    if descriptor is not None and frame != descriptor:
                        tracker.mark_discontinuity()
                    descriptor = frame
                elif isinstance(frame, Samples) and descriptor is not None:
                    seq, lost, disc = tracker.update(frame.first_index, len(frame.counts))
                    yield descriptor, SampleBlock(seq, frame.first_index, frame.counts, lost, disc)
    if descriptor is None:
        raise CaptureError(f"{path}: no DAQ descriptor frame found (is this a millsense capture?)")
