"""Shared pieces of the history tests: payloads in brief14's shapes, waiting on events, reading a file."""

from __future__ import annotations

import sqlite3
import threading
import time
from pathlib import Path

T0 = 1_795_000_000.0  # a fixed epoch: rows are placed in time by their payload's `t`


def estimate(rev: int, t: float, *, tool: int | None = 12, program: int | None = 1234, operation: int | None = 3,
             torque_nm: float = 4.2) -> dict:
    return {"machine": "m1", "rev": rev, "t": t, "spindle_rpm": 600.0, "gear": "low", "p_in_w": 612.0,
            "torque_nm": torque_nm, "torque_sigma_nm": 0.05, "force_n": 450.0, "force_tangential_n": 420.0,
            "feed_per_tooth_mm": 0.1667, "radial_depth_mm": 20.0, "axial_depth_mm": 2.0, "depth_status": "ok",
            "cutting": True, "valid": True, "samples": 100, "lost_samples": 0, "program": program, "tool": tool,
            "operation": operation, "process_rev": rev, "envelope_low_nm": None, "envelope_high_nm": None}


def process(n: int, t: float, *, tool: int = 12, verdict: str = "good") -> dict:
    return {"machine": "m1", "t": t, "process": n, "key": f"1234/{tool}/3", "program": 1234, "tool": tool,
            "operation": 3, "revolutions": 80, "cutting_revolutions": 70, "entry_rev": 5, "torque_peak_nm": 6.0,
            "torque_mean_nm": 4.0, "force_peak_n": 600.0, "energy_j": 1759.3, "verdict": verdict, "learned": 5,
            "learn_target": 5, "envelope": "active", "energy_ratio": 1.01, "tool_processes": n, "tool_wear_pct": 1.0}


class Events:
    """on_error / on_ok callbacks that tests can wait on."""

    def __init__(self):
        self.errors: list[str] = []
        self.oks = 0
        self.failed = threading.Event()
        self.recovered = threading.Event()

    def on_error(self, reason: str) -> None:
        self.errors.append(reason)
        self.failed.set()

    def on_ok(self) -> None:
        self.oks += 1
        self.recovered.set()


def wait_until(predicate, timeout_s: float = 30.0, step_s: float = 0.02) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(step_s)
    return predicate()


def count(path: Path, table: str = "revolutions") -> int:
    conn = sqlite3.connect(f"file:{path}?mode=ro", uri=True, timeout=5)
    try:
        return conn.execute(f"SELECT COUNT(*) FROM {table}").fetchone()[0]
    finally:
        conn.close()


def integrity(path: Path) -> str:
    """`PRAGMA integrity_check`'s answer ("ok"), or what SQLite said when it could not even run it."""
    conn = sqlite3.connect(path, timeout=5)
    try:
        return "; ".join(row[0] for row in conn.execute("PRAGMA integrity_check"))
    except sqlite3.DatabaseError as exc:
        return f"{type(exc).__name__}: {exc}"
    finally:
        conn.close()
