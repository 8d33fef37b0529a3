"""Synthetic per-revolution estimates of processes, and a shop that feeds them to a monitor.

Written for the learning tests only: a process is air revolutions (the
spindle coming up, the approach), an entry revolution at half load, a cut
at one depth then a deeper one (a depth step), a half-load exit, air again.
The numbers are the estimator's dict keys (rev, seq_end, torque_nm, force_n,
cutting, valid, samples).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from types import SimpleNamespace
from typing import Any, Callable

import numpy as np

from millsense.daemon.learning.context import Ctx
from millsense.daemon.learning.monitor import MonitorStep, ProcessMonitor

SAMPLES_PER_REV = 100
CUTTING_NM = 0.2          # the estimator's cutting threshold, as in [alarms]/[cut] min torque
FORCE_PER_NM = 150.0      # N of force per N·m of torque (a 13 mm effective radius)
LEVELS_NM = (4.0, 6.0)    # the two depths of the cut


def learning(**overrides: Any) -> SimpleNamespace:
    """`[learning]` with the documented defaults."""
    base = dict(enabled=True, processes=5, confirm=False, sigma=4.0, min_width_pct=25.0, min_width_nm=0.5,
                min_width_n=50.0, high_revolutions=3, low_revolutions=3, hold_high=True, hold_low=True,
                wear_rise_pct=15.0, wear_window=3)
    base.update(overrides)
    return SimpleNamespace(**base)


def ctx(program: int = 1001, tool: int = 12, operation: int = 1, cycle: bool = True, monitor: bool = True) -> Ctx:
    return Ctx(program, tool, operation, cycle, monitor, False, False, "daq")


@dataclass
class Shape:
    """One process's torque profile (N·m per revolution, before noise)."""

    air_before: int = 10
    cut_revs: tuple[int, int] = (20, 20)
    levels_nm: tuple[float, float] = LEVELS_NM
    air_after: int = 5
    scale: float = 1.0                     # wear, a wrong tool
    air_nm: float = 0.03
    missing_part: bool = False
    change: Callable[[int, float], float] | None = None   # (process_rev, torque) -> torque: a fault

    def torques(self) -> list[float]:
        cut = [0.5 * self.levels_nm[0]]
        cut += [self.levels_nm[0]] * self.cut_revs[0] + [self.levels_nm[1]] * self.cut_revs[1]
        cut += [0.5 * self.levels_nm[1]]
        cut = [self.scale * t for t in cut]
        if self.change is not None:
            cut = [self.change(k, t) for k, t in enumerate(cut)]
        if self.missing_part:
            cut = [self.air_nm] * len(cut)
        return [self.air_nm] * self.air_before + cut + [self.air_nm] * self.air_after


@dataclass
class Shop:
    """Feeds processes to a monitor as the estimator thread would, collecting what comes back."""

    monitor: ProcessMonitor
    rng: np.random.Generator = field(default_factory=lambda: np.random.default_rng(1))
    noise_pct: float = 2.0
    rev: int = 0
    steps: list[MonitorStep] = field(default_factory=list)
    estimates: list[dict] = field(default_factory=list)

    def estimate(self, torque_nm: float, valid: bool = True) -> dict:
        self.rev += 1
        noisy = torque_nm * (1.0 + self.noise_pct / 100.0 * self.rng.standard_normal())
        if torque_nm < CUTTING_NM:
            noisy = torque_nm + 0.01 * self.rng.standard_normal()
        est = {"rev": self.rev, "seq_end": self.rev * SAMPLES_PER_REV, "torque_nm": noisy,
               "force_n": noisy * FORCE_PER_NM if noisy >= CUTTING_NM else None,
               "cutting": noisy >= CUTTING_NM, "valid": valid, "samples": SAMPLES_PER_REV}
        if not valid:
            # a damaged revolution: what numbers it carries mean nothing (here: none of the load)
            est.update(torque_nm=0.0, force_n=None, cutting=False)
        return est

    def feed(self, est: dict, context: Ctx | None) -> MonitorStep:
        step = self.monitor.on_revolution(est, context)
        self.estimates.append(est)
        self.steps.append(step)
        return step

    def process(self, shape: Shape, context: Ctx | None = None, invalid: set[int] = frozenset()) -> list[MonitorStep]:
        """One process of `context`, ended by the cycle going off (as between parts)."""
        context = context or ctx()
        out = [self.feed(self.estimate(t, valid=i not in invalid), context) for i, t in enumerate(shape.torques())]
        out.append(self.end(context))
        return out

    def end(self, context: Ctx) -> MonitorStep:
        step = self.monitor.on_context(replace(context, cycle=False), self.rev * SAMPLES_PER_REV)
        self.steps.append(step)
        return step

    def processes(self) -> list[dict]:
        return [p for s in self.steps for p in s.processes]

    def events(self, level: str | None = None) -> list:
        return [e for s in self.steps for e in s.events if level is None or e.level == level]

    def learn(self, n: int = 5, context: Ctx | None = None, **shape: Any) -> None:
        for _ in range(n):
            self.process(Shape(**shape), context)
