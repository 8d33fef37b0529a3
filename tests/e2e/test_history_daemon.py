"""The daemon with a damaged or locked history database: a clear fault, and monitoring goes on.

tests/history/ proves the store itself (SIGKILL, torn copies, a full disk, a
lock); this proves the daemon around it: a `millsense run` whose history file
is garbage starts, moves the file aside and keeps publishing; one whose
database another process holds locked raises the fault `history` (degraded,
named in status), keeps publishing estimates, and recovers when the lock goes.
"""

from __future__ import annotations

import os
import sqlite3
from pathlib import Path

from tests.conftest import free_tcp_port
from tests.e2e.helpers import Procs, Subscriber, tcp, wait_for, write_config

SLOW_S = 60.0


def _state(machine: str) -> Path:
    return Path(os.environ["XDG_STATE_HOME"]) / "millsense" / machine


def _revolutions_written(status: dict) -> int:
    """Revolutions the daemon's history has committed, from its status (`written` counts per table)."""
    return int(((status.get("history") or {}).get("written") or {}).get("revolutions", 0))


def _start(procs, tmp_path, machine):
    z_port = free_tcp_port()
    cfg = write_config(tmp_path / "d.toml", machine=machine, daq='transport = "sim"\nscenario = "step"',
                       zenoh_listen=[tcp(z_port)])
    daemon = procs.start("daemon", ["run", "--config", str(cfg)])
    return daemon, Subscriber([tcp(z_port)], machine)


def test_a_garbage_history_file_is_moved_aside_and_monitoring_goes_on(tmp_path):
    machine = "hist-garbage"
    state = _state(machine)
    state.mkdir(parents=True)
    (state / "history.sqlite3").write_bytes(b"this is not a database, a torn copy left by a power cut\n" * 64)
    with Procs(tmp_path) as procs:
        daemon, sub = _start(procs, tmp_path, machine)
        try:
            wait_for(lambda: len(sub.get("estimate")) >= 5, SLOW_S, "estimates flowing")
            status = wait_for(lambda: [s for s in sub.get("status") if _revolutions_written(s) > 0],
                              SLOW_S, "revolutions committed to the history")[-1]
            assert status["history"]["open"] and "history" not in status["faults"]
        finally:
            sub.close()
    moved = [p.name for p in state.iterdir() if p.name.startswith("history.sqlite3.corrupt-")]
    assert moved, sorted(p.name for p in state.iterdir())
    with sqlite3.connect(state / "history.sqlite3") as conn:
        assert conn.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
        assert conn.execute("SELECT count(*) FROM revolutions").fetchone()[0] > 0


def test_a_locked_history_is_a_fault_named_in_status_and_monitoring_goes_on(tmp_path):
    machine = "hist-locked"
    state = _state(machine)
    state.mkdir(parents=True)
    from millsense.daemon.history.store import HistoryStore

    store = HistoryStore(state / "history.sqlite3", machine=machine)  # a database of an earlier run
    store.start()
    store.close()
    lock = sqlite3.connect(state / "history.sqlite3", timeout=0.1, isolation_level=None)
    lock.execute("BEGIN EXCLUSIVE")  # another process (an export tool, a backup) holds it
    with Procs(tmp_path) as procs:
        daemon, sub = _start(procs, tmp_path, machine)
        try:
            faulted = wait_for(lambda: [s for s in sub.get("status") if "history" in s.get("faults", {})],
                               SLOW_S, "fault history in status")[-1]
            assert faulted["state"] == "degraded" and "lock" in faulted["faults"]["history"].lower()
            n = len(sub.get("estimate"))
            wait_for(lambda: len(sub.get("estimate")) >= n + 5, SLOW_S, "estimates while the history is locked")
            lock.execute("ROLLBACK")
            lock.close()
            wait_for(lambda: [s for s in sub.get("status")[-2:] if "history" not in s.get("faults", {})
                              and _revolutions_written(s) > 0], SLOW_S, "the fault recovered")
        finally:
            sub.close()
            if lock is not None:
                try:
                    lock.close()
                except sqlite3.Error:
                    pass
