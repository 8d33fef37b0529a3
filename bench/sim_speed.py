"""How fast the plant simulator runs, wall clock and CPU reported apart.

* capture (`write_capture`, as fast as it goes): simulated seconds per wall-clock
  second ("× real time", what a user waits), and the CPU it used over that wall
  time (% of one core; below 100 % the rest is I/O or waiting).
* paced at 1 kHz in 10-sample steps on the monotonic clock, as the emulator serves:
  the CPU share of one core that keeping up costs, and whether it kept up (the
  worst lag behind the schedule).

Run: .venv/bin/python bench/sim_speed.py [scenario ...]
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

from millsense.sim import Plant, write_capture

RATE_HZ = 1000
STEP = 10


def capture_speed(name: str) -> tuple[float, float]:
    """(simulated s per wall s, CPU s per wall s) of writing the scenario's capture."""
    with tempfile.TemporaryDirectory() as tmp:
        w0, c0 = time.perf_counter(), time.process_time()
        n = write_capture(name, Path(tmp) / "c.bin", Path(tmp) / "t.jsonl")
        wall, cpu = time.perf_counter() - w0, time.process_time() - c0
    return n / RATE_HZ / wall, cpu / wall


def paced_cpu_share(name: str, seconds: float = 5.0) -> tuple[float, float]:
    """(CPU s per wall s, worst lag behind the 1 kHz schedule in s) stepping 10 samples every 10 ms."""
    plant = Plant(name, loop=True)
    period = STEP / RATE_HZ
    start = time.monotonic()
    c0 = time.process_time()
    worst = 0.0
    for k in range(int(seconds * RATE_HZ / STEP)):
        due = start + (k + 1) * period          # the batch's samples are all due by then
        now = time.monotonic()
        if now < due:
            time.sleep(due - now)
        else:
            worst = max(worst, now - due)
        plant.step(STEP)
    wall = time.monotonic() - start
    return (time.process_time() - c0) / wall, worst


def main(names: list[str]) -> None:
    names = names or ["step", "step-1800", "fig6", "aircut-high"]
    print(f"{'scenario':<14} {'capture: x real time (wall)':>28} {'CPU over it':>12} "
          f"{'paced 1 kHz: CPU of one core':>29} {'worst lag':>10}")
    for name in names:
        speed, cpu_share = capture_speed(name)
        paced, lag = paced_cpu_share(name)
        print(f"{name:<14} {speed:>27.1f}x {100 * cpu_share:>11.0f}% {100 * paced:>28.1f}% {lag * 1e3:>8.1f} ms")


if __name__ == "__main__":
    main(sys.argv[1:])
