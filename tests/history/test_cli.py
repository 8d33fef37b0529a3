"""`millsense history` as a real subprocess: CSV and JSON lines, filtered by tool, operation and time."""

from __future__ import annotations

import csv
import io
import json
import subprocess
from datetime import datetime, timezone

import pytest

from millsense.daemon.history import HistoryStore

from .helpers import T0, estimate, process


def _iso(t: float) -> str:
    return datetime.fromtimestamp(t, tz=timezone.utc).isoformat().replace("+00:00", "Z")


@pytest.fixture
def state(tmp_path, monkeypatch):
    """A daemon's state directory holding a history: tools 12 and 7 alternating, 100 s each, and a config."""
    directory = tmp_path / "state"
    monkeypatch.setenv("STATE_DIRECTORY", str(directory))
    store = HistoryStore(directory / "history.sqlite3", machine="m1")
    store.start()
    for i in range(400):
        tool = 12 if (i // 100) % 2 == 0 else 7
        store.add_revolution(estimate(i, T0 + i, tool=tool, operation=3 if tool == 12 else 4))
    store.add_process(process(1, T0 + 100, tool=12))
    store.add_process(process(2, T0 + 200, tool=7))
    store.add_process(process(3, T0 + 300, tool=12, verdict="envelope_high"))
    store.save_limits("1234/12/3", {"state": "active"})
    store.save_limits("1234/7/4", {"state": "learning"})
    assert store.flush(30)
    store.close()
    config = tmp_path / "mill.toml"
    config.write_text('machine = "m1"\n[history]\nretention_days = 10\n')
    return config


def _run(millsense_cmd, *args, **kw):
    return subprocess.run([*millsense_cmd, "history", *args], capture_output=True, text=True, timeout=60, **kw)


@pytest.mark.quick
def test_csv_by_tool_and_time(millsense_cmd, state):
    r = _run(millsense_cmd, "--config", str(state), "--tool", "12", "--from", _iso(T0 + 50), "--to", str(T0 + 250))
    assert r.returncode == 0, r.stderr
    rows = list(csv.DictReader(io.StringIO(r.stdout)))
    # tool 12 ran 0–99 and 200–299: in [50, 250) that is 50–99 and 200–249
    assert [int(row["rev"]) for row in rows] == list(range(50, 100)) + list(range(200, 250))
    assert {row["tool"] for row in rows} == {"12"} and {row["machine"] for row in rows} == {"m1"}
    assert rows[0]["cutting"] == "true" and float(rows[0]["torque_nm"]) == 4.2


def test_jsonl_of_processes_and_operations(millsense_cmd, state, tmp_path):
    out = tmp_path / "export.jsonl"
    r = _run(millsense_cmd, "--config", str(state), "--what", "processes", "--tool", "12", "--format", "jsonl",
             "--out", str(out))
    assert r.returncode == 0, r.stderr
    lines = [json.loads(line) for line in out.read_text().splitlines()]
    assert [p["process"] for p in lines] == [1, 3]
    assert lines[1]["verdict"] == "envelope_high" and lines[1]["energy_j"] == 1759.3
    assert "wrote 2 processes rows" in r.stderr

    r = _run(millsense_cmd, "--config", str(state), "--operation", "4", "-f", "jsonl")
    revs = [json.loads(line)["rev"] for line in r.stdout.splitlines()]
    assert revs == list(range(100, 200)) + list(range(300, 400))

    r = _run(millsense_cmd, "--config", str(state), "--what", "limits", "--tool", "7", "-f", "jsonl")
    assert [json.loads(line)["key"] for line in r.stdout.splitlines()] == ["1234/7/4"]


def test_errors_are_one_line_with_their_exit_code(millsense_cmd, state, tmp_path):
    r = _run(millsense_cmd, "--config", str(state), "--from", "last tuesday")
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "--from" in r.stderr
    r = _run(millsense_cmd, "--config", str(state), "--tool", "T12")
    assert r.returncode == 2 and r.stderr.count("\n") == 1
    # beyond the numbers' widths (an internal error after the CSV header before stop 28), or another script's digits
    for option, value in (("--program", "99999999999999999999"), ("--tool", "4294967296"), ("--operation", "65536"),
                          ("--program", "١٢")):
        r = _run(millsense_cmd, "--config", str(state), option, value)
        assert r.returncode == 2 and r.stderr.count("\n") == 1 and option in r.stderr, (option, value, r.stderr)
        assert r.stdout == "", r.stdout
    r = _run(millsense_cmd, "--db", str(tmp_path / "none.sqlite3"))
    assert r.returncode == 1 and "no history database" in r.stderr and "Traceback" not in r.stderr
    bad = tmp_path / "bad.toml"
    bad.write_text('machine = "m1"\n[history]\nmax_mb = -3\n')
    r = _run(millsense_cmd, "--config", str(bad))
    assert r.returncode == 78 and r.stderr.startswith("history.max_mb")


def test_a_number_may_be_as_wide_as_its_context_field():
    """program and tool are uint32, operation uint16 (the CONTEXT frame's, a process key's fields)."""
    from millsense.daemon.commands.history import _number, _Usage

    assert _number("4294967295", "--program") == _number("4294967295", "--tool") == 2**32 - 1
    assert _number("65535", "--operation") == 2**16 - 1
    for option, value, top in (("--program", "4294967296", 2**32 - 1), ("--operation", "65536", 2**16 - 1)):
        with pytest.raises(_Usage, match=f"at most {top} "):
            _number(value, option)


def test_export_while_the_daemon_writes(millsense_cmd, tmp_path):
    """Read-only beside a live writer (WAL): the export sees the last commit, the writer never notices."""
    import threading

    from .helpers import Events

    path = tmp_path / "history.sqlite3"
    events = Events()
    store = HistoryStore(path, machine="m1", on_error=events.on_error)
    store.start()
    stop = threading.Event()

    def feed():
        rev = 0
        while not stop.is_set():
            store.add_revolution(estimate(rev, T0 + rev))
            rev += 1
            if rev % 50 == 0:
                stop.wait(0.01)

    feeder = threading.Thread(target=feed, daemon=True)
    feeder.start()
    try:
        assert store.flush(30)
        for _ in range(3):
            r = _run(millsense_cmd, "--db", str(path), "-f", "jsonl")
            assert r.returncode == 0, r.stderr
            revs = [json.loads(line)["rev"] for line in r.stdout.splitlines()]
            assert revs and revs == list(range(len(revs)))  # a prefix of what was written, in order
    finally:
        stop.set()
        feeder.join(10)
        store.close()
    assert events.errors == []
