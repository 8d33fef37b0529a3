"""In-process pipeline throughput: decode + estimate, large blocks, beside a numpy floor.

Budget (issue 13): on the `step` scenario with depth off, >= 5 M samples/s and at
least 1/4 of the numpy floor measured in the same run. The floor does the least
any estimator must do on the same decoded blocks: scale the counts, p = v.i
(three products), and one `np.add.reduceat` per revolution (boundaries from the
encoder). fig6 (d.toml: depth by root finding on every revolution) is reported
beside it. The capture is decoded in memory, then consecutive runs of samples are
joined into large blocks of up to --block-samples (16000: 16 s at 1 kHz; a block
ends early only at lost samples or a discontinuity, which must open a block of their
own); decoding and joining are inside both figures, pipeline and floor. Beside it,
the same pipeline on the blocks as decoded (`--block-samples 0`: one per DESCRIPTOR
repeat, 1000 samples, what `millsense replay` hands the core). The figure is the
best of --repeat runs, each a fresh decoder and estimator.

    .venv/bin/python bench/pipeline_throughput.py [--seconds 300] [--repeat 3] [--block-samples 16000] [--profile]
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
BUDGET_SAMPLES_S = 5e6
BUDGET_FLOOR_SHARE = 0.25


def make_capture(scenario: str, seconds: float, path: Path) -> None:
    subprocess.run([sys.executable, "-m", "millsense.daemon", "sim", "--scenario", scenario, "--loop",
                    "--duration-s", str(seconds), "--capture", str(path), "--fast"],
                   check=True, capture_output=True)


def decode(data: bytes, block_samples: int = 0):
    """(descriptor, SampleBlocks): consecutive runs joined up to `block_samples` (0: as decoded)."""
    from millsense.drivers.base import IndexTracker, SampleBlock
    from millsense.drivers.protocol import Descriptor, Samples, StreamDecoder

    tracker, descriptor, blocks = IndexTracker(), None, []
    parts: list[np.ndarray] = []   # the block being joined: its runs' counts
    head = None                    # its (seq, index, lost, discontinuity)
    size = 0

    def flush():
        if parts:
            counts = parts[0] if len(parts) == 1 else np.concatenate(parts)
            blocks.append(SampleBlock(head[0], head[1], counts, head[2], head[3]))
            parts.clear()

    for frame in StreamDecoder().feed(data):
        if isinstance(frame, Descriptor):
            descriptor = descriptor or frame
        elif isinstance(frame, Samples):
            n = len(frame.counts)
            seq, lost, disc = tracker.update(frame.first_index, n)
            if parts and not lost and not disc and size + n <= block_samples:
                parts.append(frame.counts)
                size += n
                continue
            flush()   # a gap or a restart opens a block of its own: the estimator places it before it
            parts.append(frame.counts)
            head, size = (seq, frame.first_index, lost, disc), n
    flush()
    return descriptor, blocks


def pipeline(settings, data: bytes, block_samples: int) -> tuple[float, int, int]:
    """Seconds for decode + Estimator.process over the whole capture; samples; revolutions."""
    from millsense.daemon.pipeline.estimator import Estimator

    t0 = time.perf_counter()
    descriptor, blocks = decode(data, block_samples)
    est = Estimator(settings, descriptor, descriptor.sample_rate_hz)
    revs = 0
    for block in blocks:
        revs += len(est.process(block).estimates)
    return time.perf_counter() - t0, sum(len(b.counts) for b in blocks), revs


def floor(settings, data: bytes, block_samples: int) -> float:
    """Seconds for the numpy floor on the same decoded blocks (decoding and joining included)."""
    from millsense.daemon.pipeline.scaling import Scaler

    t0 = time.perf_counter()
    descriptor, blocks = decode(data, block_samples)
    scaler = Scaler(settings, descriptor)
    r = scaler.roles
    v = [scaler.names.index(r.voltages[k]) for k in ("uv", "vw", "wu")]
    i = [scaler.names.index(r.currents[k]) for k in ("u", "v", "w")]
    cols = scaler._cols
    offsets, scales = scaler._offsets, scaler._scales
    enc_col = scaler._enc_col
    cpr = int(scaler.counts_per_rev)
    total = 0.0
    for block in blocks:
        phys = (block.counts[:, cols].astype(np.float64) - offsets) * scales
        p = phys[:, v[0]] * phys[:, i[0]] + phys[:, v[1]] * phys[:, i[1]] + phys[:, v[2]] * phys[:, i[2]]
        turn = block.counts[:, enc_col].astype(np.int64) // cpr
        starts = np.flatnonzero(np.diff(turn)) + 1
        if len(starts):
            total += float(np.add.reduceat(p, starts).sum())
    return time.perf_counter() - t0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=300.0, help="simulated seconds of the step capture")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--block-samples", type=int, default=16000,
                        help="join consecutive runs into blocks of up to this many samples (0: as decoded)")
    parser.add_argument("--profile", action="store_true", help="also print a cProfile of one step run")
    args = parser.parse_args()
    from millsense.daemon.config.load import load_config

    with tempfile.TemporaryDirectory() as tmp:
        step_cap = Path(tmp) / "step.cap"
        make_capture("step", args.seconds, step_cap)
        step = load_config(REPO / "daemon" / "demo.toml")
        step.depth.method = "off"
        fig6 = load_config(REPO / "config" / "depth-of-cut-d.toml")  # [D]: depth from two forces
        fig6_cap = Path(tmp) / "fig6.cap"
        if fig6 is not None:
            make_capture("fig6", min(args.seconds, 60.0), fig6_cap)
        step_data = step_cap.read_bytes()
        k = args.block_samples
        best_pipe = best_floor = best_fig6 = best_decoded = float("inf")
        for _ in range(args.repeat):
            dt, n, revs = pipeline(step, step_data, k)
            best_pipe = min(best_pipe, dt)
            best_floor = min(best_floor, floor(step, step_data, k))
            if k:
                best_decoded = min(best_decoded, pipeline(step, step_data, 0)[0])
            if fig6 is not None:
                dt6, n6, revs6 = pipeline(fig6, fig6_cap.read_bytes(), k)
                best_fig6 = min(best_fig6, dt6)
        rate, floor_rate = n / best_pipe, n / best_floor
        print(f"in-process decode + estimate, step, depth off, {n} samples, {revs} revolutions, "
              f"blocks of up to {k or 'as decoded'} samples (best of {args.repeat}):")
        print(f"  pipeline    {rate / 1e6:7.3f} M samples/s   {best_pipe / revs * 1e6:6.1f} us a revolution"
              f"   budget >= {BUDGET_SAMPLES_S / 1e6:.0f} M: {'met' if rate >= BUDGET_SAMPLES_S else 'MISSED'}")
        print(f"  numpy floor {floor_rate / 1e6:7.3f} M samples/s   pipeline / floor = {rate / floor_rate:.3f}"
              f"   budget >= {BUDGET_FLOOR_SHARE}: {'met' if rate >= BUDGET_FLOOR_SHARE * floor_rate else 'MISSED'}")
        if k:
            print(f"  the same pipeline on the blocks as decoded (replay's, one per DESCRIPTOR repeat): "
                  f"{n / best_decoded / 1e6:7.3f} M samples/s")
        if fig6 is not None:
            print(f"  fig6 (d.toml, depth by root finding) {n6 / best_fig6 / 1e6:7.3f} M samples/s, "
                  f"{best_fig6 / revs6 * 1e6:6.1f} us a revolution ({revs6} revolutions)")
        if args.profile:
            import cProfile
            import pstats

            prof = cProfile.Profile()
            prof.runcall(pipeline, step, step_data, k)
            pstats.Stats(prof).sort_stats("cumulative").print_stats(25)
    return 0


if __name__ == "__main__":
    sys.exit(main())
