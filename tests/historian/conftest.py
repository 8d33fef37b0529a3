"""The historian's fixtures: one PostgreSQL server per test process (worker), each test its own database."""

from __future__ import annotations

import pytest

from tests.historian.pg import PgServer


@pytest.fixture(scope="session")
def pg_server():
    server = PgServer()
    yield server
    server.remove()


@pytest.fixture
def pg_db(pg_server, tmp_path):
    """(server, database name, passfile): a fresh database owned by the historian's role."""
    return pg_server, pg_server.new_database(), pg_server.passfile(tmp_path)
