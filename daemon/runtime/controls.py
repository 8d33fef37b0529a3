"""The operator's controls of the live daemon: the one implementation of `Controls` (daemon/controls.py).

Both front doors ask this object: the Zenoh queryables (publish/sink.py, after command_auth's
challenge–response) and the local control socket (runtime/local_control.py, after the peer's uid).
The caller has authorised the request; what is decided here is whether the machine allows it:

- `reset`: refused, with the reason and the `condition`, while data newer than the hold show the
  condition still there (`ResetCheck`), a blind fault or a lost DAQ, or an applied feed override that
  nothing controls: the feed is never released only to be held again;
- `test_trip`: a proof test of the path, through the same trip as a real alarm, timed to confirmation;
- `limits`, `limits_command`: the learned limits (daemon/learning);
- `afc_command`: adaptive feed control on, off, status (afc/supervisor.py);
- `on_context_payload`: a CNC adapter's context, queued for the estimator thread;
- `status`, `config`.

Built by the Runner and given what it needs; it never imports the runtime's runner.
"""

from __future__ import annotations

import threading
import time
from typing import Any, Callable

import structlog

from millsense.daemon.audit import AuditLog
from millsense.daemon.controls import TEST_TRIP_WAIT_S, Controls
from millsense.daemon.events import AlarmEvent
from millsense.daemon.guarded import safe
from millsense.daemon.runtime.faults import BLIND_KINDS, DAQ_FAULTS
from millsense.daemon.runtime.interlock import TEST_TRIP, wait_ms

log = structlog.get_logger("millsense.runner")  # the runner's logger, as before it was carved out of it

CAP_CONTEXT = 0x02  # Descriptor.capabilities bit 1: the DAQ sends CONTEXT frames (protocol 2)
CONTEXT_INBOX = 64  # Zenoh contexts waiting for the estimator thread: a flood keeps the newest few, never grows


class OperatorControls(Controls):
    """What the operator may ask of one live daemon, from either front door."""

    def __init__(
        self,
        settings: Any,
        driver: Any,
        interlock: Any,
        core: Any,
        *,
        machine: str,
        audit: AuditLog,
        board: Any,
        frames: Any,
        afc: Any,
        live: Any,
        report: Any,
        reset_check: Any,
        check_lock: threading.Lock,
        alarm_lock: threading.Lock,
        trip: Callable[[str], str | None],
        trip_lock: threading.RLock,
        publish_alarm: Callable[[AlarmEvent, str | None], None],
        persist_limits: Callable[[set[str], bool], None],
        effective_config: Callable[[], dict] | None = None,
    ):
        self.settings = settings
        self.audit = audit
        self.machine = machine
        self._driver = driver
        self._interlock = interlock
        self._core = core
        self._board = board
        self._frames = frames
        self._afc = afc
        self._live = live
        self._report = report
        self._check = reset_check
        self._check_lock = check_lock
        self._alarm_lock = alarm_lock
        self._trip = trip
        self._trip_lock = trip_lock   # the trip path's own: a reset is judged and applied with no trip between
        self._publish_alarm = publish_alarm
        self._persist_limits = persist_limits
        self._effective_config = effective_config
        self._contexts: list[tuple[dict, str]] = []  # from Zenoh's thread, taken by the estimator's
        self._context_lock = threading.Lock()

    def status(self) -> dict[str, Any]:
        return self._report.payload()

    def status_version(self) -> tuple:
        """What a kept status answer must still match (publish/queryables.py): the daemon's state, the
        interlock's and the faults. Cheap: read on every status query."""
        il = self._interlock
        return (self._board.state, il.state, il.reason, il.hold_unconfirmed, tuple(sorted(self._board.faults.items())))

    def config(self) -> dict[str, Any]:
        if self._effective_config is None:
            return {"machine": self.machine}
        return self._effective_config()

    def reset(self, requester: str = "") -> dict[str, Any]:
        """Clear the latched interlock and the latched alarms, unless the condition that latched persists.

        The caller has authorised the request (Zenoh: command_auth; local: the socket's peer uid).
        Refused, with the reason and the `condition`, while data newer than the hold show the
        condition still there (`ResetCheck`): the feed is never released only to be held again.
        """
        if not isinstance(requester, str):  # an older caller handing over the request payload
            requester = ""
        il, faults = self._interlock, self._board.faults
        # Judged and applied under the trip path's lock: a trip that latches between the judgement and the release
        # (a crash on the reader thread, a second press answered late) would otherwise be released unjudged.
        with self._trip_lock:
            with self._check_lock:
                held = il.latched or il.device_hold
                blind = {k: faults[k] for k in BLIND_KINDS if k in faults}
                daq = next((f"{k}: {faults[k]}" for k in DAQ_FAULTS if k in faults), None)
                if daq is None and not self._driver.link_up:
                    daq = "daq_link: the link is down"
                refusal = self._check.refusal(il.reason, blind, daq) if held and il.enabled else None
                runaway = self._afc.override_runaway() if held and il.enabled else None
                if refusal is None and runaway is not None:
                    refusal = {"condition": "feed_override", "error": runaway}
            if refusal is None:
                result = il.reset()
                events = []
                if result.get("ok"):
                    with self._check_lock:
                        self._check.clear()
                    with self._alarm_lock:
                        events = self._core.reset()
                    self._frames.rearm()
        if refusal is not None:
            log.warning("interlock.reset_refused", requester=requester or "unknown", reason=il.reason, **refusal)
            result = {"ok": False, **refusal, **il.state_dict()}
            result["alarm"] = self._core.summary()
            return result
        if result.get("ok"):
            for ev in events:
                safe(self._publish_alarm, ev, None)
            safe(self._afc.release)
        result["alarm"] = self._core.summary()
        return result

    def test_trip(self, requester: str = "", wait_s: float = TEST_TRIP_WAIT_S) -> dict[str, Any]:
        """Proof test of the path: feed hold through the same trip as a real alarm, timed to confirmation.

        `daq_confirm_ms`: from the trip to the DAQ's STATUS showing feed hold. On a DAQ that sends
        CONTEXT (protocol 2, capabilities bit 1) `cnc_confirm_ms`: to the CNC's own "feed held"
        input, else null. The latch is real: the caller sends a reset afterwards.
        """
        il, drv = self._interlock, self._driver
        if not isinstance(requester, str):
            requester = ""
        result: dict[str, Any] = {"ok": False, "daq_confirm_ms": None, "cnc_confirm_ms": None}
        refusal = None
        if not il.enabled:
            refusal = "the interlock is disabled ([interlock] enabled = false)"
        elif il.latched or il.device_hold:
            refusal = f"feed hold is already asserted ({il.reason or il.state}): reset first, then test"
        elif not drv.link_up:
            refusal = "the DAQ link is down"
        desc = drv.descriptor
        cnc = bool(int(getattr(desc, "capabilities", 0) or 0) & CAP_CONTEXT)
        before_ctx = getattr(drv, "last_context", None)
        if refusal is None and cnc and before_ctx is not None and getattr(before_ctx, "feed_held", False):
            refusal = "the CNC already reports feed held: nothing to measure"
        if refusal is not None:
            log.warning("interlock.test_trip_refused", requester=requester or "unknown", error=refusal)
            return {**result, "error": refusal, "interlock": il.state, "interlock_detail": il.state_dict()}
        before_status = drv.last_status
        t0 = time.monotonic()
        written = self._trip(TEST_TRIP)
        log.warning("interlock.test_trip", requester=requester or "unknown", written=written)

        def status_held() -> bool:
            st = drv.last_status
            return st is not None and st is not before_status and bool(getattr(st, "feed_hold", False))

        def cnc_held() -> bool:
            ctx = getattr(drv, "last_context", None)
            return ctx is not None and ctx is not before_ctx and bool(getattr(ctx, "feed_held", False))

        result["daq_confirm_ms"] = wait_ms(status_held, t0, wait_s)
        if cnc:
            result["cnc_confirm_ms"] = wait_ms(cnc_held, t0, wait_s)
        result["cnc_reports_hold"] = cnc
        result["ok"] = bool(written == "feed_hold" and result["daq_confirm_ms"] is not None
                            and (not cnc or result["cnc_confirm_ms"] is not None))
        if not result["ok"]:
            if written != "feed_hold":
                result["error"] = "the DAQ did not take the feed-hold command"
            elif result["daq_confirm_ms"] is None:
                result["error"] = f"the DAQ's status did not show feed hold within {wait_s:g} s"
            else:
                result["error"] = f"the CNC did not report feed held within {wait_s:g} s"
        result["interlock"] = il.state
        result["interlock_detail"] = il.state_dict()
        self._live.last_test_trip = {k: result[k] for k in ("ok", "daq_confirm_ms", "cnc_confirm_ms")} | {"t": time.time()}
        log.info("interlock.test_trip_result", requester=requester or "unknown",
                 **{k: v for k, v in result.items() if k != "interlock_detail"})
        return result

    def limits(self) -> dict[str, Any]:
        """The `limits` queryable: learned limits per process key, and the tools' life and wear."""
        monitor = self._core.monitor
        if monitor is None:
            return {"machine": self.machine, "enabled": False, "limits": [], "tools": {}}
        with self._alarm_lock:
            return {"machine": self.machine, "enabled": True, **monitor.limits_summary()}

    def limits_command(self, args: dict, requester: str = "") -> dict[str, Any]:
        """`cmd/limits` and `millsense limits`: the operator's changes (the caller authorised them)."""
        monitor = self._core.monitor
        if monitor is None:
            return {"ok": False, "error": "learning is off ([learning] enabled = false)"}
        if not isinstance(args, dict):
            return {"ok": False, "error": "the arguments must be a JSON object"}
        key = args.get("key")
        reads = args.get("action") in ("list", "show")
        with self._alarm_lock:
            before = None if reads else monitor.bounds(key)   # reads (a query flood) add nothing under the lock
            result = monitor.command(dict(args))
            changed = list(result.pop("changed_keys", ()) or ())
            tools_changed = bool(result.pop("tools_changed", False))
            after = monitor.bounds(key) if key in changed else None
        if not reads:  # a read changes nothing: a flood of them logs nothing
            log.warning("limits.command", requester=requester or "unknown", action=args.get("action"),
                        key=args.get("key"), tool=args.get("tool"), pct=args.get("pct"), ok=result.get("ok"),
                        error=result.get("error"))
        if changed or tools_changed:
            self._persist_limits(set(changed), tools_changed)
        if key in changed:
            self._publish_limits_change(args, key, before, after, requester)
        return result

    def _publish_limits_change(self, args: dict, key: str, before: Any, after: Any, requester: str) -> None:
        """An applied change of one key's limits on `limits/change` (docs/zenoh.md), for the plant's historian:
        handed to the sink's queue (its publisher thread sends it), never on the estimator's path."""
        publish = getattr(getattr(self._report, "sink", None), "limits_change", None)   # the runner's sink
        if publish is None:
            return
        who = requester or "unknown"
        if who.startswith("local "):
            authority = "local"     # the control socket, by the peer's uid (runtime/local_control.py)
        else:
            from millsense.daemon.publish.command_auth import policy_and_token
            authority = policy_and_token(self)[0]   # "token": the reset token's proof; "open": anyone's (reads)
        payload = {"machine": self.machine, "t": time.time(), "key": key, "action": args.get("action"),
                   "pct": args.get("pct"), "before": before, "after": after, "requester": who,
                   "authority": authority}
        safe(publish, payload)

    def afc_command(self, args: dict, requester: str = "") -> dict[str, Any]:
        """`cmd/afc`, `millsense afc`: switch adaptive feed control on or off (the caller authorised it)."""
        return self._afc.command(args, requester)

    def on_context_payload(self, payload: dict, source: str = "") -> None:
        """A CNC adapter's `context` put (Zenoh's thread): applied by the estimator thread, in order. One refused
        for its content, or ignored by `[context] source`, raises ValueError here: the sink counts it refused."""
        judged = self._core.context.judge_zenoh(payload)
        if isinstance(judged, str):
            raise ValueError(judged)
        with self._context_lock:
            if len(self._contexts) < CONTEXT_INBOX:  # a flood keeps the newest few, never grows
                self._contexts.append((payload, source))
            else:
                self._contexts[-1] = (payload, source)
        wake = getattr(self._driver, "wake", None)
        if wake is not None:
            wake.set()

    @property
    def contexts_waiting(self) -> bool:
        return bool(self._contexts)

    def take_contexts(self) -> list[tuple[dict, str]]:
        """The Zenoh contexts queued since the last call, oldest first (the estimator thread's)."""
        with self._context_lock:
            taken, self._contexts = self._contexts, []
        return taken
