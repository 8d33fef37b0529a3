"""The local control socket's protocol and client: a Unix socket in the daemon's state directory.

Protocol (kept as it is; docs/interlock.md): one connection per request; the client sends one JSON line
`{"command": "reset" | "test-trip" | "status" | "limits" | "afc", "args": {...}}` and gets one JSON line
back. The server is the live daemon's (`daemon/runtime/local_control.py`); the clients are the commands
at the machine (`millsense reset`, `test-trip`, `limits`, `afc`: publish/operator_command.py) and the benches.
"""

from __future__ import annotations

import json
import os
import socket
import struct
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

SOCKET_NAME = "control.sock"
COMMANDS = ("reset", "test-trip", "status", "limits", "afc")
MAX_REQUEST_BYTES = 4096
READ_DEADLINE_S = 2.0    # the whole request, from the connection
DENIED_READ_S = 0.25     # ... from a uid that may not command: read only to name its command in the audit log
SOCKET_MODE = 0o660
# How long a local client waits for the daemon's answer. An edge box can be loaded (a slicer, a
# backup, another daemon): a daemon that is running answers, only later, and an operator at the
# machine would rather wait than be told to try again. What cannot be answered in this long is a
# daemon that is hung, and the error says so.
CLIENT_TIMEOUT_S = 30.0
UNIX_PATH_MAX = 107      # bytes of a Unix socket's address (AF_UNIX `sun_path`, its NUL aside)


class LocalControlError(Exception):
    """The local command could not be asked or answered (no daemon, no permission, a bad reply)."""


def socket_path(state_dir: Path) -> Path:
    return Path(state_dir) / SOCKET_NAME


@contextmanager
def unix_address(path: Path) -> Iterator[str]:
    """The address to bind or connect the socket at `path` by: the path itself when it fits in a Unix socket's
    107 bytes; else (Linux) through its folder's file descriptor, `/proc/self/fd/N/control.sock`, so that a deep
    `state_dir` does not leave the daemon without its local control (the folder held open while it is used)."""
    if len(os.fsencode(str(path))) <= UNIX_PATH_MAX or not hasattr(os, "O_PATH") or not os.path.isdir("/proc/self/fd"):
        yield str(path)
        return
    fd = os.open(path.parent, os.O_PATH | os.O_DIRECTORY)
    try:
        yield f"/proc/self/fd/{fd}/{path.name}"
    finally:
        os.close(fd)


# -- client ----------------------------------------------------------------------
def local_command(state_dir: Path, command: str, timeout_s: float = CLIENT_TIMEOUT_S,
                  args: dict[str, Any] | None = None) -> dict[str, Any]:
    """Ask the daemon whose state directory is `state_dir`; its JSON reply. `args`: for `limits`, `afc`.

    Raises `LocalControlError` with a sentence for the user when no daemon
    listens there, the socket is not ours to use, or nothing came back in time.
    """
    path = socket_path(state_dir)
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    sock.settimeout(timeout_s)
    try:
        try:
            with unix_address(path) as address:
                sock.connect(address)
        except FileNotFoundError:
            raise LocalControlError(f"no daemon's control socket at {path} (is millsense running for this machine?)") from None
        except PermissionError:
            raise LocalControlError(f"not allowed to use {path}: run as root or as the daemon's user") from None
        except ConnectionRefusedError:
            raise LocalControlError(f"no daemon listens on {path} (a socket left by a stopped daemon?)") from None
        except OSError as exc:
            raise LocalControlError(f"cannot connect to {path}: {exc}") from None
        try:
            request: dict[str, Any] = {"command": command} if args is None else {"command": command, "args": args}
            sock.sendall((json.dumps(request) + "\n").encode())
            data = read_line(sock)
        except socket.timeout:
            raise LocalControlError(
                f"the daemon at {path} accepted the request but did not answer within {timeout_s:g} s: "
                "it is running but hung or starved of CPU (see its log; a longer --timeout waits more)"
            ) from None
        except OSError as exc:
            raise LocalControlError(f"the daemon closed the connection: {exc}") from None
    finally:
        sock.close()
    if not data:
        raise LocalControlError("the daemon closed the connection without an answer")
    try:
        reply = json.loads(data.decode("utf-8"))
    except (UnicodeDecodeError, ValueError):
        raise LocalControlError("the daemon's answer is not JSON") from None
    if not isinstance(reply, dict):
        raise LocalControlError("the daemon's answer is not a JSON object")
    return reply


def read_line(sock: socket.socket, deadline_s: float | None = None) -> bytes:
    """One line; with `deadline_s`, all of it within that many seconds from now (socket.timeout if not)."""
    end = None if deadline_s is None else time.monotonic() + deadline_s
    buf = b""
    while b"\n" not in buf and len(buf) <= MAX_REQUEST_BYTES * 64:
        if end is not None:
            left = end - time.monotonic()
            if left <= 0:
                raise socket.timeout("no complete request in time")
            sock.settimeout(left)
        chunk = sock.recv(65536)
        if not chunk:
            break
        buf += chunk
    return buf.split(b"\n", 1)[0]


def peer_credentials(conn: socket.socket) -> tuple[int, int, int]:
    """(pid, uid, gid) of the process at the other end (Linux SO_PEERCRED)."""
    raw = conn.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, struct.calcsize("3i"))
    pid, uid, gid = struct.unpack("3i", raw)
    return pid, uid, gid


def command_of(line: bytes) -> tuple[str | None, Any]:
    """(command, args) of a request line; (None, None) for anything else."""
    try:
        obj = json.loads(line.decode("utf-8"))
    except (UnicodeDecodeError, ValueError):
        return None, None
    command = obj.get("command") if isinstance(obj, dict) else None
    if command not in COMMANDS:
        return None, None
    return command, obj.get("args")
