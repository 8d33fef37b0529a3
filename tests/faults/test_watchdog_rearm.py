"""A DAQ that restarted under the daemon is told its watchdog period again, and holds the feed within it.

A DAQ that restarts (a power blip, a brown-out, its firmware reset) comes back with the watchdog period it
powers up with: its own setting, or none, not the `[interlock] watchdog_ms` the daemon told the one before.
The runner arms it again when the link comes back up (`Runner._on_link`: the interlock's `start`); without
that, a daemon that hangs afterwards leaves the feed running until it is restarted. Issue 37's planted bug
`il-watchdog-not-rearmed` (that call removed) passed every test: the live tests restart an emulator that is
given its period on its command line, and the Modbus driver writes the period again at each reconnect of its
own, so only a transport that does not remember it (the in-process DAQ here) shows whether the runner does.
"""

from __future__ import annotations

import time

from millsense.daemon.config.load import load_config
from millsense.drivers.base import LinkEvent
from millsense.sim.emulator.device import DeviceModel
from millsense.sim.emulator.source import make_source
from tests.e2e.helpers import wait_for, write_config
from tests.faults.helpers import INTERLOCK_OPEN, runner_on_the_sim


def test_a_daq_that_restarted_is_armed_again_and_holds_the_feed_when_the_daemon_goes_silent(tmp_path):
    """The real runner on the simulated DAQ (`watchdog_ms = 1000`); the DAQ restarts with no watchdog period
    (a fresh device model, as at power-up), the link goes down and comes back: the restarted DAQ is given the
    period, and with no heartbeat after the first it holds the feed by itself (its watchdog flag raised)."""
    cfg = write_config(tmp_path / "wd.toml", machine="wdrearm-01", daq='transport = "sim"\nscenario = "step"',
                       interlock=INTERLOCK_OPEN)
    with runner_on_the_sim(load_config(cfg)) as (runner, drv, sink):
        assert runner.interlock.watchdog_ms == 1000 and drv.device.watchdog_ms == 1000   # armed at start
        with drv._io_lock:   # the DAQ restarts between two of the reader thread's reads
            drv.device = DeviceModel(make_source("step", loop=True), watchdog_ms=0)
            drv._send_descriptor = True   # a restarted board announces itself
        restarted = drv.device
        runner.handle(LinkEvent(False, "connection reset"), time.monotonic())
        runner.handle(LinkEvent(True, "connected"), time.monotonic())
        assert restarted.watchdog_ms == 1000, "the restarted DAQ was not told its watchdog period"
        assert not restarted.feed_hold
        # the runner's heartbeat thread is not started: after this one heartbeat the daemon is silent (hung)
        assert drv.heartbeat()
        wait_for(lambda: restarted.feed_hold, 30.0, "the restarted DAQ's watchdog holding the feed")
        assert restarted.status().watchdog_tripped   # its own watchdog, not a command
        assert not runner.interlock.latched
