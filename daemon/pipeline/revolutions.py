"""Spindle angle per sample, and exact per-revolution integrals.

[P] averages cutting torque over whole spindle revolutions (the cutting force
is periodic at tooth frequency; a revolution holds a whole number of tooth
periods). At 1 kHz a revolution at 2500 rpm is 24 samples, so cutting it at a
sample would err by up to 1/24 = 4 %. Here the spindle angle is linear between
samples, a boundary falls at the fractional instant the angle crosses a whole
revolution, and every quantity is integrated as the piecewise-linear curve
through its samples (trapezoid, split exactly at the boundary). A revolution
mean is then integral / duration: exact for signals that are linear between
samples, and independent of where the samples happen to fall.

Everything is vectorised over a block: crossings by `floor` of the angle, the
trapezoids between consecutive crossings summed by one `np.add.reduceat`, and a
revolution's sums as that sum plus the split intervals at its two boundaries
(never a difference of block-long running sums, which costs a sequential pass
and loses digits). Only the partial revolution is carried between blocks.

A boundary is the first crossing of its whole revolution. An angle reading
that steps back over the boundary it crossed last and forth again (torsional
chatter at low speed, where a sample advances the encoder a few counts; a
noisy count) crosses that number again twice; those crossings are no
boundaries. Before, each such wobble closed a revolution of one or two samples
(at 600 rpm: 50 000 rpm and −127 N·m, published valid). After damage (below)
the next crossing is a boundary whatever its number. An angle step between two
samples of `max_step_rev` or more (the estimator's: twice the fastest gear's
top speed) is a jump of the reading, not a turn: it damages its revolution
(`jumped`), where it would otherwise move a boundary by up to half a revolution.

Damage: a revolution that spans lost samples (an index gap) or a discontinuity
is still closed at its boundary but flagged `damaged`, with its lost-sample
count; boundaries that fall inside a gap are not trusted, so the whole span is
one damaged revolution. A revolution during which the spindle was stopped
(below `stop_rpm`) is not a revolution at all and is dropped; its lost samples
are counted in `lost_idle`. Every lost sample is counted exactly once:
`lost_total == sum(emitted lost) + lost_idle + lost_pending`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

STOP_RPM = 30.0


class EncoderAngle:
    """Spindle angle (revolutions) and speed (rpm) from an unwrapped encoder count.

    Speed is the count difference over the last `window` samples (by index, so
    a few lost samples stretch the baseline instead of faking a stop). Across a
    longer gap the count cannot be trusted: the DAQ's int16 encoder channel wraps
    every 65536 counts (16 revolutions of a 4096-count encoder, 1.6 s at 600 rpm
    and 0.3 s at 3000 rpm), so the unwrapped count after the gap may be off by
    whole wraps, and a speed taken across it is wrong by any amount. After a gap
    or a discontinuity (`restart`) the window starts again at the first sample
    after it; that sample takes the speed of the one-sample step that follows it.
    """

    def __init__(self, counts_per_rev: float, sample_rate_hz: float, window: int = 16):
        self.counts_per_rev = float(counts_per_rev)
        self.sample_rate_hz = float(sample_rate_hz)
        self.window = int(window)
        self._hist_count = np.empty(0)
        self._hist_seq = np.empty(0)

    def push(self, seq: np.ndarray, count: np.ndarray, restart: bool = False) -> tuple[np.ndarray, np.ndarray]:
        angle_rev = count / self.counts_per_rev
        if restart and len(self._hist_count):
            self._hist_count = np.empty(0)
            self._hist_seq = np.empty(0)
        else:
            restart = False
        c = np.concatenate([self._hist_count, count])
        s = np.concatenate([self._hist_seq, seq.astype(np.float64)])
        h, w = len(self._hist_count), self.window
        if h == w:   # the window's history full (every block but the first after a start or a gap): no special case
            rpm = (c[w:] - c[:-w]) / (s[w:] - s[:-w]) * (self.sample_rate_hz * 60.0 / self.counts_per_rev)
        else:
            j = np.arange(h, len(c))
            k = np.maximum(j - w, 0)
            dseq = s[j] - s[k]
            with np.errstate(invalid="ignore", divide="ignore"):
                rpm = (c[j] - c[k]) / dseq * (self.sample_rate_hz * 60.0 / self.counts_per_rev)
            rpm[dseq == 0] = 0.0  # the very first sample: speed unknown, treated as stopped
            if restart and len(rpm) > 1:
                rpm[0] = rpm[1]   # the first sample after a gap: the speed of the step that follows it
        self._hist_count = c[-self.window :].copy()
        self._hist_seq = s[-self.window :].copy()
        return angle_rev, rpm


class SpeedAngle:
    """Spindle angle (revolutions) by trapezoid integration of a speed signal (rpm).

    The origin is arbitrary (0 at the first sample): with no encoder, where a
    revolution starts is a free choice, and any whole revolution averages the
    periodic cutting force equally well.
    """

    def __init__(self, sample_rate_hz: float):
        self.sample_rate_hz = float(sample_rate_hz)
        self._last: tuple[float, float, float] | None = None  # (seq, rpm, angle)

    def push(self, seq: np.ndarray, rpm: np.ndarray, restart: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """`restart` is accepted for the same call as `EncoderAngle`: a measured speed needs no history."""
        s = seq.astype(np.float64)
        if self._last is None:
            s0, r0, a0 = s[0], rpm[0], 0.0
        else:
            s0, r0, a0 = self._last
        s_all = np.concatenate([[s0], s])
        r_all = np.concatenate([[r0], rpm])
        steps = 0.5 * (r_all[:-1] + r_all[1:]) * (s_all[1:] - s_all[:-1]) / (60.0 * self.sample_rate_hz)
        angle_rev = a0 + np.cumsum(steps)
        self._last = (float(s[-1]), float(rpm[-1]), float(angle_rev[-1]))
        return angle_rev, rpm


@dataclass(frozen=True)
class RevolutionBatch:
    """Revolutions closed by one block (arrays of length R, sample positions = seq)."""

    start_pos: np.ndarray   # (R,) float: fractional sample position of the opening boundary
    end_pos: np.ndarray     # (R,) float: ... of the closing boundary
    seq_end: np.ndarray     # (R,) int64: index of the last sample at or before the closing boundary
    integrals: np.ndarray   # (R, K): integral of each quantity over the revolution, in sample units
    samples: np.ndarray     # (R,) int64: samples received inside the revolution
    lost: np.ndarray        # (R,) int64: samples lost inside the revolution
    damaged: np.ndarray     # (R,) bool: spans a gap, a discontinuity or an impossible angle step
    jumped: np.ndarray      # (R,) bool: of its damage, an angle step faster than the spindle can turn

    def __len__(self) -> int:
        return len(self.end_pos)

    @property
    def duration(self) -> np.ndarray:
        """Revolution length in sample periods (fractional)."""
        return self.end_pos - self.start_pos

    def means(self) -> np.ndarray:
        """(R, K) exact time means over each revolution."""
        return self.integrals / self.duration[:, None]


def _empty(k: int) -> RevolutionBatch:
    z = np.empty(0)
    zi = np.empty(0, dtype=np.int64)
    return RevolutionBatch(z, z, zi, np.empty((0, k)), zi, zi, np.empty(0, dtype=bool), np.empty(0, dtype=bool))


class RevolutionSplitter:
    """Cuts a stream of (angle, quantities) into exact per-revolution integrals.

    `push` takes one block: sample indices start at `seq0`, `angle_rev` is the
    continuous spindle angle in revolutions, `values` an (n, K) array of the
    quantities to integrate, `moving` which samples turn faster than the stop
    speed. It returns the revolutions that closed in this block.

    `max_step_rev`: the largest angle step between two samples that is believed (the estimator gives twice
    the fastest gear's top speed); a larger one is a jump of the reading, not a turn of the spindle, and
    damages its revolution (`jumped`).
    """

    def __init__(self, n_quantities: int, max_step_rev: float = 1.0):
        self.k = int(n_quantities)
        self.max_step_rev = min(1.0, float(max_step_rev))
        self._last: tuple[float, float, np.ndarray, bool] | None = None
        self._active = False            # a revolution is open (its start boundary seen)
        self._acc = np.zeros(self.k)
        self._acc_samples = 0
        self._acc_lost = 0
        self._acc_damaged = False
        self._acc_jumped = False
        self._acc_stopped = False
        self._acc_start = 0.0
        self._last_cross: float | None = None   # the whole revolution the angle crossed last
        self._pending_lost = 0
        self._pending_disc = False
        self.lost_total = 0
        self.lost_idle = 0              # lost while stopped / before the first boundary

    @property
    def lost_pending(self) -> int:
        """Lost samples inside the revolution still open."""
        return self._acc_lost if self._active else 0

    @property
    def active(self) -> bool:
        return self._active

    def push(
        self,
        seq0: int,
        angle_rev: np.ndarray,
        values: np.ndarray,
        moving: np.ndarray,
        lost_before: int = 0,
        discontinuity: bool = False,
    ) -> RevolutionBatch:
        n = len(angle_rev)
        self.lost_total += int(lost_before)
        lost_before = int(lost_before) + self._pending_lost
        discontinuity = discontinuity or self._pending_disc
        if n == 0:  # nothing to place the gap against yet: keep it for the next block
            self._pending_lost, self._pending_disc = lost_before, discontinuity
            return _empty(self.k)
        self._pending_lost, self._pending_disc = 0, False

        seq = float(seq0) + np.arange(n, dtype=np.float64)
        if self._last is None:
            pos, th, x, mv = seq, np.asarray(angle_rev, float), np.asarray(values, float), np.asarray(moving, bool)
            self.lost_idle += lost_before
            carry = 0
            gap = np.zeros(n - 1, dtype=bool)
            lost_i = np.zeros(n - 1, dtype=np.int64)
        else:
            lp, lt, lx, lm = self._last
            pos = np.empty(n + 1)
            pos[0], pos[1:] = lp, seq
            th = np.empty(n + 1)
            th[0], th[1:] = lt, angle_rev
            x = np.empty((n + 1, self.k))
            x[0], x[1:] = lx, values
            mv = np.empty(n + 1, dtype=bool)
            mv[0], mv[1:] = lm, moving
            carry = 1
            gap = np.zeros(n, dtype=bool)
            gap[0] = lost_before > 0 or discontinuity or seq0 != lp + 1
            lost_i = np.zeros(n, dtype=np.int64)
            lost_i[0] = lost_before
        m = len(pos)
        self._last = (float(pos[-1]), float(th[-1]), x[-1].copy(), bool(mv[-1]))
        if m < 2:
            return _empty(self.k)

        k_pt = np.floor(th)
        dth = th[1:] - th[:-1]
        any_gap = bool(gap[0]) if len(gap) else False
        span = k_pt[-1] - k_pt[0]   # whole revolutions between the block's ends: two or more go the general way
        if not any_gap and -1.0 <= span <= 1.0 and bool(mv.all()) and np.abs(dth).max() < self.max_step_rev:   # (nan fails)
            # the live path's blocks: no gap, spindle turning, the samples one apart
            turns = np.flatnonzero(k_pt[1:] != k_pt[:-1])
            if len(turns) == 1 and self._active:
                t = int(turns[0])
                dth_t = float(dth[t])
                if (float(k_pt[t + 1]) if dth_t > 0 else float(k_pt[t])) != self._last_cross:
                    return self._close_one(t, pos, th, x, m, carry, dth_t, k_pt)
                turns = turns[:0]   # back over the boundary it crossed last and forth again: none here
            if len(turns) == 0:   # no boundary -> one trapezoid sum
                if self._active:
                    self._acc += 0.5 * (x[0] + x[-1]) + x[1:-1].sum(axis=0)
                    self._acc_samples += m - carry
                return _empty(self.k)

        dpos = pos[1:] - pos[:-1]
        area = 0.5 * (x[:-1] + x[1:]) * dpos[:, None]
        if len(gap) and gap[0]:                           # a gap can only open a block
            area[0] = 0.0                                 # no data inside a gap
        k_left = k_pt[:-1]
        k_right = k_pt[1:]
        insane = ~np.isfinite(dth) | (np.abs(dth) >= self.max_step_rev)
        damage_i = gap | insane
        cross = (k_left != k_right) & ~damage_i
        stop_i = ~(mv[:-1] & mv[1:])

        cum_dmg = np.concatenate([[0], np.cumsum(damage_i)])
        cum_jump = np.concatenate([[0], np.cumsum(insane)])
        cum_lost = np.zeros(m, dtype=np.int64)           # lost samples sit before the block's first sample
        cum_lost[1:] = lost_i[0] if len(lost_i) else 0
        cum_stop = np.concatenate([[0], np.cumsum(stop_i)])

        j = np.flatnonzero(cross)
        if len(j):
            j = self._first_crossings(j, np.where(dth[j] > 0, k_right[j], k_left[j]), cum_dmg)
        if len(j) == 0:
            if self._active:
                self._acc += area.sum(axis=0)
                self._acc_samples += m - carry
                self._acc_lost += int(cum_lost[-1])
                self._acc_damaged |= bool(cum_dmg[-1])
                self._acc_jumped |= bool(cum_jump[-1])
                self._acc_stopped |= bool(cum_stop[-1])
            else:
                self.lost_idle += int(cum_lost[-1])
            if cum_dmg[-1]:
                self._last_cross = None   # the angle across the damage is not trusted: the next crossing counts
            self._abandon_if_stopped(mv[-1])
            return _empty(self.k)

        target = np.where(dth[j] > 0, k_right[j], k_left[j])
        self._last_cross = float(target[-1])
        alpha = np.clip((target - th[j]) / dth[j], 0.0, 1.0)
        cpos = pos[j] + alpha * dpos[j]
        at_end = cpos >= pos[j + 1]                      # the boundary sits on sample j+1 (to rounding)
        dx = x[j + 1] - x[j]
        part = alpha[:, None] * x[j] + 0.5 * (alpha * alpha)[:, None] * dx   # interval j up to its crossing
        # the areas between crossings, each summed on its own (no block-long running sum to difference):
        # before the first, between each two, after the last
        seg = np.add.reduceat(area, np.concatenate([[0], j]), axis=0)
        if j[0] == 0:
            seg[0] = 0.0                                 # reduceat gives area[0] for an empty range
        count_c = j + 1 + at_end                         # points at or before each crossing
        seq_end = (pos[j] + at_end).astype(np.int64)

        # revolutions between consecutive crossings of this block
        integ = seg[1:-1] + part[1:] - part[:-1]
        samples = count_c[1:] - count_c[:-1]
        lost = cum_lost[j[1:] + 1] - cum_lost[j[:-1]]
        dmg = (cum_dmg[j[1:] + 1] - cum_dmg[j[:-1]]) > 0
        jmp = (cum_jump[j[1:] + 1] - cum_jump[j[:-1]]) > 0
        stp = (cum_stop[j[1:] + 1] - cum_stop[j[:-1]]) > 0
        start = cpos[:-1]
        end = cpos[1:]
        ends = seq_end[1:]

        j0 = j[0]
        if self._active:   # the revolution carried in closes at the first crossing
            integ = np.vstack([(self._acc + seg[0] + part[0])[None, :], integ])
            samples = np.concatenate([[self._acc_samples + count_c[0] - carry], samples])
            lost = np.concatenate([[self._acc_lost + cum_lost[j0 + 1]], lost])
            dmg = np.concatenate([[self._acc_damaged or cum_dmg[j0 + 1] > 0], dmg])
            jmp = np.concatenate([[self._acc_jumped or cum_jump[j0 + 1] > 0], jmp])
            stp = np.concatenate([[self._acc_stopped or cum_stop[j0 + 1] > 0], stp])
            start = np.concatenate([[self._acc_start], start])
            end = np.concatenate([[cpos[0]], end])
            ends = np.concatenate([[seq_end[0]], ends])
        else:
            self.lost_idle += int(cum_lost[j0 + 1])

        # the revolution left open
        jl = j[-1]
        self._active = True
        self._acc = seg[-1] - part[-1]
        self._acc_samples = int(m - count_c[-1])
        self._acc_lost = int(cum_lost[-1] - cum_lost[jl + 1])
        self._acc_damaged = bool(cum_dmg[-1] - cum_dmg[jl + 1])
        self._acc_jumped = bool(cum_jump[-1] - cum_jump[jl + 1])
        self._acc_stopped = bool(cum_stop[-1] - cum_stop[jl])
        self._acc_start = float(cpos[-1])
        if cum_dmg[-1] > cum_dmg[jl + 1]:
            self._last_cross = None
        self._abandon_if_stopped(mv[-1])

        keep = ~stp
        self.lost_idle += int(lost[stp].sum())
        return RevolutionBatch(
            start_pos=start[keep],
            end_pos=end[keep],
            seq_end=ends[keep].astype(np.int64),
            integrals=integ[keep],
            samples=samples[keep].astype(np.int64),
            lost=lost[keep].astype(np.int64),
            damaged=dmg[keep],
            jumped=jmp[keep],
        )

    def _close_one(self, j: int, pos: np.ndarray, th: np.ndarray, x: np.ndarray, m: int, carry: int, dth_j: float,
                   k_pt: np.ndarray) -> RevolutionBatch:
        """`push` for a block with one boundary (between samples j and j+1), no gap, the spindle turning and a
        revolution open: the general path's arithmetic on one crossing, in the same order, on plain floats
        where it is one number. This is the live daemon's closing block (the frames since the estimator's last
        wake-up)."""
        target = float(k_pt[j + 1]) if dth_j > 0 else float(k_pt[j])
        self._last_cross = target
        alpha = min(max((target - float(th[j])) / dth_j, 0.0), 1.0)
        cpos = float(pos[j]) + alpha * float(pos[j + 1] - pos[j])
        at_end = cpos >= float(pos[j + 1])               # the boundary sits on sample j+1 (to rounding)
        part = alpha * x[j] + 0.5 * (alpha * alpha) * (x[j + 1] - x[j])   # interval j up to its crossing
        area = 0.5 * (x[:-1] + x[1:])                    # the samples are one apart: dpos = 1
        before = area[:j].sum(axis=0) if j else np.zeros(self.k)
        count_c = j + 1 + int(at_end)
        closed = self._acc + before + part
        samples = self._acc_samples + count_c - carry
        lost, damaged, stopped, start = self._acc_lost, self._acc_damaged, self._acc_stopped, self._acc_start
        jumped = self._acc_jumped
        # the revolution left open
        self._acc = area[j:].sum(axis=0) - part
        self._acc_samples = int(m - count_c)
        self._acc_lost = 0
        self._acc_damaged = False
        self._acc_jumped = False
        self._acc_stopped = False
        self._acc_start = cpos
        if stopped:   # the spindle stopped inside it: not a revolution
            self.lost_idle += int(lost)
            return _empty(self.k)
        return RevolutionBatch(
            start_pos=np.array([start]),
            end_pos=np.array([cpos]),
            seq_end=np.array([int(float(pos[j]) + at_end)], dtype=np.int64),
            integrals=closed[None, :],
            samples=np.array([samples], dtype=np.int64),
            lost=np.array([lost], dtype=np.int64),
            damaged=np.array([bool(damaged)]),
            jumped=np.array([bool(jumped)]),
        )

    def _first_crossings(self, j: np.ndarray, crossed: np.ndarray, cum_dmg: np.ndarray) -> np.ndarray:
        """The crossings `j` (interval indices) that are boundaries: of the whole revolutions `crossed`, each
        the first crossing of its number. An angle that steps back over the boundary it crossed last and forth
        again (torsional chatter at low speed, a noisy encoder count) crosses the same number two more times:
        those are no boundaries, or each wobble would close a revolution of a sample or two. A damaged
        interval in between (a gap, an impossible step) makes the next crossing a boundary again: the angle
        across it is not trusted."""
        before = np.empty(len(j))
        before[0] = np.nan if self._last_cross is None else self._last_cross
        before[1:] = crossed[:-1]
        damaged = np.empty(len(j), dtype=bool)
        damaged[0] = cum_dmg[j[0]] > 0
        damaged[1:] = cum_dmg[j[1:]] > cum_dmg[j[:-1] + 1]
        return j[(crossed != before) | damaged]

    def _abandon_if_stopped(self, last_moving: bool) -> None:
        """A spindle that has stopped ends the open revolution: nothing to publish."""
        if self._active and not last_moving:
            self.lost_idle += self._acc_lost
            self._active = False
            self._acc_lost = 0
