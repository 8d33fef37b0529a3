"""Fixtures shared by every test folder."""

from __future__ import annotations

import socket
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"


def free_tcp_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
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
