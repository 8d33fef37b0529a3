"""The emulator's device model, pacing and the driver base, with a fake clock where time matters."""

from __future__ import annotations

import time

import numpy as np
import pytest

from millsense.drivers import DriverError, create_driver
from millsense.drivers.base import IndexTracker, SampleBlock
from millsense.sim.emulator.device import DeviceModel
from millsense.sim.emulator.pacing import Pacer
from millsense.sim.emulator.ramp import RampPlant
from millsense.drivers.protocol import CMD_HEARTBEAT, CMD_SET_OUTPUTS, Command
from tests.drivers.emulator_proc import ramp

pytestmark = pytest.mark.quick


def test_index_tracker_gap_wrap_and_restart():
    t = IndexTracker()
    assert t.update(2**32 - 10, 5) == (2**32 - 10, 0, False)
    assert t.update(2**32 - 5, 10) == (2**32 - 5, 0, False)  # crosses the wrap, seq keeps growing
    assert t.update(8, 2) == (2**32 + 8, 3, False)  # indices 5, 6, 7 lost
    seq, lost, disc = t.update(100, 1)
    assert (seq, lost, disc) == (2**32 + 100, 90, False)
    # the device restarted: the index goes back; no invented loss, seq still monotonic
    assert t.update(0, 4) == (2**32 + 101, 0, True)
    assert t.update(4, 1) == (2**32 + 105, 0, False)


def test_device_ring_holds_the_newest_samples_at_k_mod_d_across_the_wrap():
    dev = DeviceModel(RampPlant(start_index=2**32 - 100), start_index=2**32 - 100, ring_depth=64)
    first, counts = dev.produce(250)
    assert first == 2**32 - 100 and dev.head == 150
    np.testing.assert_array_equal(counts, ramp(2**32 - 100, 250))
    for k in range(150 - 64, 150):  # the newest D samples
        np.testing.assert_array_equal(dev.ring[k % 64], ramp(k, 1)[0])
    regs = dev.ring_registers((149 % 64) * 8, 8)
    assert np.array(regs, dtype=np.uint16).view(np.int16).tolist() == ramp(149, 1)[0].tolist()


def test_watchdog_is_armed_by_the_first_heartbeat_and_trips_on_time():
    plant = RampPlant()
    dev = DeviceModel(plant, watchdog_ms=200)
    assert dev.watchdog_deadline() is None  # not armed before any heartbeat
    assert not dev.check_watchdog(1000.0)
    dev.apply_command(Command(CMD_HEARTBEAT, 1), now=10.0)
    assert dev.watchdog_deadline() == pytest.approx(10.2)
    dev.apply_command(Command(CMD_HEARTBEAT, 1), now=10.15)  # same counter: not a new heartbeat
    assert not dev.check_watchdog(10.19)
    assert dev.check_watchdog(10.2)
    assert dev.status().feed_hold and dev.status().watchdog_tripped and plant.feed_hold
    # more heartbeats do not clear feed hold; only an explicit set-outputs does
    dev.apply_command(Command(CMD_HEARTBEAT, 2), now=10.3)
    assert dev.status().feed_hold
    assert dev.apply_command(Command(CMD_SET_OUTPUTS, 0), now=10.31)
    assert not dev.status().feed_hold and not dev.status().watchdog_tripped and not plant.feed_hold
    assert dev.watchdog_deadline() == pytest.approx(10.5)


def test_pacer_does_not_drift_with_late_wakeups():
    now = [100.0]
    pacer = Pacer(1000, clock=lambda: now[0])
    rng = np.random.default_rng(0)
    total = 0
    for _ in range(30_000):  # ~5 minutes of batches, each woken up to 7 ms late
        now[0] = pacer.next_time() + float(rng.uniform(0, 0.007))
        total += pacer.due()
    assert total == int((now[0] - 100.0) * 1000)


def test_pacer_sends_whole_frames_as_a_daq_does():
    """A wake-up 1-7 ms late sends whole 10-sample frames, never a 10 + 1 pair (issue 13: the emulator's
    remainder frames doubled the frames on the wire); the clock is kept within one frame, and the end of
    a finite run sends its remainder."""
    now = [100.0]
    pacer = Pacer(1000, clock=lambda: now[0], quantum=10)
    rng = np.random.default_rng(1)
    total = 0
    for _ in range(3_000):
        now[0] = pacer.next_time() + float(rng.uniform(0.001, 0.007))
        n = pacer.due()
        assert n % 10 == 0
        total += n
        assert 0 <= int((now[0] - 100.0) * 1000) - total < 10
    limit = total + 15
    now[0] += 1.0
    assert pacer.due(limit=limit) == 15   # the last, partial frame


def test_pacer_at_speed_sends_k_times_the_samples_without_drift_and_restarts():
    """`--speed K`: K seconds of samples each second of the clock, whole frames, still one wake-up per 10 ms;
    `restart` (the stream held until its first client) makes the first sample due then."""
    now = [100.0]
    pacer = Pacer(1000, clock=lambda: now[0], quantum=10, speed=3.0)
    now[0] = 250.0
    pacer.restart(now[0])
    assert pacer.due() == 0
    rng = np.random.default_rng(2)
    wakes = 0
    while now[0] < 260.0:
        now[0] = pacer.next_time() + float(rng.uniform(0, 0.004))
        n = pacer.due()
        assert n % 10 == 0
        wakes += 1
    assert 0 <= int((now[0] - 250.0) * 3000) - pacer.produced < 10
    assert 900 <= wakes <= 1001   # 10 s of the clock at one wake-up per 10 ms, not per 10/3 ms


def test_create_driver_names_the_transport_in_errors():
    with pytest.raises(DriverError, match="'carrier-pigeon'"):
        create_driver("carrier-pigeon")
    with pytest.raises(DriverError, match="'tcp'"):
        create_driver("tcp", host="", tcp_port=0)
    # options other transports use are ignored, so a whole [daq] section can be passed
    drv = create_driver("tcp", host="127.0.0.1", tcp_port=9, port="/dev/ttyX", baudrate=9600, unit=1)
    assert drv.transport == "tcp" and drv.address == "127.0.0.1:9"


def test_link_down_is_reported_once_while_retrying(tmp_path, port):
    import structlog

    drv = create_driver("tcp", host="127.0.0.1", tcp_port=port)  # nothing listens there
    with structlog.testing.capture_logs() as logs:
        drv.start()
        assert not drv.wait_connected(1.0)
        drv.close()
    downs = [e for e in logs if e["event"] == "daq.link_down"]
    assert len(downs) == 1 and downs[0]["transport"] == "tcp" and downs[0]["address"] == f"127.0.0.1:{port}"
    assert drv.stats()["connect_failures"] >= 3  # 0.1 + 0.2 + 0.4 s of doubling back-off


def test_sim_driver_in_process_real_time():
    drv = create_driver("sim", scenario="ramp")
    drv.start()
    try:
        assert drv.wait_connected(2.0)
        t0 = time.monotonic()
        blocks = []
        while time.monotonic() - t0 < 1.0:
            ev = drv.get(0.05)
            if isinstance(ev, SampleBlock):
                blocks.append(ev)
        n = sum(len(b.counts) for b in blocks)
        assert 900 <= n <= 1100
        for b in blocks:
            np.testing.assert_array_equal(b.counts, ramp(b.index, len(b.counts)))
            assert b.lost_before == 0
        drv.set_watchdog_ms(100)
        drv.heartbeat()
        deadline = time.monotonic() + 2.0
        while time.monotonic() < deadline and not (drv.last_status and drv.last_status.watchdog_tripped):
            drv.get(0.05)
        assert drv.last_status.watchdog_tripped and drv.last_status.feed_hold
        assert drv.device.source.feed_hold  # the plant sees feed hold
    finally:
        drv.close()
