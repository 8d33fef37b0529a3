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
  Only with evidence that the phases should have swung alike: the three of
  the kind measured and not summing to zero (Kirchhoff: line currents and line
  voltages always do, so a sensor reading its true share is not dead, however
  small that share), or, with two measured, the field turned through at least
  one electrical period. A standing current vector (the drive magnetising the
  motor before a start, DC braking after a stop) leaves one phase near zero.
- **Speed against the electrical frequency** (needs `[motor] pole_pairs`): the
  spindle speed (speed channel, or encoder) times a gear's ratio must be the
  synchronous speed f_e·60/pole_pairs ([P] eq. 10) within `MAX_SLIP` (an
  induction motor turns up to its breakdown slip slower, faster while it
  brakes) plus `[signals] speed_tolerance_pct`, in some gear. With both a speed
  channel and an encoder, they must agree within `speed_tolerance_pct`.
  Checked while the spindle turns, or while f_e says it should (a dead encoder
  reads "stopped" under a running drive). Only the samples with a voltage
  (`MIN_VOLTAGE_V`) count, f_e and the speeds averaged over the same ones, and
  only in a window where the drive was on for at least `ON_SHARE` of it: f_e
  read from the noise of a drive that is off means nothing (it jumps by
  hundreds of Hz a sample), and a window that holds a stop and a start would
  otherwise weigh that noise against a spindle at rest.

Cost: per block, the raw counts and a few per-sample columns go into a ring of
samples (`KEEP_S` of them). The checks run on exact sample ranges: over each
revolution's own samples as it closes (so the revolution that holds the bad
samples is the one marked, and no other), and every `EVAL_STEP_S` of samples,
counted from the first sample ever, over the last `WINDOW_S` for the fault. All
the ranges a block asks about are screened together in one numpy pass
(`_problems_many`: one `reduceat` per statistic); only a range that could hold a
problem is worded by the exact check, one at a time. Everything counts samples
by index, never by wall clock, and nothing depends on where the blocks were cut:
a replay decides exactly as the live daemon, whatever its read size. (Before
stop 16 the ring held one row per block, so a revolution was judged with the
samples of the whole blocks around it, and a replay's large blocks could make a
revolution next to a clipped one valid or invalid depending on its read size.)

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
# The speed channel and the encoder may differ by this much whatever the speed: a tacho or the drive's
# speed output lags the encoder by milliseconds, which while the spindle brakes hard for a tool change is
# 5-15 rpm, "more than 10 %" below 150 rpm. A stuck or mis-scaled channel is caught above a few hundred.
SPEED_AGREE_RPM = 20.0
MIN_VOLTAGE_V = 1.0     # space-vector amplitude below which the drive is off: f_e means nothing
HIGH_FRAC = 0.25        # a clipped current is "high" (not stuck) if it swung this share of its range
HIGH_WINDOW_S = 0.05    # ... within this much of samples before
ON_SHARE = 0.5          # f_e is judged in a window where the drive was on for at least this share of it
# Line currents and line voltages sum to zero. A dead sensor makes the sum its phase's true value (as large
# as the others' swing while the field turns); healthy sensors leave their gain errors, a few % of it.
KIRCHHOFF_SHARE = 0.25
WINDOW_S = 0.2          # fault window: at least one electrical period down to f_e = 5 Hz
EVAL_STEP_S = 0.1       # ... evaluated this often (windows overlap by half)
RAISE_S = 0.2           # bad for this long (two evaluations in a row): fault
SATURATION_RAISE_S = 0.8  # ... but currents clipped while high: a crash saturates them for a few revolutions
CLEAR_S = 1.0           # good for this long: fault cleared
# A sensor that has just failed (torn off, stuck): over the newest PIN_SAMPLES samples it moves by no more
# than PIN_COUNTS while another channel of its kind swings LIVE_COUNTS. A healthy phase at its peak moves
# more than that over 5 samples whenever another swings so much, down to f_e = 5 Hz (the others' swing
# bounds its amplitude: 0.136 A >= 200 gives 0.003 A >= 4.5 counts). Not a verdict (a revolution needs
# longer evidence): the feed controller raises no feed while it holds (afc/controller.py).
PIN_SAMPLES = 5
PIN_COUNTS = 2
KEEP_S = 2.5            # rows kept: the longest revolution (at STOP_RPM, 2 s) and some
MIN_ROWS = 512
# Ranges up to this many are checked one by one by the exact check instead of the batched screen: on the live
# closing block (a fault window and a revolution) that is fewer numpy calls, each of which costs several times
# more after the estimator thread's sleep (bench/idle_penalty.py). The screen only filters: the same verdicts.
EXACT_UP_TO = 2


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
        signed = np.ones(c)
        for k, (name, kind) in enumerate(zip(self.names, kinds)):
            cfg = channels.get(name)
            if cfg is None or kind == ChannelKind.ENCODER:
                continue
            self.lo[k], self.hi[k] = int(cfg.raw_min), int(cfg.raw_max)
            signed[k] = float(cfg.scale)
            self.scale[k] = abs(signed[k])
        col = {n: k for k, n in enumerate(self.names)}
        self.v_cols = np.array([col[n] for n in roles.voltages.values()], dtype=np.intp)
        self.i_cols = np.array([col[n] for n in roles.currents.values()], dtype=np.intp)
        self.vi_cols = np.concatenate([self.v_cols, self.i_cols])
        # no current between these touches its limit
        self._i_lo_max, self._i_hi_min = int(self.lo[self.i_cols].max()), int(self.hi[self.i_cols].min())
        nv = len(self.v_cols)
        self._groups = [range(nv), range(nv, len(self.vi_cols))]
        self._vi_scale = self.scale[self.vi_cols].tolist()
        self._vi_signed = signed[self.vi_cols]
        self._vi_scale_arr = self.scale[self.vi_cols]
        # the same as plain Python numbers, for the checks of one range (`_problems`)
        self._lo_l, self._hi_l, self._vi_l = self.lo.tolist(), self.hi.tolist(), self.vi_cols.tolist()
        self._v_names = [self.names[k] for k in self.v_cols.tolist()]
        # for each voltage/current column, the other columns of its kind (padded with the spare column)
        others = [[g for g in grp if g != j] for grp in self._groups for j in grp]
        width = max(1, max(len(o) for o in others))
        self._others = np.array([o + [len(self.vi_cols)] * (width - len(o)) for o in others], dtype=np.intp)
        self.roles = roles
        self.pole_pairs = getattr(settings.motor, "pole_pairs", None)
        self.gears = [(str(g.name), float(g.ratio)) for g in settings.gears]
        self._inv_ratios = 1.0 / np.array([ratio for _, ratio in self.gears])
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
        cap = max(MIN_ROWS, 2 * self.keep)
        self._alloc(cap, c)
        self._next_eval: int | None = None
        self._bad_since: int | None = None
        self._good_since: int | None = None
        self.faulted = False
        self.last_problems: dict[str, str] = {}
        # the fault's changes decided by the last `push`, in order: (seq of the window's end, reason; "" cleared).
        # A large block (a replay's, a live catch-up) can raise and clear it within itself.
        self.changes: list[tuple[int, str]] = []
        # the problems and saturation of the revolutions handed to the last `push`
        self.revolution_verdicts: tuple[list[dict[str, str]], np.ndarray] = ([], np.zeros(0, dtype=bool))

    _RING = ("seq", "v", "sums")
    # the columns of `sums`, summed over a range: samples, moving ones, f_e (Hz) where the drive is on, samples
    # with the drive on, rpm of the angle source, of the speed channel, and each of these where the drive is on
    N, MOVING, FE_ON, ON, SRC, SP, SRC_ON, SP_ON = range(8)

    def _alloc(self, cap: int, c: int) -> None:
        """The ring: one row per sample. `seq` its number, `v` its raw counts, `sums` the columns above."""
        self.cap = cap
        self.w = 0
        # one spare row past the capacity: `np.ufunc.reduceat` needs every range's end to be a valid index
        self.seq = np.zeros(cap + 1, dtype=np.int64)
        self.v = np.zeros((cap + 1, c), dtype=np.int32)
        self.sums = np.zeros((cap + 1, 8))

    # ------------------------------------------------------------------ per block
    def push(self, seq0: int, counts: np.ndarray, x: np.ndarray, rpm: np.ndarray,
             moving: np.ndarray, sp_rpm: np.ndarray | None, rev_start: np.ndarray | None = None,
             rev_end: np.ndarray | None = None) -> int | None:
        """One block: raw counts (n, C), the estimator's per-sample columns `x` (n, K) (of which `fe_col`
        is f_e in Hz and `vsq_col` the squared voltage space vector), the spindle speed (rpm) of the angle
        source, which samples turn, and the speed channel when an encoder leads. Returns the seq of its first
        clipped current sample that was high, else None; the fault's changes are left in `changes`.

        Each sample is a row, so a block of any size (the DAQ's frame, a replay's read, a catch-up) decides
        the fault at the same sample and judges every revolution on its own samples. The fault windows the
        block closes are judged in one batch (`_problems_many`), then fed in order to the raise/clear
        state machine.

        `rev_start`, `rev_end`: the start positions and last seqs of the revolutions this block closed;
        they are judged in the same pass (`revolutions` on their samples) and left in
        `revolution_verdicts`: (problems of each, saturated (R,) bool).
        """
        n = counts.shape[0]
        self.revolution_verdicts = ([], np.zeros(0, dtype=bool))
        self.changes = []
        if n == 0:
            return None
        self._reserve(n, seq0)
        r0 = self.w
        r1 = r0 + n
        self.w = r1
        self.seq[r0:r1] = np.arange(seq0, seq0 + n, dtype=np.int64)
        self.v[r0:r1] = counts
        s = self.sums[r0:r1]
        s[:, self.N] = 1.0
        s[:, self.MOVING] = moving
        on = s[:, self.ON]
        np.greater_equal(x[:, self.vsq_col], MIN_VOLTAGE_V**2, out=on, casting="unsafe")  # NaN: off
        np.multiply(x[:, self.fe_col], on, out=s[:, self.FE_ON])
        s[:, self.FE_ON][on == 0] = 0.0                    # f_e of the noise may be anything, inf or NaN too
        s[:, self.SRC] = rpm       # signed: the mean's magnitude is taken when judged
        s[:, self.SP] = sp_rpm if sp_rpm is not None else 0.0
        np.multiply(s[:, self.SRC], on, out=s[:, self.SRC_ON])
        np.multiply(s[:, self.SP], on, out=s[:, self.SP_ON])
        clip_seq = None
        # rare: a current at a limit (the other channels' limits are judged with the ranges below). The
        # currents' extremes over all of them first (a column-wise min over an (n, C) block is a strided
        # pass, several times slower), per column only if one could be at its limit
        cur = counts.take(self.i_cols, axis=1)
        if (int(cur.min()) <= self._i_lo_max or int(cur.max()) >= self._i_hi_min) and (
                (cur.min(axis=0) <= self.lo[self.i_cols]).any() or (cur.max(axis=0) >= self.hi[self.i_cols]).any()):
            clip_seq = self._high_clip(r0, r1)

        # the fault windows this block closes: every EVAL_STEP_S of samples, counted from the first sample ever
        nxt = self._next_eval if self._next_eval is not None else seq0 + self.step - 1
        if nxt < seq0:   # samples were lost over an evaluation: the next one on the same cadence
            nxt += -(-(seq0 - nxt) // self.step) * self.step
        last_seq = seq0 + n - 1
        ends = np.arange(nxt, last_seq + 1, self.step, dtype=np.int64)
        self._next_eval = int(ends[-1]) + self.step if len(ends) else nxt
        evals = list(zip((ends - seq0 + r0).tolist(), ends.tolist()))     # (row, its seq)
        revs = len(rev_start) if rev_start is not None else 0
        if evals or revs:
            # the fault windows and the closed revolutions' rows, screened in one pass
            w = self.w
            a_eval = np.searchsorted(self.seq[:w], ends - self.window + 1)
            b_eval = np.array([r + 1 for r, _ in evals], dtype=np.int64)
            if revs:
                a_rev = np.searchsorted(self.seq[:w], np.floor(rev_start))
                b_rev = np.maximum(np.searchsorted(self.seq[:w], rev_end, side="right"), a_rev + 1)
                found = self._problems_many(np.concatenate([a_eval, a_rev]), np.concatenate([b_eval, b_rev]))
            else:
                found = self._problems_many(a_eval, b_eval)
            windows = found[: len(evals)]
            if not self.faulted and evals and all(f is self._CLEAN for f in windows):
                # every window clean and nothing to clear: what `_judge` would do for each, at once
                self._bad_since = None
                if self._good_since is None:
                    self._good_since = evals[0][1] - self.step + 1
            else:
                for (_, end), f in zip(evals, windows):
                    v = self._judge(end, f)
                    if v is not None:
                        self.changes.append((end, v))
            self.revolution_verdicts = ([f[0] for f in found[len(evals):]],
                                        np.array([f[1] for f in found[len(evals):]], dtype=bool))
        else:
            self.revolution_verdicts = ([], np.zeros(0, dtype=bool))
        return clip_seq

    def _reserve(self, rows: int, seq0: int) -> None:
        """Room for `rows` more rows: drop old ones, or grow for a block larger than half the ring."""
        if self.w + rows <= self.cap:
            return
        self._compact(seq0)
        if self.w + rows <= self.cap:
            return
        cap, old = max(2 * self.cap, self.w + rows), self
        keep = {k: getattr(old, k)[: old.w].copy() for k in self._RING}
        w = self.w
        self._alloc(cap, self.v.shape[1])
        for k, v in keep.items():
            getattr(self, k)[:w] = v
        self.w = w

    @property
    def speed_suspect(self) -> bool:
        """A speed source (encoder, speed channel) is among the problems: "stopped" cannot be believed."""
        return bool(self._speed_names & set(self.last_problems))

    def _compact(self, seq0: int) -> None:
        """Drop rows older than the longest revolution; keep at most half the ring."""
        w = self.w
        start = int(np.searchsorted(self.seq[:w], seq0 - self.keep))
        start = max(start, w - self.cap // 2)
        keep = w - start
        for name in self._RING:
            a = getattr(self, name)
            a[:keep] = a[start:w]
        self.w = keep

    def _high_clip(self, r0: int, r1: int) -> int | None:
        """The first sample of rows [r0, r1) where a current sits at a limit while it was high: it swung at
        least `HIGH_FRAC` of its range over the `high_window` samples up to it (swinging, not stuck)."""
        cols = self.i_cols
        block = self.v[r0:r1][:, cols]
        clipped = (block <= self.lo[cols]) | (block >= self.hi[cols])
        rows = np.flatnonzero(clipped.any(axis=1))
        if len(rows) == 0:
            return None
        a = self._rows_from(self.seq[r0] - self.high_window + 1, r0)   # not past a gap before the block
        span = self.v[a:r1][:, cols]
        # the window of each sample: the high_window samples up to it, within what the ring holds
        pad = self.high_window - 1 - (r0 - a)
        lo_pad = np.full((pad, len(cols)), np.iinfo(np.int32).max, dtype=np.int32)
        hi_pad = np.full((pad, len(cols)), np.iinfo(np.int32).min, dtype=np.int32)
        windows_lo = np.lib.stride_tricks.sliding_window_view(np.concatenate([lo_pad, span]), self.high_window, axis=0)
        windows_hi = np.lib.stride_tricks.sliding_window_view(np.concatenate([hi_pad, span]), self.high_window, axis=0)
        swing = windows_hi[rows].max(axis=2).astype(np.int64) - windows_lo[rows].min(axis=2)
        hit = clipped[rows] & (swing >= HIGH_FRAC * (self.hi[cols] - self.lo[cols]))
        first = np.flatnonzero(hit.any(axis=1))
        return None if len(first) == 0 else int(self.seq[r0 + rows[first[0]]])

    def newest_pinned(self) -> str | None:
        """The name of a voltage or current channel that has not moved over the newest samples while another
        of its kind swung (PIN_SAMPLES, PIN_COUNTS above), else None."""
        w, k = self.w, PIN_SAMPLES
        if w < k or self.seq[w - 1] - self.seq[w - k] != k - 1:
            return None
        tail = self.v[w - k : w][:, self.vi_cols]
        swing = (tail.max(axis=0) - tail.min(axis=0)).tolist()
        for group in self._groups:
            if any(swing[j] >= LIVE_COUNTS for j in group):
                for j in group:
                    if swing[j] <= PIN_COUNTS:
                        return self.names[self.vi_cols[j]]
        return None

    def _rows_from(self, seq: float, w: int | None = None) -> int:
        """First row whose last sample is at or after `seq`."""
        w = self.w if w is None else w
        return int(np.searchsorted(self.seq[:w], seq))

    # ------------------------------------------------------------------ verdicts
    def revolution(self, start_pos: float, end_seq: int) -> tuple[dict[str, str], bool]:
        """Problems in one revolution's samples, and whether a current saturated high."""
        problems, saturated = self.revolutions(np.array([start_pos], float), np.array([end_seq], np.int64))
        return problems[0], bool(saturated[0])

    def revolutions(self, start_pos: np.ndarray, end_seq: np.ndarray) -> tuple[list[dict[str, str]], np.ndarray]:
        """`revolution` for every revolution a block closed at once: (problems of each, saturated (R,) bool)."""
        if len(start_pos) == 0:
            return [], np.zeros(0, dtype=bool)
        w = self.w
        a = np.searchsorted(self.seq[:w], np.floor(start_pos))
        b = np.searchsorted(self.seq[:w], end_seq, side="right")
        found = self._problems_many(a, np.maximum(b, a + 1))
        return [f[0] for f in found], np.array([f[1] for f in found], dtype=bool)

    def _judge(self, end: int, found: tuple[dict[str, str], bool, set[str]]) -> str | None:
        problems, _, saturated_names = found
        if problems:
            self.last_problems = problems
            self._good_since = None
            if self._bad_since is None:
                self._bad_since = end - self.step + 1
            # currents driven past their sensors' range by a crash are a crash (its trip), not a sensor
            # fault, unless it lasts: then the range does not fit the machine
            only_saturation = set(problems) <= saturated_names
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

    _CLEAN: tuple[dict[str, str], bool, set[str]] = ({}, False, set())

    def _problems_many(self, a: np.ndarray, b: np.ndarray) -> list[tuple[dict[str, str], bool, set[str]]]:
        """`_problems` of the row ranges [a_i, b_i) (a_i < b_i), screened together.

        One numpy pass over all ranges finds those that could hold a problem; only those (a clipped,
        flat or dead channel, a speed near or past its tolerance: rare) go through the exact
        `_problems`, which words the reasons. The screen errs towards "could": its speed limits are
        a hair (relative 1e-9) tighter, so a range the exact check would fault is never passed clean.
        Up to `EXACT_UP_TO` ranges skip the screen and go straight to the exact check: fewer numpy calls.
        """
        q = len(a)
        if q <= EXACT_UP_TO:   # the live closing block's two (a window, a revolution): the exact check is cheaper
            return [self._problems(x, y) for x, y in zip(a.tolist(), b.tolist())]
        idx = np.empty(2 * q, dtype=np.intp)
        idx[0::2] = a
        idx[1::2] = b
        top = min(max(self.w, int(b.max())) + 1, len(self.sums))   # the spare row keeps every end valid
        sums = np.add.reduceat(self.sums[:top], idx, axis=0)[0::2]
        mn = np.minimum.reduceat(self.v[:top], idx, axis=0)[0::2]
        mx = np.maximum.reduceat(self.v[:top], idx, axis=0)[0::2]
        suspect = ((mn <= self.lo) | (mx >= self.hi)).any(axis=1)
        suspect |= self._flat_many(mn, mx)
        suspect |= self._speed_many(sums)
        if not suspect.any():
            return [self._CLEAN] * q
        a_l, b_l = a.tolist(), b.tolist()
        return [self._problems(a_l[i], b_l[i]) if s else self._CLEAN for i, s in enumerate(suspect.tolist())]

    def _flat_many(self, mn: np.ndarray, mx: np.ndarray) -> np.ndarray:
        """(Q,) bool: `_flat` would name some channel (the same rule, every range at once)."""
        swing = mx[:, self.vi_cols] - mn[:, self.vi_cols]
        live = swing >= LIVE_COUNTS
        n_live = live.sum(axis=1)
        phys = swing * self._vi_scale_arr
        strength = np.full((len(swing), phys.shape[1] + 1), -np.inf)   # one spare column: "no other"
        np.copyto(strength[:, :-1], phys, where=live)
        strongest = strength[:, self._others].max(axis=2)             # the strongest other live one of its kind
        weak = phys < FLAT_REL * strongest
        dead = (swing <= FLAT_COUNTS) & ((n_live[:, None] - live) > 0)
        return (dead | weak).any(axis=1) & (n_live > 0)

    def _speed_many(self, sums: np.ndarray) -> np.ndarray:
        """(Q,) bool: `_speed` could name a speed source. A screen: its limits are a relative 1e-9 tighter
        (and divisions are multiplied out, which moves a comparison by rounding only)."""
        tight = 1.0 - 1e-9
        n = sums[:, self.N]
        src = np.abs(sums[:, self.SRC] / n)
        sp = np.abs(sums[:, self.SP] / n) if self.sp_name is not None else None
        turning = sums[:, self.MOVING] == n
        out = np.zeros(len(n), dtype=bool)
        if self.pole_pairs:
            on_n = sums[:, self.ON]
            per_on = 1.0 / np.maximum(on_n, 1.0)
            fe = np.abs(sums[:, self.FE_ON] * per_on)
            implied = (fe * 60.0 / self.pole_pairs)[:, None] * self._inv_ratios      # [P] eq. 10, every gear
            on_enough = (on_n > 0) & (on_n >= ON_SHARE * n)
            checked = on_enough & (turning | (implied.min(axis=1) >= 3.0 * STOP_RPM * tight))
            if checked.any():
                band = (MAX_SLIP + self.tol) * tight * implied
                positive = implied > 0
                src_on = np.abs(sums[:, self.SRC_ON] * per_on)
                sp_on = np.abs(sums[:, self.SP_ON] * per_on) if self.sp_name is not None else None
                for rpm in (src_on, sp_on):
                    if rpm is not None:
                        fits = (positive & (np.abs(rpm[:, None] - implied) <= band)).any(axis=1)
                        out |= checked & ~fits
        if sp is not None:
            ref = np.maximum(src, 1e-9)
            near = turning | (src >= STOP_RPM * tight) | (sp >= STOP_RPM * tight)
            out |= near & (np.abs(sp - ref) > np.maximum(self.tol * ref, SPEED_AGREE_RPM) * tight)
        return out

    def _problems(self, a: int, b: int) -> tuple[dict[str, str], bool, set[str]]:
        """Problems of rows [a, b), worded; whether a current saturated high, and which."""
        if b <= a:
            return {}, False, set()
        out: dict[str, str] = {}
        sums = self.sums[a:b].sum(axis=0).tolist()   # a few numbers: plain Python from here, numpy only if clipped
        n = sums[0]
        v = self.v[a:b]
        mn = v.min(axis=0)
        mx = v.max(axis=0)
        mn_l, mx_l = mn.tolist(), mx.tolist()
        saturated = False
        saturated_names: set[str] = set()
        if any(x <= lo for x, lo in zip(mn_l, self._lo_l)) or any(x >= hi for x, hi in zip(mx_l, self._hi_l)):
            lo_n = (v <= self.lo).sum(axis=0)
            hi_n = (v >= self.hi).sum(axis=0)
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
            saturated_names = {self.names[k] for k in cols[high]}
        self._flat(a, b, mn_l, mx_l, sums, out)
        if not any(name in out for name in self._v_names):  # f_e from a bad voltage means nothing
            self._speed(sums, out)
        return out, saturated, saturated_names

    def _flat(self, a: int, b: int, mn: list[int], mx: list[int], sums: list[float], out: dict[str, str]) -> None:
        # six numbers at most: plain Python is cheaper than numpy here
        swing = [mx[k] - mn[k] for k in self._vi_l]
        live = [w >= LIVE_COUNTS for w in swing]
        n_live = sum(live)
        if not n_live:
            return  # nothing swings: the drive is off (or everything is stuck: the clip check speaks then)
        n = int(sums[self.N])
        phys = [w * f for w, f in zip(swing, self._vi_scale)]
        for group in self._groups:
            for j in group:
                dead = swing[j] <= FLAT_COUNTS and n_live - live[j] > 0          # another channel swings
                others = [phys[g] for g in group if g != j and live[g]]
                weak = bool(others) and phys[j] < FLAT_REL * max(others)         # its own kind swings more
                name = self.names[self.vi_cols[j]]
                if (dead or weak) and name not in out and self._should_swing_alike(a, b, group, others, sums):
                    out[name] = (f"{name}: flat (peak-to-peak {swing[j]} counts over {n} samples) while the drive "
                                 f"runs: a stuck, dead or unplugged sensor")

    def _should_swing_alike(self, a: int, b: int, group: range, others: list[float], sums: list[float]) -> bool:
        """Evidence that the phases of `group` should have swung alike over rows [a, b): with all three
        measured, they do not sum to zero (Kirchhoff); with two, the field turned through an electrical
        period (f_e over the samples with a voltage). A kind of which nothing swings while the other kind
        does (`others` empty: every current, or every voltage, silent) is named as before: no sum or
        frequency can be read from it, and an unplugged sensor board looks like that."""
        if not others:
            return True
        if len(group) == 3:
            cols = self.vi_cols[group.start : group.stop]
            total = self.v[a:b][:, cols] @ self._vi_signed[group.start : group.stop]
            return float(total.max() - total.min()) >= KIRCHHOFF_SHARE * max(others)
        return abs(float(sums[self.FE_ON])) / self.rate >= 1.0

    def _speed(self, sums: list[float], out: dict[str, str]) -> None:
        n, moving_n, on_n = sums[self.N], sums[self.MOVING], sums[self.ON]
        if n <= 0:
            return
        src = abs(sums[self.SRC] / n)
        sp = abs(sums[self.SP] / n) if self.sp_name is not None else None
        turning = moving_n == n
        if self.pole_pairs and on_n > 0 and on_n >= ON_SHARE * n:
            # f_e and the speeds over the same samples: those with a voltage
            fe = abs(sums[self.FE_ON] / on_n)
            src_on = abs(sums[self.SRC_ON] / on_n)
            sp_on = abs(sums[self.SP_ON] / on_n) if self.sp_name is not None else None
            sync = fe * 60.0 / self.pole_pairs                  # synchronous motor speed, rpm ([P] eq. 10)
            implied = [(name, sync / ratio) for name, ratio in self.gears]
            should_turn = min(rpm for _, rpm in implied) >= 3.0 * STOP_RPM
            if turning or should_turn:
                band = MAX_SLIP + self.tol
                bad = []
                for name, rpm in ((self.src_name, src_on), (self.sp_name, sp_on)):
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
            if abs(sp - ref) > max(self.tol * ref, SPEED_AGREE_RPM):
                out[self.sp_name] = (
                    f"{self.sp_name}: reads {sp:.0f} rpm, the encoder {self.src_name} {src:.0f} rpm "
                    f"(more than speed_tolerance_pct {100 * self.tol:g} % and {SPEED_AGREE_RPM:g} rpm apart)"
                )
