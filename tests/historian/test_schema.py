"""The historian's schema on a real PostgreSQL: day partitions ahead and a DEFAULT one, the version recorded, an
older schema upgraded in one transaction, a newer one refused; writes idempotent; retention by whole partitions,
late rows counted and dropped."""

from __future__ import annotations

import time
from datetime import UTC, datetime, timedelta

import psycopg
import pytest

from millsense.daemon.historian import rows, schema
from millsense.daemon.historian.spool import Spool
from millsense.daemon.historian.writer import Database, Writer


def connect(pg_db):
    server, name, passfile = pg_db
    return psycopg.connect(server.dsn(name), passfile=str(passfile), autocommit=True)


class Log:
    def __init__(self) -> None:
        self.events: list[tuple[str, dict]] = []

    def _add(self, event, **fields):
        self.events.append((event, fields))

    info = warning = error = _add


def test_a_new_database_gets_every_table_partitioned_by_day_with_a_default_and_version_1(pg_db):
    server, name, passfile = pg_db
    db = Database(server.dsn(name), str(passfile))
    assert db.schema_done == "created"
    today = datetime.now(UTC).date()
    for table in schema.TABLES:
        db.ensure_days(table, set(schema.ahead(today)))
    with connect(pg_db) as conn:
        assert schema.stored_version(conn) == schema.SCHEMA_VERSION == 2
        for table in schema.TABLES:
            kinds = dict(conn.execute("SELECT column_name, data_type FROM information_schema.columns "
                                      "WHERE table_name = %s", (table,)).fetchall())
            assert kinds["time"] == kinds["received_at"] == "timestamp with time zone" and kinds["machine"] == "text"
            parts = schema.partitions(conn, table)
            assert sorted(parts) == [today + timedelta(days=i) for i in range(3)], table   # 2 days ahead
            default = conn.execute("SELECT count(*) FROM pg_partitioned_table p JOIN pg_class c ON c.oid = p.partdefid "
                                   "WHERE c.relname = %s", (f"{table}_default",)).fetchone()[0]
            assert default == 1, table
    assert Database(server.dsn(name), str(passfile)).schema_done == "current"
    db.close()


def test_a_newer_schema_is_refused_and_an_older_one_upgraded_in_one_transaction(pg_db):
    with connect(pg_db) as conn:
        assert schema.ensure_schema(conn) == "created"
        # the machinery with a synthetic version 3 (the real upgrade from 1: the next test, from version 1's dump)
        broken = {2: ["ALTER TABLE alarms ADD COLUMN operator text", "ALTER TABLE nowhere ADD COLUMN x int"]}
        with pytest.raises(schema.SchemaError, match=r"from version 2 to 3 failed, nothing changed: UndefinedTable"):
            schema.ensure_schema(conn, version=3, upgrades=broken)
        assert schema.stored_version(conn) == 2
        assert "operator" not in schema_columns(conn, "alarms")   # the first statement rolled back with the second
        good = {2: ["ALTER TABLE alarms ADD COLUMN operator text"]}
        assert schema.ensure_schema(conn, version=3, upgrades=good) == "upgraded from 2"
        assert schema.stored_version(conn) == 3 and "operator" in schema_columns(conn, "alarms")
        with pytest.raises(schema.SchemaError, match="version 3, newer than this historian's 2: upgrade millsense"):
            schema.ensure_schema(conn)


def test_version_1s_dump_is_upgraded_its_rows_kept_and_a_published_limits_change_written_beside_them(pg_db, tmp_path):
    """tests/historian/schema_v1.sql (pg_dump of a version-1 database) restored with psql, then the historian's
    Database: upgraded in its transaction, the version-1 row kept (its new columns null), a version-2 row written,
    and a row spooled by a version-1 historian (8 values) written too, its later columns null."""
    import os
    import subprocess
    from pathlib import Path

    server, name, passfile = pg_db
    dump = Path(__file__).with_name("schema_v1.sql")
    done = subprocess.run([str(server.bin / "psql"), "-X", "-q", "-v", "ON_ERROR_STOP=1", "-f", str(dump),
                           server.dsn(name)], capture_output=True, text=True, timeout=60,
                          env=dict(os.environ, PGPASSFILE=str(passfile)))
    assert done.returncode == 0, done.stderr
    with connect(pg_db) as conn:
        assert schema.stored_version(conn) == 1 and "requester" not in schema_columns(conn, "limit_changes")
    writer = Writer(server.dsn(name), str(passfile), Spool(tmp_path / "spool", 10**6),
                    {t: 3650.0 for t in schema.TABLES}, Log())
    writer.flush()
    assert writer.db.schema_done == "upgraded from 1"
    now = time.time()
    change = {"machine": "m1", "t": now, "key": "1234/12/3", "action": "widen", "pct": 10,
              "before": {"state": "active", "widening": 1.0}, "after": {"state": "active", "widening": 1.1},
              "requester": "zid:ab12 (self-declared)", "authority": "token"}
    writer.add("limit_changes", rows.LimitChanges().published("m1", change, now))
    writer.add("limit_changes", [now - 1, now, "m1", "1234/12/4", "learning->pending", "pending", 5, 40])  # v1's
    writer.flush()
    assert writer.written["limit_changes"] == 2 and writer.rejected == 0, writer.status()
    writer.close()
    with connect(pg_db) as conn:
        assert schema.stored_version(conn) == 2
        got = conn.execute("SELECT machine, key, change, envelope, learned, action, pct, requester, authority, "
                           "before->>'widening', after->>'widening' FROM limit_changes ORDER BY time").fetchall()
    assert got == [
        ("mch-v1", "1234/12/3", "learning->pending", "pending", 5, None, None, None, None, None, None),
        ("m1", "1234/12/4", "learning->pending", "pending", 5, None, None, None, None, None, None),
        ("m1", "1234/12/3", "widen", "active", None, "widen", 10.0, "zid:ab12 (self-declared)", "token", "1.0", "1.1"),
    ], got


def schema_columns(conn, table):
    return {r[0] for r in conn.execute("SELECT column_name FROM information_schema.columns WHERE table_name = %s",
                                       (table,)).fetchall()}


def test_the_historian_refuses_a_newer_schema_with_one_line_and_exit_1(pg_db, millsense_cmd, tmp_path):
    import subprocess

    server, name, passfile = pg_db
    with connect(pg_db) as conn:
        schema.ensure_schema(conn)
        conn.execute("INSERT INTO schema_version (version) VALUES (7)")
    config = tmp_path / "historian.toml"
    config.write_text(f'[historian]\ndsn = "{server.dsn(name)}"\npassfile = "{passfile}"\nspool_dir = "spool"\n'
                      '[zenoh]\nmulticast_scouting = false\n')
    p = subprocess.run(millsense_cmd + ["historian", "--config", str(config), "--log-format", "json"],
                       capture_output=True, text=True, timeout=60)
    assert p.returncode == 1, p.stderr
    assert p.stderr.strip().splitlines()[-1] == ("millsense historian: error: the database's schema is version 7, "
                                                 "newer than this historian's 2: upgrade millsense (a historian never "
                                                 "writes into tables it does not know)")
    assert "Traceback" not in p.stderr


def alarm(t: float, seq: int) -> dict:
    return {"machine": "m1", "t": t, "rev": 10 + seq, "level": "overload", "quantity": "torque_nm", "value": 31.7,
            "limit": 30.0, "interlock": "feed_hold", "run_id": "r1", "alarm_seq": seq}


def test_the_same_batch_written_twice_is_one_row_each(pg_db, tmp_path):
    log = Log()
    writer = _writer(pg_db, tmp_path, log)
    now = time.time()
    batch = [("alarms", rows.alarm_row("m1", alarm(now - i, i), now)) for i in range(5)]
    batch.append(("alarms", rows.alarm_row("m1", dict(alarm(now - 9, 0), alarm_seq=None), now)))  # a replay's: no seq
    for _ in range(2):
        for table, row in batch:
            writer.add(table, row)
        writer.flush()
    assert writer.written["alarms"] == 6 and writer.duplicates == 6, writer.status()
    with connect(pg_db) as conn:
        assert conn.execute("SELECT count(*), count(DISTINCT alarm_seq) FROM alarms").fetchone() == (6, 5)
    writer.close()


def test_retention_drops_whole_partitions_and_late_rows_are_counted_never_written(pg_db, tmp_path):
    server, name, passfile = pg_db
    now = [time.time()]
    log = Log()
    writer = Writer(server.dsn(name), str(passfile), Spool(tmp_path / "spool", 10**6),
                    dict({t: 30.0 for t in schema.TABLES}, alarms=2.0), log, clock=lambda: now[0])
    day = 86400.0
    for age_days in (0.0, 1.0, 1.9):
        writer.add("alarms", rows.alarm_row("m1", alarm(now[0] - age_days * day, int(age_days * 10)), now[0]))
    writer.flush()
    with connect(pg_db) as conn:   # a day partition for each row's day (made on demand), and two days ahead
        wanted = {_day(now[0] - a * day) for a in (0.0, 1.0, 1.9)} | set(schema.ahead(_day(now[0])))
        assert set(schema.partitions(conn, "alarms")) == wanted
        assert conn.execute("SELECT count(*) FROM alarms_default").fetchone()[0] == 0
    assert writer.written["alarms"] == 3
    now[0] += 2 * day    # two days on: what is older than 2 days goes, whole partitions
    writer._next_retention = 0.0
    writer.add("alarms", rows.alarm_row("m1", alarm(now[0] - 3 * day, 99), now[0]))   # late, past retention
    writer.flush()
    assert writer.late_dropped == 1
    assert any(e == "historian.late_rows_dropped" for e, _ in log.events)
    keep_from = datetime.fromtimestamp(now[0] - 2 * day, UTC)
    with connect(pg_db) as conn:
        days = sorted(schema.partitions(conn, "alarms"))
        assert days and all(datetime(d.year, d.month, d.day, tzinfo=UTC) + timedelta(days=1) > keep_from for d in days)
        left = conn.execute("SELECT alarm_seq FROM alarms ORDER BY alarm_seq").fetchall()
        # rows whose day partition ended before keep_from are gone; the late row was never written
        assert (99,) not in left and conn.execute("SELECT count(*) FROM alarms_default").fetchone()[0] == 0
        assert len(left) < 3
    writer.close()


def _writer(pg_db, tmp_path, log) -> Writer:
    """A writer into the test's database, spooling under `tmp_path`, every table kept 30 days."""
    server, name, passfile = pg_db
    return Writer(server.dsn(name), str(passfile), Spool(tmp_path / "spool", 10**6), {t: 30.0 for t in schema.TABLES},
                  log)


def _day(t: float):
    return datetime.fromtimestamp(t, UTC).date()


def test_a_row_postgresql_refuses_for_its_data_is_counted_and_the_rest_written_never_spooled(pg_db, tmp_path):
    """PostgreSQL stores no NUL character in text or jsonb: such a row, taken for an outage, would sit at the head
    of the spool for ever and hold back everything after it."""
    log = Log()
    writer = _writer(pg_db, tmp_path, log)
    now = time.time()
    for seq in range(1, 6):
        payload = alarm(now - 10 + seq, seq)
        if seq == 3:
            payload["reason"] = "torque\x00 high"
        writer.add("alarms", rows.alarm_row("m1", payload, now))
    writer.flush()
    assert writer.status()["db"] == "up" and writer.rejected == 1 and writer.written["alarms"] == 4
    assert writer.spool.empty() and [e for e, _ in log.events].count("historian.rows_rejected") == 1
    with connect(pg_db) as conn:
        assert [r[0] for r in conn.execute("SELECT alarm_seq FROM alarms ORDER BY alarm_seq")] == [1, 2, 4, 5]
    writer.close()


def test_a_newer_schema_met_on_reconnecting_stops_the_writer_with_its_rows_spooled(pg_db, tmp_path):
    """Another (newer) historian upgraded the database while this one's connection was cut: it must stop writing,
    and keep what it holds for the newer one (the spool), never drop it."""
    server, name, passfile = pg_db
    writer = _writer(pg_db, tmp_path, Log())
    writer.flush()
    now = time.time()
    with server.admin(name) as admin:
        admin.execute("INSERT INTO schema_version (version) VALUES (3)")
        admin.execute("SELECT pg_terminate_backend(pid) FROM pg_stat_activity WHERE usename = 'historian'")
    writer.add("alarms", rows.alarm_row("m1", alarm(now, 1), now))
    writer.flush()                       # the cut connection: spooled
    writer._next_try = 0.0               # the retry back-off's clock
    writer.add("alarms", rows.alarm_row("m1", alarm(now + 1, 2), now))
    with pytest.raises(schema.SchemaError, match="version 3, newer"):
        writer.close()
    at = schema.column_names("alarms").index("alarm_seq")
    assert [row[at] for _, seg in writer.spool.segments() for _, row in seg] == [1, 2]


def test_an_integer_its_column_cannot_hold_is_refused_never_written_as_another_number(pg_db, tmp_path):
    """`operation` is an int4 column, `rev` int8: 2**40 and 2**70 are JSON integers neither holds. Each such row is
    refused as PostgreSQL refuses a row (counted, said, never spooled), the rest written: never the number's low
    bits written instead, never an error out of the loop (the COPY is binary since issue 43's profile)."""
    log = Log()
    writer = _writer(pg_db, tmp_path, log)
    now = time.time()
    for rev in range(1, 6):
        estimate = {"t": now - 10 + rev, "rev": rev, "valid": True, "torque_nm": 2.0, "operation": 10}
        if rev == 2:
            estimate["operation"] = 2 ** 40
        if rev == 4:
            estimate["process_rev"] = 2 ** 70
        writer.add("revolutions", rows.revolution_row("m1", estimate, now))
    writer.flush()
    assert writer.status()["db"] == "up" and writer.rejected == 2 and writer.written["revolutions"] == 3
    assert writer.spool.empty() and [e for e, _ in log.events].count("historian.rows_rejected") == 1
    with connect(pg_db) as conn:
        assert conn.execute("SELECT rev, operation FROM revolutions ORDER BY rev").fetchall() == \
            [(1, 10), (3, 10), (5, 10)]
    writer.close()
