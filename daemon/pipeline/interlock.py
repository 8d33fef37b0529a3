"""Feed hold on the DAQ: trip at once, latch until an explicit reset, heartbeat while healthy.

Why it is built this way:

- **At once, from the detecting thread.** `trip()` writes the output from the
  thread that found the overload / crash / breakage (the estimator thread); no
  queue or other thread sits between the decision and the DAQ.
- **Latching.** Once asserted, feed hold stays until `reset()` (the
  `cmd/reset` queryable) or a restart of the daemon. A restart forgets the
  latch but does not write the output: see the start policy below.
- **Fail-safe by silence.** At start the DAQ's watchdog is set to
  `watchdog_ms`; `beat()` sends heartbeats only while the caller says the
  pipeline is healthy. A daemon that hangs, dies or loses its samples stops
  beating and the DAQ stops the feed by itself (daq-protocol.md, Fail-safe).
- **Start policy.** With the interlock enabled the daemon never clears, on its
  own, a feed hold it did not set in this run: a hold found at start (latched
  by a previous run, by the DAQ's watchdog, or by someone else) is left
  asserted and reported as `held_by_device`; only an explicit `reset` clears
  it. So a restart loop can never release a machine that was stopped for a
  reason.
- **Confirmed, or written again.** A write the DAQ did not take (link down, a
  Modbus exception response) is not reported as a hold: `trip()` says so, and
  while the latch is set the hold is written again every heartbeat period
  until the write succeeds and the DAQ's own status shows feed hold.
- **Reset authority.** `reset = "open"` accepts any request, `"token"` only a
  payload carrying `reset_token` (compared with `hmac.compare_digest`, so the
  reply time does not leak the token), `"off"` none (clear at the machine and
  restart).

`outputs` is the driver (anything with `set_outputs(feed_hold, alarm_lamp)`,
`heartbeat()`, `set_watchdog_ms(ms)`).
"""

from __future__ import annotations

import hmac
import json
import threading
import time
from typing import Any

import structlog

log = structlog.get_logger("millsense.interlock")

RESET_POLICIES = ("open", "token", "off")


def _token_from_payload(payload: bytes) -> bytes:
    """The token a reset request carries: `{"token": "..."}` or the raw bytes."""
    data = bytes(payload or b"").strip()
    if data.startswith(b"{"):
        try:
            obj = json.loads(data.decode("utf-8"))
        except (UnicodeDecodeError, ValueError):
            return data
        if isinstance(obj, dict) and isinstance(obj.get("token"), str):
            return obj["token"].encode("utf-8")
        return b""
    return data


def _secret(settings: Any) -> str:
    """The reset token as plain text: `InterlockSettings.token()` (also covers
    `reset_token_file`), a pydantic SecretStr, or a plain string."""
    reader = getattr(settings, "token", None)
    if callable(reader):
        return str(reader() or "")
    token = getattr(settings, "reset_token", None)
    if token is None:
        return ""
    reveal = getattr(token, "get_secret_value", None)
    return str(reveal() if callable(reveal) else token)


class Interlock:
    """The daemon's side of the feed-hold interlock. Thread-safe."""

    def __init__(self, outputs: Any, settings: Any):
        self._out = outputs
        self.enabled = bool(getattr(settings, "enabled", False))
        self.heartbeat_ms = int(getattr(settings, "heartbeat_ms", 100) or 100)
        self.watchdog_ms = int(getattr(settings, "watchdog_ms", 500) or 0)
        policy = str(getattr(settings, "reset", "open") or "open")
        self.reset_policy = policy if policy in RESET_POLICIES else "off"
        self._token = _secret(settings).encode("utf-8")
        self._lock = threading.Lock()
        self.latched = False  # feed hold asserted by this daemon in this run
        self.reason: str | None = None
        self.device_hold = False  # last STATUS from the DAQ said feed hold is on
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
                return None if self.hold_unconfirmed else "feed_hold"
            self.latched = True
            self.reason = reason
            self.trips += 1
            ok = self._write(True)
        log.warning("interlock.feed_hold", reason=reason, written=ok)
        return "feed_hold" if ok else None

    def reassert(self) -> None:
        """After a reconnect: the DAQ may have restarted; write the latched hold again."""
        if self.enabled and self.latched:
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
    def authorise(self, payload: bytes) -> str | None:
        """None if a reset with this payload is allowed, else why not."""
        if self.reset_policy == "off":
            return "reset is disabled (interlock.reset = off): clear feed hold at the machine and restart"
        if self.reset_policy == "token":
            given = _token_from_payload(payload)
            if not self._token:
                return "reset needs a token but interlock.reset_token is empty"
            if not hmac.compare_digest(given, self._token):
                return "wrong or missing reset token"
        return None

    def reset(self, payload: bytes) -> dict[str, Any]:
        """Clear the latch and the DAQ's feed hold, if the policy allows it."""
        refused = self.authorise(payload)
        if refused is not None:
            log.warning("interlock.reset_refused", reason=refused)
            return {"ok": False, "error": refused, **self.state_dict()}
        with self._lock:
            was = self.latched or self.device_hold
            self.latched = False
            self.reason = None
            self.hold_unconfirmed = False
            ok = self._write(False) if self.enabled else True
            if ok:
                self.device_hold = False
                self.watchdog_tripped = False
        log.info("interlock.reset", cleared=was, write_ok=ok)
        result: dict[str, Any] = {"ok": ok, **self.state_dict()}
        if not ok:
            result["error"] = "the DAQ did not take the command (link down?)"
        return result

    # -- heartbeats and device status --------------------------------------
    def beat(self, healthy: bool) -> None:
        """Called every `heartbeat_ms`: a heartbeat only while the pipeline is healthy."""
        if not self.enabled:
            self.heartbeating = False
            return
        if self.latched and self.hold_unconfirmed:
            self._retry_hold()
        if not healthy:
            if self.heartbeating:
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
        if self.latched:
            if self.device_hold:
                self.hold_unconfirmed = False
            elif time.monotonic() - self._last_write_mono > self.CONFIRM_GRACE_S:
                self.hold_unconfirmed = True  # the DAQ lost it (a restart?) or never took it

    # -- state ------------------------------------------------------------
    @property
    def state(self) -> str:
        if not self.enabled:
            return "disabled"
        if self.latched:
            return "feed_hold"
        if self.device_hold:
            return "held_by_device"
        return "armed"

    def state_dict(self) -> dict[str, Any]:
        return {
            "interlock": self.state,
            "enabled": self.enabled,
            "reason": self.reason,
            "device_feed_hold": self.device_hold,
            "watchdog_tripped": self.watchdog_tripped,
            "heartbeating": self.heartbeating,
            "hold_unconfirmed": self.hold_unconfirmed,
            "reset": self.reset_policy,
        }
