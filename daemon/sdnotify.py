"""sd_notify: a no-op outside systemd, a handful of lines inside it (as gunicorn/systemd.py).

systemd passes `$NOTIFY_SOCKET` to a `Type=notify` service: a datagram AF_UNIX
socket path, or an abstract-namespace name written with a leading `@` (sent as
a NUL byte). Each message is newline-separated `KEY=VALUE` lines.

When to send what (the daemon's side, `run`):
`READY=1` once the DAQ streams and Zenoh is open; `WATCHDOG=1` every
`watchdog_interval_s()` *only while the pipeline makes progress* (so a stalled
estimator is restarted by systemd); `STATUS=` the one-line health;
`STOPPING=1` on shutdown.

Sending never blocks and never raises: the socket is non-blocking, and a
full or vanished socket just makes `notify` return False.
"""

from __future__ import annotations

import os
import socket

__all__ = ["notify", "notify_socket_address", "watchdog_interval_s"]


def notify_socket_address(env: dict[str, str] | None = None) -> str | None:
    """The address to send to (abstract names with their leading NUL), or None outside systemd."""
    value = (os.environ if env is None else env).get("NOTIFY_SOCKET", "")
    if not value:
        return None
    if value.startswith("@"):
        return "\0" + value[1:]
    return value if value.startswith("/") else None  # systemd only ever gives absolute paths or @names


def notify(
    ready: bool = False,
    status: str | None = None,
    watchdog: bool = False,
    stopping: bool = False,
    *,
    extra: dict[str, str] | None = None,
) -> bool:
    """Send one notification with the given fields. True if a datagram was sent.

    A no-op returning False when `$NOTIFY_SOCKET` is not set (not under systemd)
    or nothing was asked. `status` is flattened to one line.
    """
    address = notify_socket_address()
    if address is None:
        return False
    lines = []
    if ready:
        lines.append("READY=1")
    if stopping:
        lines.append("STOPPING=1")
    if status is not None:
        lines.append("STATUS=" + " ".join(str(status).split()))
    if watchdog:
        lines.append("WATCHDOG=1")
    for key, value in (extra or {}).items():
        lines.append(f"{key}={' '.join(str(value).split())}")
    if not lines:
        return False
    message = ("\n".join(lines)).encode("utf-8", "replace")
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC) as sock:
            sock.setblocking(False)
            sock.sendto(message, address)
        return True
    except OSError:  # listener gone, queue full (EAGAIN), or a path we may not write
        return False


def watchdog_interval_s(env: dict[str, str] | None = None) -> float | None:
    """How often to send `WATCHDOG=1`: half of `$WATCHDOG_USEC`, in seconds; None if no watchdog.

    `$WATCHDOG_PID`, when set, must be this process (else the watchdog is a
    parent's, not ours).
    """
    e = os.environ if env is None else env
    try:
        usec = int(e.get("WATCHDOG_USEC", ""))
    except ValueError:
        return None
    if usec <= 0:
        return None
    pid = e.get("WATCHDOG_PID")
    if pid:
        try:
            if int(pid) != os.getpid():
                return None
        except ValueError:
            return None
    return usec / 2 / 1_000_000
