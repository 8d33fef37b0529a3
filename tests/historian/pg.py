"""A real PostgreSQL for the historian's tests: Debian's `postgresql` package, a throw-away cluster.

PostgreSQL refuses to run as root (CI runs as root): the cluster is made and run by the `postgres` OS user the
package creates (`runuser`), or by the user running the tests when that is not root. Its folder is made with
mkdtemp under the system's temp folder, not under pytest's tmp_path: pytest's folders are the test user's own
(mode 0700), which the postgres user cannot enter; the folder is removed when the server stops. It listens on
127.0.0.1 at a port from `free_tcp_port()` (no Unix socket in a shared place), fsync off (a test's data need not
survive a power cut, only the server's death). The superuser is reached without a password from this host's loopback only as `postgres`;
the role the historian uses, `historian`, needs its password (scram-sha-256), which the tests write into a libpq
passfile as the historian's users must.

The binaries missing: under CI=true the tests fail (`.ci/run` installs the package); elsewhere too, saying what
to install (no skip: the historian's claims are about a real server).
"""

from __future__ import annotations

import atexit
import os
import secrets
import shutil
import subprocess
import tempfile
from pathlib import Path

import psycopg

from tests.conftest import free_tcp_port

HISTORIAN_ROLE = "historian"


def pg_bin() -> Path:
    root = Path("/usr/lib/postgresql")
    versions = sorted((p for p in root.glob("*/bin/initdb")), key=lambda p: int(p.parts[-3]) if p.parts[-3].isdigit() else 0)
    if not versions:
        raise AssertionError("PostgreSQL's server is not installed (/usr/lib/postgresql/<v>/bin/initdb): "
                             "apt-get install postgresql (.ci/run does)")
    return versions[-1].parent


class PgServer:
    def __init__(self) -> None:
        self.bin = pg_bin()
        self.as_root = os.geteuid() == 0
        self.folder = Path(tempfile.mkdtemp(prefix="millsense-pg-"))
        self.data = self.folder / "data"
        self.port = free_tcp_port()
        self.password = secrets.token_urlsafe(18)
        if self.as_root:
            shutil.chown(self.folder, "postgres", "postgres")
        self.folder.chmod(0o700)
        pwfile = self.folder / "pw"
        pwfile.write_text(self.password + "\n")
        if self.as_root:
            shutil.chown(pwfile, "postgres", "postgres")
        self._run("initdb", "-D", str(self.data), "-U", "postgres", "--auth-local=trust", "--auth-host=trust",
                  "--no-sync", "-E", "UTF8", "--locale=C")
        pwfile.unlink()
        # the superuser from loopback without a password (the fixtures); every other role with its password
        (self.data / "pg_hba.conf").write_text(
            "host all postgres 127.0.0.1/32 trust\nhost all all 127.0.0.1/32 scram-sha-256\n")
        self.start()
        atexit.register(self.remove)   # a worker that dies without its fixture's teardown leaves no server behind
        with self.admin() as conn:
            conn.execute(f"CREATE ROLE {HISTORIAN_ROLE} LOGIN PASSWORD '{self.password}'")

    def _run(self, tool: str, *args: str) -> None:
        cmd = [str(self.bin / tool), *args]
        if self.as_root:
            cmd = ["runuser", "-u", "postgres", "--", *cmd]
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=120, cwd=self.folder)
        assert done.returncode == 0, f"{tool} failed ({done.returncode}): {done.stdout}\n{done.stderr}"

    def start(self) -> None:
        self._run("pg_ctl", "start", "-w", "-D", str(self.data), "-l", str(self.folder / "log"), "-o",
                  f"-p {self.port} -c listen_addresses=127.0.0.1 -c unix_socket_directories='' -c fsync=off "
                  "-c full_page_writes=off -c max_connections=40")
        # fsync off, never synchronous_commit off: a commit must be in the WAL (the OS's cache is enough) before
        # the client hears of it, or a server killed mid-run (test_live.py) loses transactions it acknowledged

    def stop(self, mode: str = "fast") -> None:
        self._run("pg_ctl", "stop", "-w", "-D", str(self.data), "-m", mode)

    def remove(self) -> None:
        if not self.folder.exists():
            return
        if (self.data / "postmaster.pid").exists():
            try:
                self.stop("immediate")
            except (AssertionError, OSError, subprocess.SubprocessError):
                pass
        shutil.rmtree(self.folder, ignore_errors=True)

    def admin(self, dbname: str = "postgres") -> psycopg.Connection:
        return psycopg.connect(host="127.0.0.1", port=self.port, user="postgres", dbname=dbname, autocommit=True)

    def new_database(self) -> str:
        name = f"t_{secrets.token_hex(6)}"
        with self.admin() as conn:
            conn.execute(f"CREATE DATABASE {name} OWNER {HISTORIAN_ROLE}")
        return name

    def dsn(self, dbname: str) -> str:
        """The historian's DSN: no password in it (the passfile holds it)."""
        return f"host=127.0.0.1 port={self.port} dbname={dbname} user={HISTORIAN_ROLE}"

    def passfile(self, folder: Path) -> Path:
        path = folder / "pgpass"
        path.write_text(f"127.0.0.1:{self.port}:*:{HISTORIAN_ROLE}:{self.password}\n")
        path.chmod(0o600)
        return path
