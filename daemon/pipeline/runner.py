"""The live runtime: threads between the driver, the estimator, the interlock and the sink.

Threads (one job each, one hand-off queue — the driver's):

- the driver's own reader thread fills its bounded queue, and on every frame,
  before queueing it, runs `_on_frame` (the driver's `sample_hook`): the
  sample-level crash power and current (`safety_check.FrameCheck`, a few
  vector operations). A crash holds the feed from there at once (`_trip`) and
  wakes the estimator to publish it;
- **estimator** (`_estimate_loop`) owns the estimator and the alarm engine.
  It sleeps on the driver's `wake` — set by a crash, by a frame that reaches
  the revolution predicted to close next (`_wake_at_seq`), by a frame whose
  current is over `stall_current_a` (the stall check needs the revolutions),
  by any event but samples (link, status, descriptor) — or for at most
  `BATCH_S` (`BATCH_TURNING_S` while a revolution's close is predicted: that
  close wakes it anyway), then takes everything queued and runs contiguous
  frames as one block (issue 13: 50-sample blocks every 50 ms cost a third of 10-sample
  blocks every 10 ms). It trips the interlock itself for what only it can see
  (overload, breakage, stall, blindness), then hands estimates and alarms to
  the sink (whose methods return at once, so a slow subscriber never slows it);
- **heartbeat** sends the DAQ a heartbeat every `heartbeat_ms` while the
  pipeline is healthy (link up, samples arrived within `HEALTH_STALL_S`,
  estimator loop alive) and stays silent otherwise, so that the DAQ's
  watchdog stops the feed if the daemon hangs or dies;
- **status** (1 s): status payload, sd_notify `STATUS=` / `WATCHDOG=1`, the
  debug stats line and the optional live summary callback.

The interlock side (issue 10): every feed hold goes through `_trip` (alarms,
a blind condition under `[interlock] on_blind = "hold"`, `test_trip`), which
marks the hold for `ResetCheck`; `reset()` is refused while data newer than
the hold show the condition still there. With a `latch_store` the latch is
persisted off the tripping thread and asserted again at the next start.

Whatever goes wrong goes through `fault(kind, reason)`: idempotent per kind,
every handler in its own `try`, leaves a diagnostic dump in the log;
`recover(kind)` undoes it. State: starting → running ⇄ degraded → stopping.

Every trip goes through `_trip` under one lock (the reader thread's and the
estimator's): the interlock's own lock writes the hold and persists the latch,
the reset check is marked once per new latch; a frame's crash is latched in
the alarm engine and published by the estimator thread, once.

Processing latency (`latency_ms`) is measured from the moment the estimator
thread takes the frame that closes a revolution from the driver's queue to the
moment its estimate is handed to the sink; `rev_delay_ms` from the moment the
reader decoded that frame (`SampleBlock.received_mono`), so it adds the wait
for the estimator's wake-up (a close the prediction missed waits up to a frame,
or `BATCH_S`). Live `t` of an estimate is the Unix time of the revolution's last
sample (`status.SeqClock`).
"""

from __future__ import annotations

import sys
import threading
import time
import traceback
from typing import Any, Callable

import numpy as np
import structlog

from millsense.daemon.audit import AuditLog
from millsense.daemon.events import AlarmEvent
from millsense.daemon.learning import context_auth
from millsense.daemon.pipeline.alarms import alarm_payload
from millsense.daemon.pipeline.feed_control import FeedController
from millsense.daemon.pipeline.feed_output import OverrideOutput
from millsense.daemon.pipeline.interlock import TEST_TRIP, TEST_TRIP_WAIT_S, Interlock, ResetCheck, wait_ms
from millsense.daemon.pipeline.loss_check import LossCheck
from millsense.daemon.pipeline.phase_check import PhaseCheck
from millsense.daemon.pipeline.power_check import PowerSignCheck
from millsense.daemon.pipeline.rate_check import RateCheck
from millsense.daemon.pipeline.run_core import PipelineCore, estimate_payload, process_payload
from millsense.daemon.pipeline.safety_check import FrameCheck
from millsense.daemon.pipeline.status import LatencyStats, SeqClock, bad_frames, interlock_detail, status_line
from millsense.daemon.publish.alarm_state import ActiveAlarms
from millsense.drivers.base import LinkEvent, SampleBlock, name_os_thread
from millsense.drivers.protocol import Context, Descriptor, Status

log = structlog.get_logger("millsense.runner")

HEALTH_STALL_S = 0.5  # no samples / no estimator loop for this long: stop heartbeats
DAQ_STALL_S = 1.0  # no samples for this long with the link up: `daq_lost`
# AFC on, the CNC's applied feed override above both 100 % and the command by OVERRIDE_MARGIN_PCT for
# OVERRIDE_FOLLOW_S: nothing controls the feed (a DAQ refusing the command, a stuck output, a PLC): hold it.
# The CNC follows a command within tens of milliseconds, and at its own rate limit (100 %/s or more) from the
# 150 % bound within half a second.
OVERRIDE_FOLLOW_S = 1.0
OVERRIDE_MARGIN_PCT = 2.0
PROGRESS_S = 3.0  # sd_notify WATCHDOG=1 only if a revolution closed within this
BLIND_KINDS = ("signals", "descriptor")  # faults that leave the daemon unable to see a crash
DAQ_FAULTS = ("daq_link", "daq_stalled")
CAP_CONTEXT = 0x02  # Descriptor.capabilities bit 1: the DAQ sends CONTEXT frames (protocol 2)
# A thread waiting for the GIL gets it when the running one lets go, at the latest after this: the
# reader thread with a crash frame must not wait out the estimator's batch (Python's default is 5 ms).
GIL_SWITCH_S = 0.0005
BATCH_S = 0.05  # the estimator thread's longest sleep: frames are processed in batches of up to this
# ... and while the spindle turns with a revolution's close predicted: that close wakes the estimator
# anyway (every 100 ms at 600 rpm), so a 50 ms timer woke it once more each revolution for nothing
BATCH_TURNING_S = 0.1


def _noop_notify(**_kw: Any) -> None:
    return None


class Runner:
    """One machine's live pipeline. Also the `Controls` the Zenoh queryables ask."""

    def __init__(
        self,
        settings: Any,
        driver: Any,
        *,
        version: str = "0+unknown",
        notify: Callable[..., Any] = _noop_notify,
        on_second: Callable[[dict, dict | None, str], Any] | None = None,
        effective_config: Callable[[], dict] | None = None,
        estimator_factory: Any = None,
        check_descriptor: Any = None,
        latch_store: Any = None,
        audit: AuditLog | None = None,
        history: Any = None,
        limits: dict | None = None,
        tools: dict | None = None,
        first_process: int = 1,
    ):
        self.settings = settings
        self.machine = str(getattr(settings, "machine", "millsense"))
        self.driver = driver
        self.version = version
        self._notify = notify
        self._on_second = on_second
        self._effective_config = effective_config
        self.core = PipelineCore(settings, estimator_factory, check_descriptor, limits=limits, tools=tools,
                                 first_process=first_process)
        if self.core.monitor is not None:  # stored learned limits that failed their check: set aside, said once
            for event, fields in self.core.monitor.take_restore_notes():
                log.warning(event, **fields)
        # The SQLite history (daemon/history): estimates, alarms, process summaries, learned limits.
        # Its writer thread takes what it is handed; a failing disk is the fault `history`, never a stop.
        self.history = history
        self._zenoh_contexts: list[tuple[dict, str]] = []  # from Zenoh's thread, taken by the estimator's
        self._context_lock = threading.Lock()
        self._notes_said: set[str] = set()
        self._context_refused = _RefusalLog("context.refused")
        self.processes = 0
        self.last_process: dict | None = None
        il_settings = getattr(settings, "interlock", None)
        self.latch_store = latch_store
        self.interlock = Interlock(driver, il_settings, on_change=latch_store.save if latch_store is not None else None)
        if latch_store is not None:
            # a write that fails is the fault `latch_store` (the interlock goes on); one that works again recovers it
            latch_store.on_error = lambda why: self.fault("latch_store", why)
            latch_store.on_ok = lambda: self.recover("latch_store")
        self.on_blind = str(getattr(il_settings, "on_blind", "hold") or "hold")
        # Every command that changes the machine is recorded here (the sink's Zenoh commands too).
        self.audit = audit if audit is not None else AuditLog(None, self.machine)
        alarms = getattr(settings, "alarms", None)
        self._check = ResetCheck(_limit(alarms, "crash_power_w"), _limit(alarms, "crash_current_a"))
        self._check_lock = threading.Lock()
        self._trip_lock = threading.RLock()  # every trip, from the reader thread or the estimator's
        self._frame_lock = threading.Lock()  # the per-frame crash check and the crashes it found
        self.frame_check: FrameCheck | None = None
        self._frame_desc: Any = None
        self._frame_events: list[AlarmEvent] = []  # tripped on the reader thread, not yet published
        self._frame_error_said = False
        self._wake_at_seq: int | None = None  # a frame reaching this sample may close a revolution
        self._blind_lock = threading.Lock()
        self._blind_acted: set[str] = set()
        self._last_seq: int | None = None
        self._spindle_stopped = False
        self.last_test_trip: dict[str, Any] | None = None
        self.sink: Any = None
        self.latency = LatencyStats()  # per revolution: its frame handed to the estimator thread → sink
        self.delay = LatencyStats()    # per revolution: its frame decoded by the reader → sink (queue wait too)
        self.clock: SeqClock | None = None
        self.power_check = PowerSignCheck()
        self.loss_check = LossCheck(float(getattr(getattr(settings, "daq", None), "sample_rate_hz", 1000)))
        self.phase_check: PhaseCheck | None = None   # for the estimator's descriptor (`_check_phase`)
        self._phase_desc: Any = None
        self.rate_check: RateCheck | None = None   # at the estimator's descriptor's rate (`_note_arrival`)
        self._check_rate = bool(getattr(getattr(settings, "daq", None), "check_sample_rate", True))
        # Adaptive feed control (issue 15, docs/afc.md): off at start unless [afc] enabled. The controller decides per
        # revolution on the estimator thread; any thread that sees a fault or trips sets the override to
        # min(current, 100 %) at once (`_afc_safe`). One lock orders the controller's state and the writes.
        self.feed = FeedController(getattr(settings, "afc", None), getattr(settings, "material", None),
                                   batch_s=BATCH_S)
        self.feed_out = OverrideOutput(driver)
        self._afc_lock = threading.RLock()
        self.applied_override_pct: float | None = None  # the DAQ's last STATUS (what the CNC applies)
        self._override_above_since: float | None = None  # AFC on: the applied override above the command since
        # The override on the DAQ is set once to what this daemon holds at the first STATUS after each connection:
        # a daemon restarted faster than the watchdog would otherwise leave the last run's override in place.
        self._afc_resync = True

        self.state = "starting"
        self.faults: dict[str, str] = {}
        self._fault_sources: dict[str, dict[str, str]] = {}  # kind -> {check: reason} (see _signal_source)
        self._fault_lock = threading.Lock()
        self._alarm_lock = threading.Lock()  # the engine is touched by the estimator thread and reset()
        self.active_alarms = ActiveAlarms()  # numbered alarm changes, for subscribers that join late
        # who vouches for a Zenoh context: signed over this run's run_id (issue 36, learning/context_auth.py)
        self.core.context.auth = context_auth.from_settings(settings, self.active_alarms.run_id)
        self._stop = threading.Event()
        self.ready = threading.Event()
        self._threads: list[threading.Thread] = []

        now = time.monotonic()
        self.started_mono = now
        self._stall_since = now
        # the link as the events this thread handled say: the driver's `link_up` turns true before its
        # LinkEvent is queued, and the stall check must not see an old `_stall_since` with a new link
        self._link_handled_up = False
        self._last_block_mono: float | None = None
        self._loop_mono = now
        self._last_rev_mono: float | None = None
        self.samples_received = 0
        self.revolutions = 0
        self.alarms_sent = 0
        self.last_estimate: dict | None = None
        self.last_alarm: dict | None = None
        self._refused_descriptor: Any = None
        self.last_trip_ms: float | None = None
        if history is not None:  # last: a store that could not open reports at once, into the fault path
            history.on_error = lambda why: self.fault("history", why)
            history.on_ok = lambda: self.recover("history")

    # ------------------------------------------------------------------ lifecycle
    def start(self, sink: Any) -> None:
        """Arm the interlock and start the threads. The driver is already started."""
        self.sink = sink
        if self.driver.descriptor is not None:
            self.core.on_descriptor(self.driver.descriptor)  # ConfigError goes to the caller: exit 78
        # No samples yet is a stall only from now: `run` built the runner before waiting for a late DAQ.
        self._stall_since = time.monotonic()
        self._link_handled_up = bool(self.driver.link_up)
        self.interlock.start()
        self._restore_latch()
        if hasattr(self.driver, "sample_hook"):
            self.driver.sample_hook = self._on_frame
            sys.setswitchinterval(min(sys.getswitchinterval(), GIL_SWITCH_S))
        targets = [("estimator", self._estimate_loop), ("status", self._status_loop)]
        if self.interlock.enabled:
            targets.append(("heartbeat", self._heartbeat_loop))
        for name, target in targets:
            t = threading.Thread(target=_named(f"ms-{name}", target), name=f"millsense-{name}", daemon=True)
            t.start()
            self._threads.append(t)

    def stop(self, timeout_s: float = 1.0) -> None:
        """Stop the threads. Feed hold is left exactly as it is; the caller closes sink and driver."""
        if self.state != "stopping":
            self.state = "stopping"
            self._safe(lambda: self._notify(stopping=True, status="stopping"))
            log.info("daemon.stopping", interlock=self.interlock.state)
        self._afc_safe("daemon stopping")  # the heartbeat stops too: the DAQ's watchdog would do it later
        self._stop.set()
        deadline = time.monotonic() + timeout_s
        for t in self._threads:
            t.join(max(0.0, deadline - time.monotonic()))
        if self.latch_store is not None:
            self._safe(self.latch_store.close, max(0.2, deadline - time.monotonic()))
        self._safe(self.audit.flush)

    def _restore_latch(self) -> None:
        """A latch persisted by an earlier run is asserted again, and the log says why and since when."""
        store = self.latch_store
        if store is None:
            return
        state = store.load()
        store.start()
        if state is None:
            return
        since = state.get("since")
        since_iso = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(since)) if since else None
        if not self.interlock.enabled:
            log.warning("interlock.latch_ignored", reason=state["reason"], since=since, since_iso=since_iso,
                        detail="a latch persisted by an earlier run, but the interlock is disabled now")
            return
        self.interlock.restore(state["reason"], since, state.get("trips", 0))
        with self._check_lock:
            self._check.mark(None)  # everything this run sees is newer than the hold
        log.warning("interlock.latched_at_start", reason=state["reason"], since=since, since_iso=since_iso,
                    path=str(store.path),
                    detail="feed hold latched by an earlier run is asserted again until an explicit reset")

    # ------------------------------------------------------------------ estimator thread
    def _estimate_loop(self) -> None:
        drv = self.driver
        batched = hasattr(drv, "drain") and hasattr(drv, "wake")
        while not self._stop.is_set():
            try:
                if batched:
                    drv.wake.wait(BATCH_S if self._wake_at_seq is None else BATCH_TURNING_S)
                    drv.wake.clear()  # before draining: a frame queued after the drain wakes the next wait
                    events = _merged(drv.drain())
                else:
                    ev = drv.get(timeout=BATCH_S)
                    events = [] if ev is None else [(ev, None)]
            except Exception as exc:  # noqa: BLE001
                self.fault("driver", f"get failed: {type(exc).__name__}: {exc}")
                self._stop.wait(0.1)
                continue
            now = time.monotonic()
            self._loop_mono = now
            if self._zenoh_contexts:
                self._safe(self._take_zenoh_contexts)
            if not any(isinstance(ev, SampleBlock) for ev, _ in events):
                self._check_stall(now)
            for ev, parts in events:
                try:
                    self._dispatch(ev, parts, now)
                except Exception as exc:  # noqa: BLE001 - one bad block must not kill the loop
                    self.fault("estimator", f"{type(exc).__name__}: {exc}", tb=traceback.format_exc())
            if self.feed.enabled:
                self._safe(self._afc_idle, time.monotonic())

    def _dispatch(self, ev: Any, parts: list[tuple[int, int, float]] | None, now: float) -> None:
        if isinstance(ev, SampleBlock):
            self._on_block(ev, now, parts)
        elif isinstance(ev, LinkEvent):
            self._on_link(ev)
        elif isinstance(ev, Descriptor):
            self._on_descriptor(ev)
        elif isinstance(ev, Context):
            with self._alarm_lock:
                step = self.core.on_context(ev)
            self._publish_step(step)
        elif isinstance(ev, Status):
            self.interlock.observe_status(ev)
            if ev.feed_override is not None:
                self.applied_override_pct = ev.feed_override / 10.0
                if self._afc_resync:
                    self._afc_resync = False
                    self._safe(self._afc_resync_now)
                self._safe(self._check_override, now)
            self.core.on_status(ev)  # the applied override, sample by sample, for the revolutions
            if self.interlock.device_hold and not self._check.marked:
                with self._check_lock:  # a hold we did not set (the watchdog): judged from now on
                    self._check.mark(self._last_seq)

    # ------------------------------------------------------------------ reader thread
    def _on_frame(self, seq: int, counts: Any, lost: int, disc: bool) -> tuple[bool, bool]:
        """The driver's sample_hook: the crash check on one frame, where it lands. (checked, wake now).

        A crash holds the feed from here, before the frame is even queued; the estimator thread
        publishes it with the frame (`_frame_events`). While the check is latched (the feed held) it
        judges nothing: such a frame goes on unchecked, and the estimator judges it. A reset may come
        before the estimator has taken it, and then nobody else would.
        """
        t0 = time.monotonic()
        try:
            with self._frame_lock:
                fc = self._frame_check_for(self.driver.descriptor)
                if fc is None:
                    return False, True  # no check fits the DAQ: the estimator thread checks every block
                est = self.core.estimator
                gain = float(getattr(getattr(est, "physics", None), "last_gain", 1.0) or 1.0)
                judged = not fc.latched
                crash, current_high = fc.check(seq, counts, lost, disc, gain)
                if crash is not None:
                    self._frame_events.append(crash)
        except Exception as exc:  # noqa: BLE001 - the estimator thread checks the block instead
            if not self._frame_error_said:
                self._frame_error_said = True
                log.error("frame_check_failed", error=f"{type(exc).__name__}: {exc}", traceback=traceback.format_exc())
            return False, True
        last = seq + len(counts) - 1
        if crash is not None:
            self._trip(_trip_reason(crash), last, started=t0)   # frame decoded → output written
            return True, True
        wake_at = self._wake_at_seq
        return judged, current_high or (wake_at is not None and last >= wake_at)

    def _frame_check_for(self, desc: Any) -> FrameCheck | None:
        if desc is not self._frame_desc:
            self._frame_desc = desc
            try:
                self.frame_check = FrameCheck(self.settings, desc) if desc is not None else None
            except Exception:  # noqa: BLE001 - ConfigError: the estimator thread raises the fault
                self.frame_check = None
        return self.frame_check

    def _take_frame_events(self, last_seq: int) -> list[AlarmEvent]:
        """The reader's crashes up to `last_seq`: they are published with the block that holds them."""
        if not self._frame_events:
            return []
        with self._frame_lock:
            taken = [ev for ev in self._frame_events if ev.seq is None or ev.seq <= last_seq]
            self._frame_events = [ev for ev in self._frame_events if not (ev.seq is None or ev.seq <= last_seq)]
        return taken

    def _predict_close(self, step: Any) -> None:
        """The sample at which the next revolution may close, for the reader's wake-up (None: stopped)."""
        if self._spindle_stopped:
            self._wake_at_seq = None
            return
        for kind, item in reversed(step.items):
            if kind == "estimate" and item.get("seq_end") is not None:
                period = int(item.get("samples") or 0) + int(item.get("lost_samples") or 0)
                if period > 0:
                    # the first sample past the next boundary closes it, at this speed: woken earlier, the
                    # estimator found no revolution to close about half the time (a wake-up for nothing);
                    # one that speeds up closes sooner and waits at most for the next frame
                    self._wake_at_seq = int(item["seq_end"]) + period + 1
                return

    # ------------------------------------------------------------------ estimator thread, per block
    def _on_block(self, block: Any, now: float, parts: list[tuple[int, int, float]] | None = None) -> None:
        n = len(block.counts)
        self.samples_received += n
        self._last_block_mono = now
        if self.faults:   # samples flow: the link works, also from a DAQ whose descriptor does not fit
            for kind in DAQ_FAULTS:
                if kind in self.faults:
                    self.recover(kind)
        if self.core.estimator is None:
            if self.driver.descriptor is not None:
                self._on_descriptor(self.driver.descriptor)
            if self.core.estimator is None:
                self.core.skip(block)  # received but unusable; its known losses still count
                self._check_blind()
                return
        if self.clock is None:
            self.clock = SeqClock(self.core.descriptor.sample_rate_hz)
        restart = bool(block.discontinuity or block.lost_before)
        if parts is None:
            parts = [(block.seq, n, float(getattr(block, "received_mono", 0.0) or 0.0))]
        if parts[0][2] > 0.0:
            # each frame's own arrival, stamped by the reader: waiting in the queue does not make `t` late
            wall_minus_mono = time.time() - time.monotonic()
            for k, (first, count, mono) in enumerate(parts):
                self.clock.note_block(first, count, mono + wall_minus_mono, restart=restart and k == 0, mono_s=mono)
                self._note_arrival(first + count - 1, mono, block.discontinuity and k == 0)
        elif restart or self.clock.empty or self._caught_up():
            # A block that waited in the queue behind others arrived earlier than we see it:
            # its get() time would make `t` late, so only fresh blocks set the clock.
            self.clock.note_block(block.seq, n, time.time(), restart=restart, mono_s=now)
            self._note_arrival(block.seq + n - 1, now, block.discontinuity)
        frame_events = self._take_frame_events(block.seq + n - 1)
        with self._alarm_lock:
            step = self.core.process(block, frame_events)
        if "estimator" in self.faults:
            self.recover("estimator")  # only once a block went through again
        feed_check = getattr(getattr(self.core.estimator, "physics", None), "feed_check", None)
        for event, fields in feed_check.take() if feed_check is not None else ():  # per_revolution.FeedCheck
            log.warning(event, **fields)
        last_seq = step.last_seq if step.last_seq is not None else block.seq + n - 1
        self._spindle_stopped = bool(step.spindle_stopped or self.core.spindle_stopped)
        self._last_seq = last_seq  # a hold that begins now is newer than this block: its data do not count
        self._predict_close(step)
        interlock_by_event: dict[int, str | None] = {}
        for ev in step.trips:  # feed hold first, before anything is published
            interlock_by_event[id(ev)] = self._trip(_trip_reason(ev), started=now)  # block handed over → written
        for kind, reason in step.faults.items():  # signal plausibility: blind while it lasts
            self._signal_source(kind, "plausibility", reason)
        for kind in step.clear_faults:
            self._signal_source(kind, "plausibility", None)
        self._verdict("data_loss", self.loss_check.update(block.seq, n, block.lost_before, block.discontinuity,
                                                          block.after_link_up))
        self._check_blind()
        with self._check_lock:  # evidence for a reset: only what is newer than the hold counts
            self._check.on_block(block.seq, step.peaks, step.stalled, self._spindle_stopped)
            for kind, item in step.items:
                if kind == "estimate":
                    self._check.on_estimate(item, self.core.alarms.over_limits(item))
        suspect = self._newest_pinned() if self.feed.enabled else None
        stored: list[dict] = []   # into the history once the block's estimates are out (it never waits for it)
        try:
            for kind, item in step.items:
                if kind == "estimate":
                    self._verdict("wiring", self.power_check.update(item))
                    try:
                        self._afc_revolution(item, now, suspect)
                    except Exception as exc:  # noqa: BLE001 - the controller's error must not stop the estimates
                        self._afc_error(exc, item)
                    t = self.clock.time_of(int(item.get("seq_end", block.seq + n - 1)))
                    payload = estimate_payload(item, self.machine, t)
                    self.revolutions += 1  # counted before it is out: status never lags what subscribers got
                    self.last_estimate = payload
                    self.sink.estimate(payload)
                    stored.append(payload)
                    done = time.monotonic()
                    self.latency.add(done - now)
                    self.delay.add(done - _arrival(parts, int(item.get("seq_end", last_seq)), now))
                    self._last_rev_mono = now
                elif kind == "process":
                    self._publish_process(item)
                else:
                    self._publish_alarm(item, interlock_by_event.get(id(item), self._held()))
        finally:  # what went out reaches the history, even if a later item of the block raised
            if self.history is not None:
                for payload in stored:
                    self.history.add_revolution(payload)
        self._after_step(step)
        self._safe(self._check_phase, block)
        if not self.ready.is_set():
            self.state = "running" if not self.faults else "degraded"
            self.ready.set()
            self._safe(lambda: self._notify(ready=True, status="running: DAQ streaming, Zenoh open"))
            log.info("daemon.ready", machine=self.machine, interlock=self.interlock.state)

    # ------------------------------------------------------------------ adaptive feed control (feed_control.py)
    def _afc_apply(self, decision: Any, why: str) -> None:
        """Write a decision's override, if it has one. A safe decision never raises what the DAQ holds."""
        if decision is not None and decision.override_pct is not None:
            self.feed_out.write(decision.override_pct, why, only_down=decision.state == "safe")

    def _afc_safe(self, reason: str) -> None:
        """A fault, a blind signal, a trip, a stop: the override to min(current, 100 %) at once, any thread."""
        with self._afc_lock:
            self._afc_apply(self.feed.safe(reason), reason)

    def _afc_blocked(self) -> str | None:
        """Why the controller may not move the feed now: a fault, a hold (the DAQ's or ours)."""
        for kind, reason in list(self.faults.items()):
            return f"fault: {kind}: {reason}"
        il = self.interlock
        if il.latched or il.device_hold:
            return f"feed hold: {il.reason or 'held by the DAQ'}"
        return None

    def _afc_release(self) -> None:
        """The condition is gone (a fault recovered, a reset granted): control may start again from air."""
        with self._afc_lock:
            if self._afc_blocked() is None:
                self.feed.release()

    def _afc_idle(self, now: float) -> None:
        """Each estimator wake-up: no healthy revolution for too long while above 100 % -> back to 100 %."""
        with self._afc_lock:
            self._afc_apply(self.feed.on_idle(now), "no recent revolution")

    def _newest_pinned(self) -> str | None:
        """A channel that stopped moving in the newest samples the estimator has (signal_check.py), if any."""
        signals = getattr(self.core.estimator, "signals", None)
        return signals.newest_pinned() if signals is not None else None

    def _afc_revolution(self, est: dict, now: float, suspect: str | None = None) -> None:
        """The controller's step for one revolution, before it is published; the estimate carries its state.
        `suspect`: a channel that stopped moving in the newest samples: no feed is raised on it."""
        feed = self.feed
        if feed.enabled:
            seq = est.get("seq_end")
            ctx = self.core.context.at(int(seq)) if seq is not None else None
            tool = None if ctx is None else ctx.tool
            operation = None if ctx is None else ctx.operation
            learned = None
            monitor = self.core.monitor
            if monitor is not None and ctx is not None:
                with self._alarm_lock:
                    learned = monitor.learned_mean(ctx.key, feed.quantity_key)
            with self._afc_lock:
                blocked = self._afc_blocked()
                if blocked is not None:
                    decision = feed.safe(blocked)
                else:
                    decision = feed.on_revolution(
                        est, target=feed.target_for(tool, operation, learned),
                        allowed=feed.allowed(tool, operation, None if ctx is None else ctx.afc_allowed), now_s=now,
                        suspect=suspect, untrusted=context_auth.untrusted_reason(ctx))
                self._afc_apply(decision, "afc")
        est["afc"] = {"state": feed.state, "override_pct": feed.commanded_pct, "target": feed.target}

    def _afc_error(self, exc: Exception, est: dict) -> None:
        """A bug in the controller's step: the override comes down to <= 100 % and stays there; estimates go on."""
        reason = f"afc error: {type(exc).__name__}: {exc}"
        if reason not in self._notes_said:  # once per distinct error: a lasting one would log every revolution
            self._notes_said.add(reason)
            self._safe(lambda: log.error("afc.error", reason=reason, traceback=traceback.format_exc()))
        self._safe(self._afc_safe, reason)
        est["afc"] = {"state": self.feed.state, "override_pct": self.feed.commanded_pct, "target": None}

    def _afc_resync_now(self) -> None:
        """Write what the controller holds (100 % unless it is controlling) to a DAQ just (re)connected."""
        with self._afc_lock:
            self.feed_out.write(self.feed.commanded_pct, "the DAQ connected: its override set to this daemon's")

    def _afc_descriptor(self, desc: Any) -> None:
        available = bool(getattr(desc, "has_feed_override", False))
        with self._afc_lock:
            self.feed.set_available(available)
        if not available and "afc.unavailable" not in self._notes_said:
            self._notes_said.add("afc.unavailable")
            log.info("afc.unavailable", protocol_version=getattr(desc, "protocol_version", None),
                     detail="this DAQ has no feed-override output (protocol version 1): no adaptive feed control")

    def _afc_refusal(self) -> str | None:
        """Why `afc on` cannot be granted, or None."""
        available = self.feed_out.available
        if available is None:
            return "the DAQ has not described itself yet: try again once it streams"
        if not available:
            return ("this DAQ has no feed-override output (protocol version 1, or capabilities bit 0 clear): "
                    "adaptive feed control needs a protocol-2 DAQ")
        if not self.interlock.enabled:
            return ("the interlock is disabled ([interlock] enabled = false): without its heartbeat the DAQ's "
                    "watchdog could not return the override to 100 % if the daemon stopped")
        return None

    def _override_runaway(self) -> str | None:
        """AFC on: the applied override above both 100 % and the command (what it is, in words), else None."""
        applied, sent = self.applied_override_pct, self.feed_out.sent_pct
        if applied is None or not self.feed.enabled or applied <= max(sent, 100.0) + OVERRIDE_MARGIN_PCT:
            return None
        return (f"the CNC applies a {applied:.1f} % feed override where {sent:.1f} % is commanded: the feed runs "
                f"faster than programmed and nothing controls it (a DAQ that does not apply the override command, "
                f"a stuck output or PLC)")

    def _check_override(self, now: float) -> None:
        """Each STATUS: the feed held once the applied override stayed above the command for OVERRIDE_FOLLOW_S."""
        runaway = self._override_runaway()
        if runaway is None:
            self._override_above_since = None
            return
        if self._override_above_since is None:
            self._override_above_since = now
        if now - self._override_above_since < OVERRIDE_FOLLOW_S or self.interlock.latched:
            return
        held = self._trip(f"afc: {runaway}")
        log.error("afc.override_not_followed", applied_pct=self.applied_override_pct, sent_pct=self.feed_out.sent_pct,
                  detail=runaway)
        ev = AlarmEvent("overload", "feed_override_pct", self.applied_override_pct,
                        max(self.feed_out.sent_pct, 100.0), None, self._last_seq)
        self._safe(self._publish_alarm, ev, held)

    def _afc_status(self) -> dict[str, Any]:
        with self._afc_lock:
            out = dict(self.feed.status())
        out["available"] = self.feed_out.available
        out["applied_pct"] = self.applied_override_pct
        out["sent_pct"] = self.feed_out.sent_pct
        return out

    def afc_command(self, args: dict, requester: str = "") -> dict[str, Any]:
        """`cmd/afc`, `millsense afc`: switch adaptive feed control on or off (the caller authorised it)."""
        if not isinstance(args, dict):
            return {"ok": False, "reason": "the arguments must be a JSON object"}
        action = args.get("action")
        if action == "status":
            return {"ok": True, "afc": self._afc_status()}
        if action not in ("on", "off"):
            return {"ok": False, "reason": f"unknown action {action!r}: on, off or status"}
        refusal = self._afc_refusal() if action == "on" else None
        if refusal is not None:
            log.warning("afc.refused", requester=requester or "unknown", action=action, reason=refusal)
            return {"ok": False, "reason": refusal, "afc": self._afc_status()}
        with self._afc_lock:
            self._afc_apply(self.feed.switch(action == "on", time.monotonic()), f"afc {action}")
            blocked = self._afc_blocked() if action == "on" else None
            if blocked is not None:  # on, but it waits: a fault or a hold keeps it safe until it is gone
                self._afc_apply(self.feed.safe(blocked), blocked)
        log.warning("afc.switched", requester=requester or "unknown", on=action == "on", state=self.feed.state,
                    reason=blocked)
        return {"ok": True, "afc": self._afc_status()}

    # ------------------------------------------------------------------ learned limits (daemon/learning)
    def _publish_step(self, step: Any) -> None:
        """A step that closed no revolution (a context change, a lost link): trips, alarms, processes."""
        held: dict[int, str | None] = {}
        for ev in step.trips:
            held[id(ev)] = self._trip(_trip_reason(ev))
        for kind, item in step.items:
            if kind == "process":
                self._publish_process(item)
            elif kind == "alarm":
                self._publish_alarm(item, held.get(id(item), self._held()))
        self._after_step(step)

    def _publish_process(self, summary: dict) -> None:
        seq = summary.get("seq_end")
        t = self.clock.time_of(int(seq)) if (self.clock is not None and seq is not None) else time.time()
        payload = process_payload(summary, self.machine, t)
        self.processes += 1
        self.last_process = payload
        publish = getattr(self.sink, "process", None)
        if publish is not None:
            publish(payload)
        if self.history is not None:
            self.history.add_process(payload)
        log.info("process", **{k: v for k, v in payload.items() if k not in ("machine", "t")})

    def _after_step(self, step: Any) -> None:
        """Persist the learned limits that changed; say each one-time note once."""
        for event, fields in step.notes:
            if event not in self._notes_said:
                self._notes_said.add(event)
                log.info(event, **fields)
        monitor = self.core.monitor
        if self.history is None or monitor is None or not (step.changed_limits or step.tools_changed):
            return
        with self._alarm_lock:
            limits = {key: monitor.export_limits(key) for key in step.changed_limits}
            tools = monitor.export_tools() if step.tools_changed else None
        for key, data in limits.items():
            self.history.save_limits(key, data)
        if tools is not None:
            self.history.save_tools(tools)

    def on_context_payload(self, payload: dict, source: str = "") -> None:
        """A CNC adapter's `context` put (Zenoh's thread): applied by the estimator thread, in order. One refused
        for its content, or ignored by `[context] source`, raises ValueError here: the sink counts it refused."""
        judged = self.core.context.judge_zenoh(payload)
        if isinstance(judged, str):
            raise ValueError(judged)
        with self._context_lock:
            if len(self._zenoh_contexts) < 64:  # a flood keeps the newest few, never grows
                self._zenoh_contexts.append((payload, source))
            else:
                self._zenoh_contexts[-1] = (payload, source)
        wake = getattr(self.driver, "wake", None)
        if wake is not None:
            wake.set()

    def _take_zenoh_contexts(self) -> None:
        with self._context_lock:
            taken, self._zenoh_contexts = self._zenoh_contexts, []
        for payload, source in taken:
            with self._alarm_lock:
                step, refused = self.core.on_zenoh_context(payload)
            if refused:
                self._context_refused.note(source or "unknown", refused)
                continue
            self._publish_step(step)

    def limits(self) -> dict[str, Any]:
        """The `limits` queryable: learned limits per process key, and the tools' life and wear."""
        monitor = self.core.monitor
        if monitor is None:
            return {"machine": self.machine, "enabled": False, "limits": [], "tools": {}}
        with self._alarm_lock:
            return {"machine": self.machine, "enabled": True, **monitor.limits_summary()}

    def limits_command(self, args: dict, requester: str = "") -> dict[str, Any]:
        """`cmd/limits` and `millsense limits`: the operator's changes (the caller authorised them)."""
        monitor = self.core.monitor
        if monitor is None:
            return {"ok": False, "error": "learning is off ([learning] enabled = false)"}
        if not isinstance(args, dict):
            return {"ok": False, "error": "the arguments must be a JSON object"}
        with self._alarm_lock:
            result = monitor.command(dict(args))
            changed = list(result.pop("changed_keys", ()) or ())
            tools_changed = bool(result.pop("tools_changed", False))
        if args.get("action") not in ("list", "show"):  # a read changes nothing: a flood of them logs nothing
            log.warning("limits.command", requester=requester or "unknown", action=args.get("action"),
                        key=args.get("key"), tool=args.get("tool"), pct=args.get("pct"), ok=result.get("ok"),
                        error=result.get("error"))
        if changed or tools_changed:
            from millsense.daemon.pipeline.run_core import Step

            step = Step()
            step.changed_limits, step.tools_changed = set(changed), tools_changed
            self._after_step(step)
        return result

    def _note_arrival(self, seq_last: int, arrival_s: float, restart: bool) -> None:
        """The samples' arrival rate against the descriptor's (rate_check.py): fault `signals`, source
        `sample_rate`; while it holds, the estimator publishes every revolution invalid."""
        if not self._check_rate:
            return
        rate = float(self.core.descriptor.sample_rate_hz)
        last = self.rate_check
        if last is None or last.rate != rate:
            self.rate_check = RateCheck(rate, faulted=last is not None and last.faulted)
        self._verdict("sample_rate", self.rate_check.update(seq_last, arrival_s, restart))
        self.core.stream_problem = "sample_rate" if self.rate_check.faulted else None

    def _check_phase(self, block: Any) -> None:
        """The currents against each other and the voltages (phase_check.py): fault `signals`, source `phase`.
        Once a second, after the block's estimates are published: a wiring mistake is judged over seconds."""
        desc = self.core.descriptor
        if desc is not self._phase_desc:
            last = self.phase_check
            self._phase_desc, self.phase_check = desc, None
            if desc is not None:   # the estimator accepted it: so does this; it goes on from the last verdict
                self.phase_check = PhaseCheck(self.settings, desc, faulted=last is not None and last.faulted)
        if self.phase_check is None:
            return
        self._verdict("phase", self.phase_check.update(block.counts, block.lost_before, block.discontinuity))

    def _verdict(self, source: str, verdict: str | None) -> None:
        """A wiring or stream check's verdict (verdict.py) on fault `signals`, from `source`."""
        if verdict is not None:
            self._signal_source("signals", source, verdict or None)

    def _signal_source(self, kind: str, source: str, reason: str | None) -> None:
        """One fault kind fed by several checks (`signals`: plausibility, wiring, data_loss, phase):
        raised while any of them holds it, recovered only when none does. When the check that raised it
        clears while another still holds it, the fault's reason becomes the other's."""
        sources = self._fault_sources.setdefault(kind, {})
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
        with self._fault_lock:
            if self.faults.get(kind) in (None, still):
                return
            self.faults[kind] = still
        self._safe(lambda: log.warning("fault.reason_changed", kind=kind, reason=still, cleared=source,
                                       detail="one cause cleared; the fault stays for the other"))
        self._safe(lambda: self._notify(status=f"degraded: {kind}: {still}"))

    def _caught_up(self) -> bool:
        """Is the driver's queue empty, i.e. did this block just arrive?"""
        return self.driver.queued == 0

    def _held(self) -> str | None:
        return "feed_hold" if self.interlock.latched else None

    def _publish_alarm(self, ev: AlarmEvent, interlock: str | None) -> None:
        t = self.clock.time_of(ev.seq) if (self.clock is not None and ev.seq is not None) else time.time()
        payload = self.active_alarms.stamp(alarm_payload(ev, self.machine, t, interlock))
        self.sink.alarm(payload)
        self.alarms_sent += 1
        self.last_alarm = payload
        if self.history is not None:
            self.history.add_alarm(payload)
        # The alarm's kind goes under `alarm_level`: structlog's add_log_level writes the log level
        # into `level` and would overwrite it (issue 10, finding 7).
        # run_id and alarm_seq are for subscribers that catch up (alarm_state.py), not for the person reading the log
        fields = {k: v for k, v in payload.items() if k not in ("machine", "level", "run_id", "alarm_seq")}
        log.warning("alarm", alarm_level=payload["level"], **fields)

    def _trip(self, reason: str, last_seq: int | None = None, started: float | None = None) -> str | None:
        """Every feed hold goes through here, from any thread: the interlock's trip, then the mark
        for the reset check. `last_seq`: the last sample the tripping thread saw (the reader's frame);
        default the estimator's. `started`: the monotonic time the tripping data were taken; a new latch
        sets `last_trip_ms` from it to the hold's write (what follows the write is not the trip's)."""
        with self._trip_lock:
            trips = self.interlock.trips
            result = self.interlock.trip(reason)
            if self.interlock.trips != trips:  # a new latch (not one already held)
                with self._check_lock:
                    self._check.mark(self._last_seq if last_seq is None else max(last_seq, self._last_seq or 0))
                written = self.interlock.hold_written_mono
                if started is not None and written is not None:
                    self.last_trip_ms = round((written - started) * 1e3, 3)
        self._afc_safe(f"feed hold: {reason}")  # after the hold is written: it never waits for this
        return result

    def _check_blind(self) -> None:
        """on_blind: a blind condition while the spindle turns holds the feed ("hold") or only warns ("alarm").

        The time before the DAQ's first descriptor raises no fault, so it is never blind; a
        `signals` fault with the spindle stopped waits until it turns. A `descriptor` fault leaves
        no estimator to say whether it turns: it is blind at once (when in doubt, hold).
        """
        if not self.interlock.enabled:
            return
        events: list[tuple[AlarmEvent, str | None]] = []
        with self._blind_lock:
            for kind in BLIND_KINDS:
                reason = self.faults.get(kind)
                if reason is None:
                    if kind in self._blind_acted:
                        self._blind_acted.discard(kind)
                        events.append((AlarmEvent("clear", kind, None, None, None, self._last_seq), None))
                    continue
                if kind in self._blind_acted or (kind == "signals" and self._spindle_stopped):
                    continue
                self._blind_acted.add(kind)
                if self.on_blind == "hold":
                    held = self._trip(f"blind: {kind}: {reason}")
                    events.append((AlarmEvent("overload", kind, None, None, None, self._last_seq), held))
                else:
                    log.warning("interlock.blind_not_held", kind=kind, reason=reason,
                                detail='[interlock] on_blind = "alarm": the machine runs unwatched')
                    events.append((AlarmEvent("warning", kind, None, None, None, self._last_seq), None))
        for ev, held in events:
            self._safe(self._publish_alarm, ev, held if ev.level != "clear" else self._held())

    def _on_link(self, ev: Any) -> None:
        self._link_handled_up = bool(ev.up)
        if ev.up:  # the driver logged it (`daq.link_up`, with transport and address)
            self._stall_since = time.monotonic()
            # A DAQ that restarted forgot its watchdog and maybe the latched output; its override is 100 %, or
            # (a link that only dropped) still what it was: set again at its first STATUS.
            self.feed_out.device_restarted()
            self._afc_resync = True
            self._safe(self.interlock.start)
            self._safe(self.interlock.reassert)
        else:
            self.fault("daq_link", f"lost communication with the DAQ: {ev.reason}")

    def _on_descriptor(self, desc: Any) -> None:
        if desc == self._refused_descriptor:
            return
        try:
            if self.core.on_descriptor(desc):
                self.clock = SeqClock(desc.sample_rate_hz)
                log.info("daq.descriptor", rate_hz=desc.sample_rate_hz, channels=list(desc.names))
        except Exception as exc:  # noqa: BLE001 - ConfigError: the DAQ no longer fits the config
            problems = getattr(exc, "problems", None) or [str(exc)]
            self._refused_descriptor = desc
            self.core.drop_estimator()
            self.fault("descriptor", "; ".join(problems))
            return
        self._refused_descriptor = None
        self._afc_descriptor(desc)
        self.recover("descriptor")

    def _check_stall(self, now: float) -> None:
        # since the last samples, or since the link came (back) up: the time it was down is `daq_link`'s
        last = max(self._last_block_mono or self._stall_since, self._stall_since)
        if self._link_handled_up and now - last > DAQ_STALL_S and "daq_stalled" not in self.faults:
            self.fault("daq_stalled", f"no samples for {now - last:.1f} s with the link up")

    # ------------------------------------------------------------------ fault path
    def fault(self, kind: str, reason: str, tb: str | None = None) -> None:
        """The one fault path. Idempotent per kind; each handler in its own try."""
        with self._fault_lock:
            if kind in self.faults:
                return
            self.faults[kind] = reason
        if self.state in ("running", "starting") and self.ready.is_set():
            self.state = "degraded"
        self._safe(self._afc_safe, f"fault: {kind}: {reason}")  # first: the feed never runs above programmed unseen
        self._safe(lambda: log.error("fault", kind=kind, reason=reason, dump=self._diagnostics(), traceback=tb))
        self._safe(lambda: self.interlock.beat(self.healthy(), stopping=self.state == "stopping"))
        if kind in ("daq_link", "daq_stalled"):
            self._safe(self._daq_alarm, False)
        if kind in BLIND_KINDS:  # and again per block: a `signals` fault waits for a turning spindle
            self._safe(self._check_blind)
        self._safe(lambda: self._notify(status=f"degraded: {kind}: {reason}"))

    def recover(self, kind: str) -> None:
        with self._fault_lock:
            if self.faults.pop(kind, None) is None:
                return
            remaining = bool(self.faults)
        if kind in ("daq_link", "daq_stalled") and not any(k in self.faults for k in ("daq_link", "daq_stalled")):
            self._safe(self._daq_alarm, True)
        if not remaining and self.state == "degraded":
            self.state = "running"
        log.info("recovered", kind=kind)
        if kind in BLIND_KINDS:
            self._safe(self._check_blind)
        self._safe(self._afc_release)

    def _daq_alarm(self, ok: bool) -> None:
        with self._alarm_lock:
            events = self.core.alarms.on_daq(ok)
            lost = self.core.on_link_lost() if not ok else None
        for ev in events:
            self._publish_alarm(ev, self._held())
        if lost is not None:
            self._publish_step(lost)

    def _diagnostics(self) -> dict[str, Any]:
        d: dict[str, Any] = {"samples": self.samples_received, "revolutions": self.revolutions}
        for name, fn in (("driver", getattr(self.driver, "stats", None)), ("sink", getattr(self.sink, "stats", None))):
            try:
                d[name] = fn() if fn else None
            except Exception as exc:  # noqa: BLE001
                d[name] = f"unavailable: {exc}"
        d["interlock"] = self.interlock.state_dict()
        d["last_estimate"] = self.last_estimate
        return d

    @staticmethod
    def _safe(fn: Callable[..., Any], *args: Any) -> None:
        try:
            fn(*args)
        except Exception as exc:  # noqa: BLE001
            try:
                log.error("fault_handler_failed", handler=getattr(fn, "__name__", "?"), error=f"{type(exc).__name__}: {exc}")
            except Exception:  # noqa: BLE001
                pass

    # ------------------------------------------------------------------ health, heartbeat
    def healthy(self, now: float | None = None) -> bool:
        now = time.monotonic() if now is None else now
        if self.state == "stopping" or not self.driver.link_up or self._last_block_mono is None:
            return False
        if "estimator" in self.faults or "descriptor" in self.faults:
            return False
        return now - self._last_block_mono < HEALTH_STALL_S and now - self._loop_mono < HEALTH_STALL_S

    def _heartbeat_loop(self) -> None:
        period = self.interlock.heartbeat_ms / 1000.0
        next_t = time.monotonic()
        while not self._stop.is_set():
            self.interlock.beat(self.healthy(), stopping=self.state == "stopping")
            next_t += period
            delay = next_t - time.monotonic()
            if delay < 0:
                next_t, delay = time.monotonic(), 0.0
            self._stop.wait(delay)

    # ------------------------------------------------------------------ status thread
    def progressing(self, now: float | None = None) -> bool:
        """For sd_notify WATCHDOG=1: revolutions closing, or spindle stopped with samples flowing."""
        now = time.monotonic() if now is None else now
        if self._last_rev_mono is not None and now - self._last_rev_mono < PROGRESS_S:
            return True
        return self.core.spindle_stopped and self.healthy(now)

    def _status_loop(self) -> None:
        try:
            from millsense.daemon import sdnotify

            wd = sdnotify.watchdog_interval_s()
        except Exception:  # noqa: BLE001 - no systemd watchdog: nothing to feed
            wd = None
        tick = min(1.0, wd) if wd else 1.0
        next_status = time.monotonic() + 1.0
        while not self._stop.wait(tick):
            now = time.monotonic()
            if wd and self.progressing(now):
                self._safe(lambda: self._notify(watchdog=True))
            if now < next_status:
                continue
            next_status += 1.0
            status = self.status()
            line = status_line(status)
            self._safe(self.sink.status, status)
            self._safe(lambda: self._notify(status=line))
            self._safe(lambda: log.debug("stats", **{k: v for k, v in status.items() if k not in ("machine", "version")}))
            if self._on_second is not None:
                with self._alarm_lock:
                    alarm_state = self.core.summary()
                self._safe(self._on_second, status, self.last_estimate, alarm_state)

    # ------------------------------------------------------------------ Controls
    def status(self) -> dict[str, Any]:
        stats: dict[str, Any] = {}
        try:
            stats = dict(self.driver.stats())
        except Exception:  # noqa: BLE001
            pass
        with self._alarm_lock:
            alarms = self.core.active()
            alarm = self.core.summary()
            ctx = self.core.context.at(self._last_seq) if self._last_seq is not None else None
            learning = _learning_status(self.core.monitor)
            learned = {} if self.core.monitor is None else {"learned_limits": self.core.monitor.learned_limits_status()}
        return {
            "machine": self.machine,
            "t": time.time(),
            "state": self.state,
            "daq_link": "up" if self.driver.link_up else "down",
            "samples_received": self.samples_received,
            "bad_frames": bad_frames(stats),
            "lost_samples": self.core.lost_samples_total,
            "revolutions": self.revolutions,
            "latency_ms": self.latency.percentiles_ms(),
            "rev_delay_ms": self.delay.percentiles_ms(),
            "interlock": self.interlock.state,
            "interlock_detail": interlock_detail(self.interlock, self.driver),
            "heartbeating": self.interlock.heartbeating,
            "last_trip_ms": self.last_trip_ms,
            "last_test_trip": self.last_test_trip,
            "alarm": alarm,
            "alarms": alarms,
            **self.active_alarms.snapshot(),
            "faults": dict(self.faults),
            "context": None if ctx is None else {"program": ctx.program, "tool": ctx.tool,
                                                 "operation": ctx.operation, "source": ctx.source,
                                                 "authority": ctx.authority},
            "context_auth": self.core.context.auth.status() if self.core.context.auth is not None else None,
            "processes": self.processes,
            "learning": learning,
            **learned,
            "afc": self._afc_status(),
            "history": self._history_stats(),
            "daq": stats,
            "sink": self._sink_stats(),
            "uptime_s": round(time.monotonic() - self.started_mono, 1),
            "version": self.version,
        }

    def _history_stats(self) -> dict | None:
        try:
            return self.history.stats() if self.history is not None else None
        except Exception:  # noqa: BLE001
            return None

    def _sink_stats(self) -> dict | None:
        try:
            return self.sink.stats() if self.sink is not None and hasattr(self.sink, "stats") else None
        except Exception:  # noqa: BLE001
            return None

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
        il = self.interlock
        with self._check_lock:
            held = il.latched or il.device_hold
            blind = {k: self.faults[k] for k in BLIND_KINDS if k in self.faults}
            daq = next((f"{k}: {self.faults[k]}" for k in DAQ_FAULTS if k in self.faults), None)
            if daq is None and not self.driver.link_up:
                daq = "daq_link: the link is down"
            refusal = self._check.refusal(il.reason, blind, daq) if held and il.enabled else None
            runaway = self._override_runaway() if held and il.enabled else None
            if refusal is None and runaway is not None:
                refusal = {"condition": "feed_override", "error": runaway}
        if refusal is not None:
            log.warning("interlock.reset_refused", requester=requester or "unknown", reason=il.reason, **refusal)
            result = {"ok": False, **refusal, **il.state_dict()}
            result["alarm"] = self.core.summary()
            return result
        result = il.reset()
        if result.get("ok"):
            with self._check_lock:
                self._check.clear()
            with self._alarm_lock:
                events = self.core.reset()
            with self._frame_lock:
                if self.frame_check is not None:
                    self.frame_check.rearm()
            for ev in events:
                self._safe(self._publish_alarm, ev, None)
            self._safe(self._afc_release)
        result["alarm"] = self.core.summary()
        return result

    def test_trip(self, requester: str = "", wait_s: float = TEST_TRIP_WAIT_S) -> dict[str, Any]:
        """Proof test of the path: feed hold through the same trip as a real alarm, timed to confirmation.

        `daq_confirm_ms`: from the trip to the DAQ's STATUS showing feed hold. On a DAQ that sends
        CONTEXT (protocol 2, capabilities bit 1) `cnc_confirm_ms`: to the CNC's own "feed held"
        input, else null. The latch is real: the caller sends a reset afterwards.
        """
        il, drv = self.interlock, self.driver
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
        self.last_test_trip = {k: result[k] for k in ("ok", "daq_confirm_ms", "cnc_confirm_ms")} | {"t": time.time()}
        log.info("interlock.test_trip_result", requester=requester or "unknown",
                 **{k: v for k, v in result.items() if k != "interlock_detail"})
        return result


def _trip_reason(ev: AlarmEvent) -> str:
    """The interlock's reason for a hold: the alarm, its value and the limit it crossed (from below or above)."""
    side = "<" if ev.level == "envelope_low" else ">"
    return f"{ev.level} {ev.quantity} {ev.value} {side} {ev.limit}"


def _learning_status(monitor: Any) -> dict[str, Any] | None:
    """For `status`: how many process keys are learning, pending, active (None: learning off)."""
    if monitor is None:
        return None
    return monitor.state_counts()


class _RefusalLog:
    """Refused Zenoh contexts, logged at most once per 10 s with a count (a flooding adapter)."""

    def __init__(self, event: str):
        from millsense.daemon.throttle import Throttle

        self.event = event
        self.throttle = Throttle(10.0)

    def note(self, source: str, reason: str) -> None:
        due = self.throttle.note((source, reason))
        if due is not None:
            count, (last_source, last_reason) = due
            log.warning(self.event, source=last_source, reason=last_reason, refused=count)


def _named(os_name: str, target: Callable[[], None]) -> Callable[[], None]:
    """`target`, run under `os_name` in the OS's thread list (`top -H`: which thread costs what)."""
    def run() -> None:
        name_os_thread(os_name)
        target()
    return run


def _merged(events: list[Any]) -> list[tuple[Any, list[tuple[int, int, float]] | None]]:
    """Contiguous frames as one block (one pass of the estimator), with each frame's (seq, n, arrival).

    A frame after lost samples or a discontinuity, or checked differently, starts a new block.
    """
    out: list[tuple[Any, list[tuple[int, int, float]] | None]] = []
    run: list[Any] = []

    def flush() -> None:
        if not run:
            return
        parts = [(b.seq, len(b.counts), b.received_mono) for b in run]
        first = run[0]
        block = first if len(run) == 1 else SampleBlock(
            first.seq, first.index, np.concatenate([b.counts for b in run]), first.lost_before,
            first.discontinuity, first.checked, run[-1].received_mono, first.after_link_up)
        out.append((block, parts))
        run.clear()

    for ev in events:
        if isinstance(ev, SampleBlock):
            prev = run[-1] if run else None
            if prev is not None and not (ev.seq == prev.seq + len(prev.counts) and not ev.lost_before
                                         and not ev.discontinuity and not ev.after_link_up
                                         and ev.checked == prev.checked
                                         and ev.counts.shape[1:] == prev.counts.shape[1:]):
                flush()
            run.append(ev)
        else:
            flush()
            out.append((ev, None))
    flush()
    return out


def _arrival(parts: list[tuple[int, int, float]], seq: int, default: float) -> float:
    """When the frame holding sample `seq` arrived (the reader's stamp), else `default`."""
    for first, count, mono in parts:
        if first <= seq < first + count:
            return mono if mono > 0.0 else default
    return default


def _limit(section: Any, name: str) -> float | None:
    value = getattr(section, name, None) if section is not None else None
    return None if value is None else float(value)
