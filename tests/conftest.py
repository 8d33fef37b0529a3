"""Fixtures shared by every test folder."""

from __future__ import annotations

import os
import random
import socket
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"

pytest_plugins = ["tests.parallel"]  # parallel workers, the serial phase, --cpu-report (tests/parallel.py)


# Ports handed out by `free_tcp_port` in this process: a test that asks for two gets two.
_HANDED_OUT: set[int] = set()
LOWEST_PORT = 10000


def ephemeral_range() -> tuple[int, int]:
    """The kernel's range for the local ports of outgoing connections (Linux; the usual default elsewhere)."""
    try:
        lo, hi = (int(x) for x in Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split())
        return lo, hi
    except (OSError, ValueError):
        return 32768, 60999


def worker_port_slice(lowest: int, top: int) -> tuple[int, int]:
    """This test process's own share of [lowest, top): the suite runs in parallel processes (pytest-xdist),
    and a port one worker picked but has not yet listened on must not be picked by another. Worker gwN of
    M takes the N-th of M equal slices; a run without xdist takes the whole range."""
    worker = os.environ.get("PYTEST_XDIST_WORKER", "")
    count = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1") or 1)
    if not worker.startswith("gw") or count <= 1:
        return lowest, top
    index = int(worker[2:])
    width = (top - lowest) // count
    return lowest + index * width, lowest + (index + 1) * width


def free_tcp_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on right now, below the ephemeral range.

    A test picks its ports before it starts the processes that listen on them. A port from the
    ephemeral range (what binding port 0 gives) can meanwhile become the local port of an outgoing
    connection (the daemon's, Zenoh's, the emulator's clients'): the listener then fails with
    "Address already in use" (seen in CI). Ports below that range are never given to outgoing
    connections, none is handed out twice in one process, and each parallel worker picks from its
    own slice (`worker_port_slice`): a port picked by one worker is never another's.
    """
    lo, _ = ephemeral_range()
    top = lo - 1 if lo - 1 > LOWEST_PORT + 1000 else 0
    first, stop = worker_port_slice(LOWEST_PORT, top) if top else (0, 0)
    for _ in range(200 if top else 0):
        port = random.randrange(first, stop)
        if port in _HANDED_OUT:
            continue
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
        _HANDED_OUT.add(port)
        return port
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:   # no room below the range: the kernel's pick
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def port() -> int:
    return free_tcp_port()


@pytest.fixture(scope="session")
def millsense_cmd() -> list[str]:
    """The CLI as a real subprocess: `[python, -m, millsense.daemon]`."""
    return [sys.executable, "-m", "millsense.daemon"]


@pytest.fixture(scope="session")
def repo() -> Path:
    return REPO


@pytest.fixture(autouse=True)
def _private_state_directory(tmp_path_factory, monkeypatch):
    """Daemons started by a test keep their state (latched interlock, audit log, control socket)
    in a directory of that test, never in the user's ~/.local/state: a latch left by one test
    would hold the feed of the next. A test that means a directory sets STATE_DIRECTORY itself."""
    monkeypatch.delenv("STATE_DIRECTORY", raising=False)
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path_factory.mktemp("state")))
