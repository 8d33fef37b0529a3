"""One contract, four transports: the emulator as a subprocess, the real driver here.

In one 4-s window per transport: every sample arrives once, in order, with the
ramp's values, across the 32-bit index wrap; the rate is 1000 Hz +- 1 %; feed hold round-trips; then the
heartbeat stops and the watchdog must trip within its period + 50 ms of the last
heartbeat the device saw (both times from the device's status log, same clock).

Each step waits on events, never on a STATUS within a deadline: first the device's
own log (the command it took, the heartbeats it heard, its trips), then the
driver's STATUS showing it. On a loaded box a heartbeat may come a period late and
the device then trips, rightly: its log says so, every trip is checked against the
heartbeats it heard, and a step that needs the device clear answers such a trip
with a clear. A step that fails prints the device's outputs and heartbeat events.
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
# The window: 4 s of stream (10 s before issue 37). Its rate is a least-squares slope over every block's
# arrival, so a shorter window keeps the same +-10 Hz bound with room (a Modbus poll's 20 ms of jitter is
# 0.5 % of 4 s at one end alone, and the fit averages over about 200 polls); the wrap, 3000 samples after
# the device's start, still falls inside it, the feed hold and its release inside it too.
WINDOW_S = 4.0
HOLD_AT_S, RELEASE_AT_S = 1.0, 2.0
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


@pytest.mark.serial
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
        dev = DeviceLog(emu, col)

        t0 = time.monotonic()
        next_hb = t0
        held = released = False
        while time.monotonic() - t0 < WINDOW_S:
            now = time.monotonic()
            if now >= next_hb:
                driver.heartbeat()
                next_hb = now + HEARTBEAT_S
            if not held and now - t0 > HOLD_AT_S:
                dev.round_trip(True, "feed hold")
                held = True
            if held and not released and now - t0 > RELEASE_AT_S:
                dev.round_trip(False, "feed hold release")
                released = True
            col.pump(0.01)
        window = list(col.blocks)  # judged at the end: the watchdog's part follows with the heartbeat going

        # The watchdog, judged on the device's own log (its events, its clock). Start from a device that is
        # clear and hears the heartbeat after its clear; a heartbeat late on a loaded box trips it, rightly
        # (checked below), and each such trip is answered with a clear.
        reclears = dev.clear_with_heartbeat()
        # no more heartbeats: feed hold must come by itself, one period after the last heartbeat the device heard
        stopped = time.monotonic()
        final = dev.wait(lambda ev: _trips_since(ev, dev.cleared_mono), "the watchdog trip after the heartbeat stopped",
                         since=stopped)[0]
        events = emu.events()
        # the driver shows this trip: a STATUS with the counter of the last heartbeat the device heard (a STATUS
        # of a trip before the clear carries an older one)
        (counter,) = [e["counter"] for e in events if e["event"] == "heartbeat"
                      and e["mono"] == final["last_heartbeat_mono"]]
        assert col.pump(HANG_S, until=lambda: driver.last_status and driver.last_status.last_heartbeat == counter
                        and driver.last_status.watchdog_tripped and driver.last_status.feed_hold), \
            "the device tripped, the driver never showed it: " + dev.story(stopped)
        col.pump(0.3)
        assert driver.last_status.feed_hold, "feed hold cleared without a command"
        after = [e for e in emu.events("outputs") if e["mono"] > final["mono"]]
        assert not after, f"the outputs changed without a command after the trip: {after}"
        events = emu.events()
        beats = [e["mono"] for e in events if e["event"] == "heartbeat"]  # CLOCK_MONOTONIC, the test's clock
        trips = [e["mono"] for e in events if e["event"] == "outputs" and e["cause"] == "watchdog"]
        # never a trip while heartbeats came within the period
        for trip in trips:
            before = [b for b in beats if b < trip]  # a late heartbeat is logged after the trip it finds
            assert before and trip - before[-1] >= WATCHDOG_MS / 1000, f"tripped {trip - t0:.3f} s into the window, " \
                f"{(trip - before[-1]) * 1000:.1f} ms after a heartbeat: " + dev.story(t0)
        # the last command that changed the outputs (the clear above)
        commanded = max(e["mono"] for e in events if e["event"] == "outputs" and e["cause"] == "command")
        assert commanded == dev.cleared_mono
        assert [t for t in trips if t > commanded] == [final["mono"]], "more than one trip after the heartbeat stopped"
        heard = [b for b in beats if commanded < b < final["mono"]]
        assert heard and heard[-1] == final["last_heartbeat_mono"], dev.story(dev.cleared_mono)
        late_s = final["mono"] - heard[-1]

        # every sample of the window once, in order, with its value, across the 32-bit wrap
        blocks = [b for _, b in window]
        n = check_every_sample_once(blocks)
        assert blocks[0].index > blocks[-1].index, "the window should cross the index wrap"
        t_recv = np.array([t for t, _ in window])
        assert t_recv[-1] - t_recv[0] >= WINDOW_S - 0.5
        # the slope of "samples received so far" against arrival time: a least-squares
        # line, so one late wake-up of the reader at either end does not bias it
        ends = np.array([b.seq + len(b.counts) for b in blocks], dtype=float)
        rate = np.polyfit(t_recv - t_recv[0], ends - ends[0], 1)[0]
        print(f"{transport}: {n} samples, {rate:.2f} Hz, watchdog tripped {late_s * 1000:.1f} ms after last heartbeat"
              f" ({len(trips) - 1} trips on late heartbeats, {reclears} answered by a clear before the check)")
        assert abs(rate - 1000.0) <= 10.0, f"rate {rate:.1f} Hz"
        assert WATCHDOG_MS / 1000 <= late_s <= WATCHDOG_MS / 1000 + 0.050, f"tripped {late_s * 1000:.1f} ms after: " + \
            dev.story(dev.cleared_mono)
        # an explicit clear (with the heartbeat back, or the watchdog trips again at once)
        driver.heartbeat()
        dev.round_trip(False, "the explicit clear")
    finally:
        if driver is not None:
            driver.close()
        emu.stop()


# Only so that a device that never does what the test waits for fails instead of hanging: no step is judged by
# it. Every wait below is for an event: the device's (its log) or the driver's (a STATUS showing what the log says).
HANG_S = 30.0


def _outputs_commanded_since(events: list[dict], since: float, feed_hold: bool) -> list[dict]:
    return [e for e in events if e["event"] == "outputs" and e["cause"] == "command" and e["mono"] > since
            and e["feed_hold"] == feed_hold]


def _trips_since(events: list[dict], since: float) -> list[dict]:
    return [e for e in events if e["event"] == "outputs" and e["cause"] == "watchdog" and e["mono"] > since]


class DeviceLog:
    """The test's waits on what the emulated device did (its status log), keeping the heartbeat going where
    the step needs it; on a failure, the device's outputs and heartbeat events say which of the causes it was:
    the command never reached the device, the device tripped again on a late heartbeat, or its reply was lost."""

    def __init__(self, emu: Emulator, col: Collector) -> None:
        self.emu, self.col, self.driver = emu, col, col.driver
        self.cleared_mono: float | None = None  # the device's time of the clear the watchdog check starts from

    def wait(self, found, what: str, since: float, heartbeat_s: float | None = None) -> list[dict]:
        """Pump the driver until `found(device events)` is not empty; returns it."""
        got: list[dict] = []

        def until() -> bool:
            got[:] = found(self.emu.events())
            return bool(got)

        assert self.col.pump(HANG_S, until=until, heartbeat_s=heartbeat_s), f"{what}: not in the device's log. " + \
            self.story(since)
        return got

    def round_trip(self, feed_hold: bool, what: str) -> None:
        """Set the outputs, heartbeat going: the device logs the command, then a STATUS shows it to the driver
        (each heartbeat brings a STATUS too, so a reply lost on a starved pty is not the end of it). A clear
        answers each trip the device logs after it (a heartbeat late by a period trips it again, rightly)."""
        sent = time.monotonic()
        clear = None if feed_hold else _Clear(self.driver, sent)
        taken = [self.driver.set_outputs(True)] if feed_hold else [True]

        def found(ev: list[dict]) -> list[dict]:
            if clear is not None:
                clear.answer(ev)
            got = _outputs_commanded_since(ev, sent, feed_hold)
            if not got and not taken[0]:  # the driver says it was not sent, or not answered (Modbus): again
                taken[0] = self.driver.set_outputs(True)
            return got

        self.wait(found, f"{what} command", sent, HEARTBEAT_S)

        def shown() -> bool:
            if clear is not None:
                clear.answer(self.emu.events())
            return self.driver.last_status is not None and self.driver.last_status.feed_hold == feed_hold

        assert self.col.pump(HANG_S, until=shown, heartbeat_s=HEARTBEAT_S), \
            f"{what} is in the device's log, the driver never showed it: " + self.story(sent)

    def clear_with_heartbeat(self) -> int:
        """Clear the outputs, heartbeat going, until the device's log shows it clear and a heartbeat heard after
        the clear. A trip the device logs meanwhile (a heartbeat late by a period) is answered with a clear.
        Returns how many trips were answered so."""
        sent = time.monotonic()
        self.driver.heartbeat()
        clear = _Clear(self.driver, sent)

        def ready(ev: list[dict]) -> list[dict]:
            if clear.answer(ev):
                return []
            outs = [e for e in ev if e["event"] == "outputs"]
            last = outs[-1] if outs else None
            if last is None or last["feed_hold"] or last["watchdog"]:
                return []  # the clear is on its way
            beats = [e for e in ev if e["event"] == "heartbeat" and e["mono"] > max(last["mono"], sent)]
            return [last] if beats else []

        (last,) = self.wait(ready, "a cleared device hearing the heartbeat", sent, HEARTBEAT_S)
        # a device already clear logs no command: the check then starts from its last change
        self.cleared_mono = last["mono"]
        return clear.answered

    def story(self, since: float) -> str:
        """The device's outputs and heartbeat events from `since` (test's clock = device's clock), one line."""
        parts = []
        prev_beat = None
        for e in self.emu.events():
            if e["mono"] < since - 1.0 or e["event"] not in ("outputs", "heartbeat"):
                continue
            t = f"{e['mono'] - since:+.3f}"
            if e["event"] == "heartbeat":
                gap = "" if prev_beat is None else f" (+{(e['mono'] - prev_beat) * 1000:.0f} ms)"
                prev_beat = e["mono"]
                parts.append(f"{t} hb{gap}")
            else:
                state = ("hold" if e["feed_hold"] else "clear") + (" wd" if e["watchdog"] else "")
                parts.append(f"{t} outputs {state} by {e['cause']}")
        if len(parts) > 60:
            parts = [f"({len(parts) - 60} earlier)", *parts[-60:]]
        return "device log (s from the step): " + "; ".join(parts) + f"; driver's last STATUS {self.driver.last_status}"


class _Clear:
    """A clear of the outputs that answers each watchdog trip the device logs after it with a clear again, and
    sends again a clear the driver says it did not send (or that was not answered, on Modbus)."""

    def __init__(self, driver, sent: float) -> None:
        self.driver, self.sent = driver, sent
        self.taken = driver.set_outputs(False)
        self._seen: set[float] = set()

    @property
    def answered(self) -> int:
        return len(self._seen)

    def answer(self, events: list[dict]) -> bool:
        """True if a clear went out now."""
        for e in _trips_since(events, self.sent):
            if e["mono"] not in self._seen:
                self._seen.add(e["mono"])
                self.taken = False
        if not self.taken:
            self.taken = self.driver.set_outputs(False)
            return True
        return False
