"""The live runtime: threads between the driver, the estimator, the interlock and the sink.

Threads (one job each, one hand-off queue — the driver's):

- the driver's own reader thread fills its bounded queue, and on every frame,
  before queueing it, runs the frame guard (`frame_guard.FrameGuard.on_frame`,
  the driver's `sample_hook`): the sample-level crash power and current
  (`safety_check.FrameCheck`, a few vector operations). A crash holds the feed
  from there at once (`_trip`) and wakes the estimator to publish it;
- **estimator** (`_estimate_loop`) owns the estimator and the alarm engine.
  It sleeps on the driver's `wake` — set by a crash, by a frame that reaches
  the revolution predicted to close next (`FrameGuard.wake_at_seq`), by a frame whose
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
- **status** (1 s): status payload (`status.StatusReport`), sd_notify `STATUS=` /
  `WATCHDOG=1`, the debug stats line and the optional live summary callback.

The Runner keeps the threads, the estimator loop, `_on_block` and the one trip
path (`_trip`); what it builds, each with its own state and given what it needs:
the frame guard (frame_guard.py), the fault board (faults.py: `fault`, `recover`,
the blind check), the operator's controls (controls.py: the one `Controls`, asked
by the Zenoh sink and the local socket alike), the status payload (status.py),
the interlock (interlock.py) and adaptive feed control (afc/supervisor.py).

The interlock side (issue 10): every feed hold goes through `_trip` (alarms,
a blind condition under `[interlock] on_blind = "hold"`, `test_trip`), which
marks the hold for `ResetCheck`; `reset()` is refused while data newer than
the hold show the condition still there. With a `latch_store` the latch is
persisted off the tripping thread and asserted again at the next start.

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

import structlog

from millsense.daemon.afc.supervisor import AfcSupervisor
from millsense.daemon.audit import AuditLog
from millsense.daemon.events import AlarmEvent
from millsense.daemon.guarded import safe
from millsense.daemon.learning import context_auth
from millsense.daemon.pipeline.alarms import alarm_payload
from millsense.daemon.pipeline.loss_check import LossCheck
from millsense.daemon.pipeline.phase_check import PhaseCheck
from millsense.daemon.pipeline.power_check import PowerSignCheck
from millsense.daemon.pipeline.rate_check import RateCheck
from millsense.daemon.pipeline.run_core import PipelineCore, Step, estimate_payload, process_payload
from millsense.daemon.publish.alarm_state import ActiveAlarms
from millsense.daemon.runtime.blocks import arrival, merged
from millsense.daemon.runtime.controls import OperatorControls
from millsense.daemon.runtime.faults import DAQ_FAULTS, FaultBoard
from millsense.daemon.runtime.frame_guard import FrameGuard
from millsense.daemon.runtime.interlock import Interlock, ResetCheck, trip_reason
from millsense.daemon.runtime.ports import DescriptorCheck, Driver, EstimatorFactory, History, LatchStore, Sink
from millsense.daemon.runtime.status import LiveState, SeqClock, StatusReport
from millsense.daemon.status_text import status_line
from millsense.drivers.base import LinkEvent, SampleBlock, name_os_thread
from millsense.drivers.protocol import Context, Descriptor, Status

log = structlog.get_logger("millsense.runner")

HEALTH_STALL_S = 0.5  # no samples / no estimator loop for this long: stop heartbeats
DAQ_STALL_S = 1.0  # no samples for this long with the link up: `daq_lost`
PROGRESS_S = 3.0  # sd_notify WATCHDOG=1 only if a revolution closed within this
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
    """One machine's live pipeline: its threads, the estimator loop and the one trip path.

    `controls` is what the Zenoh queryables and the local socket ask (`Controls`); `board` its faults
    and state; `frames` the reader thread's crash check; `afc` adaptive feed control; `live` what the
    estimator thread counted and last saw."""

    def __init__(
        self,
        settings: Any,
        driver: Driver,
        *,
        version: str = "0+unknown",
        notify: Callable[..., Any] = _noop_notify,
        on_second: Callable[[dict, dict | None, str], Any] | None = None,
        effective_config: Callable[[], dict] | None = None,
        estimator_factory: EstimatorFactory | None = None,
        check_descriptor: DescriptorCheck | None = None,
        latch_store: LatchStore | None = None,
        audit: AuditLog | None = None,
        history: History | None = None,
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
        self.core = PipelineCore(settings, estimator_factory, check_descriptor, limits=limits, tools=tools,
                                 first_process=first_process)
        if self.core.monitor is not None:  # stored learned limits that failed their check: set aside, said once
            for event, fields in self.core.monitor.take_restore_notes():
                log.warning(event, **fields)
        # The SQLite history (daemon/history): estimates, alarms, process summaries, learned limits.
        # Its writer thread takes what it is handed; a failing disk is the fault `history`, never a stop.
        self.history = history
        self._notes_said: set[str] = set()
        self._context_refused = _RefusalLog("context.refused")
        il_settings = getattr(settings, "interlock", None)
        self.latch_store = latch_store
        self.interlock = Interlock(driver, il_settings, on_change=latch_store.save if latch_store is not None else None)
        # Every command that changes the machine is recorded here (the sink's Zenoh commands too).
        self.audit = audit if audit is not None else AuditLog(None, self.machine)
        alarms = getattr(settings, "alarms", None)
        self.reset_check = ResetCheck(_limit(alarms, "crash_power_w"), _limit(alarms, "crash_current_a"))
        self.check_lock = threading.Lock()
        self._trip_lock = threading.RLock()  # every trip, from the reader thread or the estimator's
        self._alarm_lock = threading.Lock()  # the engine is touched by the estimator thread and reset()
        self.sink: Sink | None = None
        self.live = LiveState(time.monotonic())
        self.clock: SeqClock | None = None
        self.power_check = PowerSignCheck()
        self.loss_check = LossCheck(float(getattr(getattr(settings, "daq", None), "sample_rate_hz", 1000)))
        self.phase_check: PhaseCheck | None = None   # for the estimator's descriptor (`_check_phase`)
        self._phase_desc: Any = None
        self.rate_check: RateCheck | None = None   # at the estimator's descriptor's rate (`_note_arrival`)
        self._check_rate = bool(getattr(getattr(settings, "daq", None), "check_sample_rate", True))
        self.active_alarms = ActiveAlarms()  # numbered alarm changes, for subscribers that join late
        # who vouches for a Zenoh context: signed over this run's run_id (issue 36, learning/context_auth.py)
        self.core.context.auth = context_auth.from_settings(settings, self.active_alarms.run_id)
        self._stop = threading.Event()
        self.ready = threading.Event()
        self.threads: list[threading.Thread] = []

        # The parts the Runner builds: each its own object with its own state, handed what it needs.
        # Adaptive feed control (issue 15, docs/afc.md): off at start unless [afc] enabled. The controller decides
        # per revolution on the estimator thread; any thread that sees a fault or trips sets the override to
        # min(current, 100 %) at once (`afc.safe`).
        self.afc = AfcSupervisor(settings, driver, self.interlock, self.core, batch_s=BATCH_S,
                                 faults=lambda: self.board.faults, trip=self._trip, publish_alarm=self._publish_alarm,
                                 last_seq=lambda: self.live.last_seq, alarm_lock=self._alarm_lock)
        self.board = FaultBoard(self.interlock, self.core, self.live,
                                on_blind=str(getattr(il_settings, "on_blind", "hold") or "hold"),
                                alarm_lock=self._alarm_lock, ready=self.ready, trip=self._trip, held=self._held,
                                publish_alarm=self._publish_alarm, publish_step=self._publish_step,
                                afc_safe=self.afc.safe, afc_release=self.afc.release, healthy=self.healthy,
                                diagnostics=self._diagnostics, notify=self._notify)
        self.frames = FrameGuard(settings, driver, self.core, self._trip)
        self.report = StatusReport(self.machine, version, driver, self.core, self.interlock, self.live,
                                   board=self.board, afc=self.afc, active_alarms=self.active_alarms,
                                   alarm_lock=self._alarm_lock, history=history)
        self.controls = OperatorControls(settings, driver, self.interlock, self.core, machine=self.machine,
                                         audit=self.audit, board=self.board, frames=self.frames, afc=self.afc,
                                         live=self.live, report=self.report, reset_check=self.reset_check,
                                         check_lock=self.check_lock, alarm_lock=self._alarm_lock, trip=self._trip,
                                         trip_lock=self._trip_lock,
                                         publish_alarm=self._publish_alarm, persist_limits=self._persist_limits,
                                         effective_config=effective_config)
        if latch_store is not None:
            # a write that fails is the fault `latch_store` (the interlock goes on); one that works again recovers it
            latch_store.on_error = lambda why: self.board.fault("latch_store", why)
            latch_store.on_ok = lambda: self.board.recover("latch_store")

        now = self.live.started_mono
        self._stall_since = now
        # the link as the events this thread handled say: the driver's `link_up` turns true before its
        # LinkEvent is queued, and the stall check must not see an old `_stall_since` with a new link
        self._link_handled_up = False
        self._last_block_mono: float | None = None
        self._loop_mono = now
        self._last_rev_mono: float | None = None
        self._refused_descriptor: Any = None
        if history is not None:  # last: a store that could not open reports at once, into the fault path
            history.on_error = lambda why: self.board.fault("history", why)
            history.on_ok = lambda: self.board.recover("history")

    @property
    def state(self) -> str:
        """starting → running ⇄ degraded → stopping (the fault board's)."""
        return self.board.state

    @property
    def faults(self) -> dict[str, str]:
        """What is wrong now: kind -> reason (the fault board's)."""
        return self.board.faults

    # ------------------------------------------------------------------ lifecycle
    def start(self, sink: Sink) -> None:
        """Arm the interlock and start the threads. The driver is already started."""
        self.sink = sink
        self.report.sink = sink
        if self.driver.descriptor is not None:
            self.core.on_descriptor(self.driver.descriptor)  # ConfigError goes to the caller: exit 78
        # No samples yet is a stall only from now: `run` built the runner before waiting for a late DAQ.
        self._stall_since = time.monotonic()
        self._link_handled_up = bool(self.driver.link_up)
        self.interlock.start()
        self._restore_latch()
        if hasattr(self.driver, "sample_hook"):
            self.driver.sample_hook = self.frames.on_frame
            sys.setswitchinterval(min(sys.getswitchinterval(), GIL_SWITCH_S))
        targets = [("estimator", self._estimate_loop), ("status", self._status_loop)]
        if self.interlock.enabled:
            targets.append(("heartbeat", self._heartbeat_loop))
        for name, target in targets:
            t = threading.Thread(target=_named(f"ms-{name}", target), name=f"millsense-{name}", daemon=True)
            t.start()
            self.threads.append(t)

    def stop(self, timeout_s: float = 1.0) -> None:
        """Stop the threads. Feed hold is left exactly as it is; the caller closes sink and driver."""
        if self.board.state != "stopping":
            self.board.state = "stopping"
            safe(lambda: self._notify(stopping=True, status="stopping"))
            log.info("daemon.stopping", interlock=self.interlock.state)
        self.afc.safe("daemon stopping")  # the heartbeat stops too: the DAQ's watchdog would do it later
        self._stop.set()
        deadline = time.monotonic() + timeout_s
        for t in self.threads:
            t.join(max(0.0, deadline - time.monotonic()))
        if self.latch_store is not None:
            safe(self.latch_store.close, max(0.2, deadline - time.monotonic()))
        safe(self.audit.flush)

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
        with self.check_lock:
            self.reset_check.mark(None)  # everything this run sees is newer than the hold
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
                    drv.wake.wait(BATCH_S if self.frames.wake_at_seq is None else BATCH_TURNING_S)
                    drv.wake.clear()  # before draining: a frame queued after the drain wakes the next wait
                    events = merged(drv.drain())
                else:
                    ev = drv.get(timeout=BATCH_S)
                    events = [] if ev is None else [(ev, None)]
            except Exception as exc:  # noqa: BLE001
                self.board.fault("driver", f"get failed: {type(exc).__name__}: {exc}")
                self._stop.wait(0.1)
                continue
            now = time.monotonic()
            self._loop_mono = now
            if self.controls.contexts_waiting:
                safe(self._take_zenoh_contexts)
            if not any(isinstance(ev, SampleBlock) for ev, _ in events):
                self.check_stall(now)
            for ev, parts in events:
                try:
                    self.handle(ev, now, parts)
                except Exception as exc:  # noqa: BLE001 - one bad block must not kill the loop
                    self.board.fault("estimator", f"{type(exc).__name__}: {exc}", tb=traceback.format_exc())
            if self.afc.enabled:
                safe(self.afc.idle, time.monotonic())

    def handle(self, ev: Any, now: float, parts: list[tuple[int, int, float]] | None = None) -> None:
        """One event from the driver's queue, as the estimator thread handles it (a block, the link, the
        DAQ's descriptor, CONTEXT or STATUS). `parts`: the frames a merged block is made of."""
        if isinstance(ev, SampleBlock):
            self._on_block(ev, now, parts)
        elif isinstance(ev, LinkEvent):
            self._on_link(ev, now)
        elif isinstance(ev, Descriptor):
            self._on_descriptor(ev)
        elif isinstance(ev, Context):
            with self._alarm_lock:
                step = self.core.on_context(ev)
            self._publish_step(step)
        elif isinstance(ev, Status):
            self.interlock.observe_status(ev)
            if ev.feed_override is not None:
                self.afc.on_override(ev.feed_override / 10.0, now)
            self.core.on_status(ev)  # the applied override, sample by sample, for the revolutions
            if self.interlock.device_hold and not self.reset_check.marked:
                with self.check_lock:  # a hold we did not set (the watchdog): judged from now on
                    self.reset_check.mark(self.live.last_seq)

    # ------------------------------------------------------------------ estimator thread, per block
    def _on_block(self, block: Any, now: float, parts: list[tuple[int, int, float]] | None = None) -> None:
        n = len(block.counts)
        live, board = self.live, self.board
        live.samples_received += n
        self._last_block_mono = now
        if board.faults:   # samples flow: the link works, also from a DAQ whose descriptor does not fit
            for kind in DAQ_FAULTS:
                if kind in board.faults:
                    board.recover(kind)
        if self.core.estimator is None:
            if self.driver.descriptor is not None:
                self._on_descriptor(self.driver.descriptor)
            if self.core.estimator is None:
                self.core.skip(block)  # received but unusable; its known losses still count
                board.check_blind()
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
        frame_events = self.frames.take_events(block.seq + n - 1)
        with self._alarm_lock:
            step = self.core.process(block, frame_events)
        if "estimator" in board.faults:
            board.recover("estimator")  # only once a block went through again
        feed_check = getattr(getattr(self.core.estimator, "physics", None), "feed_check", None)
        for event, fields in feed_check.take() if feed_check is not None else ():  # per_revolution.FeedCheck
            log.warning(event, **fields)
        last_seq = step.last_seq if step.last_seq is not None else block.seq + n - 1
        live.spindle_stopped = bool(step.spindle_stopped or self.core.spindle_stopped)
        live.last_seq = last_seq  # a hold that begins now is newer than this block: its data do not count
        self.frames.predict_close(step, live.spindle_stopped)
        interlock_by_event: dict[int, str | None] = {}
        for ev in step.trips:  # feed hold first, before anything is published
            interlock_by_event[id(ev)] = self._trip(trip_reason(ev), started=now)  # block handed over → written
        for kind, reason in step.faults.items():  # signal plausibility: blind while it lasts
            board.signal_source(kind, "plausibility", reason)
        for kind in step.clear_faults:
            board.signal_source(kind, "plausibility", None)
        board.verdict("data_loss", self.loss_check.update(block.seq, n, block.lost_before, block.discontinuity,
                                                          block.after_link_up))
        board.check_blind()
        with self.check_lock:  # evidence for a reset: only what is newer than the hold counts
            self.reset_check.on_block(block.seq, step.peaks, step.stalled, live.spindle_stopped)
            for kind, item in step.items:
                if kind == "estimate":
                    self.reset_check.on_estimate(item, self.core.alarms.over_limits(item))
        suspect = self._newest_pinned() if self.afc.enabled else None
        stored: list[dict] = []   # into the history once the block's estimates are out (it never waits for it)
        try:
            for kind, item in step.items:
                if kind == "estimate":
                    board.verdict("wiring", self.power_check.update(item))
                    try:
                        self.afc.revolution(item, now, suspect)   # AFC after the block's trips
                    except Exception as exc:  # noqa: BLE001 - the controller's error must not stop the estimates
                        self.afc.error(exc, item)
                    t = self.clock.time_of(int(item.get("seq_end", block.seq + n - 1)))
                    payload = estimate_payload(item, self.machine, t)
                    live.revolutions += 1  # counted before it is out: status never lags what subscribers got
                    live.last_estimate = payload
                    self.sink.estimate(payload)
                    stored.append(payload)
                    done = time.monotonic()
                    live.latency.add(done - now)
                    live.delay.add(done - arrival(parts, int(item.get("seq_end", last_seq)), now))
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
        safe(self._check_phase, block)
        if not self.ready.is_set():
            board.state = "running" if not board.faults else "degraded"
            self.ready.set()
            safe(lambda: self._notify(ready=True, status="running: DAQ streaming, Zenoh open"))
            log.info("daemon.ready", machine=self.machine, interlock=self.interlock.state)

    def _newest_pinned(self) -> str | None:
        """A channel that stopped moving in the newest samples the estimator has (signal_check.py), if any."""
        signals = getattr(self.core.estimator, "signals", None)
        return signals.newest_pinned() if signals is not None else None

    # ------------------------------------------------------------------ publication
    def _publish_step(self, step: Any) -> None:
        """A step that closed no revolution (a context change, a lost link): trips, alarms, processes."""
        held: dict[int, str | None] = {}
        for ev in step.trips:
            held[id(ev)] = self._trip(trip_reason(ev))
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
        self.live.processes += 1
        self.live.last_process = payload
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

    def _persist_limits(self, changed: set[str], tools_changed: bool) -> None:
        """An operator's change of the learned limits (`limits_command`): into the history like a learned one."""
        step = Step()
        step.changed_limits, step.tools_changed = changed, tools_changed
        self._after_step(step)

    def _take_zenoh_contexts(self) -> None:
        for payload, source in self.controls.take_contexts():
            with self._alarm_lock:
                step, refused = self.core.on_zenoh_context(payload)
            if refused:
                self._context_refused.note(source or "unknown", refused)
                continue
            self._publish_step(step)

    def _publish_alarm(self, ev: AlarmEvent, interlock: str | None) -> None:
        t = self.clock.time_of(ev.seq) if (self.clock is not None and ev.seq is not None) else time.time()
        payload = self.active_alarms.stamp(alarm_payload(ev, self.machine, t, interlock))
        self.sink.alarm(payload)
        self.live.alarms_sent += 1
        self.live.last_alarm = payload
        if self.history is not None:
            self.history.add_alarm(payload)
        # The alarm's kind goes under `alarm_level`: structlog's add_log_level writes the log level
        # into `level` and would overwrite it (issue 10, finding 7).
        # run_id and alarm_seq are for subscribers that catch up (alarm_state.py), not for the person reading the log
        fields = {k: v for k, v in payload.items() if k not in ("machine", "level", "run_id", "alarm_seq")}
        log.warning("alarm", alarm_level=payload["level"], **fields)

    # ------------------------------------------------------------------ the stream's checks
    def _note_arrival(self, seq_last: int, arrival_s: float, restart: bool) -> None:
        """The samples' arrival rate against the descriptor's (rate_check.py): fault `signals`, source
        `sample_rate`; while it holds, the estimator publishes every revolution invalid."""
        if not self._check_rate:
            return
        rate = float(self.core.descriptor.sample_rate_hz)
        last = self.rate_check
        if last is None or last.rate != rate:
            self.rate_check = RateCheck(rate, faulted=last is not None and last.faulted)
        self.board.verdict("sample_rate", self.rate_check.update(seq_last, arrival_s, restart))
        self._set_stream_problem()

    def _check_phase(self, block: Any) -> None:
        """The currents against each other and the voltages (phase_check.py): fault `signals`, source `phase`.
        Once a second, after the block's estimates are published: a wiring mistake is judged over seconds."""
        desc = self.core.descriptor
        if desc is not self._phase_desc:
            last = self.phase_check
            self._phase_desc, self.phase_check = desc, None
            if desc is not None:   # the estimator accepted it: so does this; it goes on from the last verdict
                self.phase_check = PhaseCheck(self.settings, desc, faulted=last is not None and last.faulted)
        if self.phase_check is not None:
            self.board.verdict("phase", self.phase_check.update(block.counts, block.lost_before, block.discontinuity))
        self._set_stream_problem()

    def _set_stream_problem(self) -> None:
        """While the rate, the phase or the power check holds fault `signals`, every revolution is published
        invalid with its name: the numbers of a stream at another rate, or of swapped or turned current sensors,
        are wrong however whole the revolution (nothing downstream, learning or AFC, takes them as measured)."""
        rate, phase = self.rate_check, self.phase_check
        self.core.stream_problem = ("sample_rate" if rate is not None and rate.faulted else
                                    "phase" if phase is not None and phase.faulted else
                                    "wiring" if self.power_check.faulted else None)

    def _caught_up(self) -> bool:
        """Is the driver's queue empty, i.e. did this block just arrive?"""
        return self.driver.queued == 0

    # ------------------------------------------------------------------ the one trip path
    def _held(self) -> str | None:
        return "feed_hold" if self.interlock.latched else None

    def _trip(self, reason: str, last_seq: int | None = None, started: float | None = None) -> str | None:
        """Every feed hold goes through here, from any thread: the interlock's trip, then the mark
        for the reset check. `last_seq`: the last sample the tripping thread saw (the reader's frame);
        default the estimator's. `started`: the monotonic time the tripping data were taken; a new latch
        sets `last_trip_ms` from it to the hold's write (what follows the write is not the trip's)."""
        with self._trip_lock:
            trips = self.interlock.trips
            result = self.interlock.trip(reason)
            if self.interlock.trips != trips:  # a new latch (not one already held)
                seen = self.live.last_seq
                with self.check_lock:
                    self.reset_check.mark(seen if last_seq is None else max(last_seq, seen or 0))
                written = self.interlock.hold_written_mono
                if started is not None and written is not None:
                    self.live.last_trip_ms = round((written - started) * 1e3, 3)
        self.afc.safe(f"feed hold: {reason}")  # after the hold is written: it never waits for this
        return result

    # ------------------------------------------------------------------ the DAQ
    def _on_link(self, ev: Any, now: float) -> None:
        self._link_handled_up = bool(ev.up)
        if ev.up:  # the driver logged it (`daq.link_up`, with transport and address)
            self._stall_since = now   # the wake-up that took the event, as a block's `_last_block_mono`
            # A DAQ that restarted forgot its watchdog and maybe the latched output; its override is 100 %, or
            # (a link that only dropped) still what it was: set again at its first STATUS.
            self.afc.on_link_up()
            safe(self.interlock.start)
            safe(self.interlock.reassert)
        else:
            self.board.fault("daq_link", f"lost communication with the DAQ: {ev.reason}")

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
            self.board.fault("descriptor", "; ".join(problems))
            return
        self._refused_descriptor = None
        self.afc.on_descriptor(desc)
        self.board.recover("descriptor")

    def check_stall(self, now: float) -> None:
        """No samples for DAQ_STALL_S with the link up: the fault `daq_stalled` (each estimator wake-up
        without samples)."""
        # since the last samples, or since the link came (back) up: the time it was down is `daq_link`'s
        last = max(self._last_block_mono or self._stall_since, self._stall_since)
        if self._link_handled_up and now - last > DAQ_STALL_S and "daq_stalled" not in self.board.faults:
            self.board.fault("daq_stalled", f"no samples for {now - last:.1f} s with the link up")

    def _diagnostics(self) -> dict[str, Any]:
        d: dict[str, Any] = {"samples": self.live.samples_received, "revolutions": self.live.revolutions}
        for name, fn in (("driver", getattr(self.driver, "stats", None)), ("sink", getattr(self.sink, "stats", None))):
            try:
                d[name] = fn() if fn else None
            except Exception as exc:  # noqa: BLE001
                d[name] = f"unavailable: {exc}"
        d["interlock"] = self.interlock.state_dict()
        d["last_estimate"] = self.live.last_estimate
        return d

    # ------------------------------------------------------------------ health, heartbeat
    def healthy(self, now: float | None = None) -> bool:
        now = time.monotonic() if now is None else now
        if self.board.state == "stopping" or not self.driver.link_up or self._last_block_mono is None:
            return False
        if "estimator" in self.board.faults or "descriptor" in self.board.faults:
            return False
        return now - self._last_block_mono < HEALTH_STALL_S and now - self._loop_mono < HEALTH_STALL_S

    def _heartbeat_loop(self) -> None:
        period = self.interlock.heartbeat_ms / 1000.0
        next_t = time.monotonic()
        while not self._stop.is_set():
            self.interlock.beat(self.healthy(), stopping=self.board.state == "stopping")
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
                safe(lambda: self._notify(watchdog=True))
            if now < next_status:
                continue
            next_status += 1.0
            status = self.report.payload()
            line = status_line(status)
            safe(self.sink.status, status)
            safe(lambda: self._notify(status=line))
            safe(lambda: log.debug("stats", **{k: v for k, v in status.items() if k not in ("machine", "version")}))
            if self._on_second is not None:
                with self._alarm_lock:
                    alarm_state = self.core.summary()
                safe(self._on_second, status, self.live.last_estimate, alarm_state)


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


def _limit(section: Any, name: str) -> float | None:
    value = getattr(section, name, None) if section is not None else None
    return None if value is None else float(value)
