"""The emulator in-process (``transport = "sim"``), paced in real time; used by the demo.

No bytes and no frames: the device model's samples are handed over directly, but
through the same base class (queue, index tracking, outputs, watchdog), so the
daemon cannot tell it from a real DAQ except by speed of setup. With
``protocol=2`` it is a version-2 DAQ with the simulated CNC: ``Context`` events,
the feed override (which the simulated CNC applies through its lag,
``cnc_override_lag_ms``, and rate limit, ``cnc_override_rate_pct_s``, and which
drives the plant's feed), the CNC's "feed held" after ``cnc_hold_lag_ms``;
``afc_allowed`` sets CONTEXT flag bit 2 (adaptive feed allowed) for a simple
scenario (a part program sets it per operation).
"""

from __future__ import annotations

import time

from millsense.drivers.base import Driver, LinkDown


class SimDriver(Driver):
    transport = "sim"

    def __init__(
        self,
        scenario: str = "step",
        *,
        seed: int = 0,
        realtime: bool = True,
        loop: bool = True,
        start_index: int = 0,
        watchdog_ms: int = 0,
        batch_s: float = 0.01,
        filter_cutoff_hz: float | None = None,
        protocol: int = 1,
        cnc_hold_lag_ms: float = 30.0,
        cnc_override_lag_ms: float = 40.0,
        cnc_override_rate_pct_s: float = 1000.0,
        afc_allowed: bool = False,
        **kwargs,
    ) -> None:
        super().__init__(**kwargs)
        self.scenario = scenario
        self.seed = int(seed)
        self.realtime = bool(realtime)
        self.loop = bool(loop)
        self.start_index = int(start_index)
        self.batch_s = batch_s
        self.filter_cutoff_hz = filter_cutoff_hz
        self.protocol = int(protocol)
        self.cnc_hold_lag_ms = float(cnc_hold_lag_ms)
        self.cnc_override_lag_ms = float(cnc_override_lag_ms)
        self.cnc_override_rate_pct_s = float(cnc_override_rate_pct_s)
        self.afc_allowed = bool(afc_allowed)
        from millsense.sim.emulator.cnc_override import CncOverride

        CncOverride(self.cnc_override_lag_ms, self.cnc_override_rate_pct_s)  # a bad value: ValueError now, not later
        self._initial_watchdog_ms = int(watchdog_ms)
        self.device = None
        self._pacer = None
        self._send_descriptor = True
        self._last_status = None

    @classmethod
    def from_options(
        cls,
        scenario: str = "step",
        seed: int = 0,
        realtime: bool = True,
        filter_cutoff_hz: float | None = None,
        protocol: int = 1,
        cnc_override_lag_ms: float = 40.0,
        cnc_override_rate_pct_s: float = 1000.0,
        afc_allowed: bool = False,
        **_ignored,
    ) -> SimDriver:
        """``filter_cutoff_hz`` of the [daq] section becomes the simulated DAQ's filter,
        so the demo's config and its simulated hardware agree."""
        return cls(scenario, seed=seed, realtime=realtime, filter_cutoff_hz=filter_cutoff_hz, protocol=protocol,
                   cnc_override_lag_ms=cnc_override_lag_ms, cnc_override_rate_pct_s=cnc_override_rate_pct_s,
                   afc_allowed=afc_allowed)

    @property
    def address(self) -> str:
        return f"sim:{self.scenario}"

    def _connect(self) -> None:
        if self.device is not None:
            return
        from millsense.sim.emulator.device import DeviceModel
        from millsense.sim.emulator.pacing import Pacer
        from millsense.sim.emulator.source import SourceError, is_program, make_source

        try:
            source = make_source(
                self.scenario,
                seed=self.seed,
                loop=self.loop,
                start_index=self.start_index,
                filter_cutoff_hz=self.filter_cutoff_hz,
            )
        except SourceError as exc:
            raise LinkDown(str(exc)) from exc
        program = is_program(self.scenario)
        protocol = 2 if program else self.protocol  # a part program is there for its CONTEXT
        self.device = DeviceModel(source, start_index=self.start_index, watchdog_ms=self._initial_watchdog_ms,
                                  protocol=protocol, cnc_hold_lag_ms=self.cnc_hold_lag_ms,
                                  cnc_override_lag_ms=self.cnc_override_lag_ms,
                                  cnc_override_rate_pct_s=self.cnc_override_rate_pct_s,
                                  afc_allowed=self.afc_allowed and not program)
        self._pacer = Pacer(self.device.sample_rate_hz, realtime=self.realtime, batch_s=self.batch_s)

    def _disconnect(self) -> None:
        """Nothing to close: the device lives as long as the driver."""

    def _read(self) -> list:
        pacer = self._pacer
        if pacer.realtime:
            wait = pacer.next_time() - time.monotonic()
            if wait > 0:
                time.sleep(min(wait, 0.2))
        elif len(self._queue) > self._queue.maxsize // 2:
            time.sleep(0.001)  # fast mode: a generator, not a device; let the consumer catch up
            return []
        out: list = []
        with self._io_lock:
            now = time.monotonic()
            self.device.check_watchdog(now)
            if self._send_descriptor:
                self._send_descriptor = False
                out.append(self.device.descriptor)
            n = pacer.due(now)
            if n:
                first, counts = self.device.produce(n)
                # a part program's CONTEXTs, and a STATUS where the CNC's applied override moved, in between
                out.extend(self.device.stream_items(first, counts))
            self.device.update_cnc(now)
            context = self.device.context()
            status = self.device.status()
        out.append(status)
        if context is not None:
            out.append(context)  # the base class passes on changes only
        return out

    def _send_outputs(self, bits: int) -> None:
        self.device.set_outputs(bits, time.monotonic())

    def _send_heartbeat(self, counter: int) -> None:
        self.device.heartbeat(counter, time.monotonic())

    def _send_request_descriptor(self) -> None:
        self._send_descriptor = True

    def _send_feed_override(self, tenths: int) -> None:
        self.device.set_feed_override(tenths, time.monotonic())

    def set_watchdog_ms(self, ms: int) -> None:
        self._initial_watchdog_ms = int(ms)
        if self.device is not None:
            with self._io_lock:
                self.device.set_watchdog_ms(int(ms), time.monotonic())
