"""Sample-level trips (pipeline/safety_check.py): stall, crash current, clipped current, per block.

A spindle that stops under load closes no revolution and its power falls with
its speed: only the current tells. The blocks here are what the estimator
hands over (smoothed per-sample power and largest line current, the
revolutions that closed); time is in samples.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from millsense.daemon.pipeline.alarms import AlarmEngine
from millsense.daemon.pipeline.safety_check import SafetyCheck

pytestmark = pytest.mark.quick

RATE = 1000.0
BLOCK = 10


def alarms(**limits):
    base = dict.fromkeys(("torque_warn_nm", "torque_limit_nm", "force_warn_n", "force_limit_n", "power_warn_w",
                          "power_limit_w", "crash_power_w", "breakage_drop_pct", "crash_current_a",
                          "stall_current_a"))
    base.update(revolutions=2, hysteresis_pct=10.0, breakage_min_torque_nm=1.0)
    base.update(limits)
    return SimpleNamespace(**base)


def stream(current_a, rev_ends, stopped_from=None, clip_at=None):
    """Blocks of BLOCK samples: current per sample, revolutions closing at the given sample indices."""
    current_a = np.asarray(current_a, float)
    ends = sorted(rev_ends)
    last_end = None
    for seq in range(0, len(current_a), BLOCK):
        closing = [e for e in ends if seq <= e < seq + BLOCK]
        estimates = []
        for e in closing:
            samples = e - last_end if last_end is not None else 100
            estimates.append({"rev": len(estimates), "seq_end": e, "samples": samples, "lost_samples": 0})
            last_end = e
        clip = clip_at if clip_at is not None and seq <= clip_at < seq + BLOCK else None
        yield SimpleNamespace(seq=seq, p_gap_w=np.full(BLOCK, 500.0), current_a=current_a[seq : seq + BLOCK],
                              estimates=estimates, clip_seq=clip,
                              spindle_stopped=stopped_from is not None and seq >= stopped_from)


def run(settings, blocks):
    engine = AlarmEngine(settings)
    check = SafetyCheck(settings, RATE)
    events, stalled, peaks = [], [], []
    for res in blocks:
        out = check.on_block(res, engine)
        events += out.events
        stalled.append((res.seq, out.stalled))
        peaks.append(out.peaks)
    return events, stalled, peaks, engine


def test_a_spindle_stopping_under_load_trips_within_twice_its_last_period():
    # 600 rpm (100 samples a revolution) at 30 A, then the spindle stops at sample 1000 with the current held
    current = np.full(3000, 30.0)
    events, stalled, _, engine = run(alarms(stall_current_a=20.0), stream(current, range(99, 1000, 100),
                                                                           stopped_from=1050))
    assert [(e.level, e.quantity, e.limit) for e in events] == [("crash", "stall", 20.0)]
    # last revolution closed at 999: no close by 999 + 2·100 trips
    assert 1199 <= events[0].seq <= 1199 + BLOCK
    assert not any(s for seq, s in stalled if seq < 1190) and stalled[-1][1]
    assert engine.crash_latched and engine.active()["crash"] == "crash"
    assert [(e.level, e.quantity) for e in engine.reset()] == [("clear", "stall")]


def test_revolutions_closing_or_the_current_low_is_no_stall():
    current = np.full(3000, 30.0)
    events, stalled, *_ = run(alarms(stall_current_a=20.0), stream(current, range(99, 3000, 100)))
    assert not events and not any(s for _, s in stalled)
    # the spindle coasts to a stop with the drive's current below the limit: no stall
    low = np.concatenate([np.full(1000, 30.0), np.full(2000, 5.0)])
    events, stalled, *_ = run(alarms(stall_current_a=20.0), stream(low, range(99, 1000, 100), stopped_from=1100))
    assert not events


def test_a_start_from_standstill_under_high_current_is_no_stall():
    # stopped with the current low for 1 s, then a run-up at 40 A whose first revolution closes 0.6 s later
    current = np.concatenate([np.full(1000, 2.0), np.full(2000, 40.0)])
    ends = [99, 199, 299, 399] + list(range(1600, 3000, 100))
    events, *_ = run(alarms(stall_current_a=20.0), _start(current, ends))
    assert not events


def _start(current, ends):
    for res in stream(current, ends):
        res.spindle_stopped = 400 <= res.seq < 1000   # stood still after the first revolutions
        yield res


def test_crash_current_and_a_clipped_current_trip_at_once():
    current = np.concatenate([np.full(500, 30.0), np.full(500, 90.0)])
    events, _, peaks, _ = run(alarms(crash_current_a=80.0), stream(current, range(99, 1000, 100)))
    assert [(e.quantity, e.seq) for e in events] == [("current_a", 500)]
    assert max(p["current_a"] for p in peaks) == 90.0
    # a sample at its ADC limit while the current was high: over any limit, whatever it reads
    events, _, peaks, _ = run(alarms(crash_current_a=500.0), stream(np.full(1000, 60.0), [], clip_at=321))
    assert [(e.quantity, e.seq, e.limit) for e in events] == [("current_a", 321, 500.0)]
    assert peaks[32]["current_a"] == float("inf") and peaks[31]["current_a"] == 60.0


def test_nothing_armed_nothing_trips_but_peaks_are_filled():
    events, stalled, peaks, _ = run(alarms(), stream(np.full(1000, 90.0), [], clip_at=321))
    assert not events and not any(s for _, s in stalled)
    assert all(set(p) == {"p_gap_w", "current_a"} for p in peaks) and peaks[0]["p_gap_w"] == 500.0
