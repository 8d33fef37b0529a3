"""Sample blocks -> per-revolution estimates and per-sample air-gap power.

Per block, vectorised: scale counts (`scaling.py`), instantaneous input power
and copper loss ([P] eq. 11 terms), the voltage space vector's rotation rate,
spindle angle (encoder or integrated speed), then exact per-revolution
integrals (`revolutions.py`). Per block, over all the revolutions it closed at
once: their plausibility (`signal_check.py`) and the physics chain of
`per_revolution.py` on (R,) columns, or, when the block closed one good
revolution (the live daemon's block), the same chain on that revolution's
plain floats (`_one_revolution`); only what one revolution hands the next (the
previous speed, the f_e window) is a short loop on plain floats.

The electrical frequency f_e (filter gain, gear, slip-free speed) is the mean
rotation rate of the Clarke voltage vector over the revolution — or over the
last few revolutions when one revolution is shorter than `MIN_FE_WINDOW`
samples. Its sum telescopes to (end phase − start phase)/time, so noise enters
only through two phase readings, and it costs nothing per revolution (a
least-squares phase fit per revolution took ~0.2 ms, a fifth of the budget).

A revolution in which the spindle speeds up by more than `ACCEL_RISE_PCT`
(at least `ACCEL_RISE_MIN_RPM`; its speed at the end against its start: the
per-sample speed rise, summed over the revolution, which telescopes), or that
turns more than
`ACCEL_STEP_PCT` faster than the revolution before it, is published with
`accelerating: true` — information only (a display hint): the alarms judge
every revolution. While the spindle speeds up (a start, a programmed speed
change) the motor's power goes into the rotating masses too (60–77 N·m in the
simulator's speed steps of 150 rpm, with no cut at all); `per_revolution.py`
subtracts that share, J·dω/dt over the revolution ([P] eq. 13 with inertia),
from the speed reading's rise over the revolution (the `rpm_rise` column) and
the gear's `inertia_kgm2`. Without a known J nothing is subtracted, and a
speed-up reads as load (the safe side; `check-config` warns).

A revolution that spans lost samples or a discontinuity is published with
`valid: false`, every physical quantity null and its exact `lost_samples`:
a number built on missing data must not look like a measurement (the
interlock acts on these numbers).

A revolution whose samples fail a plausibility check (`signal_check.py`: a
clipped, flat or dead channel, a speed that disagrees with the electrical
frequency) is published the same way, with `invalid: "signals"` (a damaged
one: `invalid: "lost_samples"`). `saturated: true` marks a revolution in which
a current clipped at its sensor's limit while it was high: a real crash
saturates the sensors, and the alarms count it as over every armed limit.

The tool in the spindle: `Estimator.tool_at`, set by the runner, gives the CNC
tool number at a revolution's last sample (None: unknown); feed per tooth,
force and depth then use that tool's `[tools.N]` geometry, `[tool]` for a tool
the configuration does not list (`per_revolution.py`).

The CNC's feed override: `Estimator.override` (an `OverrideTrack`, shared by
the runner, which notes each STATUS's applied override in it) gives every
revolution its time-weighted mean override, published as `feed_override_pct`
(100.0 when the DAQ reports none, on an invalid revolution too: it is the DAQ's
report, not a figure built from the revolution's samples). Without a feed-rate
channel the feed per tooth and depths use the configured feed times it.

Also per sample: the air-gap power and the largest line current, lightly
smoothed, so that a crash can trip within milliseconds instead of waiting for
the revolution to close (`safety_check.py`).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from itertools import repeat

import numpy as np

from millsense.daemon.physics.power import (
    clarke_alpha_beta_v,
    copper_loss_w,
    input_power_symmetric_w,
    input_power_two_wattmeter_w,
)
from millsense.daemon.pipeline.override_track import OverrideTrack
from millsense.daemon.pipeline.per_revolution import RevolutionColumns, RevolutionMeans, RevolutionPhysics
from millsense.daemon.pipeline.revolutions import STOP_RPM, EncoderAngle, RevolutionSplitter, SpeedAngle
from millsense.daemon.pipeline.scaling import Scaler
from millsense.daemon.pipeline.signal_check import SignalCheck

# Electrical frequency window: the revolution itself, but never fewer samples than
# this (at 4500 rpm a revolution is 13 samples: two phase readings 13 ms apart).
MIN_FE_WINDOW = 100
MIN_VOLTAGE_V = 1.0                # below this space-vector amplitude the drive is off: no f_e
ACCEL_RISE_PCT = 0.25              # speed rise within one revolution that counts as accelerating,
ACCEL_RISE_MIN_RPM = 2.0           # but never less than this (steady cutting reads up to ±0.9 rpm, at
                                   # most 1.8: the encoder's resolution over its 16-sample window)
ACCEL_STEP_PCT = 0.5               # ... or over the revolution before (steady cutting: < 0.08 % in
                                   # every simulated scenario)
# An angle step between two samples faster than this many times the fastest gear's top speed is a jump of
# the reading (an encoder count or a speed sample gone wild for a sample), not a turn: it would move a
# boundary by up to half a revolution (a revolution of 50 samples at "1200 rpm" next to one of 150 at 600).
MAX_STEP_FACTOR = 2.0
# up to this many gain steps in a block (revolutions closed in it, plus one) are divided slice by slice: fewer
# numpy calls than building the per-sample gains, for the live blocks' one or two
SLICED_STEPS = 4
P_GAP_SMOOTH_SAMPLES = 5           # moving average of the sample-level air-gap power and line current

NULL_FIELDS = (
    "spindle_rpm", "gear", "p_in_w", "p_gap_w", "p_inertia_w", "spindle_accel_rad_s2", "torque_nm",
    "torque_sigma_nm", "force_n", "force_tangential_n", "force_feed_n", "feed_per_tooth_mm", "radial_depth_mm",
    "axial_depth_mm", "depth_status",
)

_BASE_KEYS = ("rev", "seq_end", "samples", "lost_samples", "feed_override_pct")


@dataclass
class BlockResult:
    """What one block produced."""

    estimates: list[dict] = field(default_factory=list)   # one per closed revolution
    p_gap_w: np.ndarray = field(default_factory=lambda: np.empty(0))  # per sample, smoothed
    seq: int = 0                                          # seq of p_gap_w[0]
    spindle_stopped: bool = False                         # last sample below the stop speed
    current_a: np.ndarray = field(default_factory=lambda: np.empty(0))  # largest |line current|, smoothed
    clip_seq: int | None = None                           # first current sample at its ADC limit while high
    # fault `signals` raised (its reason) or cleared (""), every change in order, at the seq that decided it
    signal_changes: list[tuple[int, str]] = field(default_factory=list)


class _PhaseRate:
    """Per-sample rotation rate (Hz) of the line-voltage space vector, carried across blocks."""

    def __init__(self, sample_rate_hz: float):
        self.scale = sample_rate_hz / (2.0 * np.pi)
        self._angle: float | None = None
        self._rate = 0.0

    def push(self, v_uv, v_vw, v_wu, contiguous: bool) -> tuple[np.ndarray, np.ndarray]:
        alpha, beta = clarke_alpha_beta_v(v_uv, v_vw, v_wu)
        angle = np.arctan2(beta, alpha)
        first = self._angle if (contiguous and self._angle is not None) else angle[0]
        step = np.empty_like(angle)
        step[0] = angle[0] - first
        np.subtract(angle[1:], angle[:-1], out=step[1:])
        step = (step + np.pi) % (2.0 * np.pi) - np.pi            # wrap into [-pi, pi)
        rate = step * self.scale
        if not (contiguous and self._angle is not None):
            rate[0] = rate[1] if len(rate) > 1 else self._rate   # no step across a gap
        self._angle, self._rate = float(angle[-1]), float(rate[-1])
        return rate, alpha * alpha + beta * beta


class _MovingAverage:
    """Causal moving average over `width` samples of k signals at once ((k, n) blocks), carried across
    blocks, restarted after a gap. One pass for all of them: this runs on every frame."""

    def __init__(self, width: int):
        self.width = int(width)
        self._tail = np.empty((0, 0))

    def push(self, p: np.ndarray, contiguous: bool) -> np.ndarray:
        w = self.width
        k, n = p.shape
        ext = np.empty((k, n + w - 1))
        if contiguous and self._tail.shape == (k, w - 1):
            ext[:, : w - 1] = self._tail
        else:
            ext[:, : w - 1] = p[:, :1]
        ext[:, w - 1 :] = p
        # each mean summed from its own samples, oldest first (w − 1 vector adds): the same numbers whatever
        # the block size, where a running sum's differences would carry the block's rounding
        out = ext[:, :n].copy()
        for j in range(1, w):
            out += ext[:, j : j + n]
        self._tail = ext[:, n:]
        out /= w
        return out


class Estimator:
    """Per-revolution torque/force/depth estimator for one DAQ descriptor.

    `friction_zero=True` (calibration) publishes `torque_nm = P_g/ω`, the
    quantity friction is fitted to. `force_magnitude=True` adds
    `force_measured_n`, the revolution mean of the dynamometer's instantaneous
    |(F_x, F_y)| (the quantity [P] eq. 18 estimates), when fx and fy exist.

    `tool_at` (set by whoever knows the machine's context): given a revolution's
    last sample seq, the CNC tool number in the spindle, or None when unknown.
    None (the default): every revolution uses `[tool]`. `cut_at` likewise: the engagement of the
    operation the CNC reports where `[operations]` declares a constant cut (per_revolution.OperationEngagement),
    which the force's C_f is taken at; None (the default, or no such operation): `[cut]`'s.
    """

    tool_at: Callable[[int], int | None] | None = None
    cut_at: Callable[[int], Any] | None = None

    def __init__(self, settings, descriptor, sample_rate_hz: float | None = None, *,
                 friction_zero: bool = False, force_magnitude: bool = False):
        self.scaler = Scaler(settings, descriptor)
        self.sample_rate_hz = float(sample_rate_hz or descriptor.sample_rate_hz)
        roles = self.scaler.roles
        self.roles = roles
        self.winding = str(settings.motor.winding)
        self.stator_resistance_ohm = float(settings.motor.stator_resistance_ohm)
        self._symmetric = len(roles.voltages) == 3 and len(roles.currents) == 3
        if roles.encoder is not None:
            self.angle = EncoderAngle(self.scaler.counts_per_rev, self.sample_rate_hz)
        else:
            self.angle = SpeedAngle(self.sample_rate_hz)

        feed_force = None
        for name, ff in (getattr(settings, "feed_force", None) or {}).items():
            feed_force = (name, float(ff.newton_per_amp), float(ff.friction_n))
            break   # one feed axis: the force along the feed ([D] F_ax)
        has_dyn = "x" in roles.forces and "y" in roles.forces
        self.physics = RevolutionPhysics(settings, has_dynamometer=has_dyn, feed_force=feed_force,
                                         friction_zero=friction_zero)
        # the filter gain the last block's sample-level power was divided by, from each seq on (`process`)
        self.gain_steps: list[tuple[int, float]] = []

        # columns integrated per revolution
        cols = ["p_in", "p_cu", "p_gap_sq", "f_e", "v_sq", "rpm_rise"]
        if roles.motor_speed:
            cols.append("motor_rpm")
        if roles.feed_rates:
            cols.append("feed_rate")
        if feed_force is not None:
            cols.append("feed_current")
        if has_dyn:
            cols += ["fx", "fy"]
            if force_magnitude:
                cols.append("f_mag")
        self._cols = {c: k for k, c in enumerate(cols)}
        fastest_rpm = max((float(g.max_spindle_rpm) for g in settings.gears), default=math.inf)
        self.splitter = RevolutionSplitter(len(cols), MAX_STEP_FACTOR * fastest_rpm / 60.0 / self.sample_rate_hz)
        self._feed_channel = feed_force[0] if feed_force else None
        self._phase = _PhaseRate(self.sample_rate_hz)
        self._fe_recent: deque[tuple[float, float]] = deque(maxlen=64)   # (f_e integral, duration)
        self._last_seq: int | None = None
        self._smooth = _MovingAverage(P_GAP_SMOOTH_SAMPLES)   # air-gap power, largest line current
        self.signals = SignalCheck(settings, descriptor, roles, self.sample_rate_hz,
                                   fe_col=self._cols["f_e"], vsq_col=self._cols["v_sq"])
        self._sp_name = roles.spindle_speed if roles.encoder is not None else None
        self._stopped = True
        self._prev_rev: tuple[float, float] | None = None  # (end position, spindle rpm) of the last valid revolution
        self._last_rpm: float | None = None
        self.rev = 0
        self.override = OverrideTrack()   # the runner's track replaces it (STATUS frames go there)
        self.stream_problem: str | None = None   # set by PipelineCore: every revolution invalid with this reason

    # --- accounting ------------------------------------------------------------------

    @property
    def lost_samples_total(self) -> int:
        """Every sample the driver reported lost, counted once."""
        return self.splitter.lost_total

    @property
    def lost_samples_idle(self) -> int:
        """Lost while no revolution was open (stopped spindle, start-up)."""
        return self.splitter.lost_idle

    @property
    def spindle_stopped(self) -> bool:
        """The last sample seen turned slower than the stop speed (or none seen yet)."""
        return self._stopped

    @property
    def lost_samples_pending(self) -> int:
        """Lost inside the revolution still open; they will appear in its estimate."""
        return self.splitter.lost_pending

    # --- the block path --------------------------------------------------------------

    def _three(self, phys: dict, names: dict, keys: tuple[str, str, str]) -> tuple[np.ndarray, ...]:
        """The three line quantities; a missing one from the other two (they sum to zero)."""
        got = {k: phys[names[k]] for k in keys if k in names}
        for k in keys:
            if k not in got:
                a, b = (got[o] for o in keys if o != k)
                got[k] = -(a + b)
        return tuple(got[k] for k in keys)

    def process(self, block) -> BlockResult:
        counts = np.asarray(block.counts)
        n = counts.shape[0]
        seq0 = int(block.seq)
        if n == 0:
            self.splitter.push(seq0, np.empty(0), np.empty((0, len(self._cols))), np.empty(0, bool),
                               block.lost_before, block.discontinuity)
            return BlockResult(seq=seq0, spindle_stopped=self._stopped)
        counts = counts.reshape(n, -1)
        r = self.roles
        phys = self.scaler.scale(counts)
        v_uv, v_vw, v_wu = self._three(phys, r.voltages, ("uv", "vw", "wu"))
        i_u, i_v, i_w = self._three(phys, r.currents, ("u", "v", "w"))
        if self._symmetric:
            p_in = input_power_symmetric_w(v_uv, v_vw, v_wu, i_u, i_v, i_w)
        else:
            p_in = input_power_two_wattmeter_w(v_uv, v_vw, i_u, i_v)
        p_cu = copper_loss_w(i_u, i_v, i_w, self.winding, self.stator_resistance_ohm)
        p_meas = p_in - p_cu

        seq = seq0 + np.arange(n, dtype=np.int64)
        contiguous = (self._last_seq is not None and seq0 == self._last_seq + 1
                      and not block.lost_before and not block.discontinuity)
        angle_source = phys[r.encoder] if r.encoder is not None else phys[r.spindle_speed]
        angle_rev, rpm = self.angle.push(seq, angle_source, restart=not contiguous)
        moving = np.abs(rpm) >= STOP_RPM

        x = np.empty((n, len(self._cols)))
        c = self._cols
        x[:, c["p_in"]] = p_in
        x[:, c["p_cu"]] = p_cu
        x[:, c["p_gap_sq"]] = p_meas * p_meas
        x[:, c["f_e"]], x[:, c["v_sq"]] = self._phase.push(v_uv, v_vw, v_wu, contiguous)
        rise = x[:, c["rpm_rise"]]  # rpm gained since the sample before: summed over a revolution, end − start
        rise[0] = rpm[0] - self._last_rpm if (contiguous and self._last_rpm is not None) else 0.0
        np.subtract(rpm[1:], rpm[:-1], out=rise[1:])
        self._last_rpm = float(rpm[-1])
        if "motor_rpm" in c:
            x[:, c["motor_rpm"]] = phys[r.motor_speed]
        if "feed_rate" in c:
            x[:, c["feed_rate"]] = np.sqrt(sum(phys[nm] ** 2 for nm in r.feed_rates))
        if "feed_current" in c:
            x[:, c["feed_current"]] = phys[self._feed_channel]
        if "fx" in c:
            x[:, c["fx"]] = phys[r.forces["x"]]
            x[:, c["fy"]] = phys[r.forces["y"]]
            if "f_mag" in c:
                x[:, c["f_mag"]] = np.hypot(x[:, c["fx"]], x[:, c["fy"]])

        self._last_seq = seq0 + n - 1
        batch = self.splitter.push(seq0, angle_rev, x, moving, block.lost_before, block.discontinuity)
        # plausibility: the revolutions closing in this block are judged with this block's samples, in the
        # same pass as the fault windows
        sp = phys[self._sp_name] if self._sp_name is not None else None
        clip_seq = self.signals.push(seq0, counts, x, rpm, moving, sp, batch.start_pos, batch.seq_end)

        # the filter gain the sample-level power is divided by, from each seq on: the one of the last revolution
        # closed before each sample (so a block's size does not move it); `_estimates` adds this block's
        self.gain_steps = [(seq0, self.physics.last_gain)]
        estimates = self._estimates(batch) if len(batch) else []

        # sample-level air-gap power and line current for the crash trip
        both = np.empty((2, n))
        steps = self.gain_steps   # one step per revolution closed in the block
        # each sample over its own step's gain (a step per revolution closed: one or two in a live block,
        # thousands in a replay's; those get one division by the gains repeated over their steps' samples)
        if len(steps) <= SLICED_STEPS:
            for k, (start, gain) in enumerate(steps):
                a = start - seq0
                b = steps[k + 1][0] - seq0 if k + 1 < len(steps) else n
                np.divide(p_meas[a:b], gain, out=both[0, a:b])
        else:
            bounds = np.array([start for start, _ in steps] + [seq0 + n], dtype=np.int64)
            np.divide(p_meas, np.repeat([gain for _, gain in steps], np.diff(bounds)), out=both[0])
        np.abs(np.stack((i_u, i_v, i_w)), out=None).max(axis=0, out=both[1])
        p_gap, current = self._smooth.push(both, contiguous)
        # a stuck encoder reads "stopped": not believed while a speed source is among the signal problems
        self._stopped = not bool(moving[-1]) and not self.signals.speed_suspect
        return BlockResult(estimates=estimates, p_gap_w=p_gap, seq=seq0, spindle_stopped=self._stopped,
                           current_a=current, clip_seq=clip_seq, signal_changes=self.signals.changes)

    def _one_revolution(self, batch, i: int, rpm: float, mean: np.ndarray, f_e_hz: float, prev_rpm: float,
                        override_pct: float | None) -> tuple[dict[str, list], list[bool]]:
        """`_estimates`' physics of a block that closed one good revolution `i` (the live daemon's block):
        its floats to `RevolutionPhysics.estimate`, the numbers of the columns' path (`estimate_many`)."""
        c = self._cols
        row = mean[i].tolist()

        def column(name):
            return row[c[name]] if name in c else None

        rise = float(batch.integrals[i, c["rpm_rise"]])
        means = RevolutionMeans(
            spindle_rpm=rpm, p_in_meas_w=row[c["p_in"]], p_cu_meas_w=row[c["p_cu"]],
            p_gap_sq_meas_w2=row[c["p_gap_sq"]], samples=int(batch.samples[i]),
            f_e_hz=None if math.isnan(f_e_hz) else f_e_hz, motor_rpm=column("motor_rpm"),
            feed_rate_mm_min=column("feed_rate"), feed_current_a=column("feed_current"),
            force_x_n=column("fx"), force_y_n=column("fy"), speed_rise_rpm=rise,
            prev_spindle_rpm=None if math.isnan(prev_rpm) else prev_rpm, feed_override_pct=override_pct,
        )
        end = int(batch.seq_end[i])
        phys = {k: [v] for k, v in self.physics.estimate(
            means, None if self.tool_at is None else self.tool_at(end),
            None if self.cut_at is None else self.cut_at(end)).items()}
        if end < self._last_seq:   # its filter gain holds for the sample-level power from the sample after it
            self.gain_steps.append((end + 1, self.physics.last_gain))
        if "f_mag" in c:
            phys["force_measured_n"] = [row[c["f_mag"]]]
        return phys, [bool(self._accelerating(rpm, rise, prev_rpm))]

    @staticmethod
    def _accelerating(spindle_rpm, rise_rpm, prev_rpm):
        """Sped up against the revolution just before (nan: none), or within this one while not slowing on
        the whole; over arrays of revolutions, or one revolution's floats."""
        step_pct = 100.0 * (spindle_rpm - prev_rpm) / spindle_rpm
        # A rise within the revolution while its mean speed fell clearly is a drive catching up after a
        # spindle bogged down by its load: that torque is load, and the overload must see it.
        slowing = step_pct < -ACCEL_STEP_PCT
        rising = rise_rpm > np.maximum(ACCEL_RISE_PCT / 100.0 * spindle_rpm, ACCEL_RISE_MIN_RPM)
        return (step_pct > ACCEL_STEP_PCT) | (rising & np.logical_not(slowing))

    def _f_e_hz(self, integral_hz: float, duration: float, mean_v_sq: float) -> float | None:
        """Mean f_e over this revolution, extended back over recent ones to MIN_FE_WINDOW samples."""
        if not mean_v_sq >= MIN_VOLTAGE_V**2:
            self._fe_recent.clear()
            return None
        self._fe_recent.append((integral_hz, duration))
        if duration >= MIN_FE_WINDOW:   # the revolution alone is window enough (600 rpm and slower at 1 kHz)
            return abs(integral_hz / duration)
        total, span = 0.0, 0.0
        for integ, dur in reversed(self._fe_recent):
            total += integ
            span += dur
            if span >= MIN_FE_WINDOW:
                break
        return abs(total / span)

    def _estimates(self, batch) -> list[dict]:
        """The estimates of every revolution a block closed, built once over the batch's columns.

        A revolution is judged before any physics: one built on implausible samples (or a damaged one)
        gets none and is published `valid: false` with its reason. What carries from one revolution to
        the next (the previous revolution's speed, the f_e window) is a short loop on plain floats; the
        physics runs once over the good revolutions' columns (`RevolutionPhysics.estimate_many`).
        """
        count = len(batch)
        problems, saturated = self.signals.revolution_verdicts     # judged by this block's `signals.push`
        sat = saturated.tolist()
        seq_end, samples, lost = batch.seq_end.tolist(), batch.samples.tolist(), batch.lost.tolist()
        # the applied override per revolution: a few steps at most, never per sample
        track = self.override
        overrides = track.means([e - max(n, 1) + 1 for e, n in zip(seq_end, samples)], seq_end)
        if seq_end:
            track.forget_before(seq_end[-1])   # the next revolution starts after this sample
        # damage from lost samples, a gap or a restart: "lost_samples"; only an impossible angle step: "signals"
        # a fault of the whole stream (`stream_problem`, the runner's rate check) before any of these
        own = [("lost_samples" if dmg and (n_lost or not jmp) else "signals" if dmg or prob or s else None)
               for dmg, jmp, n_lost, prob, s in zip(batch.damaged.tolist(), batch.jumped.tolist(), lost, problems, sat)]
        invalid = [self.stream_problem or reason for reason in own]
        c = self._cols
        duration = batch.end_pos - batch.start_pos
        mean = batch.integrals / duration[:, None]
        rpm = 60.0 * self.sample_rate_hz / duration
        starts, ends, rpm_l = batch.start_pos.tolist(), batch.end_pos.tolist(), rpm.tolist()
        fe_int, dur_l = batch.integrals[:, c["f_e"]].tolist(), duration.tolist()
        v_sq = mean[:, c["v_sq"]].tolist()
        good: list[int] = []
        f_e: list[float] = []
        prev_rpm: list[float] = []
        for i in range(count):
            if invalid[i] is not None:
                # what the physics carries to the next revolution must not come from these samples
                self._fe_recent.clear()
                self._prev_rev = None
                continue
            prev = self._prev_rev   # the revolution just before, if it ended where this one starts
            prev_rpm.append(prev[1] if prev is not None and abs(prev[0] - starts[i]) < 1e-6 else np.nan)
            self._prev_rev = (ends[i], rpm_l[i])
            fe = self._f_e_hz(fe_int[i], dur_l[i], v_sq[i])
            f_e.append(np.nan if fe is None else fe)
            good.append(i)

        phys: dict[str, list] = {}
        accelerating: list[bool] = []
        if len(good) == 1:   # the live daemon's block: one revolution, on plain floats
            i = good[0]
            phys, accelerating = self._one_revolution(batch, i, rpm_l[i], mean, f_e[0], prev_rpm[0],
                                                      overrides[i] if track.reported else None)
        elif good:
            g = np.array(good, dtype=np.intp)
            m = mean[g]
            rise = batch.integrals[g, c["rpm_rise"]]   # end − start speed: the inertia term's Δω
            prev = np.array(prev_rpm)

            def column(name):
                return m[:, c[name]] if name in c else None

            cols = RevolutionColumns(
                spindle_rpm=rpm[g], p_in_meas_w=m[:, c["p_in"]], p_cu_meas_w=m[:, c["p_cu"]],
                p_gap_sq_meas_w2=m[:, c["p_gap_sq"]], samples=batch.samples[g], f_e_hz=np.array(f_e),
                motor_rpm=column("motor_rpm"), feed_rate_mm_min=column("feed_rate"),
                feed_current_a=column("feed_current"), force_x_n=column("fx"), force_y_n=column("fy"),
                speed_rise_rpm=rise, prev_spindle_rpm=prev,
                feed_override_pct=None if not track.reported else np.array([overrides[i] for i in good]),
            )
            tool_at = self.tool_at
            tools = None if tool_at is None else [tool_at(s) for s in batch.seq_end[g].tolist()]
            cut_at = self.cut_at
            cuts = None if cut_at is None else [cut_at(s) for s in batch.seq_end[g].tolist()]
            phys = self.physics.estimate_many(cols, tools, cuts)
            # each revolution's filter gain holds for the sample-level power from the sample after it
            ends, gains = batch.seq_end[g].tolist(), self.physics.gains
            self.gain_steps += [(e + 1, gain) for e, gain in zip(ends, gains) if e < self._last_seq]
            accelerating = self._accelerating(rpm[g], rise, prev).tolist()
            if "f_mag" in c:
                phys["force_measured_n"] = m[:, c["f_mag"]].tolist()

        # one dict per revolution, built in one go from its row (this runs for every revolution of a replay)
        first = self.rev + 1
        self.rev += count
        rounded = {o: round(o, 2) for o in set(overrides)}   # a batch holds one override, or a few
        ovr = [rounded[o] for o in overrides]
        has_fm = "f_mag" in c
        fm = (("force_measured_n",) if has_fm else ())
        out: list[dict | None] = [None] * count
        if good:
            keys = [k for k in phys if k != "force_measured_n"]
            names = (*keys, *_BASE_KEYS, "valid", "invalid", "accelerating", *fm, "saturated")
            base = ([first + i for i in good], [seq_end[i] for i in good], [samples[i] for i in good],
                    [lost[i] for i in good], [ovr[i] for i in good])
            rows = zip(*(phys[k] for k in keys), *base, repeat(True), repeat(None), accelerating,
                       *(phys[k] for k in fm), [sat[i] for i in good])
            for i, row in zip(good, rows):
                out[i] = dict(zip(names, row))
        for i in range(count):
            if out[i] is None:
                est = dict.fromkeys(NULL_FIELDS)
                est.update(zip(_BASE_KEYS, (first + i, seq_end[i], samples[i], lost[i], ovr[i])), valid=False,
                           invalid=invalid[i], cutting=False, accelerating=False)
                if own[i] is None:   # whole, invalid only for the stream's fault: the wiring check still reads it
                    est["wiring_p_in_w"], est["wiring_rpm"] = float(mean[i, c["p_in"]]), rpm_l[i]
                if has_fm:
                    est["force_measured_n"] = None
                est["saturated"] = sat[i]
                out[i] = est
        return out
