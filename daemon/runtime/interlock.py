"""Feed hold on the DAQ: trip at once, latch until an explicit reset, heartbeat while healthy.

Why it is built this way:

- **At once, from the detecting thread.** `trip()` writes the output from the
  thread that found the condition: the driver's reader thread for a
  sample-level crash (the frame check), the estimator thread for an overload,
  breakage, stall or blindness; no queue or other thread sits between the
  decision and the DAQ. Both may call it: one lock keeps the latch, its
  persistence and the counters consistent (the first trip latches, a later
  one finds it latched).
- **Latching.** Once asserted, feed hold stays until `reset()` (the
  `cmd/reset` queryable, or the local control socket). The latch outlives a
  restart: the runner persists it (`latch_store.py`) and `restore()` asserts
  it again at the next start, with its original reason and time.
- **Fail-safe by silence.** At start the DAQ's watchdog is set to
  `watchdog_ms`; `beat()` sends heartbeats only while the caller says the
  pipeline is healthy. A daemon that hangs, dies or loses its samples stops
  beating and the DAQ stops the feed by itself (daq-protocol.md, Fail-safe).
- **Start policy.** With the interlock enabled the daemon never clears, on its
  own, a feed hold it did not set in this run: a hold found at start (latched
  by a previous run, by the DAQ's watchdog, or by someone else) is left
  asserted and reported as `held_by_device` (or, when the latch store kept
  it, latched again with its reason); only an explicit `reset` clears it. So a restart loop can never release a machine that was stopped for a
  reason.
- **Confirmed, or written again.** A write the DAQ did not take (link down, a
  Modbus exception response) is not reported as a hold: `trip()` says so, and
  while the latch is set the hold is written again every heartbeat period
  until the write succeeds and the DAQ's own status shows feed hold.
- **No authority here.** `reset()` clears the latch for whoever calls it:
  the caller has already decided that the request may be granted (the Zenoh
  queryable authorises it in `publish/command_auth.py`; the local control
  socket checks the peer's uid; `OperatorControls.reset` checks that the condition that
  latched is gone). `reset_policy` is kept only to be reported in the state.
- **Persisted by others.** `on_change` (if given) is called with the latch
  record after every change, from the changing thread, and must return at
  once (the latch store hands the write to its own thread): the trip never
  waits for a disk.

`outputs` is the driver (anything with `set_outputs(feed_hold, alarm_lamp)`,
`heartbeat()`, `set_watchdog_ms(ms)`).
"""

from __future__ import annotations

import threading
import time
from typing import Any, Callable

import structlog

log = structlog.get_logger("millsense.interlock")

RESET_POLICIES = ("open", "token", "off")
TEST_TRIP = "test-trip"  # the reason of a proof test's latch (`OperatorControls.test_trip`)


class Interlock:
    """The daemon's side of the feed-hold interlock. Thread-safe."""

    def __init__(self, outputs: Any, settings: Any, on_change: Callable[[dict[str, Any]], Any] | None = None):
        self._out = outputs
        self._on_change = on_change
        self.enabled = bool(getattr(settings, "enabled", False))
        self.heartbeat_ms = int(getattr(settings, "heartbeat_ms", 100) or 100)
        self.watchdog_ms = int(getattr(settings, "watchdog_ms", 500) or 0)
        policy = str(getattr(settings, "reset", "open") or "open")
        self.reset_policy = policy if policy in RESET_POLICIES else "off"
        self._lock = threading.Lock()
        self.latched = False  # feed hold asserted by this daemon in this run
        self.reason: str | None = None
        self.since: float | None = None  # Unix time the latch was set (kept across restarts by the latch store)
        self.device_hold = False  # last STATUS from the DAQ said feed hold is on
        # A hold the DAQ had that this run did not set (its watchdog, a previous run, someone else): kept until an
        # authorised reset, and written again to a DAQ that lost it (a restart, a power blip), as a latch is.
        self.device_hold_kept = False
        self._rewrite_said_mono = -1e9
        self.watchdog_tripped = False
        self.heartbeating = False
        self.heartbeats_sent = 0
        self.trips = 0
        self.write_errors = 0
        self.hold_writes = 0
        # the latched hold is not known to be on the DAQ: its write failed, or a
        # status newer than the write still says no feed hold
        self.hold_unconfirmed = False
        self._last_write_mono = 0.0
        self.hold_written_mono: float | None = None   # monotonic time the last new latch's hold was written

    # -- start ------------------------------------------------------------
    def start(self) -> None:
        """Arm the DAQ's watchdog. Never writes the outputs (start policy above)."""
        if not self.enabled:
            return
        if self.watchdog_ms > 0:
            self._out.set_watchdog_ms(self.watchdog_ms)
        status = getattr(self._out, "last_status", None)
        if status is not None:
            self.observe_status(status)
        if self.device_hold:
            log.warning(
                "interlock.hold_found_at_start",
                detail="feed hold is active on the DAQ and was not set by this run; left asserted (`millsense reset` clears it)",
            )

    # -- the trip ---------------------------------------------------------
    def trip(self, reason: str) -> str | None:
        """Assert feed hold now. Returns "feed_hold" if it is asserted by us, else None."""
        if not self.enabled:
            return None
        with self._lock:
            if self.latched:
                if self.reason == TEST_TRIP and reason != TEST_TRIP:
                    # a real condition during a proof test: the latch now stands for it
                    self.reason = reason
                    self._changed()
                return None if self.hold_unconfirmed else "feed_hold"
            self.latched = True
            self.reason = reason
            self.since = time.time()
            self.trips += 1
            ok = self._write(True)
            self.hold_written_mono = self._last_write_mono   # the trip's end, for its timing (not the log after it)
            self._changed()
        log.warning("interlock.feed_hold", reason=reason, written=ok)
        return "feed_hold" if ok else None

    def restore(self, reason: str, since: float | None, trips: int = 0) -> None:
        """A latch persisted by an earlier run: latch again and write the hold (the link is up or comes up).

        Not a new trip: `since` and the reason are the original ones, nothing is re-persisted.
        """
        if not self.enabled:
            return
        with self._lock:
            self.latched = True
            self.reason = reason
            self.since = since
            self.trips = max(self.trips, int(trips or 0))
            self._write(True)

    def record(self) -> dict[str, Any]:
        """The latch as the latch store keeps it."""
        return {"latched": self.latched, "reason": self.reason, "since": self.since, "trips": self.trips}

    def _changed(self) -> None:
        if self._on_change is None:
            return
        try:
            self._on_change(self.record())
        except Exception as exc:  # noqa: BLE001 - persistence must never stop a trip
            log.error("interlock.persist_failed", error=f"{type(exc).__name__}: {exc}")

    def reassert(self) -> None:
        """After a reconnect: the DAQ may have restarted; write the latched (or kept) hold again."""
        if self.enabled and (self.latched or self.device_hold_kept):
            with self._lock:
                self._write(True)

    # A status younger than this after a hold write may predate the write.
    CONFIRM_GRACE_S = 0.3

    def _write(self, hold: bool) -> bool:
        try:
            ok = self._out.set_outputs(hold, hold) is not False  # None: an output that does not say
        except Exception as exc:  # noqa: BLE001 - link down: the watchdog still holds the line
            ok, error = False, f"{type(exc).__name__}: {exc}"
        else:
            error = "the DAQ did not take the command (link down, or refused)"
        self._last_write_mono = time.monotonic()
        if hold:
            self.hold_writes += 1
            self.hold_unconfirmed = not ok
        if not ok:
            self.write_errors += 1
            log.error("interlock.write_failed", feed_hold=hold, error=error)
        return ok

    def _retry_hold(self) -> None:
        """While latched and not confirmed on the DAQ, write the hold again (heartbeat thread)."""
        with self._lock:
            if self.latched and self.hold_unconfirmed:
                if self._write(True):
                    log.warning("interlock.feed_hold_rewritten", reason=self.reason)

    # -- reset ------------------------------------------------------------
    def reset(self) -> dict[str, Any]:
        """Clear the latch and the DAQ's feed hold. The caller has authorised it and checked the condition."""
        with self._lock:
            was = self.latched or self.device_hold
            self.latched = False
            self.reason = None
            self.since = None
            self.hold_unconfirmed = False
            ok = self._write(False) if self.enabled else True
            if ok:
                self.device_hold = False
                self.device_hold_kept = False
                self.watchdog_tripped = False
            self._changed()
            # The state this reset left, read under its lock: a STATUS the DAQ sent before it took the release
            # may land right after (the reader thread's `observe_status`) and say held until the next one.
            result: dict[str, Any] = {"ok": ok, **self.state_dict()}
        log.info("interlock.reset", cleared=was, write_ok=ok)
        if not ok:
            result["error"] = "the DAQ did not take the command (link down?)"
        return result

    # -- heartbeats and device status --------------------------------------
    def beat(self, healthy: bool, stopping: bool = False) -> None:
        """Called every `heartbeat_ms`: a heartbeat only while the pipeline is healthy.

        `stopping`: the daemon is stopping on purpose; the heartbeats end as asked (info, not warning).
        """
        if not self.enabled:
            self.heartbeating = False
            return
        if self.latched and self.hold_unconfirmed:
            self._retry_hold()
        if not healthy:
            if self.heartbeating and stopping:
                log.info("interlock.heartbeats_stopped", asked=True,
                         detail="the daemon is stopping, as asked; the DAQ watchdog takes over")
            elif self.heartbeating:
                log.warning("interlock.heartbeats_stopped", detail="pipeline not healthy; the DAQ watchdog takes over")
            self.heartbeating = False
            return
        try:
            sent = self._out.heartbeat() is not False
            error = "the DAQ did not take the heartbeat (link down, or refused)"
        except Exception as exc:  # noqa: BLE001
            sent, error = False, str(exc)
        if not sent:
            if self.heartbeating:
                log.warning("interlock.heartbeat_failed", error=error)
            self.heartbeating = False
            self.write_errors += 1
            return
        if not self.heartbeating:
            log.info("interlock.heartbeats_started")
        self.heartbeating = True
        self.heartbeats_sent += 1

    def observe_status(self, status: Any) -> None:
        """A STATUS from the DAQ (outputs, watchdog flag)."""
        self.device_hold = bool(getattr(status, "feed_hold", False))
        self.watchdog_tripped = bool(getattr(status, "watchdog_tripped", False))
        settled = time.monotonic() - self._last_write_mono > self.CONFIRM_GRACE_S   # not a status older than a write
        if self.latched:
            if self.device_hold:
                self.hold_unconfirmed = False
            elif settled:
                self.hold_unconfirmed = True  # the DAQ lost it (a restart?) or never took it
        elif self.enabled and settled:
            if self.device_hold and not self.device_hold_kept:
                self.device_hold_kept = True
                log.warning("interlock.device_hold_kept", watchdog_tripped=self.watchdog_tripped,
                            detail="the DAQ holds the feed, not set by this run: kept until `millsense reset`, and "
                                   "written again if the DAQ loses it")
            elif self.device_hold_kept and not self.device_hold:
                with self._lock:   # the DAQ restarted (a power blip) or someone released it: not a reset
                    ok = self._write(True)
                if time.monotonic() - self._rewrite_said_mono > 10.0:   # a DAQ refusing it: a line each 10 s
                    self._rewrite_said_mono = time.monotonic()
                    log.warning("interlock.device_hold_rewritten", written=ok,
                                detail="the DAQ no longer held the feed it held, with no reset: written again")

    # -- state ------------------------------------------------------------
    @property
    def state(self) -> str:
        if not self.enabled:
            return "disabled"
        if self.latched:
            return "feed_hold"
        if self.device_hold or self.device_hold_kept:
            return "held_by_device"
        return "armed"

    def state_dict(self) -> dict[str, Any]:
        return {
            "interlock": self.state,
            "enabled": self.enabled,
            "reason": self.reason,
            "since": self.since,
            "device_feed_hold": self.device_hold,
            "watchdog_tripped": self.watchdog_tripped,
            "heartbeating": self.heartbeating,
            "hold_unconfirmed": self.hold_unconfirmed,
            "reset": self.reset_policy,
        }


class ResetCheck:
    """Is the condition that latched gone? Judged only on data newer than the hold. Not thread-safe.

    Why only newer data: the revolution that tripped, and the block that held
    the crash, are over their limits by definition; a reset judged on them
    would always be refused, one judged on nothing would release a machine
    whose overload persists (issue 10, finding 4: the feed went 3 → 0 → 3).
    So `mark()` notes the last sample processed when the hold began, and only
    revolutions that *started* after it, and blocks after it, count.

    The rule (`refusal()`), in order; the first that holds refuses:

    1. a blind condition (fault `signals` or `descriptor`): nothing can be judged;
    2. no samples since the hold, or the DAQ link lost or stalled;
    3. the spindle stopped since the hold and nothing new is over: the condition is gone (a block that
       stands still while stalled or over a crash limit is not "stopped" here: it is over);
    4. the latest block is stalled (the stall check holds);
    5. the latest block's sample-level peaks at or over `crash_power_w` / `crash_current_a`;
    6. the latest closed valid revolution over an armed overload limit (a
       `saturated` one counts as over every limit);
    7. the spindle turns and no valid revolution has closed since the hold
       (when in doubt, hold) — except after a test-trip, which latched for no
       condition.
    """

    def __init__(self, crash_power_w: float | None = None, crash_current_a: float | None = None):
        self.crash_power_w = crash_power_w
        self.crash_current_a = crash_current_a
        self.clear()

    def clear(self) -> None:
        self.marked = False
        self.hold_seq: int | None = None
        self._evidence_reset()
        self.stopped_since = False

    def _evidence_reset(self) -> None:
        self.blocks = 0
        self.rev_over: list[str] | None = None  # None: no valid revolution closed since the hold (or the stop)
        self.rev: int | None = None
        self.peaks_over: str | None = None
        self.stalled = False
        self.stopped_now = False

    def mark(self, last_seq: int | None) -> None:
        """A hold began; `last_seq` is the last sample processed before it (None: everything to come counts)."""
        self.clear()
        self.marked = True
        self.hold_seq = last_seq

    def _after(self, seq: int | None) -> bool:
        return self.hold_seq is None or (seq is not None and seq > self.hold_seq)

    def on_block(self, first_seq: int, peaks: dict[str, float], stalled: bool, stopped: bool) -> None:
        if not self.marked or not self._after(first_seq):
            return
        over = self._peaks_over(peaks)
        if stopped and not stalled and over is None:
            # the condition is gone with the spindle; what comes after a restart is judged afresh. Not while
            # the block is over a sample-level limit: a jammed spindle stands still at its stall current, and
            # a crash's current outlasts the turning
            self._evidence_reset()
            self.stopped_since = True
            self.stopped_now = True
            self.blocks = 1
            return
        self.blocks += 1
        self.stopped_now = False
        self.stalled = bool(stalled)
        self.peaks_over = over

    def _peaks_over(self, peaks: dict[str, float]) -> str | None:
        """What in a block's peaks is over a crash limit, said for the refusal; None: nothing."""
        p_w, i_a = _number(peaks.get("p_gap_w")), _number(peaks.get("current_a"))
        if self.crash_power_w is not None and p_w is not None and p_w >= self.crash_power_w:
            return f"air-gap power peak {p_w:.0f} W >= crash_power_w {self.crash_power_w:g} W"
        if self.crash_current_a is not None and i_a is not None and i_a >= self.crash_current_a:
            shown = "clipped at the sensor's limit" if i_a == float("inf") else f"{i_a:.1f} A"
            return f"current peak {shown} >= crash_current_a {self.crash_current_a:g} A"
        return None

    def on_estimate(self, est: dict[str, Any], over: list[str]) -> None:
        """A closed revolution; `over` = AlarmEngine.over_limits(est)."""
        if not self.marked:
            return
        end = est.get("seq_end")
        if end is None:
            return
        span = int(est.get("samples") or 0) + int(est.get("lost_samples") or 0)
        if not self._after(int(end) - span + 1 if span else None):
            return  # began before the hold: it is the evidence that tripped, not news
        if est.get("saturated"):
            self.rev_over, self.rev = ["saturated"], est.get("rev")
        elif est.get("valid", True):
            self.rev_over, self.rev = list(over), est.get("rev")

    def refusal(self, reason: str | None, blind: dict[str, str], daq_fault: str | None) -> dict[str, str] | None:
        """None: the condition is gone. Else {"error": why, "condition": kind}."""
        if blind:
            kind, why = next(iter(blind.items()))
            return {"condition": "blind", "error": f"the daemon is blind ({kind}: {why}): the condition cannot be judged"}
        if daq_fault:
            return {"condition": "no_data", "error": f"no data from the DAQ ({daq_fault}): the condition cannot be judged"}
        test = reason == TEST_TRIP
        if self.blocks == 0:
            if test:
                return None
            return {"condition": "no_data", "error": "no samples since the hold yet: the condition cannot be judged"}
        if self.stopped_now or (self.stopped_since and not self.rev_over and not self.stalled and not self.peaks_over):
            return None
        if self.stalled:
            return {"condition": "stall", "error": "the spindle is still stalled: high current and no revolution closing"}
        if self.peaks_over:
            return {"condition": "crash", "error": f"still over the sample-level limit: {self.peaks_over}"}
        if self.rev_over:
            what = ", ".join(self.rev_over)
            return {"condition": "overload",
                    "error": f"revolution {self.rev} since the hold is still over its limit ({what})"}
        if self.rev_over is None and not test and not self.stopped_since:
            return {"condition": "no_revolution",
                    "error": "the spindle turns and no valid revolution has closed since the hold: try again in a moment"}
        return None


def _number(value: Any) -> float | None:
    try:
        f = float(value)
    except (TypeError, ValueError):
        return None
    return f if f == f else None  # inf stays: a current clipped while high is beyond what the sensor measures


def wait_ms(done: Callable[[], bool], t0: float, wait_s: float) -> float | None:
    """Milliseconds from `t0` until `done()`, polled every half millisecond; None if not within wait_s.
    How a proof test times the DAQ's and the CNC's confirmation of a hold (`OperatorControls.test_trip`, `commission`)."""
    while True:
        now = time.monotonic()
        if done():
            return round((now - t0) * 1e3, 2)
        if now - t0 > wait_s:
            return None
        time.sleep(0.0005)


def trip_reason(ev: Any) -> str:
    """The interlock's reason for a hold: the alarm, its value and the limit it crossed (from below or above)."""
    side = "<" if ev.level in ("envelope_low", "expected_low") else ">"
    return f"{ev.level} {ev.quantity} {_shown(ev.value)} {side} {_shown(ev.limit)}"


def _shown(x: Any) -> str:
    """A value as a reason shows it: a float to 3 decimals (`12.345678901` read as a measurement's precision)."""
    return repr(round(x, 3)) if isinstance(x, float) else str(x)
