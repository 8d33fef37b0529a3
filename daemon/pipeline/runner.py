"""The live runtime: threads between the driver, the estimator, the interlock and the sink.

Threads (one job each, one hand-off queue — the driver's):

- the driver's own reader thread(s) fill its bounded queue;
- **estimator** (`_estimate_loop`) owns the estimator and the alarm engine,
  pulls `driver.get`, trips the interlock itself the moment an alarm asks for
  feed hold (no queue in between), then hands estimates and alarms to the
  sink (whose methods return at once, so a slow subscriber never slows it);
- **heartbeat** sends the DAQ a heartbeat every `heartbeat_ms` while the
  pipeline is healthy (link up, samples arrived within `HEALTH_STALL_S`,
  estimator loop alive) and stays silent otherwise, so that the DAQ's
  watchdog stops the feed if the daemon hangs or dies;
- **status** (1 s): status payload, sd_notify `STATUS=` / `WATCHDOG=1`, the
  debug stats line and the optional live summary callback.

Whatever goes wrong goes through `fault(kind, reason)`: idempotent per kind,
every handler in its own `try`, leaves a diagnostic dump in the log;
`recover(kind)` undoes it. State: starting → running ⇄ degraded → stopping.

Processing latency is measured from the moment `driver.get` hands over the
block that closes a revolution to the moment its estimate is handed to the
sink. Live `t` of an estimate is the Unix time of the revolution's last
sample (`status.SeqClock`).
"""

from __future__ import annotations

import threading
import time
import traceback
from typing import Any, Callable

import structlog

from millsense.daemon.pipeline.alarms import AlarmEvent, alarm_payload
from millsense.daemon.pipeline.interlock import Interlock
from millsense.daemon.pipeline.power_check import PowerSignCheck
from millsense.daemon.pipeline.run_core import PipelineCore, estimate_payload
from millsense.daemon.pipeline.status import LatencyStats, SeqClock, bad_frames, status_line

log = structlog.get_logger("millsense.runner")

HEALTH_STALL_S = 0.5  # no samples / no estimator loop for this long: stop heartbeats
DAQ_STALL_S = 1.0  # no samples for this long with the link up: `daq_lost`
PROGRESS_S = 3.0  # sd_notify WATCHDOG=1 only if a revolution closed within this


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
    ):
        self.settings = settings
        self.machine = str(getattr(settings, "machine", "millsense"))
        self.driver = driver
        self.version = version
        self._notify = notify
        self._on_second = on_second
        self._effective_config = effective_config
        self.core = PipelineCore(settings, estimator_factory, check_descriptor)
        self.interlock = Interlock(driver, getattr(settings, "interlock", None))
        self.sink: Any = None
        self.latency = LatencyStats()
        self.clock: SeqClock | None = None
        self.power_check = PowerSignCheck()

        self.state = "starting"
        self.faults: dict[str, str] = {}
        self._fault_lock = threading.Lock()
        self._alarm_lock = threading.Lock()  # the engine is touched by the estimator thread and reset()
        self._stop = threading.Event()
        self.ready = threading.Event()
        self._threads: list[threading.Thread] = []

        now = time.monotonic()
        self.started_mono = now
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

    # ------------------------------------------------------------------ lifecycle
    def start(self, sink: Any) -> None:
        """Arm the interlock and start the threads. The driver is already started."""
        self.sink = sink
        if self.driver.descriptor is not None:
            self.core.on_descriptor(self.driver.descriptor)  # ConfigError goes to the caller: exit 78
        self.interlock.start()
        targets = [("estimator", self._estimate_loop), ("status", self._status_loop)]
        if self.interlock.enabled:
            targets.append(("heartbeat", self._heartbeat_loop))
        for name, target in targets:
            t = threading.Thread(target=target, name=f"millsense-{name}", daemon=True)
            t.start()
            self._threads.append(t)

    def stop(self, timeout_s: float = 1.0) -> None:
        """Stop the threads. Feed hold is left exactly as it is; the caller closes sink and driver."""
        if self.state != "stopping":
            self.state = "stopping"
            self._safe(lambda: self._notify(stopping=True, status="stopping"))
            log.info("daemon.stopping", interlock=self.interlock.state)
        self._stop.set()
        deadline = time.monotonic() + timeout_s
        for t in self._threads:
            t.join(max(0.0, deadline - time.monotonic()))

    # ------------------------------------------------------------------ estimator thread
    def _estimate_loop(self) -> None:
        from millsense.drivers.base import LinkEvent, SampleBlock
        from millsense.drivers.protocol import Descriptor, Status

        drv = self.driver
        while not self._stop.is_set():
            try:
                ev = drv.get(timeout=0.05)
            except Exception as exc:  # noqa: BLE001
                self.fault("driver", f"get failed: {type(exc).__name__}: {exc}")
                self._stop.wait(0.1)
                continue
            now = time.monotonic()
            self._loop_mono = now
            try:
                if isinstance(ev, SampleBlock):
                    self._on_block(ev, now)
                elif ev is None:
                    self._check_stall(now)
                elif isinstance(ev, LinkEvent):
                    self._on_link(ev)
                elif isinstance(ev, Descriptor):
                    self._on_descriptor(ev)
                elif isinstance(ev, Status):
                    self.interlock.observe_status(ev)
            except Exception as exc:  # noqa: BLE001 - one bad block must not kill the loop
                self.fault("estimator", f"{type(exc).__name__}: {exc}", tb=traceback.format_exc())

    def _on_block(self, block: Any, now: float) -> None:
        n = len(block.counts)
        self.samples_received += n
        self._last_block_mono = now
        if self.core.estimator is None:
            if self.driver.descriptor is not None:
                self._on_descriptor(self.driver.descriptor)
            if self.core.estimator is None:
                self.core.skip(block)  # received but unusable; its known losses still count
                return
        if self.clock is None:
            self.clock = SeqClock(self.core.descriptor.sample_rate_hz)
        restart = bool(block.discontinuity or block.lost_before)
        if restart or self.clock.empty or self._caught_up():
            # A block that waited in the queue behind others arrived earlier than we see it:
            # its get() time would make `t` late, so only fresh blocks set the clock.
            self.clock.note_block(block.seq, n, time.time(), restart=restart, mono_s=now)
        if self.faults:
            for kind in ("daq_link", "daq_stalled"):
                if kind in self.faults:
                    self.recover(kind)
        with self._alarm_lock:
            step = self.core.process(block)
        if "estimator" in self.faults:
            self.recover("estimator")  # only once a block went through again
        interlock_by_event: dict[int, str | None] = {}
        for ev in step.trips:  # feed hold first, before anything is published
            interlock_by_event[id(ev)] = self.interlock.trip(f"{ev.level} {ev.quantity} {ev.value} > {ev.limit}")
            self.last_trip_ms = round((time.monotonic() - now) * 1e3, 3)  # block handed over → output written
        for kind, item in step.items:
            if kind == "estimate":
                self._check_power(item)
                t = self.clock.time_of(int(item.get("seq_end", block.seq + n - 1)))
                payload = estimate_payload(item, self.machine, t)
                self.sink.estimate(payload)
                self.latency.add(time.monotonic() - now)
                self.last_estimate = payload
                self.revolutions += 1
                self._last_rev_mono = now
            else:
                self._publish_alarm(item, interlock_by_event.get(id(item), self._held()))
        if not self.ready.is_set():
            self.state = "running" if not self.faults else "degraded"
            self.ready.set()
            self._safe(lambda: self._notify(ready=True, status="running: DAQ streaming, Zenoh open"))
            log.info("daemon.ready", machine=self.machine, interlock=self.interlock.state)

    def _check_power(self, est: dict) -> None:
        verdict = self.power_check.update(est)
        if verdict:
            self.fault("signals", verdict)
        elif verdict == "":
            self.recover("signals")

    def _caught_up(self) -> bool:
        """Is the driver's queue empty, i.e. did this block just arrive?"""
        return self.driver.queued == 0

    def _held(self) -> str | None:
        return "feed_hold" if self.interlock.latched else None

    def _publish_alarm(self, ev: AlarmEvent, interlock: str | None) -> None:
        t = self.clock.time_of(ev.seq) if (self.clock is not None and ev.seq is not None) else time.time()
        payload = alarm_payload(ev, self.machine, t, interlock)
        self.sink.alarm(payload)
        self.alarms_sent += 1
        self.last_alarm = payload
        log.warning("alarm", **{k: v for k, v in payload.items() if k != "machine"})

    def _on_link(self, ev: Any) -> None:
        if ev.up:  # the driver logged it (`daq.link_up`, with transport and address)
            # A DAQ that restarted forgot its watchdog and maybe the latched output.
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
        self.recover("descriptor")

    def _check_stall(self, now: float) -> None:
        last = self._last_block_mono if self._last_block_mono is not None else self.started_mono
        if self.driver.link_up and now - last > DAQ_STALL_S and "daq_stalled" not in self.faults:
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
        self._safe(lambda: log.error("fault", kind=kind, reason=reason, dump=self._diagnostics(), traceback=tb))
        self._safe(lambda: self.interlock.beat(self.healthy()))
        if kind in ("daq_link", "daq_stalled"):
            self._safe(self._daq_alarm, False)
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

    def _daq_alarm(self, ok: bool) -> None:
        with self._alarm_lock:
            events = self.core.alarms.on_daq(ok)
        for ev in events:
            self._publish_alarm(ev, self._held())

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
            self.interlock.beat(self.healthy())
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
                    alarm_state = self.core.alarms.summary()
                self._safe(self._on_second, status, self.last_estimate, alarm_state)

    # ------------------------------------------------------------------ Controls
    def status(self) -> dict[str, Any]:
        stats: dict[str, Any] = {}
        try:
            stats = dict(self.driver.stats())
        except Exception:  # noqa: BLE001
            pass
        with self._alarm_lock:
            alarms = self.core.alarms.active()
            alarm = self.core.alarms.summary()
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
            "interlock": self.interlock.state,
            "interlock_detail": self.interlock.state_dict(),
            "heartbeating": self.interlock.heartbeating,
            "last_trip_ms": self.last_trip_ms,
            "alarm": alarm,
            "alarms": alarms,
            "faults": dict(self.faults),
            "daq": stats,
            "sink": self._sink_stats(),
            "uptime_s": round(time.monotonic() - self.started_mono, 1),
            "version": self.version,
        }

    def _sink_stats(self) -> dict | None:
        try:
            return self.sink.stats() if self.sink is not None and hasattr(self.sink, "stats") else None
        except Exception:  # noqa: BLE001
            return None

    def config(self) -> dict[str, Any]:
        if self._effective_config is None:
            return {"machine": self.machine}
        return self._effective_config()

    def reset(self, payload: bytes) -> dict[str, Any]:
        """`cmd/reset`: clear the latched interlock and the latched alarms (policy permitting)."""
        result = self.interlock.reset(payload)
        if result.get("ok"):
            with self._alarm_lock:
                events = self.core.alarms.reset()
            for ev in events:
                self._safe(self._publish_alarm, ev, None)
        result["alarm"] = self.core.alarms.summary()
        return result
