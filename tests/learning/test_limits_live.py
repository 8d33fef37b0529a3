"""Issue 36 on a real daemon: a widen storm and non-finite stored rows never stop `millsense run`.

Finding 1: about 400 `millsense limits widen KEY --pct 500` overflowed the band to inf, stored as JSON null;
afterwards `millsense run` exited 1 at every start (`float(None)` in the envelope's restore), and with no daemon
neither `relearn` nor a reset was reachable.

Here the history database a daemon starts on holds (a) a key that took 1 000 widen commands through the one
argument check and the monitor's dispatch (what `cmd/limits`, `millsense limits` and the local socket all call),
saved by the real `HistoryStore`, and (b) two rows written with sqlite3 directly: the null the overflow left, and an
`Infinity`. The real daemon (`millsense run`, the in-process simulated DAQ's step scenario) must run, show (b) as
set aside in `status`, `limits list` and `limits show`, refuse a further widen through the real CLI with the cap,
take `limits low-off` (audited), trip on an overload above the fixed limit, and start again.
"""

from __future__ import annotations

import json
import math
import signal
import sqlite3

import numpy as np
import pytest
from types import SimpleNamespace

from millsense.daemon.history.store import HistoryStore
from millsense.daemon.learning.monitor import ProcessMonitor
from millsense.daemon.publish.limits_args import check_args
from tests.conftest import free_tcp_port
from tests.e2e.helpers import Procs, Subscriber, tcp, wait_for, write_config
from tests.e2e.test_limits_cli import _audit, _cli
from tests.learning.synth import Shop, ctx, learning

TOKEN = "limits-token-of-at-least-32-characters-0123456789"
SLOW_S = 60.0                 # detects a hang; no budget
TORQUE_LIMIT_NM = 3.0         # between the step scenario's 2 and 4 N·m plateaus: the second one overloads
STORMED, NULLED, INFINITE = "4321/7/2", "4321/7/3", "4321/7/4"


def _stormed_rows() -> dict[str, dict]:
    """A learned key after 1 000 widens, and the good row the two bad ones are made from."""
    m = ProcessMonitor(learning(), alarms=SimpleNamespace(torque_limit_nm=TORQUE_LIMIT_NM, force_limit_n=None))
    s = Shop(m, rng=np.random.default_rng(4), noise_pct=2.0)
    for operation in (2, 3, 4):
        s.learn(5, context=ctx(program=4321, tool=7, operation=operation), scale=0.35)
    for pct in (500, 100, 50, 10, 1) * 200:
        m.command(check_args({"action": "widen", "key": STORMED, "pct": pct}))
    return {k: m.export_limits(k) for k in m.keys}


def _numbers(value) -> list[float]:
    if isinstance(value, bool) or value is None or isinstance(value, str):
        return []
    if isinstance(value, (int, float)):
        return [float(value)]
    items = value.values() if isinstance(value, dict) else value
    return [n for v in items for n in _numbers(v)]


def _seed(db, rows: dict[str, dict]) -> None:
    store = HistoryStore(db, machine="lim-storm")
    store.start()
    store.save_limits(STORMED, rows[STORMED])
    assert store.flush(SLOW_S)
    store.close()
    nulled = json.loads(json.dumps(rows[NULLED]))
    nulled["envelope"]["entry"]["margin"] = None          # what the overflow left: inf through strict JSON
    nulled["envelope"]["energy"]["h_j"] = None
    infinite = json.loads(json.dumps(rows[INFINITE]))
    infinite["envelope"]["torque"]["h_high"][5] = math.inf
    with sqlite3.connect(db) as conn:
        conn.executemany("INSERT INTO limits (key, t, payload) VALUES (?, 0, ?)",
                         [(NULLED, json.dumps(nulled, allow_nan=False)), (INFINITE, json.dumps(infinite))])


@pytest.mark.slow
def test_a_widen_storm_and_non_finite_rows_leave_a_daemon_that_runs_trips_and_restarts(tmp_path):
    rows = _stormed_rows()
    assert all(math.isfinite(v) for v in _numbers(rows[STORMED]))
    state = tmp_path / "state"
    state.mkdir()
    _seed(state / "history.sqlite3", rows)
    machine = "lim-storm"
    z_port = free_tcp_port()
    cfg = write_config(
        tmp_path / "d.toml", machine=machine, daq='transport = "sim"\nscenario = "step"',
        zenoh_listen=[tcp(z_port)], alarms=f"torque_limit_nm = {TORQUE_LIMIT_NM}\nrevolutions = 2",
        interlock=f'enabled = true\nreset = "token"\nreset_token = "{TOKEN}"',
        extra='\n[context]\nsource = "zenoh"\n',
    )
    token_file = tmp_path / "token"
    token_file.write_text(TOKEN + "\n")
    env = {"STATE_DIRECTORY": str(state)}
    where = ["--machine", machine, "--connect", tcp(z_port), "--no-scouting", "--timeout", "10"]
    aside_keys = {NULLED, INFINITE}
    with Procs(tmp_path) as procs:
        daemon = procs.start("daemon", ["run", "--config", str(cfg)], env_extra=env)
        sub = Subscriber([tcp(z_port)], machine)
        try:
            wait_for(lambda: sub.get("estimate") or daemon.poll() is not None, SLOW_S, "estimates")
            assert daemon.poll() is None, procs.text("daemon")[-3000:]
            status = wait_for(lambda: [s for s in sub.get("status") if "learned_limits" in s], SLOW_S,
                              "status with learned_limits")[-1]
            aside = {a["key"]: a["reason"] for a in status["learned_limits"]["set_aside"]}
            assert set(aside) == aside_keys and status["learned_limits"]["low_off"] == [], status["learned_limits"]
            assert aside[NULLED] == "envelope.entry.margin: not a number (missing)"
            assert aside[INFINITE].startswith("not JSON: Infinity is not a JSON number")
            # said once in the log, each key
            logged = [json.loads(x) for x in procs.text("daemon", "out").splitlines() + procs.text("daemon").splitlines()
                      if x.startswith("{") and '"learning.set_aside"' in x]
            assert sorted(e["key"] for e in logged) == sorted(aside_keys), logged

            # `limits list` and `show`: the stormed key active, finite, under the fixed limit; the others learning
            p = _cli(["list", "--json", *where], env)
            assert p.returncode == 0, p.stderr
            listed = {e["key"]: e for e in json.loads(p.stdout)["limits"]}
            assert listed[STORMED]["state"] == "active" and 1.0 < listed[STORMED]["widening"] <= 4.0 + 1e-9
            for key in aside_keys:
                assert listed[key]["state"] == "learning" and listed[key]["set_aside"] == aside[key]
            p = _cli(["list", *where], env)
            assert p.returncode == 0 and p.stdout.count("! stored limits set aside") == 2, p.stdout
            p = _cli(["show", STORMED, "--json", *where], env)
            shown = json.loads(p.stdout)
            assert p.returncode == 0 and all(math.isfinite(v) for v in _numbers(shown)), p.stdout
            assert max(h for h in shown["torque_high_nm"] if h is not None) <= TORQUE_LIMIT_NM + 1e-4
            p = _cli(["show", NULLED, *where], env)
            assert p.returncode == 0 and "! stored limits set aside (envelope.entry.margin" in p.stdout, p.stdout

            # the real CLI: one more widen is refused with the cap; low-off is its own audited command
            p = _cli(["widen", STORMED, "--pct", "10", "--token-file", str(token_file), *where], env)
            assert p.returncode == 1 and "capped at 4× the learned width since the last relearn" in p.stderr, p.stderr
            p = _cli(["low-off", STORMED, "--json", "--token-file", str(token_file), *where], env)
            assert p.returncode == 0 and json.loads(p.stdout)["low_check"] is False, p.stdout + p.stderr
            granted = [a for a in _audit(state) if a["command"] == "limits" and a["granted"]]
            assert [a["result"]["action"] for a in granted] == ["widen", "low_off"], granted
            wait_for(lambda: [s for s in sub.get("status")
                              if (s.get("learned_limits") or {}).get("low_off") == [STORMED]], SLOW_S,
                     "low_off in status")

            # the fixed limit still trips: the second plateau is over it
            alarm = wait_for(lambda: [a for a in sub.get("alarm") if a["level"] == "overload"], SLOW_S,
                             "overload above the fixed limit")[0]
            assert alarm["interlock"] == "feed_hold" and alarm["value"] > TORQUE_LIMIT_NM, alarm
        finally:
            sub.close()
            daemon.send_signal(signal.SIGTERM)
            daemon.wait(SLOW_S)
        assert daemon.returncode == 0, procs.text("daemon")[-3000:]

        # it starts again on what it saved: the set-aside keys still shown, low-off kept
        daemon = procs.start("daemon2", ["run", "--config", str(cfg)], env_extra=env)
        sub = Subscriber([tcp(z_port)], machine)
        try:
            status = wait_for(lambda: [s for s in sub.get("status") if "learned_limits" in s]
                              or daemon.poll() is not None, SLOW_S, "status after the restart")
            assert daemon.poll() is None, procs.text("daemon2")[-3000:]
            learned = status[-1]["learned_limits"]
            assert {a["key"] for a in learned["set_aside"]} == aside_keys and learned["low_off"] == [STORMED]
            wait_for(lambda: sub.get("estimate"), SLOW_S, "estimates after the restart")
        finally:
            sub.close()
            daemon.send_signal(signal.SIGTERM)
            daemon.wait(SLOW_S)
        assert daemon.returncode == 0, procs.text("daemon2")[-3000:]
