"""The feed hold through the DAQ (test-trip) and the DAQ's watchdog, timed, on the bench.

Why not the running daemon's `test-trip`: the daemon must not run while `commission` does (two masters on one
DAQ fight over the hold and the watchdog), and the watchdog step must stop the heartbeats, which a running
daemon would never let a client do. So both steps drive the daemon's own `Interlock` (the same trip, the same
write, the same reset) on the bench, and time the confirmations as `OperatorControls.test_trip` does (`wait_ms`).
"""

from __future__ import annotations

import time
from typing import Any

from millsense.daemon.commission.bench import Bench
from millsense.daemon.commission.report import Step
from millsense.daemon.runtime.interlock import TEST_TRIP
from millsense.daemon.controls import TEST_TRIP_WAIT_S
from millsense.daemon.runtime.interlock import wait_ms
from millsense.drivers.protocol import CAP_CONTEXT

WATCHDOG_SLACK_MS = 500.0   # beyond the watchdog period: the STATUS's way back and the host's scheduling


def _cnc_reports(driver: Any) -> bool:
    return bool(int(getattr(driver.descriptor, "capabilities", 0) or 0) & CAP_CONTEXT)


def trip_step(bench: Bench, say) -> Step:
    """Assert the feed hold as a trip does, time the DAQ's STATUS (and the CNC's "feed held"), release it."""
    step = Step("test-trip", "the DAQ shows the feed hold (and the CNC reports it held, protocol 2) "
                             f"within {TEST_TRIP_WAIT_S:g} s")
    drv, il = bench.driver, bench.interlock
    if not il.enabled:
        step.fail("the interlock is disabled in the configuration: no feed hold is ever written",
                  "interlock.enabled = true")
        return step
    cnc = _cnc_reports(drv)
    before_status, before_ctx = drv.last_status, drv.last_context
    say("  asserting the feed hold (test-trip) ...")
    t0 = time.monotonic()
    written = il.trip(TEST_TRIP)
    daq_ms = wait_ms(lambda: drv.last_status is not before_status and bool(drv.last_status.feed_hold), t0,
                      TEST_TRIP_WAIT_S)
    cnc_ms = wait_ms(lambda: drv.last_context is not before_ctx and bool(drv.last_context.feed_held), t0,
                      TEST_TRIP_WAIT_S) if cnc else None
    step.figures.update(written=written == "feed_hold", daq_confirm_ms=daq_ms, cnc_reports_hold=cnc,
                        cnc_confirm_ms=cnc_ms)
    if written != "feed_hold":
        step.fail("the DAQ did not take the feed-hold command", "check the DAQ's link and that it accepts "
                  "SET_OUTPUTS (docs/protocol.md)")
    elif daq_ms is None:
        step.fail(f"the DAQ's STATUS did not show the feed hold within {TEST_TRIP_WAIT_S:g} s",
                  "the DAQ does not report its output: check its firmware against docs/protocol.md, STATUS")
    elif cnc and cnc_ms is None:
        step.fail(f"the CNC did not report the feed held within {TEST_TRIP_WAIT_S:g} s",
                  "wire the DAQ's feed-hold output to the CNC's feed-hold input, and the CNC's 'feed held' "
                  "signal back to the DAQ (docs/interlock.md)")
    if step.problems:
        say("  the feed hold stays asserted: the test failed (`millsense reset` clears it once the daemon runs)")
        return step
    released = il.reset()
    step.figures["released"] = bool(released.get("ok"))
    say(f"  DAQ shows the hold after {daq_ms:.1f} ms" + (f", the CNC after {cnc_ms:.1f} ms" if cnc else
                                                          " (the CNC's confirmation: not reported, protocol 1)"))
    say("  feed hold released again: this step set it" if released.get("ok") else
        "  the release was not taken: the feed stays held (`millsense reset` clears it once the daemon runs)")
    return step


def watchdog_step(bench: Bench, say) -> Step:
    """Stop the heartbeats; the DAQ must hold the feed by itself within its watchdog period."""
    il, drv = bench.interlock, bench.driver
    limit_ms = il.watchdog_ms + WATCHDOG_SLACK_MS
    step = Step("watchdog", f"with the heartbeats stopped the DAQ holds the feed within interlock.watchdog_ms "
                            f"({il.watchdog_ms} ms) + {WATCHDOG_SLACK_MS:g} ms")
    if not il.enabled or not il.watchdog_ms:
        step.fail("the interlock is disabled in the configuration: no heartbeat feeds the DAQ's watchdog",
                  "interlock.enabled = true")
        return step
    say(f"  heartbeats stopped; waiting for the DAQ's watchdog ({il.watchdog_ms} ms) ...")
    before = drv.last_status
    last_beat = bench.stop_beats()

    def held() -> bool:
        st = drv.last_status
        return st is not None and st is not before and bool(st.feed_hold) and bool(st.watchdog_tripped)

    wait_s = 2.0 * limit_ms / 1000.0 + 1.0
    seen_ms = wait_ms(held, last_beat, wait_s)
    step.figures.update(watchdog_ms=il.watchdog_ms, hold_after_ms=seen_ms, waited_ms=round(wait_s * 1000.0))
    if seen_ms is None:
        step.fail(f"the DAQ did not hold the feed within {wait_s:g} s of the last heartbeat (no STATUS with "
                  "watchdog_tripped and feed_hold)",
                  f"enable the DAQ's watchdog at {il.watchdog_ms} ms (stream DAQs: a device setting; Modbus: the "
                  "daemon writes holding register 101) or repair it: without it a hung daemon never stops the feed")
    elif seen_ms > limit_ms:
        step.fail(f"the DAQ held the feed {seen_ms:.0f} ms after the last heartbeat, later than {limit_ms:g} ms",
                  f"set the DAQ's watchdog period to interlock.watchdog_ms = {il.watchdog_ms} ms")
    else:
        say(f"  the DAQ held the feed {seen_ms:.0f} ms after the last heartbeat")
    bench.resume_beats()   # first: a release with the heartbeat still stopped would trip again at once
    if seen_ms is not None:
        released = il.reset()
        step.figures["released"] = bool(released.get("ok"))
        say("  feed hold released again: this step's watchdog trip set it" if released.get("ok") else
            "  the release was not taken: the feed stays held (`millsense reset` clears it once the daemon runs)")
    return step
