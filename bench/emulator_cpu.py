"""CPU of the emulator and of the reader at 1 kHz real time, per transport (~10 s each per source).

The emulator runs as a subprocess driven by the plant simulator, as the tests and
the demo run it (`millsense sim --scenario step`: the plant computes every sample);
beside it, as a baseline, the same server fed the synthetic `ramp` (no plant: the
cost of serving alone). The emulator's CPU time comes from /proc/<pid>/stat
(utime + stime). The reader is the real driver in this process, its thread
consuming the queue; its CPU time is this process's `resource.getrusage` delta.
Both are printed as % of one core over the wall-clock time measured.
Run: python bench/emulator_cpu.py [seconds] [scenario]
"""

from __future__ import annotations

import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from millsense.drivers import create_driver  # noqa: E402
from millsense.drivers.base import SampleBlock  # noqa: E402
from tests.conftest import free_tcp_port as free_port  # noqa: E402
from tests.procstat import proc_cpu_s  # noqa: E402

def self_cpu_s() -> float:
    ru = resource.getrusage(resource.RUSAGE_SELF)
    return ru.ru_utime + ru.ru_stime


def measure(transport: str, seconds: float, scenario: str) -> None:
    tmp = tempfile.mkdtemp()
    port = free_port()
    if transport == "pty":
        link = os.path.join(tmp, "link")
        sim_args, make = ["--pty", link], lambda: create_driver("serial", port=link)
    elif transport == "tcp":
        sim_args, make = ["--tcp", f"127.0.0.1:{port}"], lambda: create_driver("tcp", host="127.0.0.1", tcp_port=port)
    elif transport == "modbus-rtu":
        link = os.path.join(tmp, "link")
        sim_args = ["--modbus-rtu", link]
        make = lambda: create_driver("modbus-rtu", port=link, poll_ms=20)  # noqa: E731
    else:
        sim_args = ["--modbus-tcp", f"127.0.0.1:{port}"]
        make = lambda: create_driver("modbus-tcp", host="127.0.0.1", tcp_port=port, poll_ms=20)  # noqa: E731
    cmd = [sys.executable, "-m", "millsense.daemon", "sim", "--scenario", scenario, "--loop", *sim_args]
    proc = subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True)
    driver = None
    try:
        proc.stderr.readline()
        driver = make()
        driver.start()
        if not driver.wait_connected(10):
            raise SystemExit(f"{transport}: driver did not connect")
        settle = time.monotonic() + 1.0
        while time.monotonic() < settle or driver.get(0) is not None:  # settle, then start with an empty queue
            driver.get(0.05)
        e0, r0, w0 = proc_cpu_s(proc.pid), self_cpu_s(), time.monotonic()
        n = 0
        while time.monotonic() - w0 < seconds:
            ev = driver.get(0.1)
            if isinstance(ev, SampleBlock):
                n += len(ev.counts)
        e1, r1, w1 = proc_cpu_s(proc.pid), self_cpu_s(), time.monotonic()
        wall = w1 - w0
        print(
            f"{transport:<10} {scenario:<8} emulator {100 * (e1 - e0) / wall:5.1f} %  reader {100 * (r1 - r0) / wall:5.1f} %  "
            f"of one core ({n / wall:.0f} samples/s over {wall:.1f} s)"
        )
    finally:
        if driver is not None:
            driver.close()
        proc.terminate()
        proc.wait(5)


if __name__ == "__main__":
    secs = float(sys.argv[1]) if len(sys.argv) > 1 else 10.0
    plant = sys.argv[2] if len(sys.argv) > 2 else "step"
    for t in ("pty", "tcp", "modbus-tcp", "modbus-rtu"):
        for source in (plant, "ramp"):      # the plant-driven emulator, then the ramp as the baseline
            measure(t, secs, source)
