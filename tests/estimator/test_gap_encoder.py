"""A gap in the samples longer than the encoder channel's wrap must not read as a wrong speed.

The DAQ's encoder channel is int16: it wraps every 65536 counts, 16 revolutions of
the simulated 4096-count encoder (1.6 s at 600 rpm, 0.53 s at 1800 rpm). Across a
longer gap the unwrapped count is off by whole wraps, so a speed taken over a
window that spans the gap is wrong by any amount. It was: the revolution after a
1.2 s gap was judged `"invalid": "signals"` (speed channel against encoder), and
live the same windows raised the `signals` fault, which holds the feed
(found under load by tests/faults/test_link.py, where a flapping link loses
a second at a time). The revolution spanning the gap is `lost_samples`; every
later one must be valid.
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest

from millsense.drivers.decoder import StreamDecoder
from millsense.drivers.protocol import Descriptor, Samples, encode_descriptor, encode_samples

from tests import captures
from tests.e2e.helpers import CMD

DEMO = Path(__file__).resolve().parents[2] / "daemon" / "demo.toml"
GAP_FROM = 12_000  # sample index where the gap starts: inside the cut


@pytest.fixture(scope="module", params=["step", "step-1800"])
def capture(request, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("gap")
    cap = tmp / "c.cap"
    captures.sim("--scenario", request.param, "--capture", cap, "--duration-s", "20")
    return request.param, cap


def _with_gap(cap: Path, out: Path, gap: int) -> Path:
    """The same frames with `gap` samples (whole 10-sample frames) left out from GAP_FROM on."""
    data = bytearray()
    for item in StreamDecoder().feed(cap.read_bytes()):
        if isinstance(item, Descriptor):
            data += encode_descriptor(item)
        elif isinstance(item, Samples):
            for k in range(0, len(item.counts), 10):
                index = item.first_index + k
                if not GAP_FROM <= index < GAP_FROM + gap:
                    data += encode_samples(index, item.counts[k : k + 10])
    out.write_bytes(bytes(data))
    return out


def _replay(cap: Path) -> list[dict]:
    p = subprocess.run(CMD + ["replay", "--config", str(DEMO), str(cap)], capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    return [json.loads(line) for line in p.stdout.splitlines() if line.strip()]


@pytest.mark.parametrize("gap", [20, 600, 1200, 2500])
def test_only_the_revolution_spanning_a_gap_is_invalid(capture, tmp_path, gap):
    scenario, cap = capture
    lines = _replay(_with_gap(cap, tmp_path / "gap.cap", gap))
    estimates = [x for x in lines if x.get("type") == "estimate"]  # t: the index time of its last sample, s
    invalid = [(x["rev"], x["invalid"]) for x in estimates if not x["valid"]]
    assert [why for _, why in invalid] == ["lost_samples"], (scenario, gap, invalid)
    # and the revolutions right after it read the speed they should
    after = [x for x in estimates if x["valid"] and x["t"] * 1000 > GAP_FROM + gap][:5]
    before = [x for x in estimates if x["valid"] and x["t"] * 1000 < GAP_FROM][-3:]
    assert len(after) == 5 and before
    rpm = sum(x["spindle_rpm"] for x in before) / len(before)
    for x in after:
        assert abs(x["spindle_rpm"] / rpm - 1.0) < 0.02, (scenario, gap, x["rev"], x["spindle_rpm"], rpm)
