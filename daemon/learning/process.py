"""One process being watched: its revolutions, per-revolution arrays and alarms. Pure.

A process is the revolutions of one key while the CNC's `cycle` and `monitor`
flags are set (brief: "Words"). Its entry is the first of two valid revolutions
in a row with `cutting` true and the spindle not changing speed; `process_rev` counts
revolutions from there, which is what the envelope is indexed by. Its cutting
energy is 2π · Σ torque_nm over its valid revolutions (one revolution turns
2π rad, so Σ T·ω·Δt = 2π · Σ T).

When the feed moves (the CNC's override, `feed_override_pct` = o %, u = o/100):
- torque and force are kept normalised to the programmed feed, load / u^gain
  (torque ~ t^(1+p), [D] eq. 8; `physics.milling.load_scale`);
- `process_rev` is the progress along the programmed path, not a count: a
  revolution at u advances the tool u programmed revolutions, and it is indexed
  by its middle, round(Σ u before it since entry + u/2 − 1/2); skipped indices
  (u > 1) are filled between their neighbours, repeated ones (u < 1) averaged;
- the revolutions before entry count as Σ u too (the entry deadline);
- the energy sums the normalised torque times u: 2π · Σ T·u^(1−gain), the
  energy of the same cut at the programmed feed.
At u = 1 every one of these is exactly the plain count and value.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from millsense.daemon.events import AlarmEvent, finite
from millsense.daemon.learning.context import Ctx
from millsense.daemon.physics.milling import load_scale

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
    gain: float = 1.0                # load ~ feed^gain: normalises torque and force to the programmed feed
    progress: float = 0.0            # Σ override/100 over its revolutions (== revolutions at 100 %)
    entry_progress: int | None = None   # progress from start to entry, rounded (== entry_rev at 100 %)
    _since_entry: float = 0.0        # Σ override/100 over the revolutions from entry
    _counts: list[int] = field(default_factory=list)   # revolutions averaged into each process_rev
    # (index, torque, force, cutting, override/100, load scale, progress before it): revolutions that may
    # make the entry (torque and force normalised)
    _tentative: list[tuple[int, float | None, float | None, bool, float, float, float]] = field(default_factory=list)

    @property
    def key(self) -> str:
        return self.ctx.key

    @property
    def energy_j(self) -> float:
        return 2.0 * math.pi * self.torque_sum_nm

    @property
    def teaches(self) -> bool:
        """Could this process teach its key (it cut, and enough of it was seen)? Else it would teach a wrong footprint."""
        return self.entry_rev is not None and not self.too_damaged and bool(self.torque_nm)

    @property
    def too_damaged(self) -> bool:
        return self.invalid > MAX_INVALID_FRACTION * max(self.revolutions, 1)

    @property
    def progress_without_entry(self) -> float:
        """Progress before the entry, for the missing-entry check: up to the first revolution of an entry
        still being confirmed (it began when that revolution did), else all of it."""
        return self._tentative[0][6] if self._tentative else self.progress

    def add(self, est: dict[str, Any]) -> int | None:
        """One revolution; returns its process_rev (None before entry)."""
        index = self.revolutions
        self.revolutions += 1
        pct = est.get("feed_override_pct")
        u = 1.0 if pct is None or not pct > 0.0 else float(pct) / 100.0
        scale = load_scale(pct, self.gain)
        progress_before = self.progress
        self.progress += u
        self.last_rev, self.last_seq = est.get("rev"), est.get("seq_end")
        if index == 0 and self.last_seq is not None:
            self.first_seq = int(self.last_seq) - max(int(est.get("samples") or 1), 1) + 1
        valid = bool(est.get("valid", True))
        torque = finite(est.get("torque_nm")) if valid else None
        force = finite(est.get("force_n")) if valid else None
        if scale != 1.0:   # the load the same cut takes at the programmed feed
            torque = None if torque is None else torque / scale
            force = None if force is None else force / scale
        cutting = valid and bool(est.get("cutting")) and torque is not None
        # entry: not while the spindle changes speed (what the masses take is not all out of the torque then)
        entering = cutting and not est.get("accelerating")
        if not valid or torque is None:
            self.invalid += 1
        if torque is not None:
            self.torque_sum_nm += torque * u  # the energy counts every valid revolution, before entry too
        if self.entry_rev is None:
            # The entry is the first of ENTRY_REVOLUTIONS entering revolutions in a row: one revolution
            # just over the cutting threshold in the air (the spindle settling after its start) would
            # shift every process_rev of the process against the envelope.
            if not entering:
                self._tentative.clear()
                return None
            self._tentative.append((index, torque, force, cutting, u, scale, progress_before))
            if len(self._tentative) < ENTRY_REVOLUTIONS:
                return None
            self.entry_rev = self._tentative[0][0]
            self.entry_progress = int(round(self._tentative[0][6]))
            if self.entry_rev == 0:
                self.resumed = True  # cutting from its first revolution: the approach was not seen
            for _, t, f, c, uu, sc, _ in self._tentative[:-1]:
                self._record(t, f, c, uu, sc)
            self._tentative.clear()
        return self._record(torque, force, cutting, u, scale)

    def _record(self, torque: float | None, force: float | None, cutting: bool, u: float = 1.0,
                scale: float = 1.0) -> int:
        """One revolution from entry on (torque and force normalised, `scale` undoes it): peaks, the cutting
        mean (of the loads as cut: the summary's), the per-process_rev arrays (normalised); its process_rev."""
        if torque is not None:
            raw = torque * scale
            self.torque_peak_nm = raw if self.torque_peak_nm is None else max(self.torque_peak_nm, raw)
        if force is not None:
            raw = force * scale
            self.force_peak_n = raw if self.force_peak_n is None else max(self.force_peak_n, raw)
        if cutting:
            self.cutting_revolutions += 1
            self.cutting_sum_nm += torque * scale
        # indexed by its middle along the programmed path: at u = 1 exactly 0, 1, 2, ...
        k = max(int(round(self._since_entry + u / 2.0 - 0.5)), 0)
        self._since_entry += u
        t = math.nan if torque is None else torque
        f = math.nan if force is None else force
        n = len(self.torque_nm)
        if k >= n:
            # u > 1 skips indices: fill them on the line from the last value (a ramp stays a ramp)
            t0 = self.torque_nm[-1] if n else t
            f0 = self.force_n[-1] if n else f
            gap = k - n + 1
            for j in range(1, gap):
                self.torque_nm.append(t0 + (t - t0) * j / gap)
                self.force_n.append(f0 + (f - f0) * j / gap)
                self._counts.append(1)
            self.torque_nm.append(t)
            self.force_n.append(f)
            self._counts.append(1)
            return k
        # u < 1: a second revolution on the same index; the mean of them (NaN: an invalid one is not a value)
        k = n - 1
        c = self._counts[k]
        for values, v in ((self.torque_nm, t), (self.force_n, f)):
            old = values[k]
            if math.isnan(old):
                values[k] = v
            elif not math.isnan(v):
                values[k] = (old * c + v) / (c + 1)
        self._counts[k] = c + 1
        return k

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
