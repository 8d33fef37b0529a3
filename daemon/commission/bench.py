"""The DAQ on the bench of `millsense commission`: connected as the daemon connects, fed as the daemon feeds it.

The commissioning drives the DAQ itself, through the driver layer and the daemon's own `Interlock` (its
heartbeat, its feed-hold write, its reset), and never beside a daemon: `commission` holds the machine's state
directory (`claim_state_dir`) for its whole run, as `run` does. Two masters on one DAQ would fight over
the feed hold and the watchdog.

The hold this command sets it remembers (`asserted`); one it found (`found_held`) it releases only when told,
and asserts again before it ends (docs/commissioning.md, "The feed hold").
"""

from __future__ import annotations

import threading
import time
from typing import Any

import numpy as np

from millsense.daemon.runtime.interlock import Interlock
from millsense.drivers.base import LinkEvent, SampleBlock
from millsense.drivers.protocol import Status

FIRST_STATUS_S = 3.0   # the DAQ answers the first heartbeat with a STATUS (a stream) or is polled (Modbus)


class BenchError(Exception):
    """The DAQ did not do what the bench needs (no samples, no status): the message says what."""


class Bench:
    """One DAQ: a pump thread takes the driver's events (samples when asked, STATUS to the interlock), a
    heartbeat thread feeds the watchdog while `beating`."""

    def __init__(self, settings: Any, driver: Any):
        self.settings = settings
        self.driver = driver
        self.interlock = Interlock(driver, settings.interlock)
        self.heartbeat_s = self.interlock.heartbeat_ms / 1000.0
        self.found_held = False
        self.last_beat_mono: float | None = None
        self._beating = threading.Event()
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._want = 0
        self._parts: list[np.ndarray] = []
        self._have = 0
        self._full = threading.Event()
        self._threads = [threading.Thread(target=self._pump, name="ms-comm-pump", daemon=True),
                         threading.Thread(target=self._beat, name="ms-comm-beat", daemon=True)]

    # -- start and end ------------------------------------------------------------
    def start(self) -> None:
        """Arm the watchdog, beat, and read the first STATUS (what the feed hold was when we came)."""
        for t in self._threads:
            t.start()
        # a STATUS answers every command (a stream DAQ says nothing unasked): asked for before any heartbeat arms
        # the watchdog, so that what the feed hold was is known before anything here could change it
        self.driver.request_descriptor()
        deadline = time.monotonic() + FIRST_STATUS_S
        while self.driver.last_status is None:
            if time.monotonic() > deadline:
                raise BenchError(f"the DAQ sent no STATUS within {FIRST_STATUS_S:g} s of a command "
                                 "(docs/protocol.md: a STATUS answers every command)")
            time.sleep(0.01)
        self.found_held = bool(self.driver.last_status.feed_hold)
        self.interlock.start()
        if self.interlock.enabled:
            self.resume_beats()

    def close(self) -> None:
        self._beating.clear()
        self._stop.set()
        for t in self._threads:
            t.join(1.0)

    @property
    def asserted(self) -> bool:
        """A hold this command set and has not released."""
        return self.interlock.latched

    # -- heartbeats -----------------------------------------------------------------
    def resume_beats(self) -> None:
        self.interlock.beat(True)
        self.last_beat_mono = time.monotonic()
        self._beating.set()

    def stop_beats(self) -> float:
        """No heartbeat from now; returns when the last one went out (monotonic)."""
        self._beating.clear()
        with self._lock:   # a beat being sent now is the last one
            return float(self.last_beat_mono or time.monotonic())

    def _beat(self) -> None:
        while not self._stop.wait(self.heartbeat_s):
            if not self._beating.is_set():
                continue
            with self._lock:
                if self._beating.is_set():
                    self.interlock.beat(True)
                    self.last_beat_mono = time.monotonic()

    # -- samples and status ---------------------------------------------------------
    def _pump(self) -> None:
        while not self._stop.is_set():
            ev = self.driver.get(timeout=0.05)
            if isinstance(ev, Status):
                self.interlock.observe_status(ev)
            elif isinstance(ev, SampleBlock):
                self._take(ev)
            elif isinstance(ev, LinkEvent) and ev.up:
                self.interlock.reassert()

    def _take(self, block: SampleBlock) -> None:
        with self._lock:
            if self._want <= 0:
                return
            if block.lost_before or block.discontinuity:
                self._parts, self._have = [], 0   # a window is contiguous samples
            self._parts.append(block.counts)
            self._have += len(block.counts)
            if self._have >= self._want:
                self._want = 0
                self._full.set()

    def samples(self, seconds: float) -> np.ndarray:
        """`seconds` of contiguous raw counts (n, C), from now on."""
        rate = float(self.driver.descriptor.sample_rate_hz)
        n = max(16, int(round(seconds * rate)))
        with self._lock:
            self._parts, self._have, self._want = [], 0, n
            self._full.clear()
        if not self._full.wait(seconds * 3.0 + 5.0):
            with self._lock:
                self._want = 0
            raise BenchError(f"the DAQ did not send {seconds:g} s of contiguous samples within {seconds * 3 + 5:g} s")
        with self._lock:
            return np.concatenate(self._parts)[:n]
