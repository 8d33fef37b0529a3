"""The spool while PostgreSQL refuses the historian: rows kept on disk in order, the bound honoured (the oldest
dropped, counted and said), and replayed in order once the server takes them, each row once.

The refusal is real: the passfile is not there yet, so the server refuses the historian's role (password
authentication), as it would a rotated password; writing the passfile is the server "coming back"."""

from __future__ import annotations

import time

import psycopg

from millsense.daemon.historian import rows, schema
from millsense.daemon.historian.spool import Spool
from millsense.daemon.historian.writer import Writer
from tests.historian.test_schema import Log, alarm


def test_rows_spool_within_the_bound_the_oldest_dropped_and_counted_then_replayed_once(pg_db, tmp_path):
    server, name, _ = pg_db
    passfile = tmp_path / "later" / "pgpass"
    log = Log()
    spool = Spool(tmp_path / "spool", 40_000)   # segments of 5 000 bytes: about 12 alarm rows each
    writer = Writer(server.dsn(name), str(passfile), spool, {t: 30.0 for t in schema.TABLES}, log)
    now = time.time()
    seqs = list(range(1, 201))
    for chunk in (seqs[i:i + 10] for i in range(0, len(seqs), 10)):
        for seq in chunk:
            writer.add("alarms", rows.alarm_row("m1", alarm(now - 100 + seq * 0.1, seq), now))
        writer.flush()
        writer._next_try = 0.0   # the clock of the retry back-off: try at every flush here
    state = writer.status()
    assert state["db"] == "down" and "password" in state["db_error"], state
    assert [e for e, _ in log.events].count("historian.db_down") == 1
    assert "historian.spooling" in [e for e, _ in log.events]
    full = [f for e, f in log.events if e == "historian.spool_full"]
    assert full and full[-1]["dropped_total"] == state["spool_dropped"] > 0
    assert state["spool_bytes"] <= 40_000 and state["spooled_rows"] + state["spool_dropped"] == 200, state

    at = schema.column_names("alarms").index("alarm_seq")
    in_order = [row[at] for _, segment in spool.segments() for _, row in segment]
    assert in_order == seqs[-state["spooled_rows"]:]   # on disk in the order they came, the newest kept

    passfile.parent.mkdir()
    server.passfile(passfile.parent)     # the server takes the historian again
    writer.flush()
    assert writer.status()["db"] == "up" and writer.status()["spooled_rows"] == 0
    assert "historian.spool_replayed" in [e for e, _ in log.events]
    with psycopg.connect(server.dsn(name), passfile=str(passfile)) as conn:
        stored = [r[0] for r in conn.execute("SELECT alarm_seq FROM alarms ORDER BY received_at, time").fetchall()]
    kept = state["spooled_rows"]
    assert stored == seqs[-kept:]   # the newest, every one, once; the oldest were the ones dropped
    writer.flush()                  # nothing left to replay a second time
    with psycopg.connect(server.dsn(name), passfile=str(passfile)) as conn:
        assert conn.execute("SELECT count(*) FROM alarms").fetchone()[0] == kept
    writer.close()


def test_a_spool_left_by_a_stopped_historian_is_taken_up_in_order_by_the_next(tmp_path):
    first = Spool(tmp_path / "spool", 40_000)
    for i in range(30):
        first.append([("alarms", [float(i), 0.0, "m1"])])
    first.close()
    (tmp_path / "spool" / "spool-000000000009.jsonl").write_bytes(b'["alarms",[99.0,0.0,"m1"]]\n["alar')  # cut short
    second = Spool(tmp_path / "spool", 40_000)
    assert second.rows_waiting() == 31   # whole lines: the torn one is not counted
    second.append([("alarms", [30.0, 0.0, "m1"])])
    order = [row[0] for _, segment in second.segments() for _, row in segment]
    assert order == [float(i) for i in range(30)] + [99.0, 30.0]   # the torn line skipped, the rest in order
