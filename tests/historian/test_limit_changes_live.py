"""An operator's limits change, live: a real daemon (program 1001 on the in-process emulator, its operations'
expected bands from `[operations]`), an authorised `millsense limits widen` over Zenoh with the reset token and a
`limits low-off` at the machine (the control socket), a real `millsense historian` and the test's PostgreSQL.

Each applied change is one `limit_changes` row with its action, the bounds before and after, the requester exactly
as the daemon's audit log records it and the authority; a refused change (a wrong token) is no row."""

from __future__ import annotations

import json
import os
import signal
import subprocess

import pytest

from tests.conftest import free_tcp_port
from tests.e2e.helpers import CMD, Procs, tcp, wait_for
from tests.historian.live import historian_config, p1001_daemon
from tests.historian.test_live import has_event, rows

pytestmark = pytest.mark.slow

SLOW_S = 60.0   # detects a hang; no budget
MACHINE = "hist-limits"
KEY = "1001/11/10"
TOKEN = "hist-limits-token-of-at-least-32-characters-0123"


def _limits(args: list[str], env: dict[str, str]) -> subprocess.CompletedProcess:
    return subprocess.run(CMD + ["limits", *args], capture_output=True, text=True, timeout=SLOW_S,
                          env=dict(os.environ, **env))


def test_an_authorised_widen_and_a_local_low_off_are_rows_with_the_requester_and_the_bounds(pg_db, tmp_path):
    server, db, passfile = pg_db
    z_port = free_tcp_port()
    cfg = p1001_daemon(tmp_path / "d.toml", MACHINE, zenoh={"listen": [tcp(z_port)]}, operations=True,
                       interlock={"enabled": True, "heartbeat_ms": 50, "watchdog_ms": 1000, "reset": "token",
                                  "reset_token": TOKEN})
    hist = historian_config(tmp_path / "historian.toml", server, db, passfile, connect=[tcp(z_port)])
    (tmp_path / "token").write_text(TOKEN + "\n")
    (tmp_path / "wrong").write_text("w" * 48 + "\n")
    state = tmp_path / "state"
    env = {"STATE_DIRECTORY": str(state)}
    where = ["--machine", MACHINE, "--connect", tcp(z_port), "--no-scouting", "--timeout", "10"]
    with Procs(tmp_path) as procs:
        daemon = procs.start("daemon", ["run", "--config", str(cfg)], env_extra=env)
        historian = procs.start("historian", ["historian", "--config", str(hist)])
        wait_for(lambda: has_event(procs, "historian.subscribed"), SLOW_S, "the historian subscribed")
        # the historian hears the daemon: its first status change is written
        wait_for(lambda: rows(server, db, "SELECT count(*) FROM status_changes WHERE machine = %s",
                              (MACHINE,))[0][0], SLOW_S, "the daemon's status in PostgreSQL")

        p = _limits(["widen", KEY, "--pct", "10", "--token-file", str(tmp_path / "wrong"), *where], env)
        assert p.returncode == 3, p.stderr   # refused by the daemon: nothing changed, nothing published
        p = _limits(["widen", KEY, "--pct", "10", "--json", "--token-file", str(tmp_path / "token"), *where], env)
        assert p.returncode == 0, p.stdout + p.stderr
        assert json.loads(p.stdout)["ok"] is True
        p = _limits(["low-off", KEY, "--local", "--config", str(cfg), "--json"], env)
        assert p.returncode == 0, p.stdout + p.stderr

        query = ("SELECT action, change, pct, requester, authority, before, after, envelope, payload->>'machine' "
                 "FROM limit_changes WHERE machine = %s AND action IS NOT NULL ORDER BY time")
        got = wait_for(lambda: (lambda r: r if len(r) == 2 else None)(rows(server, db, query, (MACHINE,))),
                       SLOW_S, "both changes in PostgreSQL")
        daemon.send_signal(signal.SIGTERM)
        assert daemon.wait(SLOW_S) == 0, procs.text("daemon")[-3000:]
        historian.send_signal(signal.SIGTERM)
        assert historian.wait(SLOW_S) == 0, procs.text("historian")[-3000:]

    audit = [json.loads(line) for line in (state / "audit.log").read_text().splitlines()]
    granted = [a for a in audit if a["command"] == "limits" and a["granted"]]
    assert [a["result"]["action"] for a in granted] == ["widen", "low_off"], audit
    (widen, widen_change, pct, requester, authority, before, after, envelope, machine), low_off = got
    assert (widen, widen_change, pct, authority, machine) == ("widen", "widen", 10.0, "token", MACHINE)
    assert requester == granted[0]["requester"] and requester.startswith("zid:"), (requester, granted[0])
    # an operation's expected band widened before anything was learned: the key did not exist before it
    assert before is None, before
    assert after["state"] == "learning" and after["widening"] is None and after["low_check"] is True
    assert after["expected_widening"] == {"high": pytest.approx(1.1), "low": pytest.approx(1.1)}, after
    assert envelope == "learning"

    action, change, pct, requester, authority, before, after, *_ = low_off
    assert (action, change, pct, authority) == ("low_off", "low_off", None, "local")
    assert requester == granted[1]["requester"] and requester.startswith("local uid="), (requester, granted[1])
    assert before["low_check"] is True and after["low_check"] is False
    assert before["expected_widening"] == after["expected_widening"]   # low-off widens nothing
    # one row per change: the refused widen is none, and nothing was inferred beside them
    assert rows(server, db, "SELECT count(*) FROM limit_changes WHERE machine = %s", (MACHINE,))[0][0] == 2
