"""A Modbus reader that keeps falling a ring behind is blind, live: the daemon says so and holds the feed.

Stop 29's finding A, through the real daemon, the emulator's Modbus server and a gateway (tests/faults/
netfault.py's proxy) answering every read 40 ms late: 15 samples a request cannot keep up with 1 kHz, so the
reader falls a ring behind again and again and skips half a second or more each time, the link up all along.
Before stop 34 the loss check took each skip for an outage of the link: status `running`, interlock `armed`,
60 % of the stream lost.
"""

from __future__ import annotations

import pytest

from tests.e2e.helpers import read_jsonl, wait_for
from tests.faults.helpers import modbus_proxy_daemon, outputs, wait_status

pytestmark = pytest.mark.slow

FC_READ_INPUT = 4
SLOW_S = 60.0  # detects a failure; no budget (CI is a loaded 2-core box)


def test_a_gateway_too_slow_for_the_samples_is_blind_and_holds_the_feed(tmp_path):
    machine = "mb-slow-01"
    with modbus_proxy_daemon(tmp_path, machine) as (procs, daemon, sub, sim_log, proxy):
        st = wait_status(sub, machine, lambda s: s["samples_received"] > 2000, SLOW_S, "the stream flowing")
        assert st["state"] == "running" and not st.get("faults"), st
        proxy.late(FC_READ_INPUT, 10**9, 0.04)   # every ring read from now on
        st = wait_status(sub, machine, lambda s: "signals" in s.get("faults", {}) or daemon.poll() is not None,
                         SLOW_S, "fault signals")
        assert daemon.poll() is None, procs.text("daemon", "out")[-3000:]
        reason = st["faults"]["signals"]
        assert "with the link up" in reason and "overrun" in reason, reason
        assert st["daq_link"] == "up", st
        wait_for(lambda: outputs(read_jsonl(sim_log), feed_hold=True, cause="command"), SLOW_S,
                 "the daemon holds the feed (on_blind = hold)")
        wait_status(sub, machine, lambda s: s["interlock"] == "feed_hold", SLOW_S, "status: feed held")
