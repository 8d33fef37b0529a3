"""A simple closed loop for the feed controller's tests: the cut as the controller sees it.

Per 1 ms sample: the CNC follows the commanded override through its first-order
lag, then its rate limit; the feed moves the tool along x; the load is the
depth under the tool (a slot: load ~ axial depth) times (override/100)^gain; a
revolution's estimate is the mean load over the revolution, reaching the
controller `batch_s` after the revolution closes (the estimator's batching, at
its worst). Written for the tests, from the design in docs/afc.md, not from the
simulator: it has none of the plant's cutting mechanics.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from millsense.daemon.afc.controller import FeedController

SAMPLE_S = 0.001


@dataclass
class Cut:
    rpm: float
    feed_mm_min: float
    levels_mm: tuple[float, ...] = (2.0, 3.0, 2.5)
    level_len_mm: float = 25.0
    tool_diameter_mm: float = 0.0      # 0: a step in depth is a step in load; D: the tool crosses the wall over D
    gain: float = 0.56                 # the plant's d ln(load) / d ln(feed)
    load_per_mm: float = 4.0           # load at the programmed feed per mm of depth
    cnc_lag_s: float = 0.04
    cnc_rate_pct_s: float = 200.0
    batch_s: float = 0.05

    def depth_mm(self, x_mm: float) -> float:
        """The depth the tool sees at tool-centre position x: a linear blend across the wall over the diameter."""
        edges = [self.level_len_mm * (k + 1) for k in range(len(self.levels_mm) - 1)]
        k = sum(1 for e in edges if x_mm >= e)
        d = self.levels_mm[min(k, len(self.levels_mm) - 1)]
        if self.tool_diameter_mm > 0:
            r = self.tool_diameter_mm / 2.0
            for j, e in enumerate(edges):
                if e - r <= x_mm < e + r:
                    frac = (x_mm - (e - r)) / (2.0 * r)
                    d = self.levels_mm[j] + frac * (self.levels_mm[j + 1] - self.levels_mm[j])
        return d

    def level_starts_mm(self) -> list[float]:
        """Where each level's depth is fully under the tool."""
        r = self.tool_diameter_mm / 2.0
        return [0.0] + [self.level_len_mm * (k + 1) + r for k in range(len(self.levels_mm) - 1)]


@dataclass
class Revolution:
    t_end_s: float
    x_end_mm: float
    load: float
    applied_pct: float
    commanded_pct: float
    state: str


@dataclass
class Run:
    cut: Cut
    revolutions: list[Revolution] = field(default_factory=list)

    def level(self, k: int) -> list[Revolution]:
        """The revolutions fully inside level k (its depth under the whole tool), first past the wall first."""
        starts = self.cut.level_starts_mm()
        last = k == len(self.cut.levels_mm) - 1
        end = self.cut.level_len_mm * (k + 1) - (0.0 if last else self.cut.tool_diameter_mm / 2.0)
        rev_mm = self.cut.feed_mm_min / self.cut.rpm
        out = []
        for r in self.revolutions:
            x_start = r.x_end_mm - rev_mm * r.applied_pct / 100.0  # near enough: where the revolution began
            if x_start >= starts[k] and r.x_end_mm <= end:
                out.append(r)
        return out


def run(cut: Cut, controller: FeedController, target: float, *, start_mm: float = 0.0,
        until_mm: float | None = None) -> Run:
    """Cut from x = `start_mm` to the end of the last level; the controller decides at each estimate's arrival."""
    end_mm = until_mm if until_mm is not None else cut.level_len_mm * len(cut.levels_mm)
    rev_s = 60.0 / cut.rpm
    samples_per_rev = max(1, round(rev_s / SAMPLE_S))
    alpha = 1.0 - math.exp(-SAMPLE_S / cut.cnc_lag_s) if cut.cnc_lag_s > 0 else 1.0
    lagged = applied = controller.commanded_pct
    x_mm, t_s, acc, acc_pct, n = start_mm, 0.0, 0.0, 0.0, 0
    pending: list[tuple[float, dict, float]] = []   # (arrival time, estimate, x at close)
    out = Run(cut)
    step_pct = cut.cnc_rate_pct_s * SAMPLE_S
    while x_mm < end_mm:
        lagged += alpha * (controller.commanded_pct - lagged)
        applied += min(max(lagged - applied, -step_pct), step_pct)
        x_mm += cut.feed_mm_min / 60.0 * applied / 100.0 * SAMPLE_S
        t_s += SAMPLE_S
        acc += cut.load_per_mm * cut.depth_mm(x_mm) * (applied / 100.0) ** cut.gain
        acc_pct += applied
        n += 1
        if n == samples_per_rev:  # the estimate: the revolution's mean load and mean applied override, as the daemon's
            est = {"valid": True, "cutting": True, "spindle_rpm": cut.rpm, "torque_nm": acc / n,
                   "feed_override_pct": acc_pct / n}
            pending.append((t_s + cut.batch_s, est, x_mm))
            acc, acc_pct, n = 0.0, 0.0, 0
        while pending and pending[0][0] <= t_s + 1e-9:
            _, est, x_close = pending.pop(0)
            d = controller.on_revolution(est, target=target, allowed=True, now_s=t_s)
            out.revolutions.append(Revolution(t_s, x_close, est["torque_nm"], est["feed_override_pct"],
                                              controller.commanded_pct, d.state))
    return out
