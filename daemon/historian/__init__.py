"""`millsense historian`: the plant's history in PostgreSQL (docs/historian.md), a separate process.

`schema.py` (tables, day partitions, the schema's version and its upgrades), `rows.py` (a payload → rows, pure),
`load.py` (per-second aggregates of the revolutions), `spool.py` (the bounded local spool while PostgreSQL is
down), `writer.py` (batched COPY through staging tables, idempotent), `service.py` (Zenoh in, the writer's
thread, status), `read.py` (`millsense history --dsn`). Needs the `historian` extra (psycopg 3); the edge daemon
never imports it.
"""
