"""A wiring check on the raw samples: do the line currents fit each other and the line voltages?

Two mistakes at installation leave every power, torque and force wrong while each
channel swings like a live one, and the input power stays positive or near zero, so
the power check (`power_check.py`, a negative input power) misses both:

- **A current sensor turned round** (mounted the wrong way, a negative `scale`) or of
  the wrong scale, with all three line currents measured. A motor has no neutral:
  its three line currents sum to zero at every sample (Kirchhoff). One turned round,
  their sum swings twice as much as a phase; at half its gain, half as much. A sound
  set of sensors keeps the sum's peak-to-peak under a few percent of a phase's
  (noise; offsets drop out of a peak-to-peak): `KIRCHHOFF_SHARE` apart.
- **Two current channels, or two voltage channels, swapped** (the phases out of order).
  The current space vector then turns against the voltage space vector, and v·i
  averages to about zero: at a steady 600 rpm the step cut read ±33 W, every
  revolution valid, the 3 mm overload unseen. An induction motor's current vector
  always turns with its voltage vector, motoring or braking, either way round.

Judged on each `WINDOW_S` of samples while the drive runs (the voltage vector turning
at `MIN_FE_HZ` or faster, a current swinging `LIVE_COUNTS` or more, none at its sensor's
`raw_min` / `raw_max` and none flat: the signal check names those): `WINDOWS` bad
windows in a row raise fault `signals` (source `phase`, blind: `on_blind`), as many
good ones clear it. Windows with lost samples or a discontinuity are not judged.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from millsense.daemon.physics.power import clarke_alpha_beta_v
from millsense.daemon.pipeline.safety_check import three_lines
from millsense.daemon.pipeline.scaling import line_channels
from millsense.daemon.pipeline.signal_check import FLAT_REL, KIRCHHOFF_SHARE, LIVE_COUNTS
from millsense.daemon.pipeline.verdict import InARow

WINDOW_S = 1.0
WINDOWS = 2          # bad (good) windows in a row that raise (clear) the fault
MIN_FE_HZ = 2.0      # slower than this, the vectors' turning is not told from their noise


class PhaseCheck:
    """Collects a window of raw samples; says when to raise and to clear the fault."""

    def __init__(self, settings: Any, descriptor: Any, faulted: bool = False):
        """`faulted`: the verdict of the check this one replaces (the DAQ announced another descriptor): a
        fault it raised is cleared only by good windows of this one, or at once if this one cannot judge."""
        lc = line_channels(settings, descriptor)
        self.v_keys, self.i_keys, self.v_names, self.i_names = lc.v_keys, lc.i_keys, lc.v_names, lc.i_names
        self.usable = len(self.v_keys) >= 2 and len(self.i_keys) >= 2
        # a current at its sensor's limit (a crash, a range too small: the signal check names it) breaks Kirchhoff
        self._i_lo, self._i_hi = np.array(lc.i_raw_min), np.array(lc.i_raw_max)
        self._v = (list(lc.v_cols), np.array(lc.v_offsets), np.array(lc.v_scales))
        self._i = (list(lc.i_cols), np.array(lc.i_offsets), np.array(lc.i_scales))
        self.rate = float(descriptor.sample_rate_hz)
        self.window = max(8, int(round(WINDOW_S * self.rate)))
        self._min_turn = math.sin(2.0 * math.pi * MIN_FE_HZ / self.rate)   # mean sin of the angle a sample turns
        self._parts: list[np.ndarray] = []
        self._n = 0
        self._verdict = InARow(WINDOWS)
        self._verdict.faulted = bool(faulted)
        self.changes: list[tuple[int, str]] = []   # every verdict of the last `update`: (that index, verdict)

    @property
    def faulted(self) -> bool:
        return self._verdict.faulted

    def update(self, counts: np.ndarray, lost_before: int = 0, discontinuity: bool = False) -> str | None:
        """One block of raw counts (n, C). Returns the verdict (verdict.py): the reason when raised, "" when
        cleared, else None; the last one, if the block completed several windows (`changes` has each, with the
        index of its window's last sample in `counts`). A gap starts the window again: a window is contiguous
        samples."""
        self.changes = []
        if not self.usable:
            if self._verdict.faulted:   # the last descriptor's fault, which these channels cannot judge
                self._verdict.faulted = False
                self.changes.append((len(counts) - 1, ""))
                return ""
            return None
        if len(counts) == 0:
            return None
        if lost_before or discontinuity:
            self._parts, self._n = [], 0
        before = self._n   # samples of the window begun in earlier blocks
        self._parts.append(counts)
        self._n += len(counts)
        m = self._n // self.window
        if m == 0:
            return None
        block = np.concatenate(self._parts) if len(self._parts) > 1 else self._parts[0]
        rest = block[m * self.window :]
        self._parts, self._n = ([rest], len(rest)) if len(rest) else ([], 0)
        for k in range(m):
            problem = self.problem(block[k * self.window : (k + 1) * self.window])
            if problem is not None and self._verdict.observe(bool(problem)):   # None: the drive not running
                self.changes.append(((k + 1) * self.window - 1 - before, problem))
        return self.changes[-1][1] if self.changes else None

    def problem(self, raw: np.ndarray) -> str | None:
        """One window's verdict: the problem in words, "" when the wiring fits, None when the drive is not
        running (nothing to judge)."""
        cols, off, scale = self._i
        i_raw = raw[:, cols]
        lo, hi = i_raw.min(axis=0), i_raw.max(axis=0)
        if int((hi.astype(np.int32) - lo).max()) < LIVE_COUNTS or (lo <= self._i_lo).any() or (hi >= self._i_hi).any():
            return None   # the drive not running, or a current clipped: not judged here
        i = (i_raw - off) * scale
        v = (raw[:, self._v[0]] - self._v[1]) * self._v[2]
        if _one_flat(i) or _one_flat(v):
            return None   # a stuck, dead or unplugged sensor breaks both rules: the signal check names it
        v_alpha, v_beta = clarke_alpha_beta_v(*three_lines(dict(zip(self.v_keys, v.T)), ("uv", "vw", "wu")))
        i_u, i_v, i_w = three_lines(dict(zip(self.i_keys, i.T)), ("u", "v", "w"))
        i_alpha, i_beta = (2.0 * i_u - i_v - i_w) / 3.0, (i_v - i_w) / math.sqrt(3.0)   # Clarke, as the voltages'
        turn_v, turn_i = _turning(v_alpha, v_beta), _turning(i_alpha, i_beta)
        if abs(turn_v) < self._min_turn:
            return None   # a voltage vector standing still (or none): f_e says nothing of the order
        problems = []
        if len(self.i_keys) == 3:
            phase_ptp = float(np.ptp(i, axis=0).max())
            sum_ptp = float(np.ptp(i.sum(axis=1)))
            if sum_ptp > KIRCHHOFF_SHARE * phase_ptp:
                problems.append(
                    f"{', '.join(self.i_names)}: the line currents do not sum to zero (their sum swings "
                    f"{sum_ptp:.1f} A peak-to-peak, a phase {phase_ptp:.1f} A): a current sensor turned round "
                    f"(mounted the wrong way, or a negative scale in [channels]) or of the wrong scale")
        if abs(turn_i) >= self._min_turn and (turn_i > 0) != (turn_v > 0):
            problems.append(
                f"{', '.join(self.i_names)}: the current space vector turns against the voltages' "
                f"({', '.join(self.v_names)}): two current channels, or two voltage channels, swapped (not in the "
                f"same phase order); the input power averages to about zero")
        return "; ".join(problems) + ("; torque and force are wrong until this is fixed" if problems else "")


def _one_flat(x: np.ndarray) -> bool:
    """Does one channel of a kind swing less than FLAT_REL of the largest (the signal check's flat rule)?"""
    swing = np.ptp(x, axis=0)
    return bool(swing.min() < FLAT_REL * swing.max())


def _turning(alpha: np.ndarray, beta: np.ndarray) -> float:
    """Mean sine of the angle the vector turns from one sample to the next, weighted by its size: > 0
    counter-clockwise, < 0 clockwise, about 0 when it stands still or is noise."""
    cross = float(np.dot(alpha[:-1], beta[1:]) - np.dot(beta[:-1], alpha[1:]))
    norm = float(np.sqrt(np.dot(alpha[:-1], alpha[:-1]) + np.dot(beta[:-1], beta[:-1])) *
                 np.sqrt(np.dot(alpha[1:], alpha[1:]) + np.dot(beta[1:], beta[1:])))
    return cross / norm if norm > 0.0 else 0.0

