"""A context put every few milliseconds, each naming a new program, tool and operation (a buggy CNC adapter, or
any peer on an open network), live: learning stays bounded and the heartbeat goes on.

Before stop 26 each such context's process made a process key: 10 a second at 600 rpm, every one in every
`status` (each second) and `limits` answer, built while the estimator thread waited. A probe grew 8,000 keys in
ten minutes, then a `status` and `limits` flood starved the estimator until the DAQ's watchdog held the feed. A
process seen for a revolution or two teaches nothing: now it makes no key.
"""

from __future__ import annotations

import json
import random
import time

import pytest

from tests.e2e.helpers import read_jsonl, wait_for
from tests.faults.flood import holds
from tests.faults.helpers import live_daemon, status

MACHINE = "ctxflood-01"


def _flood(sub, seconds: float) -> None:
    """A new program, tool and operation put every 5 ms for `seconds`."""
    pub = sub.session.declare_publisher(f"millsense/{MACHINE}/context")
    rng = random.Random(7)
    end = time.monotonic() + seconds
    while time.monotonic() < end:   # ~200 a second: what the daemon takes of a flood (20 per 0.1 s)
        pub.put(json.dumps({"program": rng.randrange(2**31), "tool": rng.randrange(1, 10_000),
                            "operation": rng.randrange(65536), "cycle": True, "monitor": True}).encode())
        time.sleep(0.005)
    pub.undeclare()


@pytest.mark.slow
def test_a_new_context_every_few_milliseconds_makes_no_learned_key(tmp_path):
    """The flood's counts alone, no timing (the heartbeat through the flood is the serial test below)."""
    with live_daemon(tmp_path, MACHINE, ["--protocol", "1"], interlock='enabled = false\nreset = "open"') as (
            procs, daemon, sub, _log):
        wait_for(lambda: status(sub, MACHINE)["revolutions"] >= 5, 60.0, "estimates before the flood")
        _flood(sub, 12.0)
        st = status(sub, MACHINE)
        assert daemon.poll() is None, procs.text("daemon", "out")[-3000:]
        assert st["sink"]["context_taken"] >= 500, st["sink"]      # the flood reached the monitor
        assert st["processes"] >= 50, st["processes"]              # and cut it into processes
        assert st["learning"] == {"learning": 0, "pending": 0, "active": 0}, st["learning"]


@pytest.mark.serial
def test_the_heartbeat_goes_on_through_a_context_flood(tmp_path):
    """No watchdog hold: the heartbeats (every 100 ms) keep within the DAQ's 500 ms watchdog while the daemon
    takes the flood. A bound on the heartbeat's period, so serial (docs/testing.md): beside six workers at load
    ~8 a heartbeat came 0.62 s after the last one and the DAQ held the feed. The daemon then judged itself
    healthy (no `interlock.heartbeats_stopped`); the heartbeat thread was late: the flood takes about 10 % of a
    core (4 % without it), and a starved process's threads wait the longer for the GIL. Alone on the box the
    largest gap through the flood was 0.12 s. The timed part short: 4 s of flood, about 800 contexts."""
    il = 'enabled = true\nheartbeat_ms = 100\nwatchdog_ms = 500\nreset = "open"'
    with live_daemon(tmp_path, MACHINE, ["--protocol", "1"], interlock=il, watchdog_ms=500) as (procs, daemon, sub, log):
        wait_for(lambda: status(sub, MACHINE)["revolutions"] >= 5, 60.0, "estimates before the flood")
        _flood(sub, 4.0)
        st = status(sub, MACHINE)
        assert daemon.poll() is None, procs.text("daemon", "out")[-3000:]
        assert st["sink"]["context_taken"] >= 300, st["sink"]      # the flood reached the monitor
        assert st["interlock"] == "armed", st["interlock_detail"]
    assert [e for e in holds(read_jsonl(log)) if e.get("cause") == "watchdog"] == []


def test_contexts_refused_for_their_content_are_counted_refused(tmp_path):
    """An adapter integrator reads `context_taken` to see the context arrive. Before stop 28 a context the daemon
    refused for its content (a program as a string, a negative tool, a field missing) was counted taken: the counter
    rose while the daemon had no context at all (no processes, no learning); only a throttled log line said why."""
    machine = "ctxcount-01"
    with live_daemon(tmp_path, machine, ["--protocol", "1"]) as (procs, daemon, sub, log):
        wait_for(lambda: status(sub, machine)["revolutions"] >= 3, 60.0, "estimates")
        before = status(sub, machine)["sink"]
        pub = sub.session.declare_publisher(f"millsense/{machine}/context")
        wait_for(lambda: pub.matching_status.matching, 10.0, "the daemon's context subscriber")
        for ctx in ({"program": "12", "tool": 1, "operation": 1}, {"program": 1, "tool": -5, "operation": 1},
                    {"tool": 1, "operation": 1}, {"program": 1, "tool": 1, "operation": 1}):
            pub.put(json.dumps(ctx).encode())
        pub.undeclare()

        def counted() -> tuple[int, int]:
            st = status(sub, machine)["sink"]
            return st["context_taken"] - before["context_taken"], st["context_refused"] - before["context_refused"]

        wait_for(lambda: sum(counted()) == 4, 20.0, "the four contexts counted")
        assert counted() == (1, 3)
        assert daemon.poll() is None
