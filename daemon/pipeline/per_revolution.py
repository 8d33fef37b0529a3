"""One closed revolution's means -> the `estimate` payload fields.

The chain of `shared/spec/physics.md`, per revolution: filter gain divided out
of the measured powers, air-gap power ([P] eq. 11), gear from the measured
motor/spindle ratio, cutting torque ([P] eq. 13, slip-free power speed),
its uncertainty ([P] eq. 20), resultant force ([P] eq. 18), feed-drive force,
feed per tooth, and depths of cut ([D] §3) by the configured method.

Kept apart from the sample-level code in `estimator.py` so that the physics of
a revolution can be read (and tested) on plain floats.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from millsense.daemon.physics import depth as depth_mod
from millsense.daemon.physics.force import cf_model, resultant_force_magnitude_n
from millsense.daemon.physics.milling import Material, average_chip_thickness_mm, engagement_angles_rad
from millsense.daemon.physics.power import air_gap_power_w, butterworth_power_gain
from millsense.daemon.physics.torque import (
    cutting_torque_nm,
    inertia_torque_nm,
    select_gear,
    synchronous_spindle_omega_rad_s,
    torque_sigma_nm,
)

TWO_PI = 2.0 * math.pi

# The configured feed against a feed-rate channel (docs/config.md, [cut] feed_mm_min). The feed per
# tooth enters the depths through K_s·t^p and r_1(t) ([D] eqs. 8-10): a feed 5 % off moves a depth by
# up to ~4 % (docs/accuracy.md: 10 % gives up to 8 %), about the accuracy the depths claim; a wrong
# example config was 100 % off (250 against fig6's 500 mm/min). The simulated feed-rate channel reads
# within 0.1 % over a revolution, so 5 % is never noise.
FEED_MISMATCH_REL = 0.05
FEED_STEADY_REL = 0.01      # judged only while the measured feed holds within 1 % of the revolution before
FEED_AGREE_REVS = 20        # re-armed after this many agreeing steady cutting revolutions in a row


class FeedCheck:
    """Does the configured feed match the measured one? Judged on steady cutting revolutions.

    The measured feed is used for the physics whenever the channel exists; this only
    tells the operator that the configuration is wrong for the cut. State changes only,
    returned by `take()` for the runner to log (nothing logs on the block path):
    `feed.mismatch` once, again only after FEED_AGREE_REVS agreeing revolutions.
    """

    def __init__(self, configured_mm_min: float | None):
        self.configured_mm_min = configured_mm_min
        self.warned = False
        self._agreeing = 0
        self._last_mm_min: float | None = None
        self._events: list[tuple[str, dict]] = []

    def update(self, measured_mm_min: float | None, steady_cutting: bool) -> None:
        last, self._last_mm_min = self._last_mm_min, measured_mm_min
        configured = self.configured_mm_min
        if configured is None or measured_mm_min is None or last is None or not steady_cutting:
            return
        if abs(measured_mm_min - last) > FEED_STEADY_REL * max(abs(last), 1e-9):
            return   # a feed change inside the revolution: its mean is neither feed
        if abs(measured_mm_min - configured) > FEED_MISMATCH_REL * configured:
            self._agreeing = 0
            if not self.warned:
                self.warned = True
                if len(self._events) < 16:   # nobody drains them in calibrate: bounded
                    self._events.append(("feed.mismatch", {
                        "configured_mm_min": configured,
                        "measured_mm_min": round(measured_mm_min, 1),
                        "off_pct": round(100.0 * (measured_mm_min / configured - 1.0), 1),
                        "detail": "using the measured feed for feed per tooth and depths; "
                                  "set [cut] feed_mm_min to the cut's feed",
                    }))
        elif self.warned:
            self._agreeing += 1
            if self._agreeing >= FEED_AGREE_REVS:
                self.warned, self._agreeing = False, 0

    def take(self) -> list[tuple[str, dict]]:
        """State changes since the last call: (event, fields)."""
        out, self._events = self._events, []
        return out


@dataclass(frozen=True)
class RevolutionMeans:
    """What the sample-level stage measured over one whole revolution."""

    spindle_rpm: float           # 60 / revolution duration (s)
    p_in_meas_w: float           # mean measured input power (through the DAQ filter)
    p_cu_meas_w: float           # mean copper loss from the measured currents
    p_gap_sq_meas_w2: float      # mean of (p_in - p_cu)^2, measured
    samples: int
    f_e_hz: float | None         # electrical frequency from the voltages
    motor_rpm: float | None      # mean motor speed channel, if any
    feed_rate_mm_min: float | None   # mean feed-rate magnitude, if channels
    feed_current_a: float | None     # mean feed-drive current of the configured channel
    force_x_n: float | None          # dynamometer means
    force_y_n: float | None
    speed_rise_rpm: float = 0.0      # spindle speed at the revolution's end minus at its start
    prev_spindle_rpm: float | None = None  # mean speed of the revolution just before (None: not contiguous)


@dataclass(frozen=True)
class Gear:
    name: str
    ratio: float
    max_spindle_rpm: float
    friction_torque_nm: float
    viscous_nms: float
    inertia_kgm2: float | None = None   # referred to the spindle; None: unknown, no compensation


class RevolutionPhysics:
    """Configuration-bound physics of one revolution (see module docstring)."""

    def __init__(self, settings, *, has_dynamometer: bool, feed_force: tuple[str, float, float] | None,
                 friction_zero: bool = False):
        gears = sorted(settings.gears, key=lambda g: g.max_spindle_rpm)
        self.gears = tuple(
            Gear(g.name, float(g.ratio), float(g.max_spindle_rpm),
                 0.0 if friction_zero else float(g.friction_torque_nm),
                 0.0 if friction_zero else float(g.viscous_nms),
                 None if friction_zero or g.inertia_kgm2 is None else float(g.inertia_kgm2))
            for g in gears
        )
        self._max_rpm = tuple(g.max_spindle_rpm for g in self.gears)
        self._ratios = tuple(g.ratio for g in self.gears)
        self.cutoff_hz = float(settings.daq.filter_cutoff_hz or 0.0)
        self.filter_order = int(getattr(settings.daq, "filter_order", 2) or 2)
        pp = getattr(settings.motor, "pole_pairs", None)
        self.pole_pairs = int(pp) if pp else None
        self.tool_radius_mm = float(settings.tool.diameter_mm) / 2.0
        self.flutes = int(settings.tool.flutes)
        cf = settings.tool.cf
        self.cf_model = isinstance(cf, str)
        self.cf = None if self.cf_model else float(cf)
        m = settings.material
        self.material = Material(float(m.ks), float(m.ks_exp), float(m.r1), float(m.r1_exp), float(m.r2), float(m.r2_exp))
        cut = settings.cut
        self.mode = str(cut.mode)
        self.feed_mm_min = None if cut.feed_mm_min is None else float(cut.feed_mm_min)
        self.feed_check = FeedCheck(self.feed_mm_min)
        self.known_axial_mm = None if getattr(cut, "axial_depth_mm", None) is None else float(cut.axial_depth_mm)
        self.known_radial_mm = None if getattr(cut, "radial_depth_mm", None) is None else float(cut.radial_depth_mm)
        self.min_torque_nm = float(settings.depth.min_torque_nm)
        self.feed_force = feed_force            # (channel, newton_per_amp, friction_n) or None
        self.method = self._resolve_method(str(settings.depth.method), has_dynamometer)
        self.last_gain = 1.0

    def _resolve_method(self, method: str, has_dynamometer: bool) -> str:
        """`auto` -> the best source of a second force this configuration has ([D] §3)."""
        if method != "auto":
            return method
        if has_dynamometer:
            return "dynamometer"
        if self.feed_force is not None:
            return "feed-drive"
        if self.known_axial_mm is not None or self.known_radial_mm is not None or self.mode == "slot":
            return "torque-only"
        return "none"

    # ---------------------------------------------------------------------------------

    def filter_gain(self, f_e_hz: float | None) -> float:
        """|H(f_e)|² of the DAQ's anti-alias filter (physics.md §1); 1 with no filter."""
        if self.cutoff_hz <= 0.0 or f_e_hz is None or not math.isfinite(f_e_hz):
            return 1.0
        return float(butterworth_power_gain(f_e_hz, self.cutoff_hz, self.filter_order))

    def gear_index(self, r: RevolutionMeans) -> int:
        """Gear from the motor/spindle speed ratio when measurable, else by spindle speed."""
        ratio = None
        if r.motor_rpm is not None and r.spindle_rpm > 0:
            ratio = r.motor_rpm / r.spindle_rpm
        elif self.pole_pairs and r.f_e_hz and r.spindle_rpm > 0:
            ratio = (60.0 * r.f_e_hz / self.pole_pairs) / r.spindle_rpm   # synchronous speed / spindle
        return int(select_gear(r.spindle_rpm, self._max_rpm, self._ratios, motor_to_spindle_ratio=ratio))

    def estimate(self, r: RevolutionMeans) -> dict:
        """All physical fields of one good revolution (payload of interfaces.md)."""
        gain = self.filter_gain(r.f_e_hz)
        self.last_gain = gain
        gi = self.gear_index(r)
        gear = self.gears[gi]
        omega = TWO_PI * r.spindle_rpm / 60.0
        p_in_w = r.p_in_meas_w / gain
        p_gap_w = float(air_gap_power_w(r.p_in_meas_w, r.p_cu_meas_w, gain))               # eq. (11)
        power_omega = None
        if self.pole_pairs and r.f_e_hz:
            power_omega = float(synchronous_spindle_omega_rad_s(r.f_e_hz, self.pole_pairs, gear.ratio))
        torque_nm = float(cutting_torque_nm(p_gap_w, omega, gear.friction_torque_nm, gear.viscous_nms,
                                            power_omega_rad_s=power_omega))              # eq. (13)
        p_inertia_w = None
        if gear.inertia_kgm2 is not None:
            inertia_nm = self.inertia_nm(gear.inertia_kgm2, r, omega)                        # eq. (13) + J·dω/dt
            torque_nm -= inertia_nm
            p_inertia_w = inertia_nm * omega
        p_gap_meas = r.p_in_meas_w - r.p_cu_meas_w
        var_w2 = max(r.p_gap_sq_meas_w2 - p_gap_meas * p_gap_meas, 0.0)
        sigma_p_w = math.sqrt(var_w2 / max(r.samples, 1)) / gain                           # std. error of the mean
        sigma_nm = float(torque_sigma_nm(sigma_p_w, power_omega or omega))                  # eq. (20)

        feed_mm_min = r.feed_rate_mm_min if r.feed_rate_mm_min is not None else self.feed_mm_min
        feed_per_tooth_mm = None
        if feed_mm_min is not None and r.spindle_rpm > 0:
            feed_per_tooth_mm = feed_mm_min / (self.flutes * r.spindle_rpm)
        force_feed_n = None
        if self.feed_force is not None and r.feed_current_a is not None:
            _, n_per_a, friction_n = self.feed_force
            force_feed_n = n_per_a * r.feed_current_a - friction_n
        tangential_n = torque_nm / (self.tool_radius_mm * 1e-3)

        cutting = torque_nm >= self.min_torque_nm
        self.feed_check.update(r.feed_rate_mm_min, cutting and self.steady(r))
        depth = self._depth(torque_nm, tangential_n, force_feed_n, feed_per_tooth_mm, r, cutting)
        force_n = self._force(torque_nm, feed_per_tooth_mm, depth, self.force_noise_nm(sigma_nm))
        return {
            "spindle_rpm": r.spindle_rpm,
            "gear": gear.name,
            "p_in_w": p_in_w,
            "p_gap_w": p_gap_w,
            "p_inertia_w": p_inertia_w,
            "spindle_accel_rad_s2": self.accel_rad_s2(r),
            "torque_nm": torque_nm,
            "torque_sigma_nm": sigma_nm,
            "force_n": force_n,
            "force_tangential_n": tangential_n,
            "force_feed_n": force_feed_n,
            "feed_per_tooth_mm": feed_per_tooth_mm,
            "radial_depth_mm": depth.radial_depth_mm,
            "axial_depth_mm": depth.axial_depth_mm,
            "depth_status": depth.status,
            "cutting": bool(cutting),
        }

    @staticmethod
    def accel_rad_s2(r: RevolutionMeans) -> float:
        """Mean angular acceleration over the revolution, Δω/Δt (rad/s²), Δt = 60/rpm."""
        return TWO_PI / 60.0 * r.speed_rise_rpm * r.spindle_rpm / 60.0

    # A spindle at a steady speed has no inertia torque, but the speed reading's rise over a revolution
    # still scatters by its quantisation (an encoder of 4096 counts read over 16 samples: steps of
    # 0.92 rpm, so up to ±1.8 rpm), which J turns into ±2.8 N·m a revolution at 600 rpm in the low gear
    # (sd 1.06 N·m measured at 700 rpm against 0.006 without the term). So the term is taken as 0 while
    # both the rise and the step from the revolution before (from revolution durations: steady cutting
    # stays under 0.03 % in every simulated scenario) sit inside their noise. What that can leave
    # uncompensated is a ramp slower than STEADY_STEP per revolution: J·Δω/Δt ≤ 0.8 N·m at 600 rpm and
    # 1.2 N·m at 900 rpm in the low gear (docs/physics.md, "Inertia").
    STEADY_RISE_RPM = 2.0
    STEADY_STEP_RPM = 0.5
    STEADY_STEP_PCT = 0.05

    @staticmethod
    def steady(r: RevolutionMeans) -> bool:
        """Is the speed's change over this revolution within the speed readings' noise?"""
        if abs(r.speed_rise_rpm) > RevolutionPhysics.STEADY_RISE_RPM:
            return False
        if r.prev_spindle_rpm is None:
            return True
        band = max(RevolutionPhysics.STEADY_STEP_RPM, RevolutionPhysics.STEADY_STEP_PCT / 100.0 * r.spindle_rpm)
        return abs(r.spindle_rpm - r.prev_spindle_rpm) <= band

    @staticmethod
    def inertia_nm(inertia_kgm2: float, r: RevolutionMeans, omega: float) -> float:
        """The masses' share of the revolution's mean torque: ½J(ω_end² − ω_start²)/(Δt·ω̄).

        Δt = 2π/ω̄ exactly (a revolution); ω_start, ω_end = ω̄ ∓ Δω/2 with Δω the
        speed reading's rise over the revolution, so this is J·Δω/Δt. Why the rise
        and not the difference of consecutive revolutions' mean speeds (which is
        far less noisy): that difference is centred half a revolution earlier, and
        in a crash the speed turns within a revolution: the lagged term hands the
        recovering revolution's load to the masses (reads low, the unsafe side).
        See docs for the noise (J·σ_Δω·ω̄/2π).
        """
        if not omega > 0.0 or RevolutionPhysics.steady(r):
            return 0.0
        d_omega = TWO_PI * r.speed_rise_rpm / 60.0
        duration_s = TWO_PI / omega
        return float(inertia_torque_nm(inertia_kgm2, omega - d_omega / 2.0, omega + d_omega / 2.0, duration_s, omega))

    def _depth(self, torque_nm, tangential_n, force_feed_n, t_c, r: RevolutionMeans, cutting: bool):
        if self.method == "off":
            return depth_mod.DepthResult(None, None, None)
        if not cutting:
            return depth_mod.DepthResult(None, None, depth_mod.AIR_CUT)
        if t_c is None or not t_c > 0:
            return depth_mod.DepthResult(None, None, depth_mod.OUT_OF_RANGE)
        common = dict(feed_per_tooth_mm=t_c, tool_radius_mm=self.tool_radius_mm, flutes=self.flutes,
                      material=self.material, mode=self.mode)
        try:
            if self.method == "dynamometer":
                if r.force_x_n is None or r.force_y_n is None:
                    return depth_mod.DepthResult(None, None, depth_mod.NO_SECOND_FORCE)
                return depth_mod.depths_from_forces(fx_n=r.force_x_n, fy_n=r.force_y_n, **common)
            if self.method == "feed-drive":
                if force_feed_n is None:
                    return depth_mod.DepthResult(None, None, depth_mod.NO_SECOND_FORCE)
                return depth_mod.depths_from_forces(tangential_n=tangential_n, feed_n=force_feed_n, **common)
            if self.method == "torque-only":
                known_radial = self.known_radial_mm
                known_axial = self.known_axial_mm if known_radial is None else None
                return depth_mod.depth_from_torque(torque_nm, known_radial_mm=known_radial,
                                                   known_axial_mm=known_axial, **common)
        except ValueError:   # a known depth outside the tool, etc.: no estimate, not a crash
            return depth_mod.DepthResult(None, None, depth_mod.OUT_OF_RANGE)
        return depth_mod.DepthResult(None, None, depth_mod.NO_SECOND_FORCE)

    # How far below zero a torque estimate still counts as zero for the force magnitude: the
    # configured no-cut floor (a torque as far below zero as air is below the cutting threshold) plus
    # three standard errors of the revolution's own mean (eq. 20), which grow in a transient. Steady
    # air scatters by ±0.01 N·m (0 N). After the simulated crash the drive brakes an overspeed: with
    # no J the revolutions read -1.4 to -37 N·m, with J the slow end of the ramp that the STEADY_*
    # rule below leaves uncompensated reads -0.6 N·m: null either way, eq. (18) has no cut to size.
    FORCE_NOISE_SIGMAS = 3.0

    def force_noise_nm(self, sigma_nm: float) -> float:
        return self.min_torque_nm + self.FORCE_NOISE_SIGMAS * (sigma_nm if math.isfinite(sigma_nm) else 0.0)

    def _force(self, torque_nm: float, t_c: float | None, depth, noise_nm: float) -> float | None:
        """Resultant in-plane force magnitude, [P] eq. (18), >= 0 or None (force.resultant_force_magnitude_n);
        C_f constant or from r_1(t_a) ([D] eqs. 8-9)."""
        if not self.cf_model:
            return resultant_force_magnitude_n(torque_nm, self.tool_radius_mm, self.cf, noise_nm)
        radial_mm = depth.radial_depth_mm if depth.radial_depth_mm is not None else self.known_radial_mm
        if self.mode == "slot":
            radial_mm = 2.0 * self.tool_radius_mm
        if radial_mm is None or t_c is None or not t_c > 0:
            return None
        entry, exit_ = engagement_angles_rad(radial_mm / self.tool_radius_mm, self.mode)
        t_a = float(average_chip_thickness_mm(t_c, entry, exit_))
        if not (math.isfinite(t_a) and t_a > 0):
            return None
        cf = float(cf_model(t_a, self.material.r1, self.material.r1_exp))
        return resultant_force_magnitude_n(torque_nm, self.tool_radius_mm, cf, noise_nm)
