"""Adaptive feed control live (issue 15, docs/afc.md): the controller and the override output, run by the daemon.

`AfcSupervisor` is built by the Runner and given what it needs; it never imports the runtime. It

- steps the controller once per published revolution, on the estimator thread, after that block's
  trips (`revolution`), and back to 100 % when no healthy revolution came for too long (`idle`);
- puts the override to min(current, 100 %) at once from whichever thread sees a fault, a blind
  signal, a trip or a stop (`safe`), and lets control start again from air once the condition
  is gone (`release`);
- follows the DAQ: its description (has it an override output?), a (re)connection (the override
  set again to what this daemon holds), each STATUS's applied override, which must follow the
  command: above both 100 % and the command for OVERRIDE_FOLLOW_S, nothing controls the feed,
  and the feed is held through the Runner's one trip path (`check_override`);
- answers `cmd/afc` and the local `afc` (`command`; the arguments are checked by afc/args.py).

One lock (`lock`) orders the controller's state and the writes.
"""

from __future__ import annotations

import threading
import time
import traceback
from typing import Any, Callable

import structlog

from millsense.daemon.afc.controller import FeedController
from millsense.daemon.afc.output import OverrideOutput
from millsense.daemon.events import AlarmEvent
from millsense.daemon.guarded import safe
from millsense.daemon.learning import context_auth

log = structlog.get_logger("millsense.runner")  # the runner's logger, as before it was carved out of it

# AFC on, the CNC's applied feed override above both 100 % and the command by OVERRIDE_MARGIN_PCT for
# OVERRIDE_FOLLOW_S: nothing controls the feed (a DAQ refusing the command, a stuck output, a PLC): hold it.
# The CNC follows a command within tens of milliseconds, and at its own rate limit (100 %/s or more) from the
# 150 % bound within half a second.
OVERRIDE_FOLLOW_S = 1.0
OVERRIDE_MARGIN_PCT = 2.0


class AfcSupervisor:
    """The controller, the output and the checks around them, for one live daemon."""

    def __init__(
        self,
        settings: Any,
        driver: Any,
        interlock: Any,
        core: Any,
        *,
        batch_s: float,
        faults: Callable[[], dict[str, str]],
        trip: Callable[[str], str | None],
        publish_alarm: Callable[[AlarmEvent, str | None], None],
        last_seq: Callable[[], int | None],
        alarm_lock: threading.Lock,
    ):
        self.feed = FeedController(getattr(settings, "afc", None), getattr(settings, "material", None),
                                   batch_s=batch_s)
        self.feed_out = OverrideOutput(driver)
        self.lock = threading.RLock()
        self._interlock = interlock
        self._core = core
        self._faults = faults
        self._trip = trip
        self._publish_alarm = publish_alarm
        self._last_seq = last_seq
        self._alarm_lock = alarm_lock  # the learned limits' monitor is the alarm engine's
        self._notes_said: set[str] = set()
        self.applied_override_pct: float | None = None  # the DAQ's last STATUS (what the CNC applies)
        self._override_above_since: float | None = None  # AFC on: the applied override above the command since
        # The override on the DAQ is set once to what this daemon holds at the first STATUS after each connection:
        # a daemon restarted faster than the watchdog would otherwise leave the last run's override in place.
        self._resync = True

    @property
    def enabled(self) -> bool:
        return self.feed.enabled

    def apply(self, decision: Any, why: str) -> None:
        """Write a decision's override, if it has one. A safe decision never raises what the DAQ holds."""
        if decision is not None and decision.override_pct is not None:
            self.feed_out.write(decision.override_pct, why, only_down=decision.state == "safe")

    def safe(self, reason: str) -> None:
        """A fault, a blind signal, a trip, a stop: the override to min(current, 100 %) at once, any thread."""
        with self.lock:
            self.apply(self.feed.safe(reason), reason)

    def blocked(self) -> str | None:
        """Why the controller may not move the feed now: a fault, a hold (the DAQ's or ours)."""
        for kind, reason in list(self._faults().items()):
            return f"fault: {kind}: {reason}"
        il = self._interlock
        if il.latched or il.device_hold:
            return f"feed hold: {il.reason or 'held by the DAQ'}"
        return None

    def release(self) -> None:
        """The condition is gone (a fault recovered, a reset granted): control may start again from air."""
        with self.lock:
            if self.blocked() is None:
                self.feed.release()

    def idle(self, now: float) -> None:
        """Each estimator wake-up: no healthy revolution for too long while above 100 % -> back to 100 %."""
        with self.lock:
            self.apply(self.feed.on_idle(now), "no recent revolution")

    def revolution(self, est: dict, now: float, suspect: str | None = None) -> None:
        """The controller's step for one revolution, before it is published; the estimate carries its state.
        `suspect`: a channel that stopped moving in the newest samples: no feed is raised on it."""
        feed = self.feed
        if feed.enabled:
            seq = est.get("seq_end")
            ctx = self._core.context.at(int(seq)) if seq is not None else None
            tool = None if ctx is None else ctx.tool
            operation = None if ctx is None else ctx.operation
            learned = None
            monitor = self._core.monitor
            if monitor is not None and ctx is not None:
                with self._alarm_lock:
                    learned = monitor.learned_mean(ctx.key, feed.quantity_key)
            with self.lock:
                blocked = self.blocked()
                if blocked is not None:
                    decision = feed.safe(blocked)
                else:
                    decision = feed.on_revolution(
                        est, target=feed.target_for(tool, operation, learned),
                        allowed=feed.allowed(tool, operation, None if ctx is None else ctx.afc_allowed), now_s=now,
                        suspect=suspect, untrusted=context_auth.untrusted_reason(ctx))
                self.apply(decision, "afc")
        est["afc"] = {"state": feed.state, "override_pct": feed.commanded_pct, "target": feed.target}

    def error(self, exc: Exception, est: dict) -> None:
        """A bug in the controller's step: the override comes down to <= 100 % and stays there; estimates go on."""
        reason = f"afc error: {type(exc).__name__}: {exc}"
        if reason not in self._notes_said:  # once per distinct error: a lasting one would log every revolution
            self._notes_said.add(reason)
            safe(lambda: log.error("afc.error", reason=reason, traceback=traceback.format_exc()))
        safe(self.safe, reason)
        est["afc"] = {"state": self.feed.state, "override_pct": self.feed.commanded_pct, "target": None}

    # ------------------------------------------------------------------ the DAQ
    def on_link_up(self) -> None:
        """A DAQ that restarted forgot its override (100 %), or (a link that only dropped) still holds what it
        was: set again at its first STATUS."""
        self.feed_out.device_restarted()
        self._resync = True

    def on_descriptor(self, desc: Any) -> None:
        available = bool(getattr(desc, "has_feed_override", False))
        with self.lock:
            self.feed.set_available(available)
        if not available and "afc.unavailable" not in self._notes_said:
            self._notes_said.add("afc.unavailable")
            log.info("afc.unavailable", protocol_version=getattr(desc, "protocol_version", None),
                     detail="this DAQ has no feed-override output (protocol version 1): no adaptive feed control")

    def on_override(self, applied_pct: float, now: float) -> None:
        """A STATUS's applied override: the first after a connection sets the DAQ's to ours; each is checked."""
        self.applied_override_pct = applied_pct
        if self._resync:
            self._resync = False
            safe(self._resync_now)
        safe(self.check_override, now)

    def _resync_now(self) -> None:
        """Write what the controller holds (100 % unless it is controlling) to a DAQ just (re)connected."""
        with self.lock:
            self.feed_out.write(self.feed.commanded_pct, "the DAQ connected: its override set to this daemon's")

    def override_runaway(self) -> str | None:
        """AFC on: the applied override above both 100 % and the command (what it is, in words), else None."""
        applied, sent = self.applied_override_pct, self.feed_out.sent_pct
        if applied is None or not self.feed.enabled or applied <= max(sent, 100.0) + OVERRIDE_MARGIN_PCT:
            return None
        return (f"the CNC applies a {applied:.1f} % feed override where {sent:.1f} % is commanded: the feed runs "
                f"faster than programmed and nothing controls it (a DAQ that does not apply the override command, "
                f"a stuck output or PLC)")

    def check_override(self, now: float) -> None:
        """Each STATUS: the feed held once the applied override stayed above the command for OVERRIDE_FOLLOW_S."""
        runaway = self.override_runaway()
        if runaway is None:
            self._override_above_since = None
            return
        if self._override_above_since is None:
            self._override_above_since = now
        if now - self._override_above_since < OVERRIDE_FOLLOW_S or self._interlock.latched:
            return
        held = self._trip(f"afc: {runaway}")
        log.error("afc.override_not_followed", applied_pct=self.applied_override_pct, sent_pct=self.feed_out.sent_pct,
                  detail=runaway)
        ev = AlarmEvent("overload", "feed_override_pct", self.applied_override_pct,
                        max(self.feed_out.sent_pct, 100.0), None, self._last_seq())
        safe(self._publish_alarm, ev, held)

    # ------------------------------------------------------------------ the operator
    def status(self) -> dict[str, Any]:
        with self.lock:
            out = dict(self.feed.status())
        out["available"] = self.feed_out.available
        out["applied_pct"] = self.applied_override_pct
        out["sent_pct"] = self.feed_out.sent_pct
        return out

    def refusal(self) -> str | None:
        """Why `afc on` cannot be granted, or None."""
        available = self.feed_out.available
        if available is None:
            return "the DAQ has not described itself yet: try again once it streams"
        if not available:
            return ("this DAQ has no feed-override output (protocol version 1, or capabilities bit 0 clear): "
                    "adaptive feed control needs a protocol-2 DAQ")
        if not self._interlock.enabled:
            return ("the interlock is disabled ([interlock] enabled = false): without its heartbeat the DAQ's "
                    "watchdog could not return the override to 100 % if the daemon stopped")
        return None

    def command(self, args: dict, requester: str = "") -> dict[str, Any]:
        """`cmd/afc`, `millsense afc`: switch adaptive feed control on or off (the caller authorised it)."""
        if not isinstance(args, dict):
            return {"ok": False, "reason": "the arguments must be a JSON object"}
        action = args.get("action")
        if action == "status":
            return {"ok": True, "afc": self.status()}
        if action not in ("on", "off"):
            return {"ok": False, "reason": f"unknown action {action!r}: on, off or status"}
        refusal = self.refusal() if action == "on" else None
        if refusal is not None:
            log.warning("afc.refused", requester=requester or "unknown", action=action, reason=refusal)
            return {"ok": False, "reason": refusal, "afc": self.status()}
        with self.lock:
            self.apply(self.feed.switch(action == "on", time.monotonic()), f"afc {action}")
            blocked = self.blocked() if action == "on" else None
            if blocked is not None:  # on, but it waits: a fault or a hold keeps it safe until it is gone
                self.apply(self.feed.safe(blocked), blocked)
        log.warning("afc.switched", requester=requester or "unknown", on=action == "on", state=self.feed.state,
                    reason=blocked)
        return {"ok": True, "afc": self.status()}
