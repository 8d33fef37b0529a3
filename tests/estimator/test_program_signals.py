"""A normal part program raises no signal fault: tool changes stop and restart the spindle.

Found live: braking to a stop for a tool change, the speed channel (a tacho,
which lags) read 80 rpm where the encoder read 72, "more than 10 % apart", for
longer than `RAISE_S`; the daemon declared itself blind and held the feed of a
healthy machine. Near standstill a relative tolerance means a few rpm.
"""

from __future__ import annotations

import subprocess

import pytest

from millsense.daemon.config import load_config
from millsense.daemon.pipeline.capture_reader import iter_capture_blocks
from millsense.daemon.pipeline.run_core import PipelineCore
from millsense.drivers.base import SampleBlock
from tests.e2e.helpers import CMD
from tests.e2e.learning_run import CONFIG


def frames(block: SampleBlock, n: int):
    """The block as the live reader hands it over: `n` samples at a time (0: whole)."""
    if not n:
        yield block
        return
    for k in range(0, len(block.counts), n):
        first = k == 0
        yield SampleBlock(block.seq + k, (block.index + k) & 0xFFFFFFFF, block.counts[k:k + n],
                          block.lost_before if first else 0, block.discontinuity and first)


@pytest.mark.parametrize("per_block", [0, 10, 20, 40, 60, 80])
def test_tool_changes_of_a_part_program_raise_no_signal_fault(tmp_path, per_block):
    cap = tmp_path / "three-parts.bin"
    subprocess.run(CMD + ["sim", "--scenario", "part-program", "--parts", "3", "--capture", str(cap)],
                   check=True, capture_output=True, timeout=300)
    core = PipelineCore(load_config(CONFIG))
    faults, stops = [], 0
    for desc, whole in iter_capture_blocks(cap):
        core.on_descriptor(desc)
        for block in frames(whole, per_block):
            step = core.process(block)
            faults.extend(step.faults.values())
            stops += int(step.spindle_stopped)
    assert stops > 0  # the spindle did stop (tool changes)
    assert faults == []
