"""Sample-level trips, decided on each block as it lands: crash power, crash current, stall.

Why sample level: a per-revolution alarm waits for the revolution to close.
A spindle that stops under load never closes one, and its air-gap power falls
with its speed (P = T·ω), so neither the power limit nor the crash power sees
it. The current does not fall: a stalled motor draws its limit current.

Three trips, each an `AlarmEvent` of level `crash`, latched in the alarm engine
until an operator's reset (one latch for all three; the first one wins):

- `p_gap_w`: the smoothed air-gap power over `[alarms] crash_power_w`
  (`AlarmEngine.on_power`).
- `current_a`: the smoothed largest line current, max(|i_u|, |i_v|, |i_w|)
  sample by sample over `P_GAP_SMOOTH_SAMPLES`, over `crash_current_a` (an
  instantaneous value: about 0.87–1.0 of the current's peak, 1.2–1.4 × its
  RMS). A current sample at its ADC limit while the current was high (it
  swung up to the rail, it is not stuck there) counts as over the limit
  whatever its value: a real crash saturates the sensors.
- `stall`: while the smoothed current stays above `stall_current_a`, no
  revolution closing within twice the last revolution's period. After the
  spindle stood still with the current low, the last period is forgotten and
  the longest revolution there is (at the stop speed, `STOP_RPM`) stands in
  for it, so a start from standstill is not a stall.

Also per block, for the reset's "condition gone" test: the block's peak
smoothed power and current (`inf` for the current when a current clipped while
high: it was beyond what the sensor measures) and whether the stall condition
holds.

Where it runs (issue 13). Live, the crash power and current are decided by
`FrameCheck` on every frame in the driver's reader thread, the moment the frame
is decoded, so the feed hold never waits for the estimator thread, which wakes
only every ~50 ms or when a revolution closes; `SafetyCheck` then keeps the
stall (it needs the revolutions) and the peaks (`sample_level=False`). Replay,
and a block the reader did not check, run all three here as before.
"""

from __future__ import annotations

import collections
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from millsense.daemon.events import AlarmEvent
from millsense.daemon.physics.power import copper_loss_w, input_power_symmetric_w, input_power_two_wattmeter_w
from millsense.daemon.pipeline.revolutions import STOP_RPM
from millsense.daemon.pipeline.signal_check import HIGH_FRAC, HIGH_WINDOW_S

SMOOTH_SAMPLES = 5  # the estimator's P_GAP_SMOOTH_SAMPLES: the same short mean live and in replay


@dataclass
class SafetyResult:
    """What one block said at sample level."""

    events: list[AlarmEvent] = field(default_factory=list)  # crash events that latched now, in sample order
    peaks: dict[str, float] = field(default_factory=dict)
    stalled: bool = False


def _limit(section: Any, name: str) -> float | None:
    value = getattr(section, name, None) if section is not None else None
    return None if value is None else float(value)


class SafetyCheck:
    """Sample-level crash and stall decisions for one machine. Pure: no clock, no I/O."""

    def __init__(self, alarms_settings: Any, sample_rate_hz: float):
        self.crash_current_a = _limit(alarms_settings, "crash_current_a")
        self.stall_current_a = _limit(alarms_settings, "stall_current_a")
        self.rate = float(sample_rate_hz)
        # the longest revolution there is: at the stop speed
        self.fallback_period = 60.0 / STOP_RPM * self.rate
        self._last_close: int | None = None     # seq_end of the last revolution closed
        self._period: float | None = None       # its length in samples
        self._high_since: int | None = None     # first sample of the current's run above stall_current_a

    def on_block(self, result: Any, engine: Any, sample_level: bool = True) -> SafetyResult:
        """`result`: the estimator's BlockResult; `engine`: the AlarmEngine holding the crash latch.

        `sample_level=False`: the crash power and current were decided frame by frame already
        (`FrameCheck`, live): only the stall and the peaks here.
        """
        out = SafetyResult()
        p = result.p_gap_w
        cur = getattr(result, "current_a", None)
        seq0 = int(result.seq)
        n = len(p)
        if n:
            if sample_level:
                out.events += engine.on_power(p, seq0)
            out.peaks["p_gap_w"] = float(np.max(p))
        clip_seq = getattr(result, "clip_seq", None)
        if cur is not None and len(cur):
            out.peaks["current_a"] = math.inf if clip_seq is not None else float(np.max(cur))
            if sample_level:
                out.events += self._current(cur, seq0, clip_seq, engine)
            if self.stall_current_a is not None:
                out.events += self._stall(result, cur, seq0, engine, out)
        out.events.sort(key=lambda ev: ev.seq if ev.seq is not None else 0)
        return out

    def _current(self, cur: np.ndarray, seq0: int, clip_seq: int | None, engine: Any) -> list[AlarmEvent]:
        limit = self.crash_current_a
        if limit is None:
            return []
        over = cur > limit  # NaN compares False
        first = seq0 + int(np.argmax(over)) if over.any() else None
        if clip_seq is not None and (first is None or clip_seq < first):
            return engine.latch_crash(AlarmEvent("crash", "current_a", float(cur[clip_seq - seq0]), limit, None, clip_seq))
        if first is None:
            return []
        return engine.latch_crash(AlarmEvent("crash", "current_a", float(cur[first - seq0]), limit, None, first))

    def _stall(self, result: Any, cur: np.ndarray, seq0: int, engine: Any, out: SafetyResult) -> list[AlarmEvent]:
        for est in result.estimates:
            end = est.get("seq_end")
            if end is not None:
                self._last_close = int(end)
                self._period = float(est.get("samples") or 0) + float(est.get("lost_samples") or 0) or None
        limit = self.stall_current_a
        low = np.flatnonzero(~(cur > limit))          # NaN counts as low: no trip on nothing
        if len(low) == len(cur):
            self._high_since = None
        elif len(low):
            self._high_since = seq0 + int(low[-1]) + 1  # the run above the limit that reaches the block's end
        elif self._high_since is None:
            self._high_since = seq0
        if result.spindle_stopped and self._high_since is None:
            self._period = None                          # stood still, current low: the next start is not a stall
        if self._high_since is None:
            return []
        since = self._high_since if self._last_close is None else max(self._high_since, self._last_close)
        allowed = 2.0 * (self._period or self.fallback_period)
        last = seq0 + len(cur) - 1
        if last - since < allowed:
            return []
        out.stalled = True
        at = min(last, since + int(math.ceil(allowed)))
        return engine.latch_crash(AlarmEvent("crash", "stall", float(cur[max(0, at - seq0)]), limit, None, at))


class FrameCheck:
    """The crash power and current of one frame, where it lands (the driver's reader thread).

    What the estimator computes for the same samples (`BlockResult.p_gap_w`,
    `current_a`): the instantaneous air-gap power ([P] eq. 11: p_in − p_cu, over
    the anti-alias filter's gain |H(f_e)|² the estimator found last) and the
    largest |line current|, each as a causal mean over `SMOOTH_SAMPLES`; then the
    limits. A current sample at its ADC limit while that current swung
    `HIGH_FRAC` of its range within `HIGH_WINDOW_S` counts as over
    `crash_current_a` (a crash saturates the sensors). One crash per latch, like
    the alarm engine's: after it the check is quiet until `rearm()` (the
    operator's reset).

    Why plain Python: this runs 100 times a second on the thread that reads the
    DAQ, which sleeps about 10 ms between frames and comes back to a cold CPU.
    Warm, a dozen numpy calls on a 10-sample frame and the same arithmetic on
    Python floats cost about the same (6–8 µs); after the sleep the numpy calls
    cost 3–6 times what the floats do (`bench/idle_penalty.py`: each numpy call
    is a long C path of its own to bring back into the caches; the
    interpreter's loop is shared by every thread). So the frame's arithmetic
    is straight-line Python, compiled once per descriptor (`_frame_program`,
    its text in `program_source`): p_in − p_cu is a quadratic form in the counts (p_in is
    bilinear in v and i, the copper loss quadratic in i), `Σ_jk Q_jk x_j x_k`,
    Q read off the physics module's own functions at start (polarisation:
    Q_jj = f(e_j), Q_jk = (f(e_j + e_k) − f(e_j) − f(e_k))/2), so the formula
    lives in one place; the line currents are linear in the counts. Only a
    frame whose peak could cross a limit (rare) takes the means and the clip
    test in numpy (`_crash`).

    Not thread-safe: one caller at a time (the runtime's frame guard holds its lock).
    Raises `ConfigError` when the configuration does not fit the descriptor.
    """

    def __init__(self, settings: Any, descriptor: Any):
        from millsense.daemon.pipeline.scaling import line_channels

        lc = line_channels(settings, descriptor)
        c = len(descriptor.channels)
        v_keys, i_keys = lc.v_keys, lc.i_keys
        cols = np.array(lc.v_cols + lc.i_cols, dtype=np.intp)
        scales = np.array(lc.v_scales + lc.i_scales)
        offsets = list(lc.v_offsets + lc.i_offsets)
        self._offsets = np.zeros(c)
        self._offsets[cols] = offsets
        nv = len(v_keys)
        winding = str(settings.motor.winding)
        r_s = float(settings.motor.stator_resistance_ohm)
        symmetric = nv == 3 and len(i_keys) == 3

        def p_meas_w(x: np.ndarray) -> float:
            v = three_lines(dict(zip(v_keys, x[:nv])), ("uv", "vw", "wu"))
            i = three_lines(dict(zip(i_keys, x[nv:])), ("u", "v", "w"))
            p_in = input_power_symmetric_w(*v, *i) if symmetric else input_power_two_wattmeter_w(v[0], v[1], i[0], i[1])
            return float(p_in - copper_loss_w(*i, winding, r_s))

        q = _quadratic_form(p_meas_w, len(cols)) * np.outer(scales, scales)  # in counts
        # each line current from the measured ones (a missing third: minus the other two), A per count
        lines = [[(nv + k, (1.0 if key == other else -1.0) * scales[nv + k]) for k, key in enumerate(i_keys)
                  if key == other or other not in i_keys] for other in ("u", "v", "w")]
        self._amps_per_count = np.zeros(c)   # the largest |line current| one count of each column can make
        for line in lines:
            for k, coef in line:
                self._amps_per_count[cols[k]] = max(self._amps_per_count[cols[k]], abs(coef))
        self._frame_values, self.program_source = _frame_program(
            cols.tolist(), offsets, q, lines)
        # raw limits per column; columns that are not currents get limits no int16 reaches
        self._lo = np.full(c, -40000)
        self._hi = np.full(c, 40000)
        self._lo[list(lc.i_cols)], self._hi[list(lc.i_cols)] = lc.i_raw_min, lc.i_raw_max
        self._i_cols = cols[nv:]
        self._high_swing = HIGH_FRAC * (self._hi[self._i_cols] - self._lo[self._i_cols])
        self._high_window = max(2, int(round(HIGH_WINDOW_S * float(descriptor.sample_rate_hz))))
        self._recent: collections.deque[np.ndarray] = collections.deque()  # raw frames of the last window
        self._recent_n = 0
        alarms = getattr(settings, "alarms", None)
        self.crash_power_w = _limit(alarms, "crash_power_w")
        self.crash_current_a = _limit(alarms, "crash_current_a")
        self.stall_current_a = _limit(alarms, "stall_current_a")
        inf = math.inf
        self._limits = np.array([inf if self.crash_power_w is None else self.crash_power_w,
                                 inf if self.crash_current_a is None else self.crash_current_a])
        self._p_limit, self._i_limit = float(self._limits[0]), float(self._limits[1])
        self._stall = inf if self.stall_current_a is None else self.stall_current_a
        # a current sample at its sensor's limit reads at least this much: below it none can be clipped
        self._i_gate = min(self._i_limit, min((min(abs(self._lo[k] - self._offsets[k]), abs(self._hi[k] - self._offsets[k]))
                                               * self._amps_per_count[k] for k in self._i_cols), default=inf))
        self.latched = False
        self._next_seq: int | None = None
        self._tail: tuple[list[float], list[float]] = ([], [])  # the last samples' power, current: the next mean's
        self._prev_peak_w = self._prev_peak_a = -inf
        self._frame: tuple[list[float], list[float], list[float], list[float]] | None = None  # this frame's, tail's
        self._smooth: np.ndarray | None = None
        self._mean: dict[int, np.ndarray] = {}           # frame length -> its banded averaging matrix

    def rearm(self) -> None:
        """The operator's reset: the next crash trips again."""
        self.latched = False

    def check(self, seq0: int, counts: np.ndarray, lost_before: int = 0,
              discontinuity: bool = False, gain: float = 1.0) -> tuple[AlarmEvent | None, bool]:
        """One frame, raw counts (n, C): (the crash it holds, or None; the current may be over
        `stall_current_a` in it: its raw peak is, an upper bound of the smoothed one)."""
        n = counts.shape[0]
        if n == 0:
            return None, False
        contiguous = self._next_seq == seq0 and not lost_before and not discontinuity
        self._next_seq = seq0 + n
        power, current = self._frame_values(counts.tolist(), gain)
        w = SMOOTH_SAMPLES - 1
        if contiguous:
            tail_p, tail_i = self._tail
        else:  # after a gap the mean starts afresh, from the first sample
            tail_p, tail_i = [power[0]] * w, [current[0]] * w
        self._tail = (power[-w:], current[-w:]) if n >= w else ((tail_p + power)[-w:], (tail_i + current)[-w:])
        self._frame = (power, current, tail_p, tail_i)
        self._smooth = None
        self._remember(counts, contiguous)
        # A mean is never above the largest of its samples (this frame's and the tail's, from the frame
        # before): below every limit there, nothing more to do: the common case. No NaN reaches here: integer
        # counts, finite coefficients, a gain in (0, 1].
        peak_w, peak_a = max(power), max(current)
        bound_w, bound_a = (max(peak_w, self._prev_peak_w), max(peak_a, self._prev_peak_a)) if contiguous else (peak_w, peak_a)
        self._prev_peak_w, self._prev_peak_a = peak_w, peak_a
        high = bound_a > self._stall
        if self.latched or not (bound_w > self._p_limit or bound_a >= self._i_gate):
            return None, high
        event = self._crash(seq0, counts)
        self.latched = event is not None
        return event, high

    @property
    def p_gap_w(self) -> np.ndarray:
        """The last frame's smoothed air-gap power, W (the estimator's `p_gap_w` for these samples)."""
        return self._smoothed()[:, 0]

    @property
    def current_a(self) -> np.ndarray:
        """The last frame's smoothed largest line current, A (the estimator's `current_a`)."""
        return self._smoothed()[:, 1]

    def _smoothed(self) -> np.ndarray:
        if self._smooth is None:
            if self._frame is None:
                return np.empty((0, 2))
            power, current, tail_p, tail_i = self._frame
            ext = np.array([tail_p + power, tail_i + current]).T
            self._smooth = self._averaging(len(power)) @ ext
        return self._smooth

    def _averaging(self, n: int) -> np.ndarray:
        """(n, n + SMOOTH_SAMPLES − 1): row j is the mean of rows j .. j + SMOOTH_SAMPLES − 1."""
        t = self._mean.get(n)
        if t is None:
            t = np.zeros((n, n + SMOOTH_SAMPLES - 1))
            for j in range(n):
                t[j, j : j + SMOOTH_SAMPLES] = 1.0 / SMOOTH_SAMPLES
            if len(self._mean) < 64:
                self._mean[n] = t
        return t

    def _remember(self, counts: np.ndarray, contiguous: bool) -> None:
        """Keep the raw frames of the last HIGH_WINDOW_S (did a clipped current swing high?); no copy."""
        if not contiguous:
            self._recent.clear()
            self._recent_n = 0
        self._recent.append(counts)
        self._recent_n += counts.shape[0]
        while self._recent_n - self._recent[0].shape[0] >= self._high_window:
            self._recent_n -= self._recent.popleft().shape[0]

    def _crash(self, seq0: int, counts: np.ndarray) -> AlarmEvent | None:
        """The earliest crash sample of the frame; power first at the same sample (as the engine decides)."""
        smooth = self._smoothed()
        over = smooth > self._limits                      # NaN compares False
        clipped = self.crash_current_a is not None and bool(((counts <= self._lo) | (counts >= self._hi)).any())
        if clipped:
            cols = self._i_cols
            raw = counts[:, cols]
            hit = (raw <= self._lo[cols]) | (raw >= self._hi[cols])
            recent = np.concatenate(self._recent)[-self._high_window :, cols]
            swing = recent.max(axis=0).astype(np.int32) - recent.min(axis=0)
            over[:, 1] |= (hit & (swing >= self._high_swing)).any(axis=1)
        rows = over.any(axis=1)
        if not rows.any():
            return None
        k = int(np.argmax(rows))
        if over[k, 0]:
            return AlarmEvent("crash", "p_gap_w", float(smooth[k, 0]), self.crash_power_w, None, seq0 + k)
        return AlarmEvent("crash", "current_a", float(smooth[k, 1]), self.crash_current_a, None, seq0 + k)


def _quadratic_form(f: Any, k: int) -> np.ndarray:
    """The symmetric Q with f(x) = xᵀQx, read off a quadratic function by polarisation."""
    eye = np.eye(k)
    q = np.empty((k, k))
    diag = [f(eye[j]) for j in range(k)]
    for j in range(k):
        q[j, j] = diag[j]
        for m in range(j + 1, k):
            q[j, m] = q[m, j] = 0.5 * (f(eye[j] + eye[m]) - diag[j] - diag[m])
    return q


def _frame_program(cols: list[int], offsets: list[float], q: np.ndarray,
                   lines: list[list[tuple[int, float]]]) -> tuple[Callable[[list, float], tuple[list, list]], str]:
    """The frame's arithmetic as straight-line Python, compiled once: (function, its source).

    `function(rows, gain)`: `rows` a frame's raw counts as lists (one per sample), `gain` the filter's
    |H(f_e)|²; returns each sample's air-gap power, W (xᵀQx / gain, x the counts of `cols` less their
    `offsets`), and its largest |line current|, A (each line Σ coef·x_k over `lines`). The source is made
    of column numbers and the coefficients' exact reprs only; `program_source` shows it.
    """
    names = [f"x{k}" for k in range(len(cols))]
    products = [f"{float(q[j, j] if j == m else 2.0 * q[j, m])!r} * {names[j]} * {names[m]}"
                for j in range(len(cols)) for m in range(j, len(cols)) if q[j, m] != 0.0]
    currents = [f"abs({' + '.join(f'{float(coef)!r} * {names[k]}' for k, coef in line)})" for line in lines if line]
    body = [f"        {names[k]} = r[{col}]" + (f" - {float(off)!r}" if off else "") for k, (col, off) in enumerate(zip(cols, offsets))]
    body += [f"        power.append(({' + '.join(products) or '0.0'}) / gain)",
             f"        current.append({'max(' + ', '.join(currents) + ')' if len(currents) > 1 else currents[0] if currents else '0.0'})"]
    source = "\n".join(["def frame_values(rows, gain):", "    power = []", "    current = []", "    for r in rows:",
                        *body, "    return power, current", ""])
    namespace: dict[str, Any] = {}
    exec(compile(source, "<FrameCheck program>", "exec"), namespace)  # noqa: S102 - numbers only, see above
    return namespace["frame_values"], source


def three_lines(got: dict[str, Any], keys: tuple[str, str, str]) -> tuple[Any, ...]:
    """The three line quantities; a missing one from the other two (they sum to zero)."""
    for k in keys:
        if k not in got:
            a, b = (got[o] for o in keys if o != k)
            got[k] = -(a + b)
    return tuple(got[k] for k in keys)
