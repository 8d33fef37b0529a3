"""Matching the daemon's live estimates to the emulator's truth, and emulator timing.

Time base: the emulator's status log has a `start` event with its monotonic
and wall clocks and the first sample index; its pacer releases samples in
batches of `BATCH` (10 ms at 1 kHz), sample k no earlier than its nominal time
`start + (k - first)/rate`. A live estimate's `t` is the Unix time of the
revolution's last sample, so it matches the truth revolution whose last
sample's nominal wall time is nearest.
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass

RATE_HZ = 1000.0
BATCH = 10  # samples per pacer batch of the emulator (sim/emulator/pacing.py, batch_s = 0.01)


@dataclass
class Timebase:
    mono0: float
    wall0: float
    first_index: int
    rate_hz: float = RATE_HZ

    @classmethod
    def from_status_log(cls, events: list[dict]) -> Timebase:
        start = next(e for e in events if e.get("event") == "start")
        return cls(float(start["mono"]), float(start["wall"]), int(start.get("first_index", 0)))

    def nominal_mono(self, index: int) -> float:
        """When sample `index` was due (monotonic clock of the emulator host)."""
        return self.mono0 + (index - self.first_index) / self.rate_hz

    def emitted_mono(self, index: int) -> float:
        """The earliest the emulator can have sent sample `index` (end of its pacer batch)."""
        j = index - self.first_index + 1
        return self.mono0 + math.ceil(j / BATCH) * BATCH / self.rate_hz

    def nominal_wall(self, index: int) -> float:
        return self.wall0 + (index - self.first_index) / self.rate_hz


def truth_revs(truth: list[dict]) -> list[dict]:
    return [r for r in truth if "rev" in r and "event" not in r]


def truth_events(truth: list[dict], name: str) -> list[dict]:
    return [r for r in truth if r.get("event") == name]


def match_estimates(estimates: list[dict], truth: list[dict], tb: Timebase) -> list[tuple[dict, dict, float]]:
    """(estimate, truth revolution, t_estimate − t_truth_end) under one rev offset for all.

    The daemon numbers revolutions from its own start and splits them at the
    encoder phase it first saw, so its revolution k ends somewhere inside truth
    revolution k − offset (or k − offset + 1), by a fixed phase while the speed
    is constant. The offset is the one most estimates agree on when each is
    paired with the truth revolution whose end is nearest in time; estimates
    that fall outside the truth record are left out.
    """
    revs = {int(r["rev"]): r for r in truth_revs(truth)}
    if not revs or not estimates:
        return []
    ends = sorted((tb.nominal_wall(int(r["index_end"])), k) for k, r in revs.items())
    times = [e for e, _ in ends]
    votes: dict[int, int] = {}
    for est in estimates:
        i = bisect.bisect_left(times, float(est["t"]))
        cands = [ends[j] for j in (i - 1, i) if 0 <= j < len(ends)]
        _, k = min(cands, key=lambda c: abs(c[0] - float(est["t"])))
        votes[est["rev"] - k] = votes.get(est["rev"] - k, 0) + 1
    offset = max(votes, key=votes.get)
    out = []
    for est in estimates:
        r = revs.get(int(est["rev"]) - offset)
        if r is not None:
            out.append((est, r, float(est["t"]) - tb.nominal_wall(int(r["index_end"]))))
    return out


def steady_torque_misses(matched: list[tuple[dict, dict, float]], truth: list[dict]) -> tuple[list, list]:
    """Live accuracy's check (2 % + 0.03 N·m of the plant's torque): the steady cutting revolutions a daemon
    estimated, and those off the truth as (rev, estimate, truth). A daemon revolution overlaps truth
    revolutions k and k±1: all three must be steady."""
    by_rev = {int(r["rev"]): r for r in truth_revs(truth)}
    steady = [(e, r) for e, r, _ in matched if r.get("cutting") and e.get("valid", True)
              and all(by_rev.get(int(r["rev"]) + d, {}).get("steady") for d in (-1, 0, 1))]
    bad = [(e["rev"], e["torque_nm"], round(r["torque_nm"], 4)) for e, r in steady
           if e["torque_nm"] is None or abs(e["torque_nm"] - r["torque_nm"]) > 0.02 * abs(r["torque_nm"]) + 0.03]
    return steady, bad
