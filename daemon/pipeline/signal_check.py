"""Are the DAQ's signals plausible? Clipped, flat or dead channels, and speeds that disagree.

Why: the estimator turns whatever counts arrive into torque. A current sensor
stuck at its rail, or a speed channel that reads half the real speed, gives
numbers that look like measurements (issue 10: 48 of 48 revolutions `valid`
with the currents pinned at +32767). The interlock acts on these numbers, so a
revolution built on implausible samples is published `valid: false`,
`invalid: "signals"`, and fault `signals` names the channel and the problem.

The checks, on raw counts and on what the estimator already computes:

- **Clipped** (always, even with the spindle stopped: a stopped drive reads
  about 0 V and 0 A, never a rail): a sample at or beyond the channel's
  `raw_min` / `raw_max` ([channels.X], default the int16 range).
- **Flat or dead** voltage or current channel, while the others show the drive
  running: its peak-to-peak over the window at most `FLAT_COUNTS` counts while
  another voltage or current channel swings at least `LIVE_COUNTS`, or below
  `FLAT_REL` of the swing of its own kind's others (the three phases of a
  running motor swing alike; a disconnected sensor shows only its noise).
- **Speed against the electrical frequency** (needs `[motor] pole_pairs`): the
  spindle speed (speed channel, or encoder) times a gear's ratio must be the
  synchronous speed f_e·60/pole_pairs ([P] eq. 10) within `MAX_SLIP` (an
  induction motor turns up to its breakdown slip slower, faster while it
  brakes) plus `[signals] speed_tolerance_pct`, in some gear. With both a speed
  channel and an encoder, they must agree within `speed_tolerance_pct`.
  Checked while the spindle turns, or while f_e says it should (a dead encoder
  reads "stopped" under a running drive).

Cost: per block, the column minima and maxima of the raw counts and a few sums
go into a ring of per-block rows (one numpy pass each); the counts are looked
at sample by sample only in a block that touches a limit. The checks run on
the rows: over the blocks of each revolution as it closes (so the revolution
that holds the bad samples is the one marked), and every `EVAL_STEP_S` of
samples over the last `WINDOW_S` for the fault. Everything counts samples by
index, never by wall clock: a replay decides exactly as the live daemon.

Fault: raised after `RAISE_S` of samples in which every window was bad (a
transient spike invalidates its revolution but is no fault), so within 1 s of
the problem starting; cleared after `CLEAR_S` of samples with every window
good. Currents clipped while high (they swing up to the rail: saturated, not
stuck) raise it only after `SATURATION_RAISE_S`: a crash drives them past
their sensors' range for a few revolutions (0.3 s in the simulated crash), and
that is the crash trip's business; saturation that lasts means sensors whose
range does not fit the machine.
"""

from __future__ import annotations

import numpy as np

from millsense.daemon.pipeline.revolutions import STOP_RPM
from millsense.drivers.protocol import ChannelKind

FLAT_COUNTS = 8         # a live channel swings thousands of counts; a stuck one 0, a dead one its noise
LIVE_COUNTS = 200       # ... and "the drive runs" when some voltage or current swings this much
FLAT_REL = 0.1          # the phases of a running motor swing alike; a tenth is a dead or unplugged sensor
MAX_SLIP = 0.10         # breakdown slip of spindle motors is 5-15 %; the drive's current limit keeps it lower
MIN_VOLTAGE_V = 1.0     # space-vector amplitude below which the drive is off: f_e means nothing
HIGH_FRAC = 0.25        # a clipped current is "high" (not stuck) if it swung this share of its range
HIGH_WINDOW_S = 0.05    # ... within this much of samples before
WINDOW_S = 0.2          # fault window: at least one electrical period down to f_e = 5 Hz
EVAL_STEP_S = 0.1       # ... evaluated this often (windows overlap by half)
RAISE_S = 0.2           # bad for this long (two evaluations in a row): fault
SATURATION_RAISE_S = 0.8  # ... but currents clipped while high: a crash saturates them for a few revolutions
CLEAR_S = 1.0           # good for this long: fault cleared
KEEP_S = 2.5            # rows kept: the longest revolution (at STOP_RPM, 2 s) and some
MIN_ROWS = 512


class SignalCheck:
    """Plausibility of one descriptor's signals, block by block. Not thread-safe: one owner."""

    def __init__(self, settings, descriptor, roles, sample_rate_hz: float, fe_col: int = 0, vsq_col: int = 1):
        self.rate = float(sample_rate_hz)
        self.fe_col, self.vsq_col = int(fe_col), int(vsq_col)
        channels = dict(settings.channels)
        self.names = [ch.name for ch in descriptor.channels]
        kinds = [ChannelKind(ch.kind) for ch in descriptor.channels]
        c = len(self.names)
        # limits per column; columns not checked (not configured, encoders) get limits no int16 reaches
        self.lo = np.full(c, -40000, dtype=np.int32)
        self.hi = np.full(c, 40000, dtype=np.int32)
        self.scale = np.ones(c)
        for k, (name, kind) in enumerate(zip(self.names, kinds)):
            cfg = channels.get(name)
            if cfg is None or kind == ChannelKind.ENCODER:
                continue
            self.lo[k], self.hi[k] = int(cfg.raw_min), int(cfg.raw_max)
            self.scale[k] = abs(float(cfg.scale))
        col = {n: k for k, n in enumerate(self.names)}
        self.v_cols = np.array([col[n] for n in roles.voltages.values()], dtype=np.intp)
        self.i_cols = np.array([col[n] for n in roles.currents.values()], dtype=np.intp)
        self.vi_cols = np.concatenate([self.v_cols, self.i_cols])
        nv = len(self.v_cols)
        self._groups = [range(nv), range(nv, len(self.vi_cols))]
        self._vi_scale = self.scale[self.vi_cols].tolist()
        self.roles = roles
        self.pole_pairs = getattr(settings.motor, "pole_pairs", None)
        self.gears = [(str(g.name), float(g.ratio)) for g in settings.gears]
        signals = getattr(settings, "signals", None)
        self.tol = float(getattr(signals, "speed_tolerance_pct", 10.0)) / 100.0
        # the speed sources: the angle source's rpm always; the speed channel apart when an encoder leads
        self.src_name = roles.encoder or roles.spindle_speed
        self.sp_name = roles.spindle_speed if roles.encoder is not None else None
        self._speed_names = {n for n in (roles.encoder, roles.spindle_speed) if n is not None}

        self.window = max(2, int(round(WINDOW_S * self.rate)))
        self.step = max(1, int(round(EVAL_STEP_S * self.rate)))
        self.raise_n = int(round(RAISE_S * self.rate))
        self.saturation_raise_n = int(round(SATURATION_RAISE_S * self.rate))
        self.clear_n = int(round(CLEAR_S * self.rate))
        self.keep = int(round(KEEP_S * self.rate))
        self.high_window = max(2, int(round(HIGH_WINDOW_S * self.rate)))
        cap = max(MIN_ROWS, 2 * self.keep // 10)
        self._alloc(cap, c)
        self._next_eval: int | None = None
        self._bad_since: int | None = None
        self._good_since: int | None = None
        self.faulted = False
        self.last_problems: dict[str, str] = {}

    def _alloc(self, cap: int, c: int) -> None:
        self.cap = cap
        self.w = 0
        self.first = np.zeros(cap, dtype=np.int64)
        self.last = np.zeros(cap, dtype=np.int64)
        self.mn = np.zeros((cap, c), dtype=np.int32)
        self.mx = np.zeros((cap, c), dtype=np.int32)
        self.clip_lo = np.zeros((cap, c), dtype=np.int32)
        self.clip_hi = np.zeros((cap, c), dtype=np.int32)
        # per row: samples, moving samples, sum f_e (Hz), sum v_sq, sum |rpm| (angle source), sum |speed channel|
        self.sums = np.zeros((cap, 6))

    # ------------------------------------------------------------------ per block
    def push(self, seq0: int, counts: np.ndarray, x: np.ndarray, rpm: np.ndarray,
             moving: np.ndarray, sp_rpm: np.ndarray | None) -> tuple[int | None, str | None]:
        """One block: raw counts (n, C), the estimator's per-sample columns `x` (n, K) (of which `fe_col`
        is f_e in Hz and `vsq_col` the squared voltage space vector), the spindle speed (rpm) of the angle
        source, which samples turn, and the speed channel when an encoder leads. Returns (seq of its first clipped current sample that was high, else None; the fault reason
        if the fault is raised by this block, "" if cleared, else None).

        A block longer than the evaluation step (a replay's, a catch-up read) goes in as several rows, so
        that the fault is decided at the same sample as with the DAQ's small frames.
        """
        n = counts.shape[0]
        if n <= self.step:
            return self._push(seq0, counts, x, rpm, moving, sp_rpm)
        clip_seq, verdict = None, None
        for a in range(0, n, self.step):
            b = min(n, a + self.step)
            c, v = self._push(seq0 + a, counts[a:b], x[a:b], rpm[a:b], moving[a:b],
                              None if sp_rpm is None else sp_rpm[a:b])
            clip_seq = c if clip_seq is None else clip_seq
            verdict = v if v is not None else verdict
        return clip_seq, verdict

    def _push(self, seq0: int, counts: np.ndarray, x: np.ndarray, rpm: np.ndarray,
              moving: np.ndarray, sp_rpm: np.ndarray | None) -> tuple[int | None, str | None]:
        n = counts.shape[0]
        if self.w == self.cap:
            self._compact(seq0)
        r = self.w
        self.w += 1
        mn = counts.min(axis=0)
        mx = counts.max(axis=0)
        self.first[r], self.last[r] = seq0, seq0 + n - 1
        self.mn[r], self.mx[r] = mn, mx
        xs = x.sum(axis=0)
        s = self.sums[r]
        s[0] = n
        s[1] = np.count_nonzero(moving)
        s[2] = xs[self.fe_col]
        s[3] = xs[self.vsq_col]
        s[4] = rpm.sum()        # signed: the mean's magnitude is taken when judged
        s[5] = sp_rpm.sum() if sp_rpm is not None else 0.0
        clip_seq = None
        if ((mn <= self.lo) | (mx >= self.hi)).any():
            self.clip_lo[r] = (counts <= self.lo).sum(axis=0)
            self.clip_hi[r] = (counts >= self.hi).sum(axis=0)
            clip_seq = self._high_clip(counts, seq0, r)
        else:
            self.clip_lo[r] = 0
            self.clip_hi[r] = 0
        verdict = None
        end = seq0 + n - 1
        if self._next_eval is None:
            self._next_eval = seq0 + self.step - 1
        if end >= self._next_eval:
            self._next_eval = end + self.step
            verdict = self._judge(end)
        return clip_seq, verdict

    @property
    def speed_suspect(self) -> bool:
        """A speed source (encoder, speed channel) is among the problems: "stopped" cannot be believed."""
        return bool(self._speed_names & set(self.last_problems))

    def _compact(self, seq0: int) -> None:
        """Drop rows older than the longest revolution; keep at most half the ring."""
        w = self.w
        start = int(np.searchsorted(self.last[:w], seq0 - self.keep))
        start = max(start, w - self.cap // 2)
        keep = w - start
        for a in (self.first, self.last, self.mn, self.mx, self.clip_lo, self.clip_hi, self.sums):
            a[:keep] = a[start:w]
        self.w = keep

    def _high_clip(self, counts: np.ndarray, seq0: int, r: int) -> int | None:
        """The first clipped current sample of this block, if that current was high (swinging, not stuck)."""
        cols = self.i_cols
        clipped = (counts[:, cols] <= self.lo[cols]) | (counts[:, cols] >= self.hi[cols])
        if not clipped.any():
            return None
        a = self._rows_from(seq0 + counts.shape[0] - self.high_window, r + 1)
        swing = self.mx[a : r + 1, cols].max(axis=0) - self.mn[a : r + 1, cols].min(axis=0)
        high = swing >= HIGH_FRAC * (self.hi[cols] - self.lo[cols])
        hit = clipped & high
        if not hit.any():
            return None
        return seq0 + int(np.argmax(hit.any(axis=1)))

    def _rows_from(self, seq: float, w: int | None = None) -> int:
        """First row whose last sample is at or after `seq`."""
        w = self.w if w is None else w
        return int(np.searchsorted(self.last[:w], seq))

    # ------------------------------------------------------------------ verdicts
    def revolution(self, start_pos: float, end_seq: int) -> tuple[dict[str, str], bool]:
        """Problems in the blocks holding one revolution's samples, and whether a current saturated high."""
        a = self._rows_from(np.floor(start_pos))
        b = int(np.searchsorted(self.first[: self.w], end_seq, side="right"))
        return self._problems(a, max(b, a + 1))

    def _judge(self, end: int) -> str | None:
        a = self._rows_from(end - self.window + 1)
        problems, _ = self._problems(a, self.w)
        if problems:
            self.last_problems = problems
            self._good_since = None
            if self._bad_since is None:
                self._bad_since = end - self.step + 1
            # currents driven past their sensors' range by a crash are a crash (its trip), not a sensor
            # fault, unless it lasts: then the range does not fit the machine
            only_saturation = set(problems) <= self._saturated_names
            need = self.saturation_raise_n if only_saturation else self.raise_n
            if not self.faulted and end - self._bad_since + 1 >= need:
                self.faulted = True
                return "; ".join(problems.values())
            return None
        self._bad_since = None
        if self._good_since is None:
            self._good_since = end - self.step + 1
        if self.faulted and end - self._good_since + 1 >= self.clear_n:
            self.faulted = False
            self.last_problems = {}
            return ""
        return None

    def _problems(self, a: int, b: int) -> tuple[dict[str, str], bool]:
        if b <= a:
            return {}, False
        out: dict[str, str] = {}
        sums = self.sums[a:b].sum(axis=0)
        n = sums[0]
        mn = self.mn[a:b].min(axis=0)
        mx = self.mx[a:b].max(axis=0)
        saturated = False
        self._saturated_names: set[str] = set()
        if (mn <= self.lo).any() or (mx >= self.hi).any():
            lo_n = self.clip_lo[a:b].sum(axis=0)
            hi_n = self.clip_hi[a:b].sum(axis=0)
            for k in np.flatnonzero((lo_n > 0) | (hi_n > 0)):
                which = [f"raw_min {self.lo[k]}"] if lo_n[k] else []
                which += [f"raw_max {self.hi[k]}"] if hi_n[k] else []
                pct = 100.0 * (lo_n[k] + hi_n[k]) / n
                out[self.names[k]] = f"{self.names[k]}: at {' and '.join(which)} in {pct:.0f} % of samples"
            cols = self.i_cols
            swing = mx[cols] - mn[cols]
            clipped = (lo_n[cols] + hi_n[cols]) > 0
            high = clipped & (swing >= HIGH_FRAC * (self.hi[cols] - self.lo[cols]))
            saturated = bool(high.any())
            self._saturated_names = {self.names[k] for k in cols[high]}
        self._flat(mn, mx, int(n), out)
        if not any(self.names[k] in out for k in self.v_cols):  # f_e from a bad voltage means nothing
            self._speed(sums, out)
        return out, saturated

    def _flat(self, mn: np.ndarray, mx: np.ndarray, n: int, out: dict[str, str]) -> None:
        # six numbers at most: plain Python is cheaper than numpy here
        swing = (mx[self.vi_cols] - mn[self.vi_cols]).tolist()
        live = [w >= LIVE_COUNTS for w in swing]
        n_live = sum(live)
        if not n_live:
            return  # nothing swings: the drive is off (or everything is stuck: the clip check speaks then)
        phys = [w * f for w, f in zip(swing, self._vi_scale)]
        for group in self._groups:
            for j in group:
                dead = swing[j] <= FLAT_COUNTS and n_live - live[j] > 0          # another channel swings
                others = [phys[g] for g in group if g != j and live[g]]
                weak = bool(others) and phys[j] < FLAT_REL * max(others)         # its own kind swings more
                name = self.names[self.vi_cols[j]]
                if (dead or weak) and name not in out:
                    out[name] = (f"{name}: flat (peak-to-peak {swing[j]} counts over {n} samples) while the drive "
                                 f"runs: a stuck, dead or unplugged sensor")

    def _speed(self, sums: np.ndarray, out: dict[str, str]) -> None:
        n, moving_n = sums[0], sums[1]
        if n <= 0:
            return
        fe = abs(sums[2] / n)
        v_ok = sums[3] / n >= MIN_VOLTAGE_V**2
        src = abs(sums[4] / n)
        sp = abs(sums[5] / n) if self.sp_name is not None else None
        turning = moving_n == n
        if self.pole_pairs and v_ok:
            sync = fe * 60.0 / self.pole_pairs                  # synchronous motor speed, rpm ([P] eq. 10)
            implied = [(name, sync / ratio) for name, ratio in self.gears]
            should_turn = min(rpm for _, rpm in implied) >= 3.0 * STOP_RPM
            if turning or should_turn:
                band = MAX_SLIP + self.tol
                bad = []
                for name, rpm in ((self.src_name, src), (self.sp_name, sp)):
                    if name is None or rpm is None:
                        continue
                    if not any(abs(rpm / imp - 1.0) <= band for _, imp in implied if imp > 0):
                        bad.append((name, rpm))
                for name, rpm in bad:
                    gear, imp = min(implied, key=lambda g: abs(g[1] - rpm))
                    out[name] = (
                        f"{name}: reads {rpm:.0f} rpm, but the electrical frequency {fe:.1f} Hz means {imp:.0f} rpm "
                        f"in gear {gear} (more than speed_tolerance_pct {100 * self.tol:g} % + {100 * MAX_SLIP:g} % "
                        f"slip apart in every gear)"
                    )
                if bad:
                    return
        if sp is not None and (turning or src >= STOP_RPM or sp >= STOP_RPM):
            ref = max(src, 1e-9)
            if abs(sp / ref - 1.0) > self.tol:
                out[self.sp_name] = (
                    f"{self.sp_name}: reads {sp:.0f} rpm, the encoder {self.src_name} {src:.0f} rpm "
                    f"(more than speed_tolerance_pct {100 * self.tol:g} % apart)"
                )
