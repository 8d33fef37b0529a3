"""One process being watched: its revolutions, per-revolution arrays and alarms. Pure.

A process is the revolutions of one key while the CNC's `cycle` and `monitor`
flags are set (brief: "Words"). Its entry is the first of two valid revolutions
in a row with `cutting` true and the spindle not changing speed; `process_rev` counts
revolutions from there, which is what the envelope is indexed by. Its cutting
energy is 2π · Σ torque_nm over its valid revolutions (one revolution turns
2π rad, so Σ T·ω·Δt = 2π · Σ T).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from millsense.daemon.learning.context import Ctx
from millsense.daemon.pipeline.alarms import AlarmEvent, finite  # noqa: F401 - finite: the learning package's too

MAX_INVALID_FRACTION = 0.10   # a process with more invalid revolutions than this never teaches
ENTRY_REVOLUTIONS = 2         # entering revolutions in a row that make the entry (the first of them)


@dataclass
class ProcessRun:
    """The state of one process from its first revolution to its end."""

    pid: int
    ctx: Ctx
    monitored: bool                  # a process (monitor set); False: a cycle run that never set monitor
    resumed: bool = False            # began after a link loss or mid-cut: its start was not seen
    revolutions: int = 0
    invalid: int = 0
    entry_rev: int | None = None     # revolutions from start to entry
    cutting_revolutions: int = 0
    torque_nm: list[float] = field(default_factory=list)   # per process_rev, NaN where invalid
    force_n: list[float] = field(default_factory=list)
    torque_sum_nm: float = 0.0       # over valid revolutions (energy)
    cutting_sum_nm: float = 0.0      # over valid cutting revolutions (mean)
    torque_peak_nm: float | None = None
    force_peak_n: float | None = None
    fixed_alarm: bool = False        # a fixed-limit alarm was raised during it
    raised: dict[str, AlarmEvent] = field(default_factory=dict)   # "envelope_high"/"envelope_low" → event
    runs: dict[tuple[str, str], int] = field(default_factory=dict)  # (level, quantity) → consecutive revolutions
    outside: dict[str, dict[int, float]] = field(default_factory=dict)  # level → {process_rev: value} (false alarm)
    last_rev: int | None = None
    last_seq: int | None = None
    first_seq: int | None = None     # the first sample of its first revolution
    _tentative: list[tuple[int, float | None, float | None, bool]] = field(default_factory=list)

    @property
    def key(self) -> str:
        return self.ctx.key

    @property
    def energy_j(self) -> float:
        return 2.0 * math.pi * self.torque_sum_nm

    @property
    def too_damaged(self) -> bool:
        return self.invalid > MAX_INVALID_FRACTION * max(self.revolutions, 1)

    def add(self, est: dict[str, Any]) -> int | None:
        """One revolution; returns its process_rev (None before entry)."""
        index = self.revolutions
        self.revolutions += 1
        self.last_rev, self.last_seq = est.get("rev"), est.get("seq_end")
        if index == 0 and self.last_seq is not None:
            self.first_seq = int(self.last_seq) - max(int(est.get("samples") or 1), 1) + 1
        valid = bool(est.get("valid", True))
        torque = finite(est.get("torque_nm")) if valid else None
        force = finite(est.get("force_n")) if valid else None
        cutting = valid and bool(est.get("cutting")) and torque is not None
        # entry: not while the spindle changes speed (what the masses take is not all out of the torque then)
        entering = cutting and not est.get("accelerating")
        if not valid or torque is None:
            self.invalid += 1
        if torque is not None:
            self.torque_sum_nm += torque  # the energy counts every valid revolution, before entry too
        if self.entry_rev is None:
            # The entry is the first of ENTRY_REVOLUTIONS entering revolutions in a row: one revolution
            # just over the cutting threshold in the air (the spindle settling after its start) would
            # shift every process_rev of the process against the envelope.
            if not entering:
                self._tentative.clear()
                return None
            self._tentative.append((index, torque, force, cutting))
            if len(self._tentative) < ENTRY_REVOLUTIONS:
                return None
            self.entry_rev = self._tentative[0][0]
            if self.entry_rev == 0:
                self.resumed = True  # cutting from its first revolution: the approach was not seen
            for _, t, f, c in self._tentative[:-1]:
                self._record(t, f, c)
            self._tentative.clear()
        self._record(torque, force, cutting)
        return index - self.entry_rev

    def _record(self, torque: float | None, force: float | None, cutting: bool) -> None:
        """One revolution from entry on: peaks, the cutting mean, the per-process_rev arrays."""
        if torque is not None:
            self.torque_peak_nm = torque if self.torque_peak_nm is None else max(self.torque_peak_nm, torque)
        if force is not None:
            self.force_peak_n = force if self.force_peak_n is None else max(self.force_peak_n, force)
        if cutting:
            self.cutting_revolutions += 1
            self.cutting_sum_nm += torque
        self.torque_nm.append(math.nan if torque is None else torque)
        self.force_n.append(math.nan if force is None else force)

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        return np.array(self.torque_nm, dtype=float), np.array(self.force_n, dtype=float)

    def detail(self, process_rev: int | None) -> tuple[tuple[str, Any], ...]:
        """The alarm payload's extra fields (brief: envelope/wear alarms)."""
        c = self.ctx
        return (("program", c.program), ("tool", c.tool), ("operation", c.operation),
                ("process", self.pid), ("process_rev", process_rev))

    def summary(self, verdict: str) -> dict[str, Any]:
        """The `process` payload without machine and t (brief14.md)."""
        c = self.ctx
        mean = self.cutting_sum_nm / self.cutting_revolutions if self.cutting_revolutions else None
        return {
            "process": self.pid, "key": c.key, "program": c.program, "tool": c.tool, "operation": c.operation,
            "revolutions": self.revolutions, "cutting_revolutions": self.cutting_revolutions,
            "entry_rev": self.entry_rev, "torque_peak_nm": _round(self.torque_peak_nm, 4),
            "torque_mean_nm": _round(mean, 4), "force_peak_n": _round(self.force_peak_n, 2),
            "energy_j": round(self.energy_j, 3), "verdict": verdict,
            # bookkeeping for the runner (its time, the history), not payload fields
            "seq_start": self.first_seq, "seq_end": self.last_seq,
        }


def _round(value: float | None, digits: int) -> float | None:
    return None if value is None else round(value, digits)
