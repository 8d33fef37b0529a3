"""A feed hold the DAQ's watchdog set is kept until an authorised reset, also across the DAQ restarting.

A probe in stop 28 froze the daemon for 1.5 s (SIGSTOP: a hung daemon), so the DAQ's watchdog held the feed (status
`held_by_device`, right); then the DAQ restarted (kill -9 and start again, a power blip): it came back with its
outputs released, and the daemon said `armed`, wrote nothing, and logged that the hold was "left asserted". A machine
stopped for a reason ran again with no reset.
"""

from __future__ import annotations

import os
import re
import signal
import time

from tests.e2e.helpers import read_jsonl, wait_for
from tests.faults.flood import holds
from tests.faults.helpers import live_daemon, status, wait_status

MACHINE = "wdhold-01"


def test_a_hold_the_daqs_watchdog_set_is_written_again_to_a_daq_that_restarted(tmp_path):
    il = 'enabled = true\nheartbeat_ms = 100\nwatchdog_ms = 500\nreset = "open"'
    with live_daemon(tmp_path, MACHINE, [], interlock=il, watchdog_ms=500) as (procs, daemon, sub, log):
        wait_status(sub, MACHINE, lambda st: st["interlock"] == "armed" and st["revolutions"] >= 3, 60.0, "armed")
        os.kill(daemon.pid, signal.SIGSTOP)   # a hung daemon: its heartbeats stop
        try:
            wait_for(lambda: holds(read_jsonl(log)), 30.0, "the DAQ's watchdog holding the feed")
        finally:
            os.kill(daemon.pid, signal.SIGCONT)
        wait_status(sub, MACHINE, lambda st: st["interlock"] == "held_by_device", 30.0, "held by the device")

        # the DAQ restarts (a power blip): its outputs come back released
        sim = next(p for p in procs.procs if p.name == "sim")
        sim.kill()
        sim.wait(10)
        port = re.search(r"tcp_port = (\d+)", (tmp_path / "d.toml").read_text())[1]
        log2 = tmp_path / "sim2.jsonl"
        procs.start("sim2", ["sim", "--scenario", "step", "--loop", "--tcp", f"127.0.0.1:{port}", "--realtime",
                             "--watchdog-ms", "500", "--status-log", str(log2)])
        wait_for(lambda: log2.exists() and holds(read_jsonl(log2)), 60.0, "the hold written to the restarted DAQ")
        wait_status(sub, MACHINE, lambda st: st["daq_link"] == "up" and st["samples_received"] > 0, 60.0, "link up")
        time.sleep(1.0)   # what it says a moment later, once the restarted DAQ's status came in
        st = status(sub, MACHINE)
        assert st["interlock"] == "held_by_device" and st["interlock_detail"]["device_feed_hold"], st["interlock_detail"]
        assert daemon.poll() is None
