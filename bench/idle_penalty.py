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

Then the reader thread's crash check, `FrameCheck.check` on the capture's
10-sample frames (plain Python floats since stop 22), back to back and after
sleeping 10 ms (the reader's period), beside its baseline: the same arithmetic
as numpy calls on the frame (`x @ W`, `einsum`, `abs`, `max`: how it was
written before), timed the same way.

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
    from millsense.daemon.commands.capture_reader import iter_capture_blocks
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


def frame_cases(settings, desc, blocks: list, sleep_s: float) -> tuple[float, float, float]:
    """p50 µs per 10-sample frame: `FrameCheck.check`; its arithmetic alone (the compiled program, the peaks);
    the same numbers by numpy calls (the baseline)."""
    from millsense.daemon.pipeline.safety_check import FrameCheck

    fc = FrameCheck(settings, desc)
    frames = [b.counts[k:k + 10] for b in blocks for k in range(0, len(b.counts), 10)][:2 * FRAMES]
    # the baseline: Q in counts read back from the compiled program by polarisation, and the line currents as
    # a diagonal (the demo config: no offsets, the three line currents measured, each its own column)
    assert not fc._offsets.any() and "r[" in fc.program_source
    c = frames[0].shape[1]
    probe = np.eye(c, dtype=np.int64)
    ones = [fc._frame_values([list(row)], 1.0)[0][0] for row in probe]
    q = np.empty((c, c))
    for j in range(c):
        for m in range(c):
            both = fc._frame_values([list(probe[j] + probe[m])], 1.0)[0][0]
            q[j, m] = 0.5 * (both - ones[j] - ones[m]) if j != m else ones[j]
    cur = np.zeros((c, c))
    np.fill_diagonal(cur, fc._amps_per_count)
    w = np.hstack([q, cur])
    for fr in frames[:20]:   # the two ways compute the same numbers
        power, current = fc._frame_values(fr.tolist(), 1.0)
        assert abs(numpy_way_peak(fr, w, c)[0] - max(power)) <= 1e-9 * max(1.0, abs(max(power)))
        assert abs(numpy_way_peak(fr, w, c)[1] - max(current)) <= 1e-12 * max(1.0, max(current))

    def python_way_peak(counts: np.ndarray) -> list[float]:
        power, current = fc._frame_values(counts.tolist(), 1.0)
        return [max(power), max(current)]

    ways = (lambda k, fr: fc.check(10 * k, fr, 0, False, 1.0), lambda k, fr: python_way_peak(fr),
            lambda k, fr: numpy_way_peak(fr, w, c))
    for way in ways:   # warm
        for k, fr in enumerate(frames[:FRAMES]):
            way(k, fr)
    times: list[list[float]] = [[] for _ in ways]
    for k, fr in enumerate(frames[FRAMES:], start=FRAMES):   # interleaved: each way under the same conditions
        for way, out in zip(ways, times):
            if sleep_s:
                time.sleep(sleep_s)
            t0 = time.perf_counter()
            way(k, fr)
            out.append(time.perf_counter() - t0)
    out = [float(np.median(t)) * 1e6 for t in times]
    return out[0], out[1], out[2]


FRAMES = 300


def numpy_way_peak(counts: np.ndarray, w: np.ndarray, c: int) -> list[float]:
    """The frame's peak power and current by numpy calls, as `FrameCheck` computed them before stop 22."""
    x = counts.astype(float)
    y = x @ w
    z = np.empty((len(x), 2))
    np.einsum("ij,ij->i", y[:, :c], x, out=z[:, 0])
    np.abs(y[:, c:]).max(axis=1, out=z[:, 1])
    return z.max(axis=0).tolist()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--blocks", type=int, default=200, help="blocks timed per case (default 200)")
    args = ap.parse_args()
    from millsense.daemon.config.load import load_config

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
    print(f"FrameCheck on {FRAMES} frames of 10 samples: its arithmetic (power and current per sample, the peaks) "
          "on floats, beside the same arithmetic as numpy calls (baseline); and the whole check:")
    for name, sleep_s in (("back to back", 0.0), ("after sleeping 10 ms", 0.01)):
        check_us, python_us, numpy_us = frame_cases(settings, desc, blocks, sleep_s)
        print(f"  {name:32s} floats p50 {python_us:6.1f} µs   numpy calls p50 {numpy_us:6.1f} µs   "
              f"{python_us / numpy_us:4.2f} x the baseline;   whole check p50 {check_us:6.1f} µs")
    return 0


if __name__ == "__main__":
    sys.exit(main())
