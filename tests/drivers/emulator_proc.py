"""Run `millsense sim` as a real subprocess for the tests; always killed in the end."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

SIM_CMD = [sys.executable, "-m", "millsense.daemon", "sim"]
# the ramp as daq-protocol contract tests define it: channel c of sample k is (k + 1000 c) mod 2^16
RAMP_CHANNELS = 8


def ramp(first_index: int, n: int) -> np.ndarray:
    k = (first_index + np.arange(n, dtype=np.int64))[:, None] + 1000 * np.arange(RAMP_CHANNELS)
    return (k % 65536).astype(np.uint16).view(np.int16)


class Emulator:
    """`millsense sim --scenario ramp ...` in a subprocess; a context manager."""

    def __init__(self, tmp_path: Path, *args: str, name: str = "sim") -> None:
        self.tmp_path = tmp_path
        self.status_log = tmp_path / f"{name}-status.jsonl"
        self.stderr_path = tmp_path / f"{name}-stderr.txt"
        self.args = ["--scenario", "ramp", "--status-log", str(self.status_log), *args]
        self.proc: subprocess.Popen | None = None
        self._log: list[dict] = []
        self._log_offset = 0

    def start(self, timeout_s: float = 20.0) -> Emulator:
        self._err = open(self.stderr_path, "w")  # noqa: SIM115 - closed in stop()
        self.proc = subprocess.Popen([*SIM_CMD, *self.args], stdout=subprocess.DEVNULL, stderr=self._err)
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if "serving" in self.stderr_path.read_text():
                return self
            if self.proc.poll() is not None:
                raise RuntimeError(f"emulator exited {self.proc.returncode}: {self.stderr_path.read_text()}")
            time.sleep(0.05)
        raise TimeoutError(f"emulator not ready: {self.stderr_path.read_text()}")

    def kill(self) -> None:
        """Pull the plug: SIGKILL, no goodbye."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(5)

    def stop(self) -> int | None:
        if self.proc is None:
            return None
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        self._err.close()
        return self.proc.returncode

    def events(self, kind: str | None = None) -> list[dict]:
        """What the device logged so far, in its order. Read on from where the last call stopped (a test
        that waits on the device's events calls this every few ms; the log only grows, opened to append)."""
        if self.status_log.exists():
            with open(self.status_log, "rb") as fh:
                fh.seek(self._log_offset)
                data = fh.read()
            end = data.rfind(b"\n") + 1  # a line being written right now is taken next time
            for line in data[:end].splitlines():
                try:
                    self._log.append(json.loads(line))
                except json.JSONDecodeError:
                    continue
            self._log_offset += end
        return [rec for rec in self._log if kind is None or rec["event"] == kind]

    def __enter__(self) -> Emulator:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()


def rss_kb(pid: int | None = None) -> int:
    with open(f"/proc/{pid or os.getpid()}/status") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    return 0
