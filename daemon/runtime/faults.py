"""The fault board of the live daemon: what is wrong now, and what follows from it.

Whatever goes wrong goes through `fault(kind, reason)`: idempotent per kind, every handler in
its own `try`, leaves a diagnostic dump in the log; `recover(kind)` undoes it. The board also
owns the daemon's state (starting → running ⇄ degraded → stopping), which a fault and its
recovery move between running and degraded.

- `signal_source`: one fault kind fed by several checks (`signals`: plausibility, wiring,
  data_loss, phase, sample_rate), raised while any of them holds it; `verdict` feeds it a
  wiring or stream check's verdict (pipeline/verdict.py).
- `check_blind`: under `[interlock] on_blind`, a blind condition while the spindle turns holds
  the feed (through the Runner's one trip path) or only warns.
- the DAQ's link and stall faults raise and clear the alarm engine's `daq` alarm.

Built by the Runner and given what it needs; it never imports the runtime's runner.
"""

from __future__ import annotations

import threading
from typing import Any, Callable

import structlog

from millsense.daemon.events import AlarmEvent
from millsense.daemon.guarded import safe

log = structlog.get_logger("millsense.runner")  # the runner's logger, as before it was carved out of it

BLIND_KINDS = ("signals", "descriptor")  # faults that leave the daemon unable to see a crash
DAQ_FAULTS = ("daq_link", "daq_stalled")


class FaultBoard:
    """The faults of one live daemon and its state; thread-safe."""

    def __init__(
        self,
        interlock: Any,
        core: Any,
        live: Any,
        *,
        on_blind: str,
        alarm_lock: threading.Lock,
        ready: threading.Event,
        trip: Callable[[str], str | None],
        held: Callable[[], str | None],
        publish_alarm: Callable[[AlarmEvent, str | None], None],
        publish_step: Callable[[Any], None],
        afc_safe: Callable[[str], None],
        afc_release: Callable[[], None],
        healthy: Callable[[], bool],
        diagnostics: Callable[[], dict[str, Any]],
        notify: Callable[..., Any],
    ):
        self.state = "starting"
        self.faults: dict[str, str] = {}
        self._sources: dict[str, dict[str, str]] = {}  # kind -> {check: reason} (see signal_source)
        self._lock = threading.Lock()
        self._blind_lock = threading.Lock()
        self._blind_acted: set[str] = set()
        self._interlock = interlock
        self._core = core
        self._live = live   # the estimator thread's last sample and whether the spindle stands
        self.on_blind = on_blind
        self._alarm_lock = alarm_lock
        self._ready = ready
        self._trip = trip
        self._held = held
        self._publish_alarm = publish_alarm
        self._publish_step = publish_step
        self._afc_safe = afc_safe
        self._afc_release = afc_release
        self._healthy = healthy
        self._diagnostics = diagnostics
        self._notify = notify

    def fault(self, kind: str, reason: str, tb: str | None = None) -> None:
        """The one fault path. Idempotent per kind; each handler in its own try."""
        with self._lock:
            if kind in self.faults:
                return
            self.faults[kind] = reason
        if self.state in ("running", "starting") and self._ready.is_set():
            self.state = "degraded"
        safe(self._afc_safe, f"fault: {kind}: {reason}")  # first: the feed never runs above programmed unseen
        safe(lambda: log.error("fault", kind=kind, reason=reason, dump=self._diagnostics(), traceback=tb))
        safe(lambda: self._interlock.beat(self._healthy(), stopping=self.state == "stopping"))
        if kind in DAQ_FAULTS:
            safe(self._daq_alarm, False)
        if kind in BLIND_KINDS:  # and again per block: a `signals` fault waits for a turning spindle
            safe(self.check_blind)
        safe(lambda: self._notify(status=f"degraded: {kind}: {reason}"))

    def recover(self, kind: str) -> None:
        with self._lock:
            if self.faults.pop(kind, None) is None:
                return
            remaining = bool(self.faults)
        if kind in DAQ_FAULTS and not any(k in self.faults for k in DAQ_FAULTS):
            safe(self._daq_alarm, True)
        if not remaining and self.state == "degraded":
            self.state = "running"
        log.info("recovered", kind=kind)
        if kind in BLIND_KINDS:
            safe(self.check_blind)
        safe(self._afc_release)

    def verdict(self, source: str, verdict: str | None) -> None:
        """A wiring or stream check's verdict (verdict.py) on fault `signals`, from `source`."""
        if verdict is not None:
            self.signal_source("signals", source, verdict or None)

    def signal_source(self, kind: str, source: str, reason: str | None) -> None:
        """One fault kind fed by several checks (`signals`: plausibility, wiring, data_loss, phase):
        raised while any of them holds it, recovered only when none does. When the check that raised it
        clears while another still holds it, the fault's reason becomes the other's."""
        sources = self._sources.setdefault(kind, {})
        if reason is not None:
            sources[source] = reason
            self.fault(kind, reason)
            return
        if sources.pop(source, None) is None and sources:
            return
        if not sources:
            self.recover(kind)
            return
        still = next(iter(sources.values()))
        with self._lock:
            if self.faults.get(kind) in (None, still):
                return
            self.faults[kind] = still
        safe(lambda: log.warning("fault.reason_changed", kind=kind, reason=still, cleared=source,
                                       detail="one cause cleared; the fault stays for the other"))
        safe(lambda: self._notify(status=f"degraded: {kind}: {still}"))

    def check_blind(self) -> None:
        """on_blind: a blind condition while the spindle turns holds the feed ("hold") or only warns ("alarm").

        The time before the DAQ's first descriptor raises no fault, so it is never blind; a
        `signals` fault with the spindle stopped waits until it turns. A `descriptor` fault leaves
        no estimator to say whether it turns: it is blind at once (when in doubt, hold).
        """
        if not self._interlock.enabled:
            return
        live = self._live
        events: list[tuple[AlarmEvent, str | None]] = []
        with self._blind_lock:
            for kind in BLIND_KINDS:
                reason = self.faults.get(kind)
                if reason is None:
                    if kind in self._blind_acted:
                        self._blind_acted.discard(kind)
                        events.append((AlarmEvent("clear", kind, None, None, None, live.last_seq), None))
                    continue
                if kind in self._blind_acted or (kind == "signals" and live.spindle_stopped):
                    continue
                self._blind_acted.add(kind)
                if self.on_blind == "hold":
                    held = self._trip(f"blind: {kind}: {reason}")
                    events.append((AlarmEvent("overload", kind, None, None, None, live.last_seq), held))
                else:
                    log.warning("interlock.blind_not_held", kind=kind, reason=reason,
                                detail='[interlock] on_blind = "alarm": the machine runs unwatched')
                    events.append((AlarmEvent("warning", kind, None, None, None, live.last_seq), None))
        for ev, held in events:
            safe(self._publish_alarm, ev, held if ev.level != "clear" else self._held())

    def _daq_alarm(self, ok: bool) -> None:
        with self._alarm_lock:
            events = self._core.alarms.on_daq(ok)
            lost = self._core.on_link_lost() if not ok else None
        for ev in events:
            self._publish_alarm(ev, self._held())
        if lost is not None:
            self._publish_step(lost)
