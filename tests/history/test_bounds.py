"""Retention by days and the size cap, with a clock the test moves: the file stops growing."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import pytest

from millsense.daemon.history import HistoryStore
from millsense.daemon.history.bounds import CAP_LOW_WATER
from millsense.daemon.history.store import MAINTENANCE_S, OTHER_RETENTION_FACTOR

from .helpers import T0, Events, count, estimate, process

pytestmark = pytest.mark.quick

DAY = 86400.0


class Clock:
    def __init__(self, t: float):
        self.t = t

    def __call__(self) -> float:
        return self.t


def _min_t(path: Path, table: str) -> float:
    conn = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
    try:
        return conn.execute(f"SELECT MIN(t) FROM {table}").fetchone()[0]
    finally:
        conn.close()


def _checkpoint(path: Path) -> None:
    conn = sqlite3.connect(path, timeout=10)
    try:
        conn.execute("PRAGMA wal_checkpoint(PASSIVE)").fetchall()
    finally:
        conn.close()


def test_retention_deletes_old_revolutions_and_keeps_processes_longer(tmp_path):
    path = tmp_path / "history.sqlite3"
    clock = Clock(T0)
    events = Events()
    store = HistoryStore(path, machine="m1", retention_days=2, clock=clock, on_error=events.on_error)
    store.start()
    # one revolution an hour over 10 days, one process a day over 15 days
    for h in range(10 * 24):
        store.add_revolution(estimate(h, T0 - 10 * DAY + h * 3600.0))
    for d in range(15):
        store.add_process(process(d, T0 - 15 * DAY + d * DAY + 1.0))
    assert store.flush(30)

    clock.t = T0 + MAINTENANCE_S  # a round of retention surely after every row is in
    assert store.flush(30)
    assert _min_t(path, "revolutions") >= T0 + MAINTENANCE_S - 2 * DAY
    assert count(path) == 48 - 1  # the hours of the last 2 days, less the one that aged by the minute
    # processes are kept OTHER_RETENTION_FACTOR × longer: all 15 days of them (2 days × 10 = 20)
    assert count(path, "processes") == 15

    clock.t = T0 + 12 * DAY  # now processes older than 20 days (2 days × 10) go too
    assert store.flush(30)
    assert count(path) == 0
    assert count(path, "processes") == 8
    assert _min_t(path, "processes") >= clock.t - OTHER_RETENTION_FACTOR * 2 * DAY
    store.close()
    assert events.errors == []
    assert store.stats()["deleted"]["retention"] == 240 + 7


def test_size_cap_deletes_oldest_revolutions_first_and_the_file_stops_growing(tmp_path):
    path = tmp_path / "history.sqlite3"
    max_mb = 0.5
    events = Events()
    store = HistoryStore(path, machine="m1", max_mb=max_mb, on_error=events.on_error)
    store.start()
    for d in range(5):
        store.add_process(process(d, T0 + d))
    store.save_limits("1234/12/3", {"state": "active"})
    sizes = []
    n = 0
    for chunk in range(16):  # 32 000 revolutions: about 3 MB uncapped, six times the cap
        for _ in range(2000):
            store.add_revolution(estimate(n, T0 + 10 + n * 0.1))
            n += 1
        assert store.flush(60)
        _checkpoint(path)  # what the WAL holds into the file, as SQLite's auto-checkpoint does every 1000 pages
        sizes.append(path.stat().st_size)
    assert store.stats()["dropped"] == 0
    store.close()
    assert events.errors == []

    print("file sizes by chunk:", sizes)
    cap = max_mb * 1e6
    late = sizes[len(sizes) // 2:]
    assert max(late) == min(late), "the file kept growing once at the cap"
    # above the cap by at most a batch (500 rows) between two rounds of the writer
    assert max(sizes) <= cap + 500 * 200
    assert max(sizes) > cap * 0.9, "the cap was not reached: the test proves nothing"
    kept = count(path)
    assert 0 < kept < n
    conn = sqlite3.connect(path)
    revs = [r[0] for r in conn.execute("SELECT rev FROM revolutions ORDER BY rev")]
    assert revs == list(range(n - kept, n)), "the oldest revolutions go first"
    conn.close()
    assert count(path, "processes") == 5 and count(path, "limits") == 1


def test_a_file_above_a_lowered_cap_is_shrunk(tmp_path):
    path = tmp_path / "history.sqlite3"
    store = HistoryStore(path, machine="m1", max_mb=50)
    store.start()
    for n in range(20000):
        store.add_revolution(estimate(n, T0 + n * 0.1))
        if n % 2000 == 1999:
            assert store.flush(60)
    store.close()
    big = path.stat().st_size
    assert big > 1.5e6

    store = HistoryStore(path, machine="m1", max_mb=0.5)  # the operator lowers [history] max_mb
    store.start()
    assert store.flush(60)
    store.close()
    assert path.stat().st_size <= 0.5e6 * (2 - CAP_LOW_WATER)
    assert 0 < count(path) < 20000
