"""HistoryStore: a round trip, the schema's migrations, a newer file refused, the bytes a revolution costs."""

from __future__ import annotations

import math
import os
import sqlite3
from pathlib import Path

import pytest

from millsense.daemon.history import SCHEMA_VERSION, HistoryStore
from millsense.daemon.history.schema import migrate, version_of

from .helpers import T0, Events, count, estimate, process, wait_until

pytestmark = pytest.mark.quick


def _store(path: Path, events: Events | None = None, **kw) -> HistoryStore:
    events = events or Events()
    store = HistoryStore(path, machine="m1", on_error=events.on_error, on_ok=events.on_ok, **kw)
    store.start()
    return store


def test_round_trip_of_every_kind(tmp_path):
    path = tmp_path / "state" / "history.sqlite3"
    events = Events()
    store = _store(path, events)
    for i in range(50):
        store.add_revolution(estimate(i, T0 + i * 0.1, torque_nm=1.0 + i))
    nan_estimate = estimate(50, T0 + 5.0)
    nan_estimate["torque_nm"] = float("nan")  # "null where a quantity cannot be estimated"
    store.add_revolution(nan_estimate)
    store.add_process(process(1, T0 + 6.0))
    store.add_alarm({"machine": "m1", "t": T0 + 5.5, "rev": 44, "level": "envelope_high", "quantity": "torque_nm",
                     "value": 9.0, "limit": 7.5, "interlock": "feed_hold", "program": 1234, "tool": 12,
                     "operation": 3, "process": 1, "process_rev": 39})
    store.save_limits("1234/12/3", {"mean_nm": [1.0, 2.0], "state": "active"})
    assert store.flush(30)
    store.save_limits("1234/12/3", {"mean_nm": [1.5, 2.5], "state": "active"})  # an upsert, not a second row
    store.save_tools({"12": {"processes": 7, "baseline_j": 1700.0}})
    assert store.flush(30)
    store.close()
    assert events.errors == []
    assert not Path(str(path) + "-wal").exists()  # a clean close checkpoints the WAL away

    conn = sqlite3.connect(path)
    rows = conn.execute("SELECT rev, torque_nm, tool, cutting, valid FROM revolutions ORDER BY rev").fetchall()
    assert [r[0] for r in rows] == list(range(51))
    assert rows[3][1] == 4.0 and rows[3][2] == 12 and rows[3][3] == 1 and rows[3][4] == 1
    assert rows[50][1] is None
    assert conn.execute("SELECT key, verdict FROM processes").fetchall() == [("1234/12/3", "good")]
    assert conn.execute("SELECT level, tool FROM alarms").fetchall() == [("envelope_high", 12)]
    assert conn.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    conn.close()

    again = HistoryStore(path, machine="m1")
    again.start()
    assert again.load_limits() == {"1234/12/3": {"mean_nm": [1.5, 2.5], "state": "active"}}
    assert again.load_tools() == {"12": {"processes": 7, "baseline_j": 1700.0}}
    again.close()


def test_a_v1_file_is_migrated_and_keeps_its_rows(tmp_path):
    path = tmp_path / "history.sqlite3"
    conn = sqlite3.connect(path, isolation_level=None)
    conn.execute("PRAGMA journal_mode = WAL")
    migrate(conn, str(path), upto=1)
    conn.execute("INSERT INTO revolutions (t, rev, torque_nm) VALUES (?, ?, ?)", (T0, 7, 3.5))
    cols_v1 = {r[1] for r in conn.execute("PRAGMA table_info(revolutions)")}
    conn.close()
    assert "tool" not in cols_v1

    events = Events()
    store = _store(path, events)
    store.add_revolution(estimate(8, T0 + 0.1, tool=5))
    assert store.flush(30)
    store.close()
    assert events.errors == []
    conn = sqlite3.connect(path)
    assert version_of(conn) == SCHEMA_VERSION
    assert conn.execute("SELECT rev, torque_nm, tool FROM revolutions ORDER BY rev").fetchall() == [
        (7, 3.5, None), (8, 4.2, 5)]
    conn.close()


def test_a_newer_file_is_refused_untouched_and_monitoring_goes_on(tmp_path):
    path = tmp_path / "history.sqlite3"
    conn = sqlite3.connect(path, isolation_level=None)
    migrate(conn, str(path))
    conn.execute("INSERT INTO schema_version VALUES (?, 0, 'from the future')", (SCHEMA_VERSION + 1,))
    conn.close()
    before = path.read_bytes()

    events = Events()
    store = _store(path, events)
    for i in range(10):
        store.add_revolution(estimate(i, T0 + i))  # must not raise
    store.save_limits("1/2/3", {"x": 1})
    assert events.failed.wait(10)
    store.close()
    assert "newer" in events.errors[0] and f"version {SCHEMA_VERSION + 1}" in events.errors[0]
    assert path.read_bytes() == before
    assert store.stats()["dropped"] == 10


def test_revolutions_off_keeps_processes_only(tmp_path):
    path = tmp_path / "history.sqlite3"
    store = _store(path, keep_revolutions=False)
    store.add_revolution(estimate(1, T0))
    store.add_process(process(1, T0))
    assert store.flush(30)
    store.close()
    assert count(path) == 0 and count(path, "processes") == 1


def test_bytes_per_revolution(tmp_path):
    """The figure docs/history.md quotes: a revolution's share of the file, its time index included."""
    path = tmp_path / "history.sqlite3"
    store = _store(path)
    n = 0
    for chunk in range(5):
        for i in range(2000):
            store.add_revolution(estimate(n, T0 + n * 0.1))
            n += 1
        assert store.flush(60)
    assert store.stats()["dropped"] == 0
    store.close()
    empty = tmp_path / "empty.sqlite3"
    e = _store(empty)
    e.close()
    per_rev = (path.stat().st_size - empty.stat().st_size) / n
    print(f"bytes per revolution: {per_rev:.1f}")
    # the design target of docs/history.md: a day of revolutions at 10 a second within 100 MB
    assert per_rev * 10 * 86400 < 100e6


def test_writer_thread_has_its_os_name(tmp_path):
    store = _store(tmp_path / "history.sqlite3")
    try:
        def names():
            out = set()
            for task in os.listdir("/proc/self/task"):
                try:
                    out.add(Path(f"/proc/self/task/{task}/comm").read_text().strip())
                except OSError:  # a thread that ended meanwhile
                    pass
            return out

        assert wait_until(lambda: "ms-history" in names(), 10)
    finally:
        store.close()


def test_a_malformed_payload_is_one_dropped_row_never_an_exception(tmp_path):
    path = tmp_path / "history.sqlite3"
    events = Events()
    store = _store(path, events)
    store.add_revolution(None)  # type: ignore[arg-type]
    store.add_alarm(["not", "an", "alarm"])  # type: ignore[arg-type]
    store.add_revolution({"t": "yesterday", "torque_nm": "much", "rev": math.inf})  # odd values become NULL
    store.add_revolution(estimate(1, T0))
    assert store.flush(30)
    store.close()
    assert store.stats()["dropped"] == 2 and events.errors == []
    assert count(path) == 2
