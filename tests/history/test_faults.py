"""A full disk and a locked database: a clear fault, `add_*` never block, and writing resumes after."""

from __future__ import annotations

import os
import sqlite3
import subprocess

import pytest
from structlog.testing import capture_logs

from millsense.daemon.history import HistoryStore

from .helpers import T0, Events, count, estimate, wait_until


@pytest.fixture
def small_disk(tmp_path):
    """A 2 MB tmpfs of its own: a real ENOSPC, so SQLite says SQLITE_FULL. Needs root (mount)."""
    mnt = tmp_path / "disk"
    mnt.mkdir()
    result = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=2m", "tmpfs", str(mnt)],
                            capture_output=True, text=True)
    if result.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({result.stderr.strip() or result.returncode})")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", "-l", str(mnt)], check=False)


def _fill(directory, leave_bytes: int):
    """A file that takes all but `leave_bytes` of the disk."""
    st = os.statvfs(directory)
    free = st.f_bavail * st.f_frsize
    filler = directory / "filler"
    with open(filler, "wb") as f:
        f.write(b"\0" * max(0, free - leave_bytes))
    return filler


def test_disk_full_is_a_clear_fault_and_writing_resumes(small_disk):
    path = small_disk / "history.sqlite3"
    events = Events()
    store = HistoryStore(path, machine="m1", on_error=events.on_error, on_ok=events.on_ok)
    store.start()
    store.add_revolution(estimate(0, T0))
    assert store.flush(30)
    filler = _fill(small_disk, leave_bytes=64 * 1024)
    try:
        rev = 1
        while not events.failed.is_set() and rev < 200_000:
            for _ in range(200):  # never blocks: a full disk costs rows, counted, not the caller's time
                store.add_revolution(estimate(rev, T0 + rev * 0.1))
                rev += 1
            events.failed.wait(0.01)
        assert events.failed.is_set(), "the disk never filled"
        assert len(events.errors) == 1
        reason = events.errors[0]
        assert "the disk is full" in reason and "SQLITE_FULL" in reason and str(path) in reason
        assert "monitoring goes on" in reason
        store.save_limits("1234/12/3", {"state": "active"})  # learned limits wait for space, not dropped
        for _ in range(50):
            store.add_revolution(estimate(rev, T0 + rev * 0.1))
            rev += 1
        assert wait_until(lambda: store.stats()["dropped"] > 0, 30)
        assert store.stats()["fault"] is True
    finally:
        filler.unlink()
    for i in range(20):  # space again: the next commit works and says so, once
        store.add_revolution(estimate(rev + i, T0 + (rev + i) * 0.1))
    assert events.recovered.wait(30)
    assert store.flush(30)
    store.close()
    assert events.oks == 1 and len(events.errors) == 1
    assert count(path, "limits") == 1
    assert store.stats()["fault"] is False


def test_locked_database_is_a_clear_fault_and_add_never_blocks(tmp_path):
    path = tmp_path / "history.sqlite3"
    events = Events()
    store = HistoryStore(path, machine="m1", on_error=events.on_error, on_ok=events.on_ok)
    store.start()
    store.add_revolution(estimate(0, T0))
    assert store.flush(30)

    other = sqlite3.connect(path, isolation_level=None, timeout=0)
    other.execute("BEGIN EXCLUSIVE")  # another program holding the write lock
    try:
        store.add_revolution(estimate(1, T0 + 0.1))
        assert events.failed.wait(30)
        reason = events.errors[0]
        assert "locked" in reason and "SQLITE_BUSY" in reason and str(path) in reason
        # the writer is stuck in its busy wait: adding 3× the queue returns, refusing what does not fit
        for i in range(3 * 4096):
            store.add_revolution(estimate(2 + i, T0 + 0.2 + i * 0.1))
        assert store.stats()["dropped_queue_full"] > 0, "add_revolution waited for room instead of dropping"
        assert not events.recovered.is_set()
    finally:
        other.execute("COMMIT")
        other.close()
    store.add_revolution(estimate(99_999, T0 + 9999.0))
    assert events.recovered.wait(30)
    assert store.flush(60)
    store.close()
    assert len(events.errors) == 1 and events.oks == 1
    assert count(path) == store.stats()["written"]["revolutions"]  # what was not dropped is there


def _made_and_locked(path) -> sqlite3.Connection:
    """A history file made by a store, then held under another connection's write lock (COMMIT releases it)."""
    first = HistoryStore(path, machine="m1")
    first.start()
    first.close()
    other = sqlite3.connect(path, isolation_level=None, timeout=0)
    other.execute("BEGIN EXCLUSIVE")
    return other


def test_locked_at_start_is_a_fault_the_runner_hears_and_the_writer_retries(tmp_path):
    """The daemon builds the store, starts it, and only then hands it the runner's callbacks."""
    path = tmp_path / "history.sqlite3"
    other = _made_and_locked(path)
    try:
        store = HistoryStore(path, machine="m1")
        store.start()  # returns: a fault, never an exception
        assert store.stats()["open"] is False
        events = Events()
        store.on_error = events.on_error  # as the runner does, after start
        store.on_ok = events.on_ok
        assert events.failed.is_set() and "locked" in events.errors[0]
        store.add_revolution(estimate(1, T0))  # dropped, counted
        assert wait_until(lambda: store.stats()["dropped"] == 1, 30)
    finally:
        other.execute("COMMIT")
        other.close()
    assert events.recovered.wait(30)  # reopened by the writer (it tries every few seconds)
    store.add_revolution(estimate(2, T0 + 1))
    assert store.flush(30)
    store.close()
    assert count(path) == 1 and len(events.errors) == 1


def test_a_callback_that_raises_is_logged_and_never_stops_the_store(tmp_path):
    """The runner's fault callback failing (`guarded.call_quietly`): logged, and the store goes on writing."""
    path = tmp_path / "history.sqlite3"
    other = _made_and_locked(path)
    heard: list[str] = []

    def boom(reason: str) -> None:
        heard.append(reason)
        raise RuntimeError("the fault board is gone")

    try:
        store = HistoryStore(path, machine="m1")
        store.start()
        with capture_logs() as logs:
            store.on_error = boom  # hears the fault under way at once, and raises: the setter returns
        assert heard and "locked" in heard[0]
        assert [e for e in logs if e["event"] == "history.callback_failed"] == [
            {"event": "history.callback_failed", "log_level": "error",
             "error": "RuntimeError: the fault board is gone"}]
        events = Events()
        store.on_ok = events.on_ok
    finally:
        other.execute("COMMIT")
        other.close()
    assert events.recovered.wait(30)  # the writer reopened the file despite the callback that raised
    store.add_revolution(estimate(1, T0))
    assert store.flush(30)
    store.close()
    assert count(path) == 1
