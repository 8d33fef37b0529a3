"""How fast the plant simulator runs: capture generation (x real time) and the
CPU share of pacing it at 1 kHz in 10-sample steps, as the emulator does.

Run: .venv/bin/python bench/sim_speed.py [scenario ...]
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

from millsense.drivers.sim import Plant, write_capture


def capture_speed(name: str) -> float:
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.process_time()
        n = write_capture(name, Path(tmp) / "c.bin", Path(tmp) / "t.jsonl")
        cpu = time.process_time() - t0
    return n / 1000.0 / cpu


def paced_cpu_share(name: str, seconds: float = 5.0) -> float:
    """CPU seconds per simulated second when stepped 10 samples at a time (1.0 = one core)."""
    plant = Plant(name, loop=True)
    t0 = time.process_time()
    for _ in range(int(seconds * 100)):
        plant.step(10)
    return (time.process_time() - t0) / seconds


def main(names: list[str]) -> None:
    names = names or ["step", "step-1800", "fig6", "aircut-high"]
    print(f"{'scenario':<14} {'capture x real time':>20} {'1 kHz paced CPU':>16}")
    for name in names:
        speed = capture_speed(name)
        share = paced_cpu_share(name)
        print(f"{name:<14} {speed:>19.1f}x {100 * share:>15.1f}%")


if __name__ == "__main__":
    main(sys.argv[1:])
