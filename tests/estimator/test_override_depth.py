"""The CNC's applied feed override (STATUS) enters the feed per tooth and the depth of cut.

The sim's plant cuts the `afc-step` scenario at a 120 % override (its feed servo
follows the programmed feed times the override); the capture carries what a
version-2 DAQ sends: a STATUS with the applied override (1200 tenths) before
the samples. `millsense replay` (the same `PipelineCore` as the live daemon,
`on_status`) must read the depth the plant cut, with the configured feed of
200 mm/min: without the override the feed per tooth reads 1/1.2 of the real
one and the depth from torque ~11 % high (torque ~ a·t^(1+p), [D] eq. 8).
"""

from __future__ import annotations

import io
import json
from dataclasses import replace

import pytest
from hypothesis import given
from hypothesis import strategies as st

from millsense.daemon.commands.replay import Replay
from millsense.daemon.pipeline.override_track import OverrideTrack
from millsense.drivers.protocol import CAP_FEED_OVERRIDE, Status, encode_descriptor, encode_sample_frames, encode_status
from millsense.sim.plant import Plant

from . import simcase

pytestmark = pytest.mark.quick

SCENARIO = "afc-step"
OVERRIDE_PCT = 120.0
DURATION_S = 16.0   # the 2 mm step (25 mm at 240 mm/min: 6.25 s) and most of the 3 mm one


class _Bytes(io.BytesIO):
    """Replay writes str lines; keep them."""

    def write(self, s):  # type: ignore[override]
        return super().write(s.encode() if isinstance(s, str) else s)


@pytest.fixture(scope="module")
def run_120(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("ovr")
    plant = Plant(SCENARIO, seed=3)
    plant.feed_override_pct = OVERRIDE_PCT
    descriptor = replace(plant.descriptor, protocol_version=2, capabilities=CAP_FEED_OVERRIDE)
    total = round(DURATION_S * plant.sample_rate_hz)
    data = bytearray(encode_descriptor(descriptor))
    data += encode_status(Status(0, 0, 0, feed_override=round(OVERRIDE_PCT * 10)))
    done = 0
    while done < total:
        n = min(1000, total - done)
        data += encode_sample_frames(done, plant.step(n), per_frame=10)
        done += n
    truth_path = tmp / "truth.jsonl"
    plant.truth.write_jsonl(truth_path)
    settings = simcase.settings_for(SCENARIO, tmp, method="torque-only")
    assert settings.cut.feed_mm_min == 200.0   # the programmed feed, not the one cut
    out = _Bytes()
    replay = Replay(settings, out)
    replay.feed(bytes(data))
    lines = [json.loads(line) for line in out.getvalue().decode().splitlines() if line.strip()]
    estimates = [e for e in lines if e["type"] == "estimate"]
    truth = simcase.read_truth(truth_path)
    return estimates, truth


def test_every_estimate_carries_the_applied_override(run_120):
    estimates, truth = run_120
    assert len(estimates) > 50
    assert {e["feed_override_pct"] for e in estimates} == {OVERRIDE_PCT}
    cutting = [t for t in truth if t["cutting"]]
    # the plant did cut at 120 % of the programmed feed (the test's premise)
    assert max(t["feed_override_pct"] for t in cutting) == pytest.approx(OVERRIDE_PCT)


def test_depth_with_the_override_matches_what_was_cut(run_120):
    estimates, truth = run_120
    ok = simcase.settled(truth, SCENARIO)
    pairs = [(e, t) for e, t in simcase.match(_with_seq(estimates),
                                              truth, 1) if t["rev"] in ok and e["valid"]]
    assert len(pairs) >= 12, len(pairs)   # settled: a tool radius from any step or edge
    for e, t in pairs:
        assert e["feed_per_tooth_mm"] == pytest.approx(t["feed_per_tooth_mm"], rel=0.02), (e, t)
        assert e["depth_status"] == "ok", (e, t)
        assert e["axial_depth_mm"] == pytest.approx(t["axial_depth_mm"], rel=0.05), (e, t)


def _with_seq(estimates):
    """Replay's `t` is seconds since the first sample at 1 kHz: back to the sample index (seq_end)."""
    return [dict(e, seq_end=round(e["t"] * 1000.0)) for e in estimates]


# -- the step function itself ------------------------------------------------------------------------

def test_override_track_time_weighted_mean():
    track = OverrideTrack()
    assert track.mean(0, 99) == 100.0 and not track.reported
    track.note(50, 120.0)
    assert track.reported
    assert track.mean(0, 99) == pytest.approx(110.0)        # half at 100, half at 120
    assert track.mean(100, 199) == 120.0
    track.note(150, 120.0)                                    # repeated value: no step
    track.note(175, 80.0)
    assert track.mean(100, 199) == pytest.approx((75 * 120.0 + 25 * 80.0) / 100)
    track.forget_before(180)
    assert track.at(180) == 80.0 and track.mean(180, 279) == 80.0


@given(steps=st.lists(st.tuples(st.integers(0, 2000), st.sampled_from([50.0, 80.0, 100.0, 120.0, 150.0])), max_size=6),
       spans=st.lists(st.integers(1, 300), min_size=1, max_size=12), start=st.integers(0, 1500))
def test_the_overrides_of_a_batch_of_revolutions_are_each_ones_mean(steps, spans, start):
    """`means` (one call for the revolutions a block closed, with its shortcut when no step falls inside
    them) gives what `mean` gives for each revolution."""
    track = OverrideTrack()
    for seq, pct in sorted(steps):
        track.note(seq, pct)
    firsts, lasts, first = [], [], start
    for n in spans:   # consecutive revolutions, as the estimator closes them
        firsts.append(first)
        lasts.append(first + n - 1)
        first += n
    assert track.means(firsts, lasts) == [track.mean(a, b) for a, b in zip(firsts, lasts)]
