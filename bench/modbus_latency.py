"""Modbus TCP read latency: p50/p99 of a 125-register ring read from `millsense sim --modbus-tcp`.

Starts the emulator (ramp, real time) as a subprocess on a free loopback port and
times N synchronous reads of 125 input registers with the pymodbus client.
Run: python bench/modbus_latency.py [N]
"""

from __future__ import annotations

import socket
import subprocess
import sys
import time

import numpy as np
from pymodbus.client import ModbusTcpClient


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def main(n: int = 3000) -> None:
    port = free_port()
    cmd = [sys.executable, "-m", "millsense.daemon", "sim", "--scenario", "ramp", "--modbus-tcp", f"127.0.0.1:{port}"]
    proc = subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True)
    try:
        proc.stderr.readline()  # "serving ..." once listening
        client = ModbusTcpClient("127.0.0.1", port=port, timeout=2)
        if not client.connect():
            raise SystemExit("cannot connect to the emulator")
        times = np.empty(n)
        for i in range(n):
            t0 = time.perf_counter()
            rr = client.read_input_registers(1000 + (i % 200) * 8, count=125, device_id=1)
            times[i] = time.perf_counter() - t0
            if rr.isError():
                raise SystemExit(f"read failed: {rr}")
        client.close()
        p50, p99 = np.percentile(times, [50, 99]) * 1e3
        print(
            f"modbus-tcp 125-register read: p50 {p50:.3f} ms, p99 {p99:.3f} ms, "
            f"{n / times.sum():.0f} reads/s ({n} reads)"
        )
    finally:
        proc.terminate()
        proc.wait(5)


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 3000)
