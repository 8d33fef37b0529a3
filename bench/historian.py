"""The historian's writer: rows a second it sustains into PostgreSQL, beside two baselines of the same run.

A throw-away PostgreSQL (tests/historian/pg.py: Debian's server, a loopback port, fsync off as the tests run it)
and, for `--machines` machines at `--revs` revolutions a second each, one-second batches of `revolutions` rows (the
widest table, what a plant keeps for the machines in `revolutions_for`) plus each machine's `load_1s` row, built by
the historian's own row makers (daemon/historian/rows.py) from estimate payloads shaped like the daemon's.

Three ways of writing the same batches, each into its own fresh database, in turn:
- **writer**: what the historian does (`writer.Database.write`): binary COPY into a temporary staging table, then
  `INSERT … SELECT … ON CONFLICT DO NOTHING` into the partitioned table, all tables of a batch in one transaction;
- **copy (no staging)**: the same rows COPY'd straight into the tables, in PostgreSQL's binary format as the writer
  sends them, one transaction a batch (the COPY floor: what idempotence costs is the difference); and the same in
  the text format (what the binary format saves);
- **insert**: `executemany` of `INSERT … ON CONFLICT DO NOTHING`, one transaction a batch (what COPY saves).
Then **replay**: the writer's batches written a second time (a spool replayed after an outage: every row a
duplicate, nothing inserted).

Prints rows/s (best of `--rounds`), and the 1-minute load average at the start. Not a timed test.
Run: python bench/historian.py [--machines 50] [--revs 10] [--seconds 20] [--rounds 3]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))   # tests/ from a checkout

import psycopg  # noqa: E402
from psycopg import sql  # noqa: E402
from psycopg.types.json import Jsonb  # noqa: E402

from millsense.daemon.historian import rows as rowmod  # noqa: E402
from millsense.daemon.historian import schema  # noqa: E402
from millsense.daemon.historian.writer import Database, _ts  # noqa: E402
from tests.historian.pg import PgServer  # noqa: E402


def batches(machines: int, revs: int, seconds: int, t0: float) -> list[dict[str, list[list]]]:
    """One batch a second: every machine's revolutions of that second, and the load_1s rows they close."""
    load = rowmod.LoadSeconds()
    out = []
    rev = {m: 0 for m in range(machines)}
    for s in range(seconds):
        batch: dict[str, list[list]] = {"revolutions": [], "load_1s": []}
        for m in range(machines):
            name = f"bench-{m:04d}"
            for i in range(revs):
                rev[m] += 1
                t = t0 + s + (i + 0.5) / revs
                est = {"machine": name, "t": t, "rev": rev[m], "valid": True, "spindle_rpm": 1500.0 + i,
                       "p_in_w": 2500.0 + m, "p_gap_w": 2300.0, "torque_nm": 8.0 + 0.01 * i, "force_n": 900.0 + i,
                       "radial_depth_mm": 20.0, "axial_depth_mm": 5.0, "depth_status": "ok",
                       "feed_override_pct": 100.0, "program": 1001, "tool": 11, "operation": 10, "process_rev": i}
                batch["revolutions"].append(rowmod.revolution_row(name, est, t))
                batch["load_1s"] += load.add(name, est, t)
        out.append(batch)
    return out


def _rows_in(batch: dict[str, list[list]]) -> int:
    return sum(len(r) for r in batch.values())


def _converted(table: str, row: list) -> list:
    jsonb = {i for i, (_, kind) in enumerate(schema.columns(table)) if kind.startswith("jsonb")}
    out = list(row)
    out[0], out[1] = _ts(row[0]), _ts(row[1])
    for i in jsonb:
        if out[i] is not None:
            out[i] = Jsonb(out[i])
    return out


def write_writer(db: Database, batch: dict[str, list[list]]) -> None:
    db.write(batch)


def _pg_type(kind: str) -> str:
    """A column's own type as binary COPY names it (straight into the table: no staging)."""
    return {"double precision": "float8", "bigint": "int8", "integer": "int4", "boolean": "bool", "text": "text",
            "jsonb": "jsonb", "timestamptz": "timestamptz"}[kind.replace(" NOT NULL", "")]


def write_copy(db: Database, batch: dict[str, list[list]], binary: bool = True) -> None:
    """The COPY floor: the rows straight into the tables, in PostgreSQL's binary format as the writer sends them
    (`binary=False`: the text format, what the writer sent before issue 43's profile)."""
    for table, table_rows in batch.items():
        db.ensure_days(table, {_ts(r[0]).date() for r in table_rows})
    with db.conn.transaction(), db.conn.cursor() as cur:
        for table, table_rows in batch.items():
            cols = sql.SQL(", ").join(map(sql.Identifier, schema.column_names(table)))
            how = sql.SQL(" (FORMAT BINARY)" if binary else "")
            with cur.copy(sql.SQL("COPY {t} ({c}) FROM STDIN{h}").format(t=sql.Identifier(table), c=cols,
                                                                         h=how)) as copy:
                if binary:
                    copy.set_types([_pg_type(kind) for _, kind in schema.columns(table)])
                for row in table_rows:
                    copy.write_row(_converted(table, row))


def write_copy_text(db: Database, batch: dict[str, list[list]]) -> None:
    write_copy(db, batch, binary=False)


def write_insert(db: Database, batch: dict[str, list[list]]) -> None:
    for table, table_rows in batch.items():
        db.ensure_days(table, {_ts(r[0]).date() for r in table_rows})
    with db.conn.transaction(), db.conn.cursor() as cur:
        for table, table_rows in batch.items():
            names = schema.column_names(table)
            statement = sql.SQL("INSERT INTO {t} ({c}) VALUES ({v}) ON CONFLICT DO NOTHING").format(
                t=sql.Identifier(table), c=sql.SQL(", ").join(map(sql.Identifier, names)),
                v=sql.SQL(", ").join(sql.Placeholder() * len(names)))
            cur.executemany(statement, [_converted(table, row) for row in table_rows])


def measure(server: PgServer, passfile: Path, how, data: list[dict[str, list[list]]], replay: bool = False) -> float:
    name = server.new_database()
    db = Database(server.dsn(name), str(passfile))
    try:
        if replay:
            for batch in data:
                db.write(batch)
        total = sum(_rows_in(b) for b in data)
        t = time.perf_counter()
        for batch in data:
            how(db, batch)
        return total / (time.perf_counter() - t)
    finally:
        db.close()
        with server.admin() as conn:
            conn.execute(f"DROP DATABASE {name} WITH (FORCE)")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    ap.add_argument("--machines", type=int, default=50)
    ap.add_argument("--revs", type=int, default=10, help="revolutions a second per machine")
    ap.add_argument("--seconds", type=int, default=20, help="one-second batches per case")
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args()
    load = os.getloadavg()[0]
    server = PgServer()
    try:
        passfile = server.passfile(Path(server.folder))
        if server.as_root:
            import shutil
            shutil.chown(passfile, os.getuid(), os.getgid())
        data = batches(args.machines, args.revs, args.seconds, time.time() - args.seconds - 5)
        per_batch = _rows_in(data[0])
        print(f"{args.machines} machines × {args.revs} rev/s: {per_batch} rows a batch (revolutions + load_1s), "
              f"{len(data)} batches a case, best of {args.rounds}; load {load:.2f}")
        cases = [("writer (COPY via staging, ON CONFLICT)", write_writer, False),
                 ("copy (no staging, not idempotent)", write_copy, False),
                 ("copy, text format (no staging)", write_copy_text, False),
                 ("insert (executemany, ON CONFLICT)", write_insert, False),
                 ("writer, replay (every row a duplicate)", write_writer, True)]
        best = {label: 0.0 for label, *_ in cases}
        for _ in range(args.rounds):
            for label, how, replay in cases:
                best[label] = max(best[label], measure(server, passfile, how, data, replay))
        writer = best[cases[0][0]]
        for label, *_ in cases:
            print(f"  {label:42s} {best[label]:10,.0f} rows/s  ({best[label] / writer:5.2f} × the writer)")
    finally:
        server.remove()
    return 0


if __name__ == "__main__":
    sys.exit(main())
