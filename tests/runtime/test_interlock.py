"""Interlock policy: latch, heartbeats, start policy, and the reset's condition check.

Who may reset is decided before the interlock is asked (publish/command_auth.py,
the local control socket): tests/publish and tests/runtime/test_latch.py.

The DAQ side here is a recorder of the three output calls (the interface the
interlock drives); the real emulator on TCP is exercised in tests/e2e.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest

from millsense.daemon.runtime.interlock import TEST_TRIP, Interlock, ResetCheck

pytestmark = pytest.mark.quick


class Outputs:
    def __init__(self, fail: bool = False, hold: bool = False):
        self.calls: list[tuple] = []
        self.fail = fail
        self.last_status = SimpleNamespace(feed_hold=hold, watchdog_tripped=hold)

    def set_outputs(self, feed_hold, alarm_lamp=False):
        if self.fail:
            raise ConnectionError("link down")
        self.calls.append(("outputs", feed_hold, alarm_lamp))

    def heartbeat(self):
        self.calls.append(("heartbeat",))

    def set_watchdog_ms(self, ms):
        self.calls.append(("watchdog", ms))


def cfg(**kw):
    base = dict(enabled=True, heartbeat_ms=100, watchdog_ms=500, reset="open", reset_token="")
    base.update(kw)
    return SimpleNamespace(**base)


def test_disabled_interlock_never_touches_the_daq():
    out = Outputs()
    il = Interlock(out, cfg(enabled=False))
    il.start()
    assert il.trip("overload") is None
    il.beat(True)
    assert il.reset()["ok"] is True
    assert out.calls == [] and il.state == "disabled"


def test_trip_latches_and_writes_once():
    out = Outputs()
    il = Interlock(out, cfg())
    il.start()
    assert out.calls == [("watchdog", 500)]  # start writes no output
    assert il.trip("torque overload") == "feed_hold"
    assert il.trip("again") == "feed_hold"
    assert out.calls[1:] == [("outputs", True, True)]
    assert il.state == "feed_hold" and il.reason == "torque overload"
    r = il.reset()
    assert r["ok"] is True and r["interlock"] == "armed"
    assert out.calls[-1] == ("outputs", False, False)


def test_reset_takes_no_payload_and_has_no_authority_inside():
    il = Interlock(Outputs(), cfg(reset="off"))
    il.trip("x")
    # the policy is reported, not enforced here: the caller authorised the request
    r = il.reset()
    assert r["ok"] is True and r["reset"] == "off" and il.state == "armed"
    assert not hasattr(il, "authorise")


def test_every_latch_change_is_handed_to_the_store_with_its_time():
    seen = []
    il = Interlock(Outputs(), cfg(), on_change=seen.append)
    il.trip("overload torque_nm 35 > 30")
    assert seen[-1]["latched"] is True and seen[-1]["reason"].startswith("overload") and seen[-1]["trips"] == 1
    assert seen[-1]["since"] is not None
    il.trip("again")  # already latched: nothing new to keep
    assert len(seen) == 1
    il.reset()
    assert seen[-1] == {"latched": False, "reason": None, "since": None, "trips": 1}


def test_a_persisting_store_failure_never_stops_the_trip():
    def broken(_record):
        raise OSError("read-only file system")

    out = Outputs()
    il = Interlock(out, cfg(), on_change=broken)
    assert il.trip("crash") == "feed_hold"
    assert out.calls == [("outputs", True, True)]


def test_restore_latches_again_with_the_original_reason_and_time():
    seen = []
    out = Outputs()
    il = Interlock(out, cfg(), on_change=seen.append)
    il.restore("overload p_gap_w 900 > 500", 1700000000.0, trips=3)
    assert il.state == "feed_hold" and il.since == 1700000000.0 and il.trips == 3
    assert out.calls == [("outputs", True, True)] and seen == []  # not a new trip


def test_a_real_trip_during_a_test_trip_takes_over_the_reason():
    il = Interlock(Outputs(), cfg())
    il.trip(TEST_TRIP)
    il.trip("crash p_gap_w 20000 > 15000")
    assert il.reason.startswith("crash")


def test_heartbeats_only_while_healthy():
    out = Outputs()
    il = Interlock(out, cfg())
    il.beat(True)
    il.beat(True)
    il.beat(False)
    il.beat(False)
    assert out.calls.count(("heartbeat",)) == 2 and il.heartbeating is False
    il.beat(True)
    assert out.calls.count(("heartbeat",)) == 3 and il.heartbeating is True


def test_a_hold_found_at_start_is_left_alone_until_reset():
    out = Outputs(hold=True)
    il = Interlock(out, cfg())
    il.start()
    assert il.state == "held_by_device"
    assert not any(c[0] == "outputs" for c in out.calls)
    assert il.reset()["interlock"] == "armed"
    assert out.calls[-1] == ("outputs", False, False)


def test_failed_write_keeps_the_latch_and_is_reasserted():
    out = Outputs(fail=True)
    il = Interlock(out, cfg())
    assert il.trip("crash") is None  # not asserted by us: the payload must not claim it
    assert il.state == "feed_hold" and il.write_errors == 1
    out.fail = False
    il.reassert()
    assert out.calls == [("outputs", True, True)]


# -- the reset's condition check: only data newer than the hold count -------------------------

def rev(rev_no, seq_end, valid=True, samples=100, **kw):
    return {"rev": rev_no, "seq_end": seq_end, "samples": samples, "lost_samples": 0, "valid": valid, **kw}


def check(**limits):
    c = ResetCheck(limits.get("crash_power_w"), limits.get("crash_current_a"))
    c.mark(999)  # the hold began after sample 999
    return c


def refused(c, reason="overload", blind=None, daq=None):
    r = c.refusal(reason, blind or {}, daq)
    return None if r is None else r["condition"]


def test_the_revolution_that_tripped_is_not_news():
    c = check()
    c.on_block(1000, {}, False, False)
    c.on_estimate(rev(10, 1050), ["torque_nm"])  # samples 951..1050: began before the hold
    assert refused(c) == "no_revolution"
    c.on_estimate(rev(11, 1150), ["torque_nm"])
    assert refused(c) == "overload"
    c.on_estimate(rev(12, 1250), [])
    assert refused(c) is None


def test_an_invalid_revolution_is_no_evidence_but_a_saturated_one_is_over():
    c = check()
    c.on_block(1000, {}, False, False)
    c.on_estimate(rev(11, 1150), [])
    c.on_estimate(rev(12, 1250, valid=False), [])
    assert refused(c) is None  # the latest *valid* revolution decides
    c.on_estimate(rev(13, 1350, valid=False, saturated=True), [])
    assert refused(c) == "overload"


@pytest.mark.parametrize("stopped", [False, True])
def test_sample_level_peaks_and_stall_of_the_latest_block(stopped):
    # the same with the spindle standing still: a crash's current outlasts the turning, and a jammed spindle
    # stands still at its stall current (before stop 24 a stopped block was the condition gone, peaks or not)
    c = check(crash_power_w=15000.0, crash_current_a=60.0)
    c.on_block(1000, {"p_gap_w": 16000.0, "current_a": 10.0}, False, stopped)
    c.on_estimate(rev(11, 1150), [])
    assert refused(c) == "crash"
    c.on_block(1010, {"p_gap_w": 900.0, "current_a": 61.0}, False, stopped)
    assert refused(c) == "crash"
    c.on_block(1020, {"p_gap_w": 900.0, "current_a": 12.0}, True, stopped)
    assert refused(c) == "stall"
    c.on_block(1030, {"p_gap_w": 900.0, "current_a": 12.0}, False, stopped)
    assert refused(c) is None
    # a current clipped at its sensor's limit while high is reported as inf: beyond any limit, not "no number"
    c.on_block(1040, {"p_gap_w": 900.0, "current_a": float("inf")}, False, stopped)
    assert refused(c) == "crash"


@pytest.mark.parametrize("stopped", [False, True])
@pytest.mark.parametrize("peak, limit", [("p_gap_w", 15000.0), ("current_a", 60.0)])
def test_a_peak_exactly_at_a_crash_limit_refuses_the_reset_and_just_below_allows_it(stopped, peak, limit):
    """Rule 5 is "at or over" (docs/interlock.md: a reset needs the latest block *under* the limit): exactly
    the limit is not under it. The test above uses 61 A against 60 A, which a `>` passes just as well."""
    quiet = {"p_gap_w": 900.0, "current_a": 12.0}
    c = check(crash_power_w=15000.0, crash_current_a=60.0)
    c.on_block(1000, {**quiet, peak: limit}, False, stopped)
    c.on_estimate(rev(11, 1150), [])
    assert refused(c) == "crash", f"{peak} exactly at its crash limit {limit:g} let the reset through"
    c.on_block(1010, {**quiet, peak: math.nextafter(limit, 0.0)}, False, stopped)
    assert refused(c) is None, f"{peak} just under its crash limit {limit:g} still refused the reset"
    c.on_block(1020, {**quiet, peak: limit}, False, stopped)  # the latest block decides, both ways
    assert refused(c) == "crash"


def test_a_block_from_before_the_hold_counts_for_nothing():
    c = check(crash_power_w=15000.0)
    c.on_block(990, {"p_gap_w": 20000.0}, True, False)
    assert c.blocks == 0 and refused(c) == "no_data"


def test_the_last_sample_before_the_hold_is_not_news_and_the_first_after_it_is():
    """`mark(999)`: sample 999 was processed before the hold. A block beginning there is old evidence (what
    tripped), one beginning at 1000 is the first after the hold (the boundary `test_a_block_from_before_the_hold`
    leaves 9 samples away from)."""
    c = check(crash_power_w=15000.0)
    c.on_block(999, {"p_gap_w": 900.0}, False, True)
    assert c.blocks == 0 and refused(c) == "no_data"
    c.on_block(1000, {"p_gap_w": 900.0}, False, True)
    assert c.blocks == 1 and refused(c) is None


def test_a_spindle_stopped_since_the_hold_is_the_condition_gone():
    c = check(crash_power_w=15000.0)
    c.on_block(1000, {"p_gap_w": 20000.0}, False, False)
    c.on_estimate(rev(11, 1150), ["torque_nm"])
    assert refused(c) == "crash"
    c.on_block(1200, {}, False, True)
    assert refused(c) is None
    # turning again: a new over-limit revolution is a condition again
    c.on_block(1300, {"p_gap_w": 500.0}, False, False)
    assert refused(c) is None
    c.on_estimate(rev(12, 1450), ["p_gap_w"])
    assert refused(c) == "overload"


def test_blind_or_no_data_refuses_and_a_test_trip_needs_no_revolution():
    c = check()
    assert refused(c) == "no_data"
    assert refused(c, reason=TEST_TRIP) is None
    c.on_block(1000, {}, False, False)
    assert refused(c, blind={"signals": "i_u pinned at 32767"}) == "blind"
    assert refused(c, reason=TEST_TRIP, daq="daq_link: down") == "no_data"
    assert refused(c, reason=TEST_TRIP) is None
    c.on_estimate(rev(11, 1150), ["torque_nm"])
    assert refused(c, reason=TEST_TRIP) == "overload"  # a real condition since: not granted either
