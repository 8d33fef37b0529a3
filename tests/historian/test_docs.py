"""docs/historian.md is true to the code: its schema table lists every table's columns in order, and its SQL (the
plant's questions, the Grafana role) runs on the schema the historian makes."""

from __future__ import annotations

import re

import psycopg

from millsense.daemon.historian import schema
from tests.conftest import REPO

DOC = (REPO / "docs" / "historian.md").read_text()


def test_the_schema_table_lists_every_column_in_order():
    section = DOC.split("## Schema", 1)[1].split("\n## ", 1)[0]
    found = {}
    for line in section.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) == 4 and cells[0].strip("`") in schema.TABLES:
            plain = [re.sub(r"\([^)]*\)", "", c).replace("`", "") for c in cells[1:3]]
            found[cells[0].strip("`")] = [[w.strip() for w in c.split(",")] for c in plain]
    assert sorted(found) == sorted(schema.TABLES)
    for table, (cols, unique) in found.items():
        assert cols == [n for n, _ in schema.TABLES[table][0]], table
        assert unique == list(schema.TABLES[table][1]), table


def test_the_documented_sql_runs_on_the_historians_schema(pg_db):
    server, name, passfile = pg_db
    blocks = re.findall(r"```sql\n(.*?)```", DOC, re.S)
    assert len(blocks) == 2
    with psycopg.connect(server.dsn(name), passfile=str(passfile), autocommit=True) as conn:
        schema.ensure_schema(conn)
        for statement in blocks[0].split(";"):
            if statement.strip() and not all(line.startswith("--") for line in statement.strip().splitlines()):
                conn.execute(statement).fetchall()
    with server.admin(name) as conn:
        role = blocks[1].replace("'…'", "'x'").replace("DATABASE millsense", f"DATABASE {name}")
        conn.execute(role)
        conn.execute("DROP OWNED BY grafana")
        conn.execute("DROP ROLE grafana")
