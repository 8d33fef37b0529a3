"""sd_notify against a real AF_UNIX datagram listener (path and abstract namespace)."""

from __future__ import annotations

import os
import socket
import subprocess
import sys

import pytest

from millsense.daemon import sdnotify

pytestmark = pytest.mark.quick


@pytest.fixture
def listener(tmp_path, monkeypatch):
    path = tmp_path / "notify.sock"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(path))
    sock.settimeout(2.0)
    monkeypatch.setenv("NOTIFY_SOCKET", str(path))
    try:
        yield sock
    finally:
        sock.close()


def test_ready_status_watchdog_and_stopping(listener):
    assert sdnotify.notify(ready=True, status="running: 600 rpm\nsecond line")
    assert listener.recv(4096).decode() == "READY=1\nSTATUS=running: 600 rpm second line"
    assert sdnotify.notify(watchdog=True)
    assert listener.recv(4096) == b"WATCHDOG=1"
    assert sdnotify.notify(stopping=True, status="stopping")
    assert listener.recv(4096) == b"STOPPING=1\nSTATUS=stopping"


def test_nothing_asked_sends_nothing(listener):
    assert sdnotify.notify() is False
    listener.settimeout(0.1)
    with pytest.raises(TimeoutError):
        listener.recv(4096)


def test_abstract_namespace(monkeypatch):
    name = f"millsense-test-{os.getpid()}"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    try:
        sock.bind("\0" + name)
        sock.settimeout(2.0)
        monkeypatch.setenv("NOTIFY_SOCKET", "@" + name)
        assert sdnotify.notify(ready=True)
        assert sock.recv(4096) == b"READY=1"
    finally:
        sock.close()


def test_no_op_outside_systemd(monkeypatch):
    monkeypatch.delenv("NOTIFY_SOCKET", raising=False)
    assert sdnotify.notify(ready=True, status="x", watchdog=True) is False


def test_a_vanished_listener_is_not_an_error(tmp_path, monkeypatch):
    monkeypatch.setenv("NOTIFY_SOCKET", str(tmp_path / "gone.sock"))
    assert sdnotify.notify(ready=True) is False


def test_a_full_listener_never_blocks(listener):
    # nobody reads: the kernel queue fills, then sends fail at once instead of blocking
    results = [sdnotify.notify(status="x" * 1000) for _ in range(2000)]
    assert results[0] is True and results[-1] is False


def test_watchdog_interval_is_half_of_watchdog_usec():
    assert sdnotify.watchdog_interval_s({"WATCHDOG_USEC": "5000000"}) == 2.5
    assert sdnotify.watchdog_interval_s({"WATCHDOG_USEC": "5000000", "WATCHDOG_PID": str(os.getpid())}) == 2.5
    assert sdnotify.watchdog_interval_s({"WATCHDOG_USEC": "5000000", "WATCHDOG_PID": "1"}) is None
    assert sdnotify.watchdog_interval_s({}) is None
    assert sdnotify.watchdog_interval_s({"WATCHDOG_USEC": "soon"}) is None


def test_from_a_child_process_as_systemd_would_see_it(listener, tmp_path):
    """A separate process (like the daemon under systemd) reaching the listener through the environment."""
    code = "from millsense.daemon.sdnotify import notify; notify(ready=True, status='child')"
    env = {**os.environ, "NOTIFY_SOCKET": listener.getsockname()}
    subprocess.run([sys.executable, "-c", code], env=env, check=True, timeout=30)
    assert listener.recv(4096) == b"READY=1\nSTATUS=child"
