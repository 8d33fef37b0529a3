"""The driver's queue as the estimator thread takes it: contiguous frames merged into one block (one pass of the
estimator: issue 13, 50-sample blocks every 50 ms cost a third of 10-sample blocks every 10 ms), each frame's
own arrival kept for the sample clock and `rev_delay_ms`.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from millsense.drivers.base import SampleBlock


def merged(events: list[Any]) -> list[tuple[Any, list[tuple[int, int, float]] | None]]:
    """Contiguous frames as one block (one pass of the estimator), with each frame's (seq, n, arrival).

    A frame after lost samples or a discontinuity, or checked differently, starts a new block.
    """
    out: list[tuple[Any, list[tuple[int, int, float]] | None]] = []
    run: list[Any] = []

    def flush() -> None:
        if not run:
            return
        parts = [(b.seq, len(b.counts), b.received_mono) for b in run]
        first = run[0]
        block = first if len(run) == 1 else SampleBlock(
            first.seq, first.index, np.concatenate([b.counts for b in run]), first.lost_before,
            first.discontinuity, first.checked, run[-1].received_mono, first.after_link_up)
        out.append((block, parts))
        run.clear()

    for ev in events:
        if isinstance(ev, SampleBlock):
            prev = run[-1] if run else None
            if prev is not None and not (ev.seq == prev.seq + len(prev.counts) and not ev.lost_before
                                         and not ev.discontinuity and not ev.after_link_up
                                         and ev.checked == prev.checked
                                         and ev.counts.shape[1:] == prev.counts.shape[1:]):
                flush()
            run.append(ev)
        else:
            flush()
            out.append((ev, None))
    flush()
    return out


def arrival(parts: list[tuple[int, int, float]], seq: int, default: float) -> float:
    """When the frame holding sample `seq` arrived (the reader's stamp), else `default`."""
    for first, count, mono in parts:
        if first <= seq < first + count:
            return mono if mono > 0.0 else default
    return default
