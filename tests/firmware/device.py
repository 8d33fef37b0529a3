"""The firmware's host build as a subprocess, and a raw TCP link to it (the tests' side of the wire)."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
from collections.abc import Callable
from pathlib import Path
from typing import Any

from tests.e2e.helpers import wait_for
from tests.firmware.frames import Decoder, Frame


class Firmware:
    """`msfw-host` serving a capture; its JSON-lines log is the device's own record of what it did."""

    def __init__(self, binary: Path, tmp_path: Path, capture: Path, port: int, *args: str, name: str = "fw",
                 transport: str = "--tcp", address: str | None = None) -> None:
        """Serves on 127.0.0.1:`port` (`--tcp`, `--modbus-tcp`), or at `address` (a pty link)."""
        self.log_path = tmp_path / f"{name}.jsonl"
        self.err_path = tmp_path / f"{name}.err"
        self.port = port
        where = address if address is not None else f"127.0.0.1:{port}"
        self.cmd = [str(binary), "--capture", str(capture), transport, where, "--log", str(self.log_path), *args]
        self.proc: subprocess.Popen | None = None

    def __enter__(self) -> Firmware:
        self._err = open(self.err_path, "w")  # noqa: SIM115 - closed in __exit__
        env = {**os.environ, "ASAN_OPTIONS": "abort_on_error=0:exitcode=86",
               "UBSAN_OPTIONS": "print_stacktrace=1:halt_on_error=1:exitcode=87"}
        self.proc = subprocess.Popen(self.cmd, stdout=subprocess.DEVNULL, stderr=self._err, env=env)
        wait_for(lambda: "serving" in self.stderr() or self.proc.poll() is not None, 20.0, "firmware serving")
        assert self.proc.poll() is None, self.stderr()
        return self

    def __exit__(self, *exc: object) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(5)
        self._err.close()

    def stop(self) -> int:
        """SIGTERM, and the exit code: 0, or a sanitizer's report made it fail (its text in stderr)."""
        assert self.proc is not None
        self.proc.send_signal(signal.SIGTERM)
        return self.proc.wait(10)

    def signal(self, sig: int) -> None:
        assert self.proc is not None
        self.proc.send_signal(sig)

    def stderr(self) -> str:
        try:
            return self.err_path.read_text(errors="replace")
        except OSError:
            return ""

    def events(self, kind: str | None = None) -> list[dict]:
        out = []
        try:
            text = self.log_path.read_text()
        except OSError:
            return out
        for line in text.splitlines():
            try:
                ev = json.loads(line)
            except ValueError:
                continue   # a line being written right now
            if kind is None or ev["event"] == kind:
                out.append(ev)
        return out

    def wait_event(self, kind: str, pred: Callable[[dict], bool] = lambda e: True, timeout_s: float = 20.0) -> dict:
        return wait_for(lambda: next((e for e in self.events(kind) if pred(e)), None), timeout_s,
                        f"firmware event {kind}; log tail: {self.events()[-5:]}")


class Link:
    """A host on the firmware's TCP port: sends command bytes, decodes what comes back (frames.py)."""

    def __init__(self, port: int, rcvbuf: int | None = None) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        if rcvbuf is not None:
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
        self.sock.connect(("127.0.0.1", port))
        self.sock.settimeout(0.05)
        self.decoder = Decoder()
        self.frames: list[Frame] = []

    def send(self, data: bytes) -> None:
        self.sock.sendall(data)

    def pump(self) -> None:
        try:
            data = self.sock.recv(65536)
        except (TimeoutError, socket.timeout):
            return
        if data:
            self.frames += self.decoder.feed(data)

    def wait(self, pred: Callable[[Frame], bool], timeout_s: float = 20.0, start: int = 0) -> Frame:
        def found() -> Frame | None:
            self.pump()
            return next((f for f in self.frames[start:] if pred(f)), None)

        return wait_for(found, timeout_s, "a frame from the firmware", step_s=0.0)

    def of_type(self, ftype: int) -> list[Frame]:
        return [f for f in self.frames if f.type == ftype]

    def close(self) -> None:
        self.sock.close()

