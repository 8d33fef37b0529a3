"""How late the reader hands a DAQ frame on, per stream transport (~8 s each).

The emulator (`millsense sim --scenario ramp --realtime`) sends sample k at
t0 + k/1000 in 10-sample frames; the real driver in this process reads them.
For each block, arrival time − k_last/1000 is the transport's delay plus a
constant; its minimum over the run is the best case, and how far each block
lies above it is the lateness the reader adds (waiting in a read timeout,
sleeping out a spacing). It adds directly to the sample-level crash trip.

Run: .venv/bin/python bench/reader_latency.py [seconds]
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from millsense.drivers import create_driver  # noqa: E402
from millsense.drivers.base import SampleBlock  # noqa: E402
from tests.conftest import free_tcp_port  # noqa: E402

SIM = [sys.executable, "-m", "millsense.daemon", "sim", "--scenario", "ramp", "--loop", "--realtime"]


def lateness_ms(transport: str, seconds: float) -> np.ndarray:
    with tempfile.TemporaryDirectory() as tmp:
        if transport == "serial":
            link = os.path.join(tmp, "link")
            serve, options = ["--pty", link], {"port": link}
        else:
            port = free_tcp_port()
            serve, options = ["--tcp", f"127.0.0.1:{port}"], {"host": "127.0.0.1", "tcp_port": port}
        emu = subprocess.Popen([*SIM, *serve], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            time.sleep(1.0)
            driver = create_driver(transport, **options)
            driver.start()
            if not driver.wait_connected(10.0):
                raise SystemExit(f"{transport}: no link to the emulator")
            rows = []
            end = time.monotonic() + seconds
            while time.monotonic() < end:
                ev = driver.get(0.1)
                if isinstance(ev, SampleBlock):
                    rows.append((time.monotonic(), ev.seq + len(ev.counts) - 1))
            driver.close()
        finally:
            emu.terminate()
            emu.wait(10)
    a = np.array(rows[50:], dtype=float)  # the first half second: connection, descriptor, backlog
    offset = a[:, 0] - a[:, 1] / 1000.0
    return (offset - offset.min()) * 1e3


def main() -> int:
    seconds = float(sys.argv[1]) if len(sys.argv) > 1 else 8.0
    print("reader lateness: block handed on − earliest possible, in ms")
    for transport in ("serial", "tcp"):
        late = lateness_ms(transport, seconds)
        p50, p99 = np.percentile(late, [50, 99])
        print(f"{transport:<7} p50 {p50:5.2f}  p99 {p99:5.2f}  max {late.max():5.2f}  ({len(late)} blocks)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
