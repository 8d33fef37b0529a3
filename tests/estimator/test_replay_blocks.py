"""`millsense replay` joins consecutive SAMPLES runs into large blocks (daemon/commands/replay.py).

The same capture fed in small chunks (each chunk's end closes a block: blocks of a few frames) and
whole (blocks of up to 16 384 samples, closed at every STATUS, CONTEXT or new DESCRIPTOR) gives the
same JSON lines: the same estimates, alarms and process summaries at the same revolutions, every
number within test_vectorised.py's bounds (1e-9 relative; the torque's standard error 1e-6, a
difference of two sums that summation order moves). One capture of the crash (clipped currents,
a crash trip), one of the part program (protocol 2: CONTEXT and STATUS frames between the samples,
learned limits, a broken flute).
"""

from __future__ import annotations

import io
import json
from pathlib import Path

import pytest

from millsense.daemon.commands.replay import Replay
from millsense.daemon.config.load import load_config
from tests import captures
from tests.estimator.test_vectorised import assert_same_lines

REPO = Path(__file__).resolve().parents[2]
CASES = {
    "crash": (["--scenario", "crash", "--once"], REPO / "daemon" / "demo.toml"),
    "part": (["--scenario", "part-program", "--parts", "3", "--broken-flute", "2:11"], REPO / "config" / "part-program.toml"),
}


class _Out(io.BytesIO):
    def write(self, text):  # Replay writes str lines
        return super().write(text.encode())


def _lines(settings, data: bytes, chunk: int) -> list[dict]:
    out = _Out()
    replay = Replay(settings, out)
    for a in range(0, len(data), chunk):
        replay.feed(data[a : a + chunk])
    return [json.loads(line) for line in out.getvalue().decode().splitlines() if line.strip()]


@pytest.mark.parametrize("case", sorted(CASES))
def test_joined_blocks_give_what_small_ones_give(tmp_path: Path, case: str):
    args, config = CASES[case]
    cap = tmp_path / f"{case}.cap"
    captures.sim(*args, "--capture", cap, "--fast", "--seed", "1")
    data = cap.read_bytes()
    settings = load_config(config)
    whole = _lines(settings, data, len(data))
    small = _lines(settings, data, 256)   # a chunk holds about one 10-sample frame
    kinds = {line["type"] for line in whole}
    assert "estimate" in kinds and "alarm" in kinds, kinds
    if case == "part":
        assert "process" in kinds
    assert_same_lines(small, whole, "whole against 256-byte chunks")
