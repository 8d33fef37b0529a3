"""A power cut's kin: SIGKILL during writes, torn copies of the files, a damaged file.

Each is followed by `PRAGMA integrity_check` and a restart that keeps writing.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from millsense.daemon.history import HistoryStore

from .helpers import T0, Events, count, estimate, integrity, wait_until

pytestmark = pytest.mark.quick

WRITER = Path(__file__).with_name("writer.py")
FRAME_BYTES = 24 + 4096  # a WAL frame: its header and one page (the default page size)


def _sidecars(path: Path) -> list[Path]:
    return [path.with_name(path.name + s) for s in ("", "-wal", "-shm")]


@pytest.fixture
def killed_writer(tmp_path):
    """A real process writing at full speed, killed with SIGKILL mid-stream; (path, rows seen before the kill)."""
    path = tmp_path / "history.sqlite3"
    proc = subprocess.Popen([sys.executable, str(WRITER), str(path)], stdout=subprocess.PIPE, text=True)
    try:
        lines = iter(proc.stdout.readline, "")  # log lines may come first
        assert any(line.strip() == "limits saved" for line in lines), "the writer died before saving limits"
        assert wait_until(lambda: path.exists() and count(path) >= 3000, 60), "the writer never committed"
        seen = count(path)
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
        proc.stdout.close()
    assert proc.returncode == -signal.SIGKILL
    return path, seen


def _restart_keeps_writing(path: Path) -> HistoryStore:
    """Start a store on the file as a daemon would after the event: it keeps every row a reader saw
    (a read-only reader neither checkpoints nor removes the WAL) unless it moved the file aside, and writes."""
    before = count(path) if integrity_of_copy(path) == "ok" else 0
    events = Events()
    store = HistoryStore(path, machine="m1", on_error=events.on_error)
    store.start()
    if store.moved_aside:
        before = 0
    for i in range(100):
        store.add_revolution(estimate(i, T0 + i))
    assert store.flush(30)
    assert count(path) == before + 100
    store.close()
    assert events.errors == []
    assert integrity(path) == "ok"
    return store


def integrity_of_copy(path: Path) -> str:
    """integrity_check on a copy of the three files: checking the file itself would checkpoint its WAL
    on close, and the restart that follows would no longer meet the state the event left."""
    check = path.parent / "integrity-check" / path.name
    check.parent.mkdir(exist_ok=True)
    for src, dst in zip(_sidecars(path), _sidecars(check)):
        if src.exists():
            shutil.copyfile(src, dst)
        elif dst.exists():
            dst.unlink()
    try:
        return integrity(check)
    finally:
        shutil.rmtree(check.parent)


def test_sigkill_during_writes_loses_no_committed_row(killed_writer):
    path, seen = killed_writer
    assert Path(str(path) + "-wal").exists(), "the kill left no WAL: nothing was in flight"
    assert integrity_of_copy(path) == "ok"
    assert count(path) >= seen  # every commit seen before the kill is still there
    store = _restart_keeps_writing(path)
    assert store.moved_aside == []
    again = HistoryStore(path, machine="m1")
    assert again.load_limits() == {"1234/12/3": {"state": "active", "mean_nm": [1.0, 2.0, 3.0]}}


def test_wal_truncated_mid_frame(killed_writer, tmp_path):
    path, _ = killed_writer
    wal = Path(str(path) + "-wal")
    frames = (wal.stat().st_size - 32) // FRAME_BYTES
    assert frames >= 2, "the kill left too little WAL to tear"
    copy = tmp_path / "torn" / "history.sqlite3"
    copy.parent.mkdir()
    shutil.copyfile(path, copy)
    torn_at = 32 + (frames - 1) * FRAME_BYTES + FRAME_BYTES // 2  # the last frame cut in half
    with open(wal, "rb") as src, open(str(copy) + "-wal", "wb") as dst:
        dst.write(src.read(torn_at))
    assert integrity_of_copy(copy) == "ok"
    assert count(copy) <= count(path)  # the torn transaction is dropped, never half-applied
    store = _restart_keeps_writing(copy)
    assert store.moved_aside == []


def test_files_copied_while_a_writer_commits(tmp_path):
    """A backup taken file by file under a live daemon: each copy restarts, kept or moved aside, and writes."""
    path = tmp_path / "live" / "history.sqlite3"
    store = HistoryStore(path, machine="m1")
    store.start()
    stop = threading.Event()

    def feed():
        rev = 0
        while not stop.is_set():
            for _ in range(100):
                store.add_revolution(estimate(rev, T0 + rev * 0.1))
                rev += 1
            stop.wait(0.005)

    feeder = threading.Thread(target=feed, daemon=True)
    feeder.start()
    copies = []
    try:
        assert wait_until(lambda: path.exists() and count(path) > 1000, 60)
        for k in range(8):
            copy = tmp_path / f"copy{k}" / "history.sqlite3"
            copy.parent.mkdir()
            for src, dst in zip(_sidecars(path), _sidecars(copy)):
                if src.exists():
                    shutil.copyfile(src, dst)
            copies.append(copy)
            before = count(path)
            assert wait_until(lambda: count(path) > before, 30)  # the next copy sees other commits
    finally:
        stop.set()
        feeder.join(10)
        store.close()
    for copy in copies:
        restarted = _restart_keeps_writing(copy)
        for aside in restarted.moved_aside:
            assert Path(aside).exists()


def test_damaged_file_is_moved_aside_and_a_new_one_started(tmp_path):
    path = tmp_path / "history.sqlite3"
    store = HistoryStore(path, machine="m1")
    store.start()
    for i in range(3000):
        store.add_revolution(estimate(i, T0 + i))
    assert store.flush(30)
    store.close()
    with open(path, "r+b") as f:  # pages 3 … 6 overwritten: the tables' b-trees no longer hold together
        f.seek(2 * 4096)
        f.write(os.urandom(4 * 4096))
    assert integrity(path) != "ok"

    restarted = _restart_keeps_writing(path)
    assert len(restarted.moved_aside) == 1
    aside = Path(restarted.moved_aside[0])
    assert aside.exists() and aside.name.startswith("history.sqlite3.corrupt-")
    assert count(path) == 100  # a new file: only what was written after the restart


def test_not_a_database_is_moved_aside(tmp_path):
    path = tmp_path / "history.sqlite3"
    path.write_bytes(b"this is not a database, whatever its name says\n" * 200)
    restarted = _restart_keeps_writing(path)
    assert len(restarted.moved_aside) == 1
    assert count(path) == 100
