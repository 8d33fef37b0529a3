"""One contract, four transports: the emulator as a subprocess, the real driver here.

In one 10-s window per transport: every sample arrives once, in order, with the
ramp's values; the rate is 1000 Hz +- 1 %; feed hold round-trips; then the
heartbeat stops and the watchdog must trip within its period + 50 ms of the last
heartbeat the device saw (both times from the device's status log, same clock).
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from millsense.drivers import create_driver
from millsense.drivers.base import LinkEvent, SampleBlock
from millsense.drivers.protocol import Status
from tests.drivers.emulator_proc import Emulator, ramp

WATCHDOG_MS = 200
WINDOW_S = 10.0
HEARTBEAT_S = 0.05


def open_transport(transport: str, tmp_path, port: int, *extra: str):
    """(emulator, driver) for one transport; the driver is not started."""
    if transport == "pty":
        link = str(tmp_path / "daq-link")
        emu = Emulator(tmp_path, "--pty", link, "--watchdog-ms", str(WATCHDOG_MS), *extra)
        return emu, lambda: create_driver("serial", port=link, baudrate=921600)
    if transport == "tcp":
        emu = Emulator(tmp_path, "--tcp", f"127.0.0.1:{port}", "--watchdog-ms", str(WATCHDOG_MS), *extra)
        return emu, lambda: create_driver("tcp", host="127.0.0.1", tcp_port=port)
    if transport == "modbus-rtu":
        link = str(tmp_path / "rtu-link")
        emu = Emulator(tmp_path, "--modbus-rtu", link, *extra)
        return emu, lambda: create_driver("modbus-rtu", port=link, baudrate=921600, unit=1, poll_ms=20)
    emu = Emulator(tmp_path, "--modbus-tcp", f"127.0.0.1:{port}", *extra)
    return emu, lambda: create_driver("modbus-tcp", host="127.0.0.1", tcp_port=port, unit=1, poll_ms=20)


class Collector:
    """Drains a driver's events in the test thread, timestamping sample blocks."""

    def __init__(self, driver) -> None:
        self.driver = driver
        self.blocks: list[tuple[float, SampleBlock]] = []
        self.links: list[LinkEvent] = []
        self.statuses: list[Status] = []

    def pump(self, seconds: float, until=None, heartbeat_s: float | None = None) -> bool:
        """Drain events for up to ``seconds`` or until ``until()``; with ``heartbeat_s``, keep the
        heartbeat going meanwhile (a wait for a status must not starve the device's watchdog)."""
        deadline = time.monotonic() + seconds
        next_hb = time.monotonic() + (heartbeat_s or 0.0)
        while time.monotonic() < deadline:
            if heartbeat_s is not None and time.monotonic() >= next_hb:
                self.driver.heartbeat()
                next_hb = time.monotonic() + heartbeat_s
            ev = self.driver.get(timeout=0.02)
            if isinstance(ev, SampleBlock):
                self.blocks.append((time.monotonic(), ev))
            elif isinstance(ev, LinkEvent):
                self.links.append(ev)
            elif isinstance(ev, Status):
                self.statuses.append(ev)
            if until is not None and until():
                return True
        return False


def check_every_sample_once(blocks: list[SampleBlock]) -> int:
    """Contiguous, in order, right values; returns the number of samples."""
    assert blocks, "no samples arrived"
    expected_seq = blocks[0].seq
    for b in blocks:
        assert b.seq == expected_seq, f"seq {b.seq} != {expected_seq}: a sample lost or repeated"
        assert b.lost_before == 0 and not b.discontinuity
        assert b.index == b.seq % (1 << 32)
        np.testing.assert_array_equal(b.counts, ramp(b.index, len(b.counts)))
        expected_seq += len(b.counts)
    return expected_seq - blocks[0].seq


@pytest.mark.parametrize("transport, ring", [("pty", ()), ("tcp", ()), ("modbus-tcp", ()), ("modbus-rtu", ()),
                                             # a ring depth that does not divide 2**32: the index wrap is not at
                                             # a ring wrap (before stop 28 a read across it handed over samples a
                                             # whole ring old as current, none counted lost)
                                             ("modbus-tcp", ("--ring-depth", "3000"))])
def test_contract(transport, ring, tmp_path, port):
    emu, make = open_transport(transport, tmp_path, port, "--start-index", str(2**32 - 3000), *ring)
    driver = None
    try:
        emu.start()
        driver = make()
        if transport.startswith("modbus"):
            driver.set_watchdog_ms(WATCHDOG_MS)  # holding register 101, written on connect
        driver.start()
        assert driver.wait_connected(10.0), "driver never connected"
        col = Collector(driver)
        assert col.pump(5.0, until=lambda: col.blocks), "no samples within 5 s"
        col.blocks.clear()  # the window starts with the next block

        t0 = time.monotonic()
        next_hb = t0
        hold_seen = release_seen = None
        while time.monotonic() - t0 < WINDOW_S:
            now = time.monotonic()
            if now >= next_hb:
                driver.heartbeat()
                next_hb = now + HEARTBEAT_S
            if hold_seen is None and now - t0 > 3.0:
                driver.set_outputs(True)
                hold_seen = col.pump(1.0, until=lambda: driver.last_status and driver.last_status.feed_hold,
                                     heartbeat_s=HEARTBEAT_S)
            if hold_seen and release_seen is None and now - t0 > 5.0:
                driver.set_outputs(False)
                release_seen = col.pump(1.0, until=lambda: driver.last_status and not driver.last_status.feed_hold,
                                        heartbeat_s=HEARTBEAT_S)
            col.pump(0.01)

        # every sample once, in order, with its value, across the 32-bit wrap
        blocks = [b for _, b in col.blocks]
        n = check_every_sample_once(blocks)
        assert blocks[0].index > blocks[-1].index, "the window should cross the index wrap"
        t_recv = np.array([t for t, _ in col.blocks])
        assert t_recv[-1] - t_recv[0] >= WINDOW_S - 0.5
        # the slope of "samples received so far" against arrival time: a least-squares
        # line, so one late wake-up of the reader at either end does not bias it
        ends = np.array([b.seq + len(b.counts) for b in blocks], dtype=float)
        rate = np.polyfit(t_recv - t_recv[0], ends - ends[0], 1)[0]
        assert abs(rate - 1000.0) <= 10.0, f"rate {rate:.1f} Hz"
        assert hold_seen, "feed hold never showed in STATUS / discrete input"
        assert release_seen, "feed hold release never showed"

        # On a loaded box the test's own heartbeats may have come late in the window, and the device
        # then tripped, rightly. Start the watchdog's check from a cleared device, heartbeat going.
        driver.set_outputs(False)
        assert col.pump(2.0, until=lambda: driver.last_status and not driver.last_status.watchdog_tripped
                        and not driver.last_status.feed_hold, heartbeat_s=HEARTBEAT_S), "could not clear the outputs"

        # watchdog: no more heartbeats; feed hold must come by itself
        tripped = col.pump(2.0, until=lambda: driver.last_status and driver.last_status.watchdog_tripped)
        assert tripped and driver.last_status.feed_hold
        col.pump(0.3)
        assert driver.last_status.feed_hold, "feed hold cleared without a command"
        beats = [e["mono"] for e in emu.events("heartbeat")]  # CLOCK_MONOTONIC, the test's clock
        trips = [e["mono"] for e in emu.events("outputs") if e["cause"] == "watchdog"]
        # never a trip while heartbeats came within the period
        for trip in trips:
            before = [b for b in beats if b < trip]  # a late heartbeat is logged after the trip it finds
            assert before and trip - before[-1] >= WATCHDOG_MS / 1000, f"tripped {trip - t0:.3f} s into the window, " \
                f"{(trip - before[-1]) * 1000:.1f} ms after a heartbeat"
        # the last command that changed the outputs (the clear above, or the release in the window)
        commanded = max(e["mono"] for e in emu.events("outputs") if e["cause"] == "command")
        final = [t for t in trips if t > commanded]
        assert len(final) == 1, f"{len(final)} trips after the heartbeat stopped"
        late_s = final[0] - beats[-1]
        print(f"{transport}: {n} samples, {rate:.2f} Hz, watchdog tripped {late_s * 1000:.1f} ms after last heartbeat"
              f" ({len(trips) - 1} trips in the window on late heartbeats)")
        assert WATCHDOG_MS / 1000 <= late_s <= WATCHDOG_MS / 1000 + 0.050, f"tripped {late_s * 1000:.1f} ms after"
        # an explicit clear (with the heartbeat back, or the watchdog trips again at once)
        driver.heartbeat()
        driver.set_outputs(False)
        assert col.pump(1.0, until=lambda: not driver.last_status.feed_hold), "explicit clear did not clear"
    finally:
        if driver is not None:
            driver.close()
        emu.stop()
