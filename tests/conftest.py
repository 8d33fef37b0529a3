"""Fixtures shared by every test folder."""

from __future__ import annotations

import random
import socket
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"


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


def free_tcp_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on right now, below the ephemeral range.

    A test picks its ports before it starts the processes that listen on them. A port from the
    ephemeral range (what binding port 0 gives) can meanwhile become the local port of an outgoing
    connection (the daemon's, Zenoh's, the emulator's clients'): the listener then fails with
    "Address already in use" (seen in CI). Ports below that range are never given to outgoing
    connections, and none is handed out twice in one run.
    """
    lo, _ = ephemeral_range()
    top = lo - 1 if lo - 1 > LOWEST_PORT + 1000 else 0
    for _ in range(200 if top else 0):
        port = random.randrange(LOWEST_PORT, top)
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
