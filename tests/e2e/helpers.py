"""Real processes for the end-to-end tests: the emulator, the daemon, a Zenoh subscriber.

Every process is started through `Procs`, which kills whatever is still
running when the test ends (pass or fail); every wait has a deadline.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import zenoh

from tests.estimator import configs

CMD = [sys.executable, "-m", "millsense.daemon"]

# The simulated DAQ's sensors and machine (docs/architecture.md, "drivers.sim"): one copy, in
# tests/estimator/configs.py.
SIM_CHANNELS = configs.SIM_CHANNELS + configs.ENCODER

SIM_MACHINE = """
[motor]
winding = "delta"
stator_resistance_ohm = 0.349
pole_pairs = 2
""" + configs.GEARS + """
[tool]
diameter_mm = 20.0
flutes = 2
cf = 1.075
"""


def tcp(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


def write_config(
    path: Path,
    *,
    machine: str,
    daq: str,
    zenoh_listen: list[str] | None = None,
    zenoh_connect: list[str] | None = None,
    zenoh_mode: str = "peer",
    alarms: str = "",
    interlock: str = "",
    extra: str = "",
) -> Path:
    """A daemon config for the simulated machine; `daq`, `alarms`, `interlock` are TOML bodies."""
    text = f'machine = "{machine}"\n{extra}\n[daq]\n{daq}\nfilter_cutoff_hz = 200\nfilter_order = 2\n'
    text += SIM_CHANNELS + SIM_MACHINE
    if alarms:
        text += f"\n[alarms]\n{alarms}\n"
    if "reset" not in interlock:
        # These daemons run on loopback with no listen endpoint (Zenoh's default: every interface), where
        # reset would default to "token"; the tests that mean a policy say it.
        interlock = f'{interlock}\nreset = "open"'.strip()
    text += f"\n[interlock]\n{interlock}\n"
    text += (
        f'\n[zenoh]\nmode = "{zenoh_mode}"\nlisten = {json.dumps(zenoh_listen or [])}\n'
        f"connect = {json.dumps(zenoh_connect or [])}\nmulticast_scouting = false\n"
        '\n[log]\nlevel = "info"\nformat = "json"\n'
    )
    path.write_text(text)
    return path


def wait_for(predicate: Callable[[], Any], timeout_s: float, what: str, step_s: float = 0.02) -> Any:
    deadline = time.monotonic() + timeout_s
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s} s: {what}")
        time.sleep(step_s)


class Procs:
    """Subprocesses of one test; `kill_all()` in a finally (or use as a context manager)."""

    def __init__(self, tmp: Path):
        self.tmp = tmp
        self.procs: list[subprocess.Popen] = []

    def start(self, name: str, args: list[str], env_extra: dict[str, str] | None = None, **kw: Any) -> subprocess.Popen:
        out = open(self.tmp / f"{name}.out", "wb")  # noqa: SIM115 - closed with the process
        err = open(self.tmp / f"{name}.err", "wb")  # noqa: SIM115
        env = {**os.environ, "PYTHONUNBUFFERED": "1", **(env_extra or {})}
        # A daemon keeps its latch in its state directory: one started from a bench (tests set their own
        # in conftest) must not leave a held feed in the user's ~/.local/state for the next run.
        env.setdefault("XDG_STATE_HOME", str(self.tmp / "state"))
        p = subprocess.Popen(CMD + args, stdout=out, stderr=err, env=env, **kw)
        p.name = name  # type: ignore[attr-defined]
        self.procs.append(p)
        return p

    def text(self, name: str, stream: str = "err") -> str:
        try:
            return (self.tmp / f"{name}.{stream}").read_text(errors="replace")
        except OSError:
            return ""

    def kill_all(self) -> None:
        for p in self.procs:
            if p.poll() is None:
                try:
                    os.kill(p.pid, signal.SIGCONT)  # a stopped process cannot die of SIGKILL until continued on some kernels
                except OSError:
                    pass
                p.kill()
        for p in self.procs:
            try:
                p.wait(5)
            except subprocess.TimeoutExpired:
                pass

    def __enter__(self) -> Procs:
        return self

    def __exit__(self, *exc: object) -> None:
        self.kill_all()


class Subscriber:
    """A Zenoh peer in the test, connected to the daemon over loopback TCP, scouting off."""

    def __init__(self, connect: list[str], machine: str = "*", mode: str = "peer", read: bool = True,
                 listen: list[str] | None = None):
        """`listen`: endpoints the daemon connects to instead (its `[zenoh] connect`): the subscriptions are
        declared before the daemon starts, so it is seen from the daemon's first publication on."""
        conf = zenoh.Config()
        conf.insert_json5("mode", json.dumps(mode))
        conf.insert_json5("connect/endpoints", json.dumps(connect))
        if listen:
            conf.insert_json5("listen/endpoints", json.dumps(listen))
        conf.insert_json5("scouting/multicast/enabled", "false")
        self.session = zenoh.open(conf)
        self.lock = threading.Lock()
        self.items: dict[str, list[tuple[float, dict]]] = {"estimate": [], "alarm": [], "status": [], "process": []}
        self.alive: list[tuple[float, str]] = []
        self._subs = []
        if read:
            for kind in self.items:
                self._subs.append(self.session.declare_subscriber(f"millsense/{machine}/{kind}", self._cb(kind)))
        self._subs.append(
            self.session.liveliness().declare_subscriber(f"millsense/{machine}/alive", self._alive_cb, history=True)
        )

    def _cb(self, kind: str) -> Callable[[Any], None]:
        def cb(sample: Any) -> None:
            payload = json.loads(sample.payload.to_bytes())
            with self.lock:
                self.items[kind].append((time.monotonic(), payload))

        return cb

    def _alive_cb(self, sample: Any) -> None:
        with self.lock:
            self.alive.append((time.monotonic(), str(sample.kind)))

    def get(self, kind: str) -> list[dict]:
        with self.lock:
            return [p for _, p in self.items[kind]]

    def timed(self, kind: str) -> list[tuple[float, dict]]:
        with self.lock:
            return list(self.items[kind])

    def query(self, key: str, payload: bytes | None = None, timeout: float = 3.0) -> list[dict]:
        out = []
        for reply in self.session.get(key, payload=payload, timeout=timeout):
            if reply.ok is not None:
                out.append(json.loads(reply.ok.payload.to_bytes()))
            else:
                out.append({"error": json.loads(reply.err.payload.to_bytes())})
        return out

    def close(self) -> None:
        for s in self._subs:
            try:
                s.undeclare()
            except Exception:  # noqa: BLE001
                pass
        self.session.close()


def read_jsonl(path: Path) -> list[dict]:
    out = []
    try:
        text = path.read_text()
    except OSError:
        return out
    for line in text.splitlines():
        line = line.strip()
        if line:
            try:
                out.append(json.loads(line))
            except ValueError:
                pass  # a line being written right now
    return out


class NotifyListener:
    """A fake systemd: a datagram socket at `path` that keeps (monotonic time, message)."""

    def __init__(self, path: Path):
        import socket

        self.path = path
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(str(path))
        self.sock.settimeout(0.2)
        self.messages: list[tuple[float, str]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                data = self.sock.recv(4096)
            except OSError:
                continue
            self.messages.append((time.monotonic(), data.decode("utf-8", "replace")))

    def times(self, line: str) -> list[float]:
        return [t for t, m in list(self.messages) if line in m.split("\n")]

    def close(self) -> None:
        self._stop.set()
        self._thread.join(1.0)
        self.sock.close()

