"""The plant: spindle drive, gearbox, cutting process, induction motor and DAQ, in the time domain.

Per block of n output samples (1 kHz) the plant runs, in this order:

1. the feed servo and the NC program at 1 kHz (a short sequential loop: rate-
   limited feed, position-based feed program times the CNC's feed override,
   feed hold, scenario loop);
2. the cutting torque at 1 kHz with the spindle angle extrapolated at the block's
   start speed: the load the speed loop sees (the drive's bandwidth is a few Hz,
   so this prediction's error, a speed dip of < 0.1 % over one block, is far
   below anything the drive responds to);
3. the spindle at 1 kHz (sequential): PI speed loop on motor speed, torque lag,
   torque/power limits, inertia, friction of [P] eq. 13 referred to the spindle;
4. the cutting forces again on a finer grid with the true angle and feed per
   tooth (these are the truth and the dynamometer/feed-drive signals);
5. motor voltages and currents at the internal rate (10 kHz), sensors, noise,
   anti-alias filter, sampling, quantisation.

Nothing here imports ``millsense.daemon``: this is the machine, not the model.
"""

from __future__ import annotations

import bisect
import math

import numpy as np

from millsense.drivers.protocol import Descriptor
from millsense.sim.cut_effects import material_batch
from millsense.sim.cutting import CutGeometry, cutting_forces, tooth_chip_factors
from millsense.sim.lti import BlockFilter, first_order
from millsense.sim.motor import motor_waveforms
from millsense.sim.scenarios import Scenario, get_scenario
from millsense.sim.sensors import (
    AntiAliasFilter,
    ChannelKind,
    descriptor_channels,
    encoder_counts,
    quantise,
    select_sensors,
)
from millsense.sim.truth import TruthRecorder

SAMPLE_RATE_HZ = 1000
INTERNAL_PER_SAMPLE = 10  # internal rate 10 kHz
CUT_PER_SAMPLE = 2  # cutting forces (truth, dynamometer): exact means over 0.5 ms intervals
MAX_BLOCK = 1000
PREROLL_SAMPLES = 100  # the DAQ was sampling before index 0: filters settled
TWO_PI = 2 * math.pi


class Plant:
    """One simulated machine running one scenario, producing raw DAQ counts."""

    def __init__(self, scenario: str | Scenario, *, seed: int = 0, extra_channels=None,
                 filter_cutoff_hz: float | None = None, noise_scale: float = 1.0, loop: bool = False) -> None:
        self.scenario = scenario if isinstance(scenario, Scenario) else get_scenario(scenario)
        sc = self.scenario
        if noise_scale < 0:
            raise ValueError("noise_scale must be >= 0")
        self.machine = sc.machine
        self.gear = sc.gear
        self.loop = bool(loop)
        self.sample_rate_hz = SAMPLE_RATE_HZ
        self.duration_s = math.inf if self.loop else sc.duration_s
        self.feed_hold = False
        # the CNC's applied feed override (percent): a float, or one value per sample of the next step(n),
        # set by the DAQ emulator before each step (sim/emulator/cnc_override.py)
        self.feed_override_pct: float | np.ndarray = 100.0
        self._override = np.full(0, 100.0)  # the rest of the current step's per-sample override
        self._seed, self._noise_scale, self._extras = int(seed), noise_scale, extra_channels
        extras = sc.extra_channels if extra_channels is None else extra_channels
        self.sensors = select_sensors(extras)
        self.descriptor = Descriptor(SAMPLE_RATE_HZ, descriptor_channels(self.sensors))
        self.filter_cutoff_hz = sc.filter_cutoff_hz if filter_cutoff_hz is None else float(filter_cutoff_hz)
        self._analog = [s for s in self.sensors if s.kind != ChannelKind.ENCODER]
        self._fs_int = SAMPLE_RATE_HZ * INTERNAL_PER_SAMPLE
        self._filter = AntiAliasFilter(self.filter_cutoff_hz, self._fs_int, len(self._analog))
        rng = np.random.default_rng(seed)
        self._rng = rng
        self._scales = np.array([s.scale for s in self._analog])
        # noise_scale scales every sensor imperfection: 0 gives ideal sensors (no noise, no zero offset)
        self._sigma = noise_scale * np.array([s.noise_sigma for s in self._analog])
        self._offset = noise_scale * np.array([rng.uniform(-1, 1) * s.max_offset for s in self._analog])
        tool = sc.tool
        material, effects = material_batch(sc.material, sc.effects, sc.material_offset_pct)
        self.geometry = CutGeometry(
            tool, material, sc.mode,
            np.array([x for x, _ in sc.axial_profile] or [0.0, 1.0]),
            np.array([d for _, d in sc.axial_profile] or [0.0, 0.0]),
            np.array([x for x, _ in sc.radial_profile] or [0.0, 1.0]),
            np.array([d for _, d in sc.radial_profile] or [tool.diameter_mm] * 2),
            sc.max_axial_mm, effects,
        )
        self._sound = tooth_chip_factors(tool.flutes)
        self._broken = tooth_chip_factors(tool.flutes, (sc.breakage[1],)) if sc.breakage else self._sound
        self._feed_starts = [x for x, _ in sc.feed_segments]
        self._feed_mm_s = [f / 60.0 for _, f in sc.feed_segments]
        self._sched_t = np.array([t for t, _ in sc.spindle_schedule])
        self._sched_rpm = np.array([r for _, r in sc.spindle_schedule])
        psi = math.radians(sc.path_angle_deg)
        self._cos_psi, self._sin_psi = math.cos(psi), math.sin(psi)
        fd = self.machine.feed
        self._feed_lag = math.exp(-TWO_PI * fd.current_bandwidth_hz / self._fs_int)
        a = self._feed_lag  # the servo's current loop: first order at its bandwidth, y = (1 − a)·x + a·y₋₁
        self._feed_loop = BlockFilter(first_order(1.0 - a, -a), 1)
        self.truth = TruthRecorder(self.gear.name, SAMPLE_RATE_HZ)
        self._init_state()
        self._k = -PREROLL_SAMPLES
        self._theta = -(self._omega_m / self.gear.ratio) * PREROLL_SAMPLES / SAMPLE_RATE_HZ  # 0 at t = 0
        self._turns = math.floor(self._theta / TWO_PI)
        self._theta -= self._turns * TWO_PI
        self._s -= self._v * PREROLL_SAMPLES / SAMPLE_RATE_HZ
        self._produce(PREROLL_SAMPLES)
        self._theta, self._turns = 0.0, 0  # already 0 up to rounding: make revolution 0 start exactly at t = 0
        self.truth.start(0.0)

    # -- public -------------------------------------------------------------------
    @property
    def index(self) -> int:
        """Index of the next sample."""
        return self._k

    @property
    def done(self) -> bool:
        return not self.loop and self._k >= round(self.scenario.duration_s * SAMPLE_RATE_HZ)

    def history(self, first_index: int, n: int) -> np.ndarray:
        """Plausible samples from before index 0, for an emulated device started mid-count with a
        full ring: a separate run of the same scenario (another seed), not continuous with ``step``."""
        del first_index
        return self._sibling().step(n)

    def _sibling(self) -> Plant:
        """Another run of the same machine and scenario with the next seed, looping (for ``history``)."""
        return Plant(self.scenario, seed=self._seed + 1, extra_channels=self._extras,
                     filter_cutoff_hz=self.filter_cutoff_hz, noise_scale=self._noise_scale, loop=True)

    def step(self, n: int) -> np.ndarray:
        """The next n samples as (n, C) int16 raw counts, channel order of ``descriptor``."""
        n = int(n)
        if n < 0:
            raise ValueError("n must be >= 0")
        self._override = self._override_for(n)
        parts = []
        while n > 0:
            block = self._produce(min(n, MAX_BLOCK))  # may be shorter: see _nc
            parts.append(block)
            n -= len(block)
            self._override = self._override[len(block):]
        if not parts:
            return np.zeros((0, len(self.sensors)), dtype=np.int16)
        return parts[0] if len(parts) == 1 else np.concatenate(parts)

    def _override_for(self, n: int) -> np.ndarray:
        """``feed_override_pct`` as one value per sample of the next n."""
        ovr = np.asarray(self.feed_override_pct, dtype=float)
        if ovr.ndim == 0:
            return np.full(n, float(ovr))
        if ovr.shape != (n,):
            raise ValueError(f"feed_override_pct has {ovr.size} values for a step of {n} samples")
        return ovr

    def _override_scale(self, n: int) -> list[float]:
        """The feed override as a factor on the programmed feed, for the block's first n samples."""
        ovr = self._override[:n]
        if len(ovr) < n:  # the pre-roll, or the history's sibling: at the programmed feed
            ovr = np.concatenate((ovr, np.full(n - len(ovr), 100.0)))
        return (ovr / 100.0).tolist()

    # -- state --------------------------------------------------------------------
    def _init_state(self) -> None:
        g = self.gear
        mach = self.machine
        rpm0 = self._initial_rpm()
        w_sp = rpm0 * TWO_PI / 60
        self._omega_m = self._ref_m = w_sp * g.ratio
        friction = g.friction_torque_nm * math.tanh(w_sp / 0.1) + g.viscous_nms * w_sp
        self._torque_m = friction / g.ratio  # steady state, no cut
        self._integ = self._torque_m
        self._j_m = mach.motor.rotor_inertia_kgm2 + mach.drive.spindle_inertia_kgm2 / g.ratio**2
        wc = TWO_PI * mach.drive.bandwidth_hz
        self._kp = self._j_m * wc
        self._ki = self._kp * wc * mach.drive.integral_ratio
        self._s = self.scenario.start_mm
        self._v = self._feed_at(self._s)
        self._t_origin = 0.0
        self._theta_e = 0.0
        self._breakage_done = False
        self._crash_done = False
        self._last_cut: tuple[float, np.ndarray] | None = None
        self._hold_seen = False

    def _initial_rpm(self) -> float:
        """The spindle's speed before index 0 (the scenario's first commanded speed, reached and steady)."""
        return float(self._sched_rpm[0])

    def _feed_at(self, s_mm: float) -> float:
        return self._feed_mm_s[bisect.bisect_right(self._feed_starts, s_mm) - 1]

    # -- one block ----------------------------------------------------------------
    def _produce(self, n: int) -> np.ndarray:
        dt = 1.0 / SAMPLE_RATE_HZ
        k0 = self._k
        t0 = k0 * dt
        events: list[dict] = []
        if self.feed_hold != self._hold_seen:  # takes effect at the next block (the device's next sample)
            self._hold_seen = bool(self.feed_hold)
            events.append({"event": "feed_hold", "on": self._hold_seen, "index": k0, "t_s": round(t0, 6)})
        s0, s1, v0, v1, target, rpm_cmd = self._nc(n, t0, dt, events)
        n = len(s0)
        g = self.gear
        # 2. load the speed loop sees: angle extrapolated at the start speed
        w_sp0 = self._omega_m / g.ratio
        t_cut_pred = self._torque_nm(self._theta + w_sp0 * dt * np.arange(n), 0.5 * (s0 + s1), 0.5 * (v0 + v1),
                                     np.full(n, w_sp0), w_sp0 * dt)[0]
        # 3. spindle, sequential at 1 kHz
        w_m, torque_m = self._spindle(n, dt, rpm_cmd * (TWO_PI / 60) * g.ratio, t_cut_pred)
        w_sp = w_m / g.ratio
        theta_pts = self._theta + np.concatenate(([0.0], np.cumsum(0.5 * (w_sp[:-1] + w_sp[1:]) * dt)))
        # 4. cutting forces, exact means over each sub-interval, with the true angle
        f = (np.arange(CUT_PER_SAMPLE) + 0.5) / CUT_PER_SAMPLE
        edges = self._theta_at(theta_pts, w_sp, np.arange(CUT_PER_SAMPLE + 1) / CUT_PER_SAMPLE, dt, flat=False)
        theta_c, dtheta_c = edges[:, :-1].ravel(), np.diff(edges, axis=1).ravel()
        s_c = (s0[:, None] + (s1 - s0)[:, None] * f).ravel()
        v_c = (v0[:, None] + (v1 - v0)[:, None] * f).ravel()
        w_c = (w_sp[:-1, None] + np.diff(w_sp)[:, None] * f).ravel()
        torque_c, forces, tc_c = self._torque_nm(theta_c, s_c, v_c, w_c, dtheta_c)
        # 5. electrical and sensors at the internal rate
        fi = np.arange(INTERNAL_PER_SAMPLE) / INTERNAL_PER_SAMPLE
        tq_i = (torque_m[:-1, None] + np.diff(torque_m)[:, None] * fi).ravel()
        wm_i = (w_m[:-1, None] + np.diff(w_m)[:, None] * fi).ravel()
        dt_i = dt / INTERNAL_PER_SAMPLE
        elec, self._theta_e = motor_waveforms(self.machine.motor, tq_i, wm_i, dt_i, self._theta_e)
        drive_on = self._drive_on(n)
        if drive_on is not None:  # a drive switched off at standstill: no voltage, no current
            on_i = np.repeat(drive_on, INTERNAL_PER_SAMPLE).astype(float)
            for key in ("v_uv", "v_vw", "v_wu", "i_u", "i_v", "i_w", "i_uv", "i_vw", "i_wu", "airgap_w"):
                elec[key] = elec[key] * on_i
        t_i = t0 + np.arange(n * INTERNAL_PER_SAMPLE) * dt_i
        t_c = t0 + (np.arange(n * CUT_PER_SAMPLE) + 0.5) * (dt / CUT_PER_SAMPLE)
        counts = self._sense(n, elec, wm_i, t_i, t_c, forces, v0, v1)
        counts_enc = encoder_counts(*self._wrap_angle(theta_pts[:-1]))
        # events and truth
        self._events_power(elec["airgap_w"], t_i, events)
        self._record_truth(t0, dt, theta_pts, torque_c, forces, tc_c, s_c, s0, s1, v0, v1, target, rpm_cmd,
                           w_sp, elec, events)
        self._account(k0, n, torque_c, dtheta_c)
        # carry state
        self._theta = float(theta_pts[-1])
        turns = math.floor(self._theta / TWO_PI)
        self._turns += turns
        self._theta -= turns * TWO_PI
        self._k += n
        out = np.empty((n, len(self.sensors)), dtype=np.int16)
        a = 0
        for c, spec in enumerate(self.sensors):
            if spec.kind == ChannelKind.ENCODER:
                out[:, c] = counts_enc
            else:
                out[:, c] = counts[a]
                a += 1
        return out

    def _nc(self, n, t0, dt, events):
        """The NC program for the next n samples: (s0, s1, v0, v1, feed target, commanded rpm), each of
        length m <= n (a subclass may end a block early, e.g. at a tool change)."""
        s0, s1, v0, v1, target, tprog = self._feed_program(n, t0, dt, events)
        rpm_cmd = self._sched_rpm[np.maximum(np.searchsorted(self._sched_t, np.maximum(tprog, 0.0), "right") - 1, 0)]
        return s0, s1, v0, v1, target, rpm_cmd

    def _drive_on(self, n: int) -> np.ndarray | None:
        """Per sample, whether the spindle drive is energised (None: always, as in every scenario)."""
        del n
        return None

    def _account(self, k0: int, n: int, torque_c: np.ndarray, dtheta_c: np.ndarray) -> None:
        """After a block: its cutting torque on the fine grid and the angle turned in each interval."""

    def _feed_program(self, n, t0, dt, events):
        """Feed servo and NC program at 1 kHz: rate-limited feed, position-based feed rate times the
        override, hold, loop."""
        s0, s1, v0, v1 = (np.empty(n) for _ in range(4))
        target, tprog = np.empty(n), np.empty(n)
        acc = self.machine.feed.accel_mm_s2 * dt
        scale = self._override_scale(n)
        s, v = self._s, self._v
        duration = self.scenario.duration_s
        for i in range(n):
            tp = t0 + i * dt - self._t_origin
            if self.loop and tp >= duration:
                self._t_origin += duration
                tp -= duration
                s = self.scenario.start_mm  # the tool is back at the start, moving at the program's feed
                v = 0.0 if self.feed_hold else self._feed_at(s) * scale[i]
                self._breakage_done = self._crash_done = False
                events.append({"event": "scenario_restart", "index": self._k + i, "t_s": round(t0 + i * dt, 6)})
            tgt = 0.0 if self.feed_hold else self._feed_at(s) * scale[i]  # a hold wins over any override
            v_new = v + min(max(tgt - v, -acc), acc)
            s0[i], v0[i], v1[i], target[i], tprog[i] = s, v, v_new, tgt, tp
            s += 0.5 * (v + v_new) * dt
            s1[i] = s
            v = v_new
        self._s, self._v = s, v
        return s0, s1, v0, v1, target, tprog

    def _spindle(self, n, dt, w_ref_m, t_cut_spindle):
        """Speed loop, torque lag and limits, inertia; returns motor speed and torque at n+1 instants."""
        g, drive, motor = self.gear, self.machine.drive, self.machine.motor
        lag = 1.0 - math.exp(-dt / drive.torque_lag_s)
        t_peak = drive.peak_torque_factor * motor.rated_torque_nm
        p_peak = drive.peak_power_w
        kp, ki, j = self._kp, self._ki, self._j_m
        ratio, tf, b = g.ratio, g.friction_torque_nm, g.viscous_nms
        w, te, integ, ref = self._omega_m, self._torque_m, self._integ, self._ref_m
        ramp = drive.ramp_motor_rpm_s * TWO_PI / 60 * dt
        w_out, te_out = np.empty(n + 1), np.empty(n + 1)
        w_out[0], te_out[0] = w, te
        refs = w_ref_m.tolist()
        loads = t_cut_spindle.tolist()
        for i in range(n):
            ref += min(max(refs[i] - ref, -ramp), ramp)  # the drive ramps its speed reference
            err = ref - w
            cmd = kp * err + integ
            t_max = min(t_peak, p_peak / max(abs(w), 1.0))
            if cmd > t_max:
                cmd = t_max
            elif cmd < -t_max:
                cmd = -t_max
            else:
                integ += ki * err * dt  # conditional integration: no wind-up at the limit
            te += (cmd - te) * lag
            w_sp = w / ratio
            load = (loads[i] + tf * math.tanh(w_sp / 0.1) + b * w_sp) / ratio  # [P] eq. 13 at the motor
            w += (te - load) / j * dt
            w_out[i + 1], te_out[i + 1] = w, te
        self._omega_m, self._torque_m, self._integ, self._ref_m = w, te, integ, ref
        return w_out, te_out

    @staticmethod
    def _theta_at(theta_pts, w, f, dt, flat=True):
        """Spindle angle at fractions f of each 1 ms step (speed linear within the step)."""
        dw = np.diff(w)
        out = theta_pts[:-1, None] + dt * (w[:-1, None] * f + dw[:, None] * f**2 / 2)
        return out.ravel() if flat else out

    def _wrap_angle(self, theta):
        turns = np.floor(theta / TWO_PI)
        return theta - turns * TWO_PI, turns + self._turns

    def _chip_factors(self, s_mm: np.ndarray) -> np.ndarray:
        if not self.scenario.breakage:
            return self._sound
        broken = s_mm >= self.scenario.breakage[0]
        return np.where(broken[:, None], self._broken, self._sound)

    def _torque_nm(self, theta, s, v, w_sp, dtheta):
        """Mean cutting torque at the spindle (R·F_t, [P] eq. 15) while turning from θ to θ + Δθ,
        the mean forces and the feed per tooth."""
        tool = self.geometry.tool  # the cutter in the spindle
        tc = v / (tool.flutes * np.maximum(w_sp, 1e-3) / TWO_PI)  # t_c = feed/(N·n)
        forces = cutting_forces(self.geometry, theta, s, tc, self._chip_factors(s), dtheta)
        return forces["ft_n"] * (tool.radius_mm / 1000.0), forces, tc

    # -- sensors --------------------------------------------------------------------
    def _sense(self, n, elec, wm_i, t_i, t_c, forces, v0, v1):
        fd = self.machine.feed
        cos_p, sin_p = self._cos_psi, self._sin_psi
        need = {s.name for s in self._analog}
        values = dict(elec)
        values["mot_rpm"] = wm_i * (60 / TWO_PI)
        values["sp_rpm"] = values["mot_rpm"] / self.gear.ratio
        if need & {"ix_feed", "fx", "fy", "fz", "fx_rate"}:
            fx_m = forces["fx_n"] * cos_p - forces["fy_n"] * sin_p  # machine axes
            fy_m = forces["fx_n"] * sin_p + forces["fy_n"] * cos_p
            fx_i, fy_i, fz_i = self._interp_cut(t_i, t_c, np.stack([fx_m, fy_m, forces["fz_n"]]))
            fi = np.arange(INTERNAL_PER_SAMPLE) / INTERNAL_PER_SAMPLE
            vx = (v0[:, None] + (v1 - v0)[:, None] * fi).ravel() * cos_p
            amps = (fx_i + fd.friction_n * np.tanh(vx / 0.5)) / fd.newton_per_amp
            values["ix_feed"] = self._feed_loop(amps[None, :])[0]
            values["fx_rate"] = vx * 60.0
            values["fx"], values["fy"], values["fz"] = fx_i, fy_i, fz_i
        x = np.stack([values[s.name] for s in self._analog])
        noise = self._rng.standard_normal((x.shape[1], x.shape[0])).T  # sample-major: chunking-independent
        x = x + noise * self._sigma[:, None] + self._offset[:, None]
        y = self._filter(x)[:, ::INTERNAL_PER_SAMPLE]
        return quantise(y, self._scales[:, None])

    def _interp_cut(self, t_i, t_c, vals):
        """Cut-grid values at internal instants, bridging from the previous block's last point."""
        if self._last_cut is not None:
            tt = np.concatenate(([self._last_cut[0]], t_c))
            vv = np.concatenate((self._last_cut[1][:, None], vals), axis=1)
        else:
            tt, vv = t_c, vals
        self._last_cut = (float(t_c[-1]), vals[:, -1].copy())
        return [np.interp(t_i, tt, row) for row in vv]

    # -- truth ----------------------------------------------------------------------
    def _events_power(self, p_g, t_i, events):
        thr = self.scenario.crash_power_w
        if thr is None or self._crash_done:
            return
        over = np.flatnonzero(p_g > thr)
        if over.size:
            j = int(over[0])
            self._crash_done = True
            events.append({"event": "crash_power", "index": int(math.ceil(t_i[j] * SAMPLE_RATE_HZ - 1e-9)),
                           "t_s": round(float(t_i[j]), 6), "power_w": round(float(p_g[j]), 1),
                           "threshold_w": thr})

    def _record_truth(self, t0, dt, theta_pts, torque_c, forces, tc_c, s_c, s0, s1, v0, v1, target, rpm_cmd,
                      w_sp, elec, events):
        geom, r = self.geometry, self.geometry.tool.radius_mm
        sc = self.scenario
        if sc.breakage and not self._breakage_done:
            hit = np.flatnonzero(s1 >= sc.breakage[0])
            if hit.size:
                self._breakage_done = True
                k = self._k + int(hit[0])
                events.append({"event": "tool_breakage", "index": k, "t_s": round(k * dt, 6),
                               "tooth": sc.breakage[1], "position_mm": sc.breakage[0]})
        if not self.truth.active:
            return
        axial = geom.axial_depth_mm(s_c)
        radial = np.where(axial > 0, geom.radial_depth_mm(s_c), 0.0)
        airgap = elec["airgap_w"].reshape(-1, INTERNAL_PER_SAMPLE).mean(axis=1)
        rep = CUT_PER_SAMPLE
        means = {
            "torque_nm": torque_c,
            "force_n": np.hypot(forces["fx_n"], forces["fy_n"]),
            "fx_n": forces["fx_n"], "fy_n": forces["fy_n"], "fz_n": forces["fz_n"], "ft_n": forces["ft_n"],
            "feed_per_tooth_mm": tc_c, "radial_depth_mm": radial, "axial_depth_mm": axial,
            "airgap_w": np.repeat(airgap, rep),
            "feed_mm_min": np.repeat(0.5 * (v0 + v1) * 60.0, rep),
            "feed_override_pct": np.repeat(np.asarray(self._override_scale(len(s0))) * 100.0, rep),
        }
        sm = 0.5 * (s0 + s1)
        tracked = {
            "axial_mm": geom.axial_depth_mm(sm), "radial_mm": geom.radial_depth_mm(sm),
            "axial_jump_mm": np.abs(geom.axial_depth_mm(sm + r) - geom.axial_depth_mm(sm)),
            "radial_jump_mm": np.abs(geom.radial_depth_mm(sm + r) - geom.radial_depth_mm(sm)),
            "feed_target_mm_s": target, "rpm_command": rpm_cmd.astype(float),
            "feed_mm_s": 0.5 * (v0 + v1), "spindle_rpm": 0.5 * (w_sp[:-1] + w_sp[1:]) * (60 / TWO_PI),
        }
        # commanded 0 rpm (a stop): any turning is a full error, none is none
        cmd, rpm = tracked["rpm_command"], tracked["spindle_rpm"]
        relative = np.abs(rpm / np.where(cmd != 0, cmd, 1.0) - 1.0)
        tracked["speed_error"] = np.where(cmd != 0, relative, (np.abs(rpm) > 0).astype(float))
        tracked = {k: np.repeat(v, rep) for k, v in tracked.items()}
        held = np.full(torque_c.shape, bool(self.feed_hold))
        # boundaries: the angle crosses a multiple of 2π between two 1 ms points
        rel = theta_pts / TWO_PI
        m = np.floor(rel)
        idx = np.flatnonzero(np.diff(m) > 0)
        bounds, last = [], []
        for i in idx:
            for turn in range(int(m[i]) + 1, int(m[i + 1]) + 1):
                frac = (turn - rel[i]) / (rel[i + 1] - rel[i])
                bounds.append(t0 + (i + frac) * dt)
                last.append(self._k + int(i))  # sample i is the revolution's last: θ_i < 2π·turn <= θ_i+1
        self.truth.add_block(t0, dt / rep, means, tracked, held, np.array(bounds), last, events)
