"""What a thread's idle costs the next block: the live daemon's closing block, back to back and after a sleep.

The live estimator thread sleeps about 100 ms between revolutions (600 rpm) and
then runs one block of about 100 samples. The same block, run back to back in a
loop, takes a fraction of what the live daemon's status reports
(`latency_ms`). This bench shows where the difference lies, in one process: the
same `PipelineCore.process` on the same 100-sample blocks of a `step` capture
(the closing block of a revolution at 600 rpm), timed

1. back to back (the baseline: caches and predictors warm);
2. after touching 8 MB of memory, with no sleep (data caches evicted, the
   thread never off its CPU);
3. after sleeping 10 ms (the reader thread's period between frames);
4. after sleeping 100 ms (the estimator thread's, at 600 rpm).

Each is the median and p90 of `--blocks` blocks, each on a fresh core warmed
by the same 50 blocks first. No budget: it explains issue 13's per-revolution
figure (docs/performance.md).

Run: .venv/bin/python bench/idle_penalty.py [--blocks 200]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
BLOCK_SAMPLES = 100   # a revolution at 600 rpm, 1 kHz: what the estimator takes at its wake-up
WARM_BLOCKS = 50
THRASH_BYTES = 8 << 20


def blocks_of(capture: Path) -> tuple[object, list]:
    from millsense.daemon.pipeline.capture_reader import iter_capture_blocks
    from millsense.drivers.base import SampleBlock

    desc, out = None, []
    for d, whole in iter_capture_blocks(capture):
        desc = desc or d
        for k in range(0, len(whole.counts) - BLOCK_SAMPLES + 1, BLOCK_SAMPLES):
            first = k == 0
            out.append(SampleBlock(whole.seq + k, (whole.index + k) & 0xFFFFFFFF, whole.counts[k:k + BLOCK_SAMPLES],
                                   whole.lost_before if first else 0, whole.discontinuity and first))
    return desc, out


def timed(settings, desc, blocks: list, before) -> np.ndarray:
    """µs of `PipelineCore.process` per block, `before()` run ahead of each (outside the timing)."""
    from millsense.daemon.pipeline.run_core import PipelineCore

    core = PipelineCore(settings)
    core.on_descriptor(desc)
    for b in blocks[:WARM_BLOCKS]:
        core.process(b)
    out = []
    for b in blocks[WARM_BLOCKS:]:
        before()
        t0 = time.perf_counter()
        core.process(b)
        out.append(time.perf_counter() - t0)
    return np.array(out) * 1e6


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--blocks", type=int, default=200, help="blocks timed per case (default 200)")
    args = ap.parse_args()
    from millsense.daemon.config import load_config

    settings = load_config(REPO / "daemon" / "demo.toml")
    with tempfile.TemporaryDirectory() as tmp:
        cap = Path(tmp) / "step.cap"
        seconds = (WARM_BLOCKS + args.blocks) * BLOCK_SAMPLES / 1000.0 + 2.0
        subprocess.run([sys.executable, "-m", "millsense.daemon", "sim", "--scenario", "step", "--once",
                        "--duration-s", str(seconds), "--capture", str(cap), "--fast"], check=True, capture_output=True)
        desc, blocks = blocks_of(cap)
    blocks = blocks[: WARM_BLOCKS + args.blocks]
    junk = np.zeros(THRASH_BYTES // 8)

    def thrash() -> None:
        np.add(junk, 1.0, out=junk)   # every byte of it read and written

    cases = [("back to back (baseline)", lambda: None),
             ("after touching 8 MB, no sleep", thrash),
             ("after sleeping 10 ms", lambda: time.sleep(0.01)),
             ("after sleeping 100 ms", lambda: time.sleep(0.1))]
    print(f"PipelineCore.process on {len(blocks) - WARM_BLOCKS} blocks of {BLOCK_SAMPLES} samples "
          f"(`step`, the demo config), each case on a fresh core warmed by {WARM_BLOCKS} blocks:")
    base = None
    for name, before in cases:
        us = timed(settings, desc, blocks, before)
        p50, p90 = float(np.median(us)), float(np.percentile(us, 90))
        base = base or p50
        print(f"  {name:32s} p50 {p50:7.1f} µs  p90 {p90:7.1f} µs   {p50 / base:4.2f} x the baseline")
    return 0


if __name__ == "__main__":
    sys.exit(main())
