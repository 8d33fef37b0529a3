"""`millsense history --dsn` reads the plant's database across machines (`--machine` repeatable, or all), in a
time range given in ISO 8601 with its offset; a password never on its command line. Rows written by the
historian's own writer from the daemon's payloads (docs/zenoh.md's examples), process summaries and the learned
limits' changes among them."""

from __future__ import annotations

import csv
import io
import json
import subprocess
import time
from datetime import UTC, datetime, timedelta, timezone

from millsense.daemon.historian import schema
from millsense.daemon.historian.service import Rows
from millsense.daemon.historian.spool import Spool
from millsense.daemon.historian.writer import Writer
from tests.historian.test_schema import Log, alarm

PROCESS = {"machine": "m1", "process": 17, "key": "1234/12/3", "program": 1234, "tool": 12, "operation": 3,
           "revolutions": 412, "cutting_revolutions": 380, "entry_rev": 21, "torque_peak_nm": 6.8,
           "torque_mean_nm": 4.1, "force_peak_n": 702.0, "energy_j": 9790.3, "verdict": "good", "learned": 5,
           "learn_target": 5, "envelope": "active", "energy_ratio": 1.04, "tool_processes": 88, "tool_wear_pct": 3.9}


def test_history_reads_the_plant_database_by_machine_and_time_with_offsets(pg_db, tmp_path, millsense_cmd):
    server, name, passfile = pg_db
    writer = Writer(server.dsn(name), str(passfile), Spool(tmp_path / "spool", 10**6),
                    {t: 30.0 for t in schema.TABLES}, Log())
    taker = Rows(writer, revolutions_for=set())
    now = time.time()
    for machine in ("m1", "m2", "m3"):
        for i in range(3):
            taker.take("alarm", machine, alarm(now - 3600 + i * 600, i + 1), now)
    taker.take("process", "m1", dict(PROCESS, t=now - 600, envelope="learning", learned=4), now)
    taker.take("process", "m1", dict(PROCESS, t=now - 300, process=18), now)
    writer.flush()
    assert writer.written == {"alarms": 9, "processes": 2, "limit_changes": 1}, writer.written

    plus_two = timezone(timedelta(hours=2))
    t_from = datetime.fromtimestamp(now - 3600 + 300, UTC).astimezone(plus_two).isoformat()   # +02:00
    t_to = datetime.fromtimestamp(now, UTC).isoformat()                                       # +00:00
    base = millsense_cmd + ["history", "--dsn", server.dsn(name), "--passfile", str(passfile)]
    p = subprocess.run(base + ["--what", "alarms", "--machine", "m1", "--machine", "m3", "--from", t_from,
                               "--to", t_to], capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stderr
    got = list(csv.DictReader(io.StringIO(p.stdout)))
    assert [(r["machine"], r["alarm_seq"]) for r in got] == [("m1", "2"), ("m3", "2"), ("m1", "3"), ("m3", "3")]
    assert all(r["time"].endswith("+00:00") for r in got) and got[0]["limit_value"] == "30.0"

    p = subprocess.run(base + ["--what", "processes", "--machine", "all", "--format", "jsonl"],
                       capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stderr
    processes = [json.loads(line) for line in p.stdout.splitlines()]
    assert [(r["process"], r["envelope"], r["energy_j"]) for r in processes] == [(17, "learning", 9790.3),
                                                                                 (18, "active", 9790.3)]
    p = subprocess.run(base + ["--what", "limits", "--format", "jsonl"], capture_output=True, text=True, timeout=60)
    change = [json.loads(line) for line in p.stdout.splitlines()]
    assert [(c["key"], c["change"], c["process"]) for c in change] == [("1234/12/3", "learning->active", 18)]
    writer.close()


def test_history_refuses_a_password_on_its_command_line(millsense_cmd):
    p = subprocess.run(millsense_cmd + ["history", "--dsn", "postgresql://h:s3cret@db/m"], capture_output=True,
                       text=True, timeout=60)
    assert p.returncode == 2 and p.stderr.startswith("millsense history: error: --dsn: holds a password: put it in "
                                                     "the libpq passfile given by --passfile"), p.stderr
    p = subprocess.run(millsense_cmd + ["history", "--what", "load", "--db", "x.sqlite3"], capture_output=True,
                       text=True, timeout=60)
    assert p.returncode == 2 and "only the plant's database (--dsn) keeps it" in p.stderr, p.stderr


def test_history_says_in_one_line_when_the_plant_database_cannot_be_reached(millsense_cmd, tmp_path):
    from tests.conftest import free_tcp_port

    p = subprocess.run(millsense_cmd + ["history", "--dsn", f"host=127.0.0.1 port={free_tcp_port()} dbname=m user=h",
                                        "--what", "load"], capture_output=True, text=True, timeout=60)
    assert p.returncode == 1, p.stderr
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("millsense history: error: the plant's database: "), p.stderr
