"""The daemon's state directory: where it is, made, and claimed by one daemon (`daemon.lock`).

Shared by the live daemon (its latch, history, control socket) and the commands that find a
running daemon from a shell (`reset`, `test-trip`, `afc`, `limits`, `history`, `commission`).

`state_dir(machine)`: `$STATE_DIRECTORY` (systemd's StateDirectory; the first
entry when several are given, colon-separated), else
`${XDG_STATE_HOME:-~/.local/state}/millsense/<machine>`.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

def state_dir(machine: str, env: dict[str, str] | None = None) -> Path:
    """The daemon's state directory (not created here)."""
    e = os.environ if env is None else env
    systemd = (e.get("STATE_DIRECTORY") or "").split(":")[0].strip()
    if systemd:
        return Path(systemd)
    base = (e.get("XDG_STATE_HOME") or "").strip()
    root = Path(base) if base else Path(e.get("HOME") or Path.home()) / ".local" / "state"
    return root / "millsense" / machine


SYSTEMD_STATE_ROOT = Path("/var/lib/millsense")  # the unit's StateDirectory=millsense/%i


def daemon_state_dir(machine: str, env: dict[str, str] | None = None, systemd_root: Path = SYSTEMD_STATE_ROOT) -> Path:
    """Where a *client* at the machine finds a daemon's state (its control socket).

    A shell has no STATE_DIRECTORY: a daemon run by the unit keeps its state in
    /var/lib/millsense/<machine>, one run by hand in the user's state directory.
    The unit's place is taken when a daemon's socket is there.
    """
    e = os.environ if env is None else env
    if (e.get("STATE_DIRECTORY") or "").strip():
        return state_dir(machine, e)
    unit_dir = systemd_root / machine
    if (unit_dir / "control.sock").exists():
        return unit_dir
    return state_dir(machine, e)


def ensure_dir(directory: Path) -> None:
    """Create the state directory (owner and group may enter: the control socket is group-accessible)."""
    directory.mkdir(parents=True, exist_ok=True, mode=0o750)


LOCK_FILE = "daemon.lock"


def claim_state_dir(directory: Path) -> tuple[Any, str | None]:
    """One daemon per state directory: (the held lock file, None), or (None, why not). A second daemon for the
    same machine would take over the control socket, write the same latch and history, and answer for the
    first. The lock (`flock` on `daemon.lock`, holding the pid) goes with the process, however it ends. A
    directory that cannot be made or written is (None, None): the daemon runs on and its fault says why."""
    import fcntl

    try:
        ensure_dir(directory)
        handle = open(directory / LOCK_FILE, "a+")   # noqa: SIM115 - held for the daemon's life
    except OSError:
        return None, None
    try:
        fcntl.flock(handle.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        handle.seek(0)
        pid = handle.read().strip() or "?"
        handle.close()
        return None, (f"another millsense daemon (pid {pid}) runs with the state directory {directory}: one daemon a "
                      f"machine (stop that one first, or give this configuration its own `machine`)")
    try:
        handle.seek(0)
        handle.truncate()
        handle.write(f"{os.getpid()}\n")
        handle.flush()
    except OSError:
        pass   # the lock holds all the same; only the pid for the message is missing
    return handle, None
