"""The local control socket works in a state directory of any length.

A Unix socket's address holds at most 107 bytes (AF_UNIX's `sun_path`): a state directory deep enough
(`[daemon] state_dir` on a long mount path, or a test worker's tmp folder) made the bind fail with
"AF_UNIX path too long", the daemon `degraded` and `millsense reset --local` unable to reach it. The
socket is now bound and reached through the directory's file descriptor (`/proc/self/fd/N/control.sock`).
"""

from __future__ import annotations

import os
import types
from pathlib import Path

import pytest

from millsense.daemon.local_socket import local_command, socket_path
from millsense.daemon.runtime.local_control import LocalControl

pytestmark = pytest.mark.quick


def _controls():
    audit = types.SimpleNamespace(record=lambda *a, **k: None)
    return types.SimpleNamespace(audit=audit, status=lambda: {"state": "running", "interlock": "armed"})


def test_a_state_directory_longer_than_a_unix_socket_address(tmp_path):
    deep = tmp_path / ("a-long-state-directory-name-" * 3) / "millsense" / ("machine-" * 6)
    assert len(os.fsencode(socket_path(deep))) > 108
    errors: list[tuple[str, str]] = []
    local = LocalControl(deep, _controls(), on_error=lambda kind, reason: errors.append((kind, reason)))
    try:
        assert local.start(), errors
        assert socket_path(deep).is_socket()
        reply = local_command(deep, "status")
        assert reply == {"ok": True, "state": "running", "interlock": "armed"}
    finally:
        local.close()
    assert not socket_path(deep).exists()


def test_a_short_one_as_before(tmp_path):
    short = Path(tmp_path)
    local = LocalControl(short, _controls())
    try:
        assert local.start()
        assert local_command(short, "status")["ok"] is True
    finally:
        local.close()


def test_the_socket_appears_only_once_it_listens(tmp_path, monkeypatch):
    """A client that finds `control.sock` can connect: the daemon does not show it between bind and listen (a test
    that waited for the file was refused once under load). The wait between them is stretched here (a patched
    `listen`: the one way to widen a window of microseconds); a watcher connects the moment the file shows."""
    import socket
    import threading
    import time

    seen: list[str] = []
    stop = threading.Event()

    def watch() -> None:
        path = socket_path(tmp_path)
        while not stop.is_set():
            if path.exists():
                c = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
                try:
                    c.connect(str(path))
                    seen.append("connected")
                except OSError as exc:
                    seen.append(f"refused: {exc}")
                finally:
                    c.close()
                return
            time.sleep(0.001)

    real_listen = socket.socket.listen

    def slow_listen(self, *args):
        time.sleep(0.3)
        return real_listen(self, *args)

    monkeypatch.setattr(socket.socket, "listen", slow_listen)
    watcher = threading.Thread(target=watch)
    watcher.start()
    local = LocalControl(tmp_path, _controls())
    try:
        assert local.start()
        watcher.join(5.0)
    finally:
        stop.set()
        local.close()
    assert seen == ["connected"], seen
