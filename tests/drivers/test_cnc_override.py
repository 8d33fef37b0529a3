"""The simulated CNC's feed override (issue 15): its lag and rate limit stepped per sample, the device's
commanded vs applied override, its status log; and the real emulator over TCP (stream) and Modbus TCP:
a commanded override reaches STATUS / input register 6 through the lag, the plant's feed follows it,
the watchdog returns it to 100 %, a restart starts at 100 %, and a feed hold still stops the feed."""

from __future__ import annotations

import json
import math
import time

import numpy as np
import pytest

from millsense.drivers import create_driver
from millsense.drivers.base import SampleBlock
from millsense.sim.emulator.cnc_override import CncOverride
from millsense.sim.emulator.device import DeviceModel, StatusLog
from millsense.sim.emulator.ramp import RampPlant
from millsense.drivers.protocol import CMD_HEARTBEAT, CMD_SET_FEED_OVERRIDE, Command, Status
from millsense.sim import Plant
from tests.conftest import free_tcp_port
from tests.drivers.emulator_proc import Emulator

FS_HZ = 1000.0


# -- the CNC's response, unit ----------------------------------------------------------------------

def test_the_lag_is_first_order_with_its_time_constant():
    lag_ms = 40.0
    cnc = CncOverride(lag_ms=lag_ms, rate_pct_s=0.0, sample_rate_hz=FS_HZ)  # no rate limit: the lag alone
    out = cnc.run(120.0, 1000)  # 25 time constants
    k = np.arange(1, 1001)
    expected = 120.0 - 20.0 * np.exp(-k / FS_HZ / (lag_ms / 1000.0))  # 20 % step through exp(-t/tau)
    reached = out < 120.0  # from the snap on it is the command itself
    assert reached[: round(5 * lag_ms)].all()  # not there within 5 time constants (0.13 % still to go)
    np.testing.assert_allclose(out[reached], expected[reached], rtol=0, atol=1e-9)
    assert out[-1] == 120.0 and cnc.applied_pct == 120.0  # settled exactly: a steady feed stays steady


def test_the_rate_limit_bounds_every_step():
    rate = 200.0
    cnc = CncOverride(lag_ms=0.0, rate_pct_s=rate, sample_rate_hz=FS_HZ)  # no lag: the rate limit alone
    out = cnc.run(150.0, 400)
    k = np.arange(1, 401)
    np.testing.assert_allclose(out, np.minimum(100.0 + rate * k / FS_HZ, 150.0), atol=1e-9)
    # both together, down and up: never faster than the limit, and it gets there
    cnc = CncOverride(lag_ms=40.0, rate_pct_s=rate, sample_rate_hz=FS_HZ)
    down = cnc.run(50.0, 1000)
    up = cnc.run(130.0, 1000)
    path = np.concatenate(([100.0], down, up))
    assert np.abs(np.diff(path)).max() <= rate / FS_HZ + 1e-9
    assert np.all(np.diff(down) <= 0) and np.all(np.diff(up) >= 0)
    assert down[-1] == 50.0 and up[-1] == 130.0


def test_the_response_does_not_depend_on_how_samples_are_batched():
    one = CncOverride(sample_rate_hz=FS_HZ).run(137.5, 500)
    cnc = CncOverride(sample_rate_hz=FS_HZ)
    parts = np.concatenate([cnc.run(137.5, n) for n in (1, 9, 90, 400)])
    np.testing.assert_array_equal(one, parts)


@pytest.mark.parametrize("lag_ms, rate", [(-1.0, 200.0), (40.0, -5.0), (math.nan, 200.0), (40.0, math.inf)])
def test_bad_settings_are_refused(lag_ms, rate):
    with pytest.raises(ValueError):
        CncOverride(lag_ms, rate)


# -- the device, fake clock ------------------------------------------------------------------------

def _events(path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


def test_device_applies_the_commanded_override_through_the_lag_and_logs_both(tmp_path):
    log = StatusLog(str(tmp_path / "log.jsonl"))
    dev = DeviceModel(RampPlant(), protocol=2, watchdog_ms=100, status_log=log)
    dev.apply_command(Command(CMD_SET_FEED_OVERRIDE, 1200), now=1.0)
    dev.apply_command(Command(CMD_SET_FEED_OVERRIDE, 1200), now=1.01)  # unchanged: still a command
    assert dev.feed_override_commanded == 1200
    assert dev.status().feed_override == 1000  # not applied before the CNC has run a sample
    applied = []
    for _ in range(50):
        dev.produce(10)
        applied.append(dev.status().feed_override)
        assert dev.source.feed_override_pct[-1] * 10 == pytest.approx(applied[-1], abs=0.5)  # what the plant got
    assert applied[-1] == 1200 and applied == sorted(applied)
    assert any(1000 < v < 1200 for v in applied)  # it moved through the lag, not at once
    # the watchdog: commanded back to 100 % at once, the applied one follows through the lag
    dev.apply_command(Command(CMD_HEARTBEAT, 1), now=2.0)
    assert dev.check_watchdog(2.2)
    assert dev.feed_override_commanded == 1000 and dev.status().feed_override == 1200
    back = []
    for _ in range(50):
        dev.produce(10)
        back.append(dev.status().feed_override)
    assert back[-1] == 1000 and back == sorted(back, reverse=True) and any(1000 < v < 1200 for v in back)
    log.close()
    events = _events(tmp_path / "log.jsonl")
    assert [e["value"] for e in events if e["event"] == "feed_override_command"] == [1200, 1200]
    changes = [e for e in events if e["event"] == "feed_override_applied"]
    assert [e["value"] for e in changes] == [v for i, v in enumerate(applied + back)
                                            if v != ([1000] + applied + back)[i]]  # one per block that moved it
    # a restart is a new device: commanded and applied at 100 %
    again = DeviceModel(RampPlant(), protocol=2)
    assert again.feed_override_commanded == 1000 and again.status().feed_override == 1000


def test_the_plants_feed_follows_the_applied_override_sample_by_sample():
    plant = Plant("afc-step", seed=0, noise_scale=0)
    dev = DeviceModel(plant, protocol=2, cnc_override_lag_ms=40, cnc_override_rate_pct_s=200)
    dev.produce(3000)  # in the cut at the programmed feed
    dev.set_feed_override(1200, now=0.0)
    for _ in range(300):
        dev.produce(10)
    revs = plant.truth.revolutions()
    before = [r for r in revs if r["index_end"] < 3000 and r["index_end"] > 500]
    after = [r for r in revs if r["index_end"] > 3000 + 1000]
    feed = plant.scenario.feed_segments[0][1]
    assert before and after
    assert all(r["feed_override_pct"] == 100.0 and r["feed_mm_min"] == pytest.approx(feed, rel=1e-6) for r in before)
    assert all(r["feed_override_pct"] == 120.0 for r in after)
    assert all(r["feed_mm_min"] == pytest.approx(feed * 1.2, rel=1e-6) for r in after)
    moving = [r for r in revs if 3000 < r["index_end"] <= 4000]
    assert any(100.0 < r["feed_override_pct"] < 120.0 for r in moving)  # the lag, seen by the machine



def _stream(items) -> list[tuple[int, int]]:
    """(samples before it, its override) of each STATUS among stream items, in order."""
    out, done = [], 0
    for item in items:
        if isinstance(item, Status):
            out.append((done, item.feed_override))
        elif hasattr(item, "counts"):
            done += len(item.counts)
    return out


@pytest.mark.parametrize("per_frame", [10, 25])
def test_a_large_block_carries_a_status_where_the_override_moved(per_frame):
    """`--fast` makes a second of samples at once: the STATUS of the applied override goes after each frame in
    which it moved, carrying its value at that frame's last sample, so the host learns of a change where it
    happened (a frame late at most, as in real time), not a whole block late. On the wire and in process."""
    from millsense.sim.emulator.wire import WireEmitter
    from millsense.drivers.protocol import StreamDecoder

    plant = Plant("afc-step", seed=0, noise_scale=0)
    dev = DeviceModel(plant, protocol=2, cnc_override_lag_ms=40, cnc_override_rate_pct_s=1000)
    dev.produce(1000)
    dev.set_feed_override(1300, now=0.0)
    first, counts = dev.produce(1000)
    applied = np.rint(np.asarray(plant.feed_override_pct) * 10).astype(int)  # the plant's, per sample
    emitter = WireEmitter(dev, per_frame=per_frame)
    wire = _stream(StreamDecoder().feed(emitter.descriptor(0.0) + emitter.block(first, counts, 0.0)))
    in_process = _stream(dev.stream_items(first, counts, frame=per_frame))
    for points in (wire, in_process):
        assert len(points) > 5, points                          # it moved through the lag, frame by frame
        assert all(k % per_frame == 0 or k == len(counts) for k, _ in points)
        assert all(v == applied[k - 1] for k, v in points), points
        assert points[-1][1] == 1300 and [v for _, v in points] == sorted(v for _, v in points)
        # every frame after which the override stood elsewhere than at the last STATUS has one
        ends = list(range(per_frame, len(counts) + 1, per_frame))
        said = dict(points)
        last = 1000
        for k in ends:
            if applied[k - 1] != last:
                assert said.get(k) == applied[k - 1], (k, applied[k - 1])
                last = applied[k - 1]
    # a block in which nothing moved carries none
    first, counts = dev.produce(1000)
    assert _stream(dev.stream_items(first, counts)) == []


# -- the real emulator -----------------------------------------------------------------------------

class Events:
    """A driver's events in arrival order, drained in the test thread; heartbeats while ``alive``."""

    def __init__(self, driver) -> None:
        self.driver = driver
        self.items: list = []
        self.alive = True
        self._beat = 0.0

    def pump(self, seconds: float, until) -> bool:
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            if self.alive and time.monotonic() - self._beat > 0.1:
                self._beat = time.monotonic()
                self.driver.heartbeat()
            ev = self.driver.get(timeout=0.02)
            if ev is not None:
                self.items.append(ev)
            if until():
                return True
        return False

    def overrides(self, since: int = 0) -> list[int]:
        return [e.feed_override for e in self.items[since:] if isinstance(e, Status)]

    def statuses(self, since: int = 0) -> list[Status]:
        return [e for e in self.items[since:] if isinstance(e, Status)]

    def samples_since(self, since: int) -> int:
        return sum(len(e.counts) for e in self.items[since:] if isinstance(e, SampleBlock))


def _truth(path) -> list[dict]:
    return [r for r in (json.loads(line) for line in path.read_text().splitlines()) if "rev" in r]


def test_stream_override_lag_plant_feed_hold_and_watchdog(tmp_path, port):
    truth = tmp_path / "truth.jsonl"
    emu = Emulator(tmp_path, "--tcp", f"127.0.0.1:{port}", "--scenario", "afc-step", "--protocol", "2",
                   "--watchdog-ms", "1000", "--noise-scale", "0", "--truth", str(truth),
                   "--cnc-override-lag-ms", "40", "--cnc-override-rate-pct-s", "200")
    driver = None
    try:
        emu.start()
        driver = create_driver("tcp", host="127.0.0.1", tcp_port=port)
        driver.start()
        assert driver.wait_connected(10.0)
        ev = Events(driver)
        assert ev.pump(5.0, lambda: ev.overrides() and ev.samples_since(0) > 2000), "no STATUS or samples"
        assert set(ev.overrides()) == {1000}

        # 120 %: STATUS reports the applied override, which climbs through the lag
        mark = len(ev.items)
        assert driver.set_feed_override(1200)
        assert ev.pump(5.0, lambda: ev.overrides(mark)[-1:] == [1200]), ev.overrides(mark)
        seen = ev.overrides(mark)
        assert seen == sorted(seen) and any(1000 < v < 1200 for v in seen), seen
        assert ev.pump(5.0, lambda: ev.samples_since(mark) > 1500)  # some revolutions at 120 %

        # 150 % and a feed hold: the hold wins
        assert driver.set_feed_override(1500)
        assert ev.pump(5.0, lambda: ev.overrides(mark)[-1:] == [1500])
        at150 = len(ev.items)
        assert ev.pump(3.0, lambda: ev.samples_since(at150) > 1000)
        assert driver.set_outputs(True)
        assert ev.pump(3.0, lambda: any(s.feed_hold for s in ev.statuses(mark)))
        held = len(ev.items)
        assert ev.pump(5.0, lambda: ev.samples_since(held) > 1500)
        assert driver.set_outputs(False)

        # the heartbeat stops: the watchdog commands 100 % and the applied override follows
        ev.alive = False
        assert ev.pump(5.0, lambda: any(s.watchdog_tripped for s in ev.statuses(held)))
        trip = next(i for i, e in enumerate(ev.items) if i >= held and isinstance(e, Status) and e.watchdog_tripped)
        assert ev.pump(5.0, lambda: ev.overrides(trip)[-1:] == [1000])
        down = ev.overrides(trip)
        assert down == sorted(down, reverse=True) and any(1000 < v < 1500 for v in down), down
    finally:
        if driver is not None:
            driver.close()
        emu.stop()
    commands = [e["value"] for e in emu.events("feed_override_command")]
    assert commands == [1200, 1500]
    assert [e["cause"] for e in emu.events("feed_override")] == ["command", "command", "watchdog"]
    applied = [e["value"] for e in emu.events("feed_override_applied")]
    assert applied[-1] == 1000 and 1200 in applied and 1500 in applied
    # the machine: the feed was the programmed one times the applied override, and 0 under the hold
    revs = _truth(truth)
    feed = 200.0  # afc-step's programmed feed (scenarios.py)
    for pct in (100.0, 120.0, 150.0):
        # at this override for a whole revolution and the one before, and not held: the feed settled
        steady = [r for prev, r in zip(revs, revs[1:], strict=False)
                  if all(x["feed_override_pct"] == pct and not x["feed_hold"] for x in (prev, r))]
        assert steady, pct
        assert all(r["feed_mm_min"] == pytest.approx(feed * pct / 100.0, rel=1e-6) for r in steady), pct
    stopped = [r for r in revs if r["feed_override_pct"] == 150.0 and r["feed_hold"] and r["feed_mm_min"] == 0.0]
    assert stopped, "the feed hold did not stop the feed at 150 %"


def _modbus_client(port):
    from pymodbus.client import ModbusTcpClient

    client = ModbusTcpClient("127.0.0.1", port=port, timeout=2)
    assert client.connect()
    return client


def _read(client, fn, address: int) -> int:
    return getattr(client, fn)(address, count=1, device_id=1).registers[0]


def _poll(client, until, seconds: float = 5.0) -> list[int]:
    """Input register 6 read again and again until ``until(values)``; the values read."""
    values: list[int] = []
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        values.append(_read(client, "read_input_registers", 6))
        if until(values):
            return values
        time.sleep(0.005)
    raise AssertionError(f"input register 6 never got there: {values[-20:]}")


def test_modbus_register_6_is_applied_102_commanded_watchdog_and_restart(tmp_path, port):
    args = ("--modbus-tcp", f"127.0.0.1:{port}", "--scenario", "afc-step", "--protocol", "2", "--noise-scale", "0")
    emu = Emulator(tmp_path, *args)
    client = None
    try:
        emu.start()
        client = _modbus_client(port)
        assert _read(client, "read_input_registers", 6) == 1000
        assert not client.write_register(102, 1200, device_id=1).isError()
        assert _read(client, "read_holding_registers", 102) == 1200  # commanded: at once
        rise = _poll(client, lambda v: v[-1] == 1200)
        assert rise == sorted(rise)
        applied = [e["value"] for e in emu.events("feed_override_applied")]
        assert applied[-1] == 1200 and any(1000 < v < 1200 for v in applied)  # through the lag
        # the watchdog: armed by a heartbeat, then silence
        assert not client.write_register(101, 300, device_id=1).isError()
        assert not client.write_register(100, 7, device_id=1).isError()
        fall = _poll(client, lambda v: v[-1] == 1000)
        assert fall == sorted(fall, reverse=True)
        assert _read(client, "read_holding_registers", 102) == 1000
        assert [e["cause"] for e in emu.events("feed_override")] == ["command", "watchdog"]
        # at 120 % again, then the DAQ loses power: a restart starts at 100 %
        assert not client.write_register(102, 1200, device_id=1).isError()
        _poll(client, lambda v: v[-1] == 1200)
        client.close()
        emu.kill()
        emu.stop()
        port2 = free_tcp_port()
        emu = Emulator(tmp_path, "--modbus-tcp", f"127.0.0.1:{port2}", *args[2:], name="restart")
        emu.start()
        client = _modbus_client(port2)
        assert _read(client, "read_input_registers", 6) == 1000
        assert _read(client, "read_holding_registers", 102) == 1000
        start = emu.events("start")
        assert start and start[0]["feed_override"] == 1000
    finally:
        if client is not None:
            client.close()
        emu.stop()


@pytest.mark.parametrize("extra, said", [
    (("--scenario", "part-program", "--afc-allowed"), "--afc-allowed: the part program"),
    (("--scenario", "afc-step", "--cnc-override-lag-ms", "nan"), "--cnc-override-lag-ms: expected a finite"),
    (("--scenario", "afc-step", "--cnc-override-rate-pct-s", "-1"), "expected a value >= 0"),
])
def test_sim_refuses_bad_override_options_plainly(tmp_path, extra, said):
    import subprocess

    from tests.drivers.emulator_proc import SIM_CMD

    res = subprocess.run([*SIM_CMD, *extra, "--capture", str(tmp_path / "x.cap"), "--duration-s", "0.1"],
                         capture_output=True, text=True, timeout=60)
    assert res.returncode == 2 and said in res.stderr and "Traceback" not in res.stderr, res.stderr


def test_the_in_process_sim_driver_passes_the_cnc_options():
    from millsense.drivers.protocol import CTX_AFC_ALLOWED, Context
    from millsense.drivers.sim_driver import SimDriver

    drv = create_driver("sim", scenario="afc-step", protocol=2, cnc_override_lag_ms=80.0,
                        cnc_override_rate_pct_s=50.0, afc_allowed=True)
    assert isinstance(drv, SimDriver)
    drv.start()
    try:
        assert drv.wait_connected(5)
        cnc = drv.device.cnc_override
        assert (cnc.lag_ms, cnc.rate_pct_s) == (80.0, 50.0)
        deadline = time.monotonic() + 10
        while drv.last_status is None and time.monotonic() < deadline:  # the DESCRIPTOR first: version 2
            drv.get(0.05)
        assert drv.set_feed_override(1100)
        seen: list = []
        while time.monotonic() < deadline and not (seen and seen[-1] == 1100):
            ev = drv.get(0.05)
            if isinstance(ev, Status):
                seen.append(ev.feed_override)
        assert seen[-1] == 1100 and any(1000 < v < 1100 for v in seen)
        assert isinstance(drv.last_context, Context) and drv.last_context.flags & CTX_AFC_ALLOWED
        # a refused setting is a clear error at creation, not a link that never comes up
        with pytest.raises(Exception, match="override lag"):
            create_driver("sim", scenario="afc-step", cnc_override_lag_ms=-1.0)
    finally:
        drv.close()
