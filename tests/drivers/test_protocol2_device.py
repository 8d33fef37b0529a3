"""The emulator's version-2 device model with a fake clock: the CNC's lag, the feed override,
its return to 100.0 % on a watchdog trip; and the in-process sim driver speaking version 2."""

from __future__ import annotations

import time

import pytest

from millsense.drivers.base import SampleBlock
from millsense.sim.emulator.device import DeviceModel
from millsense.sim.emulator.ramp import RampPlant
from millsense.drivers.protocol import (
    CMD_HEARTBEAT,
    CMD_SET_FEED_OVERRIDE,
    CMD_SET_OUTPUTS,
    Command,
    Context,
    Status,
)
from millsense.drivers.sim_driver import SimDriver

pytestmark = pytest.mark.quick


def _device(**kw) -> DeviceModel:
    return DeviceModel(RampPlant(), protocol=2, program=7, tool=70001, operation=3, **kw)


def test_version_2_descriptor_status_and_context():
    dev = _device()
    assert dev.descriptor.protocol_version == 2 and dev.descriptor.capabilities == 0b11
    assert dev.status().feed_override == 1000
    assert dev.context() == Context(0, 7, 70001, 3, 0b0011)  # cycle and monitoring on
    v1 = DeviceModel(RampPlant())
    assert v1.descriptor.protocol_version == 1 and v1.status().feed_override is None and v1.context() is None
    assert not v1.set_feed_override(500, 0.0) and v1.status().feed_override is None


def test_the_cnc_reports_feed_held_after_its_lag_and_follows_each_change():
    dev = _device(cnc_hold_lag_ms=30)
    dev.produce(100)
    dev.apply_command(Command(CMD_SET_OUTPUTS, 1), now=10.0)
    assert not dev.update_cnc(10.029) and not dev.context().feed_held  # not yet
    assert dev.next_cnc_time() == pytest.approx(10.03)
    assert dev.update_cnc(10.030)
    ctx = dev.context()
    assert ctx.feed_held and ctx.cycle and ctx.index == 100  # the index at which it changed
    # released and held again within the lag: the CNC goes through both, in order
    dev.produce(50)
    dev.apply_command(Command(CMD_SET_OUTPUTS, 0), now=11.0)
    dev.apply_command(Command(CMD_SET_OUTPUTS, 1), now=11.01)
    assert dev.update_cnc(11.05) and dev.context().feed_held
    assert dev.next_cnc_time() is None
    # the alarm lamp alone does not move the CNC
    dev.apply_command(Command(CMD_SET_OUTPUTS, 3), now=12.0)
    assert dev.next_cnc_time() is None


def test_feed_override_is_set_refused_out_of_range_and_reset_by_the_watchdog():
    dev = _device(watchdog_ms=100)
    dev.apply_command(Command(CMD_SET_FEED_OVERRIDE, 850), now=1.0)
    dev.produce(1000)  # the CNC applies it through its lag (test_cnc_override.py)
    assert dev.status().feed_override == 850
    assert not dev.set_feed_override(2001, now=1.1)
    assert dev.status().feed_override == 850  # a bad value changes nothing
    dev.apply_command(Command(CMD_HEARTBEAT, 1), now=2.0)
    assert dev.check_watchdog(2.1)
    dev.produce(1000)
    st = dev.status()
    assert st.watchdog_tripped and st.feed_hold and st.feed_override == 1000
    # and the CNC follows the watchdog's feed hold too
    assert dev.next_cnc_time() == pytest.approx(2.13)
    assert dev.update_cnc(2.2) and dev.context().feed_held


def test_sim_driver_speaks_version_2():
    drv = SimDriver("ramp", protocol=2, cnc_hold_lag_ms=30)
    drv.start()
    try:
        assert drv.wait_connected(5)
        events: list = []

        def pump(until, seconds=5.0) -> bool:
            deadline = time.monotonic() + seconds
            while time.monotonic() < deadline:
                ev = drv.get(0.05)
                if ev is not None and not isinstance(ev, SampleBlock):
                    events.append(ev)
                if until():
                    return True
            return False

        assert pump(lambda: drv.last_context is not None and drv.last_status is not None)
        assert drv.descriptor.capabilities == 3 and drv.last_status.feed_override == 1000
        assert drv.set_feed_override(1500)
        assert pump(lambda: any(isinstance(e, Status) and e.feed_override == 1500 for e in events))
        assert drv.set_outputs(True)
        assert pump(lambda: any(isinstance(e, Context) and e.feed_held for e in events))
        held = [e for e in events if isinstance(e, Context) and e.feed_held]
        hold_status = next(i for i, e in enumerate(events) if isinstance(e, Status) and e.feed_hold)
        assert events.index(held[0]) > hold_status  # the CNC reported after the DAQ's output
    finally:
        drv.close()
