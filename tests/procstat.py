"""CPU time and memory of a running process, from /proc (Linux): for tests and bench/ alike."""

from __future__ import annotations

import os
from pathlib import Path

TICK_S = 1.0 / os.sysconf("SC_CLK_TCK")


def proc_cpu_s(pid: int) -> float:
    """User + system CPU seconds the process has used so far."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()  # the name may hold spaces
    return (int(fields[11]) + int(fields[12])) * TICK_S  # utime, stime


def proc_kb(pid: int, key: str = "VmRSS") -> int:
    """A `/proc/PID/status` figure in kB (VmRSS, VmHWM, ...), 0 if absent."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1])
    return 0
