"""Live time of samples and latency percentiles."""

from __future__ import annotations

import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from millsense.daemon.runtime.status import LatencyStats, SeqClock, bad_frames, interlock_detail, percentile
from millsense.daemon.status_text import hold_of, status_line, summary_line
from millsense.drivers.protocol import OUT_FEED_HOLD, Status

pytestmark = pytest.mark.quick


def test_seq_clock_uses_the_least_delayed_block():
    rate = 1000.0
    c = SeqClock(rate)
    t0 = 1_700_000_000.0  # Unix time of sample 0
    assert c.time_of(0) is None
    # Blocks of 10 samples, each arriving 1..9 ms after its last sample was taken.
    delays = [0.009, 0.001, 0.005, 0.003]
    for k, d in enumerate(delays):
        c.note_block(10 * k, 10, t0 + (10 * k + 9) / rate + d)
    assert abs(c.time_of(123) - (t0 + 0.123 + 0.001)) < 1e-9


def test_seq_clock_forgets_old_blocks_and_restarts():
    c = SeqClock(1000.0, window_s=1.0)
    c.note_block(0, 10, 100.009 - 0.008)  # fast block, offset 100.0 - 0.008
    c.note_block(5000, 10, 105.009)  # 5 s later, delay 0
    assert abs(c.time_of(5009) - 105.009) < 1e-9
    c.note_block(10, 10, 50.0, restart=True)
    assert abs(c.time_of(19) - 50.0) < 1e-9


@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(0.0, 0.02), min_size=1, max_size=50))
def test_seq_clock_is_never_later_than_any_observed_arrival(delays):
    c = SeqClock(1000.0, window_s=1e9)
    t0 = 1000.0
    for k, d in enumerate(delays):
        c.note_block(10 * k, 10, t0 + (10 * k + 9) / 1000.0 + d)
    for k, d in enumerate(delays):
        t = c.time_of(10 * k + 9)
        assert t <= t0 + (10 * k + 9) / 1000.0 + d + 1e-9
        assert abs(t - (t0 + (10 * k + 9) / 1000.0 + min(delays))) < 1e-9


def test_latency_percentiles():
    s = LatencyStats(size=1000)
    assert s.percentiles_ms() == {"p50": None, "p99": None, "max": None, "n": 0}
    values = np.linspace(0.0, 0.01, 1001)  # 0..10 ms; the first value falls out of the ring
    for v in values:
        s.add(float(v))
    got = s.percentiles_ms()
    assert got["n"] == 1000
    assert abs(got["p50"] - np.percentile(values[1:], 50) * 1e3) < 1e-3
    assert abs(got["max"] - 10.0) < 1e-9


@settings(max_examples=300, deadline=None)
@given(st.lists(st.floats(0.0, 1.0, allow_nan=False), min_size=1, max_size=60), st.floats(0.0, 100.0))
def test_the_percentile_is_numpys_linear_one(values, q):
    ordered = sorted(values)
    assert abs(percentile(ordered, q) - float(np.percentile(values, q))) <= 1e-12


def test_lines_tolerate_missing_values():
    assert "–" in summary_line(None, "ok", {})
    line = summary_line({"rev": 5, "spindle_rpm": 600.0, "torque_nm": 4.2, "force_n": None}, "warning", {"state": "running"})
    assert "600 rpm" in line and "4.20" in line and "warning" in line
    assert "running" in status_line({"state": "running", "latency_ms": {"p99": 0.5}})
    assert "speeding up" not in line
    assert summary_line({"rev": 6, "accelerating": True}, "ok", {}).endswith("(speeding up)")
    assert "Zenoh 0 routers, 2 peers" in status_line({"state": "running", "sink": {"zenoh_routers": 0, "zenoh_peers": 2}})


def test_the_live_line_says_feed_held_why_and_since_until_the_daq_confirms_the_release():
    """Issue 36, finding 7 on the live line: after the alarm cleared (alarm `ok`), the held feed still reads as held."""
    since = 1_795_324_800.0
    at = time.strftime("%H:%M:%S", time.localtime(since))
    est = {"rev": 9, "spindle_rpm": 0.0}
    held = {"state": "running", "interlock": "feed_hold",
            "interlock_detail": {"reason": "overload torque_nm 9.3 > 9.0", "since": since, "daq_feed_hold": True}}
    line = summary_line(est, "ok", held)
    assert f"alarm ok        feed held: overload torque_nm 9.3 > 9.0, since {at}  rev" in line, line
    device = {"state": "running", "interlock": "held_by_device",
              "interlock_detail": {"reason": None, "since": None, "watchdog_tripped": True, "daq_feed_hold": True}}
    assert "feed held: by the DAQ, not set by this run (its watchdog tripped)  rev" in summary_line(est, "ok", device)
    releasing = {"state": "running", "interlock": "armed", "interlock_detail": {"daq_feed_hold": True}}
    assert "feed held: release not yet confirmed by the DAQ" in summary_line(est, "ok", releasing)
    released = {"state": "running", "interlock": "armed", "interlock_detail": {"daq_feed_hold": False}}
    assert "feed held" not in summary_line(est, "ok", released)
    assert hold_of(released) is None and hold_of({"interlock": "armed"}) is None


def test_interlock_detail_adds_what_the_daqs_last_status_says():
    class Interlock:
        def state_dict(self):
            return {"interlock": "armed", "reason": None}

    class Driver:
        last_status = None

    assert interlock_detail(Interlock(), Driver()) == {"interlock": "armed", "reason": None, "daq_feed_hold": None}
    Driver.last_status = Status(outputs=OUT_FEED_HOLD, flags=0, last_heartbeat=0)
    assert interlock_detail(Interlock(), Driver())["daq_feed_hold"] is True
    Driver.last_status = Status(outputs=0, flags=0, last_heartbeat=0)
    assert interlock_detail(Interlock(), Driver())["daq_feed_hold"] is False


def test_bad_frames_counts_decoder_refusals():
    assert bad_frames({"decoder_bad_crc": 3, "decoder_bad_length": 1, "decoder_frames": 100, "samples": 5}) == 4
    assert bad_frames({}) == 0


def test_crash_rev_is_the_revolution_in_progress_at_the_crossing():
    from millsense.daemon.pipeline.run_core import _rev_at_seq

    ests = [{"rev": 79, "seq_end": 8100}, {"rev": 80, "seq_end": 8200}, {"rev": 81, "seq_end": 8300}]
    assert _rev_at_seq(8229, 78, ests) == 81  # revs 79, 80 closed before it, 81 was open
    assert _rev_at_seq(8050, 78, ests) == 79
    assert _rev_at_seq(8050, None, []) is None
