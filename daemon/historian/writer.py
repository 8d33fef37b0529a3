"""The historian's writes: batched COPY into staging tables, then `INSERT … ON CONFLICT DO NOTHING` (idempotent:
a replay never duplicates), a flush at least every second, the spool while PostgreSQL is down or slow, day
partitions ahead and retention (docs/historian.md).

One thread calls `Writer.flush` (service.py): nothing here is shared between threads.
"""

from __future__ import annotations

import time
from collections import defaultdict
from datetime import UTC, date, datetime, timedelta
from typing import Any

import psycopg
from psycopg import sql
from psycopg.types.json import Jsonb

from millsense.daemon.historian import schema
from millsense.daemon.historian.spool import Spool, SpoolError

CONNECT_TIMEOUT_S = 5
STATEMENT_TIMEOUT_MS = 15000   # a write slower than this is PostgreSQL "slow": the rows go to the spool
RETRY_S = (1.0, 2.0, 5.0, 10.0)
RETENTION_EVERY_S = 3600.0


_EPOCH_DAY = date(1970, 1, 1)


def _copy_type(kind: str) -> str:
    """A column's type as the binary COPY into its staging table sends it (`integer` is staged as bigint)."""
    base = kind.replace(" NOT NULL", "")
    return {"double precision": "float8", "bigint": "int8", "integer": "int8", "boolean": "bool",
            "text": "text", "jsonb": "jsonb", "timestamptz": "timestamptz"}[base]


# An int4 column is staged as bigint: psycopg's binary int4 would write 2**40 as 0 (no error), where the
# INSERT's cast from the staging table refuses it ("integer out of range"), as the text COPY did.
_INT4_COLUMNS = {t: [n for n, k in schema.columns(t) if k.startswith("integer")] for t in schema.TABLES}
_COPY_TYPES = {t: [_copy_type(k) for _, k in schema.columns(t)] for t in schema.TABLES}


def _days(times: list[float]) -> set[date]:
    """The UTC days of Unix times, without a datetime a row: a time less than a microsecond before midnight is
    rounded into the next day by `_ts`, so the next day is in too (a partition more is harmless, one fewer is not)."""
    days = {int(t // 86400.0) for t in times} | {int((t + 1e-6) // 86400.0) for t in times}
    return {_EPOCH_DAY + timedelta(days=d) for d in days}


def _ts(seconds: float) -> datetime:
    return datetime.fromtimestamp(seconds, UTC)


class Database:
    """One connection, the schema checked, the staging tables made."""

    def __init__(self, dsn: str, passfile: str = "", application_name: str = "millsense-historian") -> None:
        extra: dict[str, Any] = {"connect_timeout": CONNECT_TIMEOUT_S, "application_name": application_name,
                                 "options": f"-c statement_timeout={STATEMENT_TIMEOUT_MS} -c timezone=UTC"}
        if passfile:
            extra["passfile"] = passfile
        self.conn = psycopg.connect(dsn, autocommit=True, **extra)
        self._days: dict[str, set] = defaultdict(set)
        try:
            self.schema_done = schema.ensure_schema(self.conn)
            for table in schema.TABLES:   # made here, outside any write's transaction: a failed write keeps them
                stage = sql.Identifier(f"stage_{table}")
                self.conn.execute(sql.SQL("CREATE TEMP TABLE {s} (LIKE {t}) ON COMMIT DELETE ROWS")
                                  .format(s=stage, t=sql.Identifier(table)))
                for name in _INT4_COLUMNS[table]:   # staged as bigint: PostgreSQL's cast says what is out of range
                    self.conn.execute(sql.SQL("ALTER TABLE {s} ALTER COLUMN {c} TYPE bigint")
                                      .format(s=stage, c=sql.Identifier(name)))
        except BaseException:
            self.conn.close()
            raise

    def close(self) -> None:
        self.conn.close()

    def ensure_days(self, table: str, days: set) -> None:
        missing = days - self._days[table]
        if missing:
            schema.ensure_partitions(self.conn, table, missing)
            self._days[table] |= missing

    def write(self, by_table: dict[str, list[list[Any]]]) -> dict[str, int]:
        """Every table's rows in one transaction; the rows new to the database, per table."""
        for table, rows in by_table.items():   # the days of the rows' times (Unix days: UTC, no leap seconds)
            self.ensure_days(table, _days([r[0] for r in rows]))
        inserted: dict[str, int] = {}
        with self.conn.transaction():
            for table, rows in by_table.items():
                inserted[table] = self._copy(table, rows)
        return inserted

    def _copy(self, table: str, rows: list[list[Any]]) -> int:
        """COPY in PostgreSQL's binary format: a double is its 8 bytes, not its decimal text (issue 43's profile:
        formatting a revolution's row as text cost 6.4 µs of the historian's CPU, as binary 0.4 µs). Every
        column's type is set (`_COPY_TYPES`): a value that does not fit it (an integer past 64 bits, a number
        where text goes) is a DataError, the row refused as PostgreSQL refuses one (`Writer._row_by_row`)."""
        stage = f"stage_{table}"
        names = schema.column_names(table)
        jsonb = [i for i, (_, kind) in enumerate(schema.columns(table)) if kind.startswith("jsonb")]
        cols = sql.SQL(", ").join(map(sql.Identifier, names))
        with self.conn.cursor() as cur:
            with cur.copy(sql.SQL("COPY {s} ({c}) FROM STDIN (FORMAT BINARY)")
                          .format(s=sql.Identifier(stage), c=cols)) as copy:
                copy.set_types(_COPY_TYPES[table])
                write_row, width = copy.write_row, len(names)
                for row in rows:
                    out = [_ts(row[0]), _ts(row[1]), *row[2:]]   # a copy: the rows stay JSON for the spool
                    if len(out) < width:
                        out += [None] * (width - len(out))   # spooled by an older version: its later columns null
                    for i in jsonb:
                        if out[i] is not None:
                            out[i] = Jsonb(out[i])
                    try:
                        write_row(out)
                    except (OverflowError, TypeError, ValueError) as exc:
                        raise psycopg.DataError(f"{table}: a value its column cannot hold ({exc})") from exc
            cur.execute(sql.SQL("INSERT INTO {t} ({c}) SELECT {c} FROM {s} ON CONFLICT DO NOTHING")
                        .format(t=sql.Identifier(table), c=cols, s=sql.Identifier(stage)))
            return cur.rowcount

    def drop_expired(self, retention_days: dict[str, float], now: float) -> list[str]:
        dropped = []
        for table, days in retention_days.items():
            dropped += schema.drop_expired(self.conn, table, _ts(now) - timedelta(days=days))
            self._days[table] = set()
        return dropped


def _pairs(by_table: dict[str, list[list[Any]]]) -> list[tuple[str, list[Any]]]:
    """Rows by table → (table, row) pairs, the spool's lines (one flush's rows are one transaction: their order
    across tables is none that matters; within a table it is kept)."""
    return [(table, row) for table, rows in by_table.items() for row in rows]


class Writer:
    """Rows in; PostgreSQL or the spool out. `flush()` at least once a second; `status()` for the log line."""

    def __init__(self, dsn: str, passfile: str, spool: Spool, retention_days: dict[str, float], log: Any,
                 clock: Any = time.time) -> None:
        self.dsn, self.passfile, self.spool, self.retention_days, self.log = dsn, passfile, spool, retention_days, log
        self.clock = clock
        self.db: Database | None = None
        self.pending: dict[str, list[list[Any]]] = {}   # table → rows, in the order added
        self.written: dict[str, int] = defaultdict(int)   # rows new to the database
        self.duplicates = 0                                # rows the database had already (a replay)
        self.late_dropped = 0                              # rows older than their table's retention
        self.spool_failed = 0                              # rows lost because the spool itself could not be written
        self.rejected = 0                                  # rows PostgreSQL refused for their data
        self.db_error: str | None = None
        self._next_try = 0.0
        self._tries = 0
        self._next_retention = 0.0
        self._spooling_said = False

    def add(self, table: str, row: list[Any]) -> None:
        self.rows(table).append(row)

    def rows(self, table: str) -> list[list[Any]]:
        """The list `table`'s pending rows go into until the next flush: the loop appends to it with no call a row
        (service.py's estimates). The same list until `flush()` takes it."""
        out = self.pending.get(table)
        if out is None:
            out = self.pending[table] = []
        return out

    # ------------------------------------------------------------------ the cycle
    def flush(self) -> None:
        if self.db is None:
            self._connect()   # SchemaError: raised with the rows still pending (close() spools them)
        by_table, self.pending = self._keep_tables_in_retention(self.pending), {}
        if self.db is not None and not self.spool.empty():
            self._replay()
        if self.db is not None and self.spool.empty():
            if by_table and not self._write_tables(by_table):
                self._to_spool(_pairs(by_table))
        elif by_table:
            self._to_spool(_pairs(by_table))
        if self.db is not None and self.clock() >= self._next_retention:
            self._retention()

    def close(self) -> None:
        try:
            self.flush()
        except schema.SchemaError:   # a newer schema met on reconnecting: keep the rows for a newer historian
            self._to_spool(_pairs(self._keep_tables_in_retention(self.pending)))
            self.pending = {}
            raise
        finally:
            self.spool.close()
        if self.db is not None:
            self.db.close()

    def _keep_in_retention(self, rows: list[tuple[str, list[Any]]]) -> list[tuple[str, list[Any]]]:
        """Rows older than their table's retention are counted and dropped: written, they would land in a day
        partition that retention dropped, or make it again."""
        now = self.clock()
        kept = [(t, r) for t, r in rows if r[0] >= now - self.retention_days[t] * 86400.0]
        if len(kept) != len(rows):
            self.late_dropped += len(rows) - len(kept)
            self.log.warning("historian.late_rows_dropped", rows=len(rows) - len(kept), total=self.late_dropped,
                             detail="older than their table's retention_days")
        return kept

    def _keep_tables_in_retention(self, by_table: dict[str, list[list[Any]]]) -> dict[str, list[list[Any]]]:
        """`_keep_in_retention` of rows by table (the loop's pending rows): one bound a table, not one a row."""
        now, out, late = self.clock(), {}, 0
        for table, rows in by_table.items():
            if not rows:
                continue
            oldest = now - self.retention_days[table] * 86400.0
            kept = rows if min(r[0] for r in rows) >= oldest else [r for r in rows if r[0] >= oldest]
            late += len(rows) - len(kept)
            if kept:
                out[table] = kept
        if late:
            self.late_dropped += late
            self.log.warning("historian.late_rows_dropped", rows=late, total=self.late_dropped,
                             detail="older than their table's retention_days")
        return out

    def _connect(self) -> None:
        now = time.monotonic()
        if now < self._next_try:
            return
        try:
            self.db = Database(self.dsn, self.passfile)
        except schema.SchemaError:
            raise
        except psycopg.Error as exc:
            self._down(exc)
            return
        was_down = self.db_error is not None
        self.db_error, self._tries = None, 0
        for table in schema.TABLES:
            self.db.ensure_days(table, set(schema.ahead(_ts(self.clock()).date())))
        if was_down:
            self.log.info("historian.db_up", spooled_rows=self.spool.rows_waiting(), detail="replaying the spool")
        else:
            self.log.info("historian.db_connected", schema=self.db.schema_done)

    def _down(self, exc: BaseException) -> None:
        message = " ".join(str(exc).split()) or type(exc).__name__
        if self.db_error is None:
            self.log.error("historian.db_down", error=message, detail="spooling to disk until PostgreSQL is back")
        self.db_error = message
        if self.db is not None:
            try:
                self.db.close()
            except psycopg.Error:
                pass
            self.db = None
        self._next_try = time.monotonic() + RETRY_S[min(self._tries, len(RETRY_S) - 1)]
        self._tries += 1

    def _write(self, rows: list[tuple[str, list[Any]]]) -> bool:
        by_table: dict[str, list[list[Any]]] = defaultdict(list)
        for table, row in rows:
            by_table[table].append(row)
        return self._write_tables(by_table)

    def _write_tables(self, by_table: dict[str, list[list[Any]]]) -> bool:
        try:
            inserted = self.db.write(by_table)
        except psycopg.Error as exc:
            if self._connection_lost(exc):
                self._down(exc)
                return False
            return self._row_by_row(by_table, exc)
        self._count(by_table, inserted)
        return True

    def _connection_lost(self, exc: BaseException) -> bool:
        """The server is gone, refused or slow (statement timeout): spool. Anything else is the rows' fault."""
        return isinstance(exc, psycopg.OperationalError) or self.db is None or self.db.conn.broken or \
            self.db.conn.closed

    def _row_by_row(self, by_table: dict[str, list[list[Any]]], first: BaseException) -> bool:
        """A batch PostgreSQL refused for its data (a string it cannot store, a value out of range): each row on
        its own, the ones refused counted and said, never spooled (they would block the spool for ever)."""
        rejected = 0
        for table, table_rows in by_table.items():
            for row in table_rows:
                try:
                    self._count({table: [row]}, self.db.write({table: [row]}))
                except psycopg.Error as exc:
                    if self._connection_lost(exc):
                        self._down(exc)
                        return False   # the whole batch to the spool: what was written is skipped on replay
                    rejected += 1
        self.rejected += rejected
        self.log.error("historian.rows_rejected", rows=rejected, total=self.rejected,
                       error=" ".join(str(first).split())[:300])
        return True

    def _count(self, by_table: dict[str, list[list[Any]]], inserted: dict[str, int]) -> None:
        for table, n in inserted.items():
            self.written[table] += n
            self.duplicates += len(by_table[table]) - n

    def _to_spool(self, rows: list[tuple[str, list[Any]]]) -> None:
        dropped = self.spool.dropped
        try:
            self.spool.append(rows)
        except SpoolError as exc:
            self.spool_failed += len(rows)
            self.log.error("historian.spool_failed", rows=len(rows), error=str(exc))
            return
        if not self._spooling_said:
            self._spooling_said = True
            self.log.warning("historian.spooling", spool_dir=str(self.spool.directory), db_error=self.db_error)
        if self.spool.dropped != dropped:
            self.log.error("historian.spool_full", dropped_rows=self.spool.dropped - dropped,
                           dropped_total=self.spool.dropped, max_mb=self.spool.max_bytes / 1e6,
                           detail="the oldest spooled rows are dropped past spool_max_mb")

    def _replay(self) -> None:
        replayed = 0
        for path, rows in self.spool.segments():
            rows = self._keep_in_retention(rows)
            if rows and not self._write(rows):
                return   # down again: the segment stays, in order
            self.spool.done(path)
            replayed += len(rows)
        self._spooling_said = False
        self.log.info("historian.spool_replayed", rows=replayed)

    def _retention(self) -> None:
        self._next_retention = self.clock() + RETENTION_EVERY_S
        try:
            dropped = self.db.drop_expired(self.retention_days, self.clock())
            for table in schema.TABLES:
                self.db.ensure_days(table, set(schema.ahead(_ts(self.clock()).date())))
        except psycopg.Error as exc:
            self._down(exc)
            return
        if dropped:
            self.log.info("historian.partitions_dropped", partitions=dropped)

    def status(self) -> dict[str, Any]:
        return {
            "db": "up" if self.db is not None else "down", "db_error": self.db_error,
            "written": dict(self.written), "duplicates": self.duplicates, "late_dropped": self.late_dropped,
            "spooled_rows": self.spool.rows_waiting(), "spool_bytes": self.spool.size_bytes(),
            "spool_dropped": self.spool.dropped, "spool_failed": self.spool_failed, "rejected": self.rejected,
        }
