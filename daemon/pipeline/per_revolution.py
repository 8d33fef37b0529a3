"""Closed revolutions' means -> the `estimate` payload fields: one revolution, or every revolution of a block.

The chain of `docs/physics.md`, over (R,) columns: filter gain divided out
of the measured powers, air-gap power ([P] eq. 11), gear from the measured
motor/spindle ratio, cutting torque ([P] eq. 13, slip-free power speed),
its uncertainty ([P] eq. 20), resultant force ([P] eq. 18), feed-drive force,
feed per tooth, and depths of cut ([D] §3) by the configured method.

Kept apart from the sample-level code in `estimator.py` so that the physics of
a revolution can be read (and tested). Two forms of one chain, step for step:
`estimate` takes one revolution's plain floats (the live daemon's block closes
one revolution: after its thread slept, numpy calls on one-element columns cost
several times the arithmetic, docs/performance.md), `estimate_many` the columns
of a block's revolutions (replay). tests/estimator/test_one_revolution.py holds
them equal in every branch. In `estimate_many`, revolution by revolution stay
only the feed check (a state machine) and, when configured, the depth's root
finding.

Tools by number (`[tools.N]`): feed per tooth, forces and depths use the tool in
the spindle. `estimate_many` takes the CNC tool number of each revolution; a
block's revolutions are grouped by tool (almost always one group: the same
arrays as with no tool at all) and a tool the configuration does not list uses
`[tool]`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from millsense.daemon.physics import depth as depth_mod
from millsense.daemon.physics import validity
from millsense.daemon.physics.force import P_MEAN_CF, engaged_cf, resultant_force_magnitudes_n
from millsense.daemon.physics.milling import Material
from millsense.daemon.physics.power import air_gap_power_w, butterworth_power_gain
from millsense.daemon.physics.torque import (
    cutting_torque_nm,
    inertia_torque_nm,
    select_gear,
    select_gears,
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

    def update(self, measured_mm_min: float | None, steady_cutting: bool, override_pct: float = 100.0) -> None:
        """One revolution: the measured feed against the configured one times the CNC's applied override."""
        last, self._last_mm_min = self._last_mm_min, measured_mm_min
        configured = None if self.configured_mm_min is None else self.configured_mm_min * override_pct / 100.0
        if configured is None or measured_mm_min is None or last is None or not steady_cutting:
            return
        if not configured > 0.0:
            return   # the CNC's override at 0 %: the axes stand, no feed to compare with
        if abs(measured_mm_min - last) > FEED_STEADY_REL * max(abs(last), 1e-9):
            return   # a feed change inside the revolution: its mean is neither feed
        if abs(measured_mm_min - configured) > FEED_MISMATCH_REL * configured:
            self._agreeing = 0
            if not self.warned:
                self.warned = True
                if len(self._events) < 16:   # nobody drains them in calibrate: bounded
                    self._events.append(("feed.mismatch", {
                        "configured_mm_min": self.configured_mm_min,
                        "override_pct": round(override_pct, 1),
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
    feed_override_pct: float | None = None  # the CNC's applied feed override, time-weighted over the revolution;
                                            # None: no report (100 %)


@dataclass(frozen=True)
class RevolutionColumns:
    """The same over R revolutions at once: (R,) arrays; nan in `f_e_hz` and `prev_spindle_rpm` = none,
    None for a column the configuration lacks."""

    spindle_rpm: np.ndarray
    p_in_meas_w: np.ndarray
    p_cu_meas_w: np.ndarray
    p_gap_sq_meas_w2: np.ndarray
    samples: np.ndarray
    f_e_hz: np.ndarray
    motor_rpm: np.ndarray | None
    feed_rate_mm_min: np.ndarray | None
    feed_current_a: np.ndarray | None
    force_x_n: np.ndarray | None
    force_y_n: np.ndarray | None
    speed_rise_rpm: np.ndarray
    prev_spindle_rpm: np.ndarray
    feed_override_pct: np.ndarray | None = None   # applied override per revolution; None: 100 % (no report)


@dataclass(frozen=True)
class ToolGeometry:
    """What the physics needs of one end mill: `[tool]` or a `[tools.N]` table."""

    radius_mm: float
    flutes: int
    cf: float | None            # C_f of [P] eq. (18); None: "model"/"auto", η·√(1 + r_1(t_a)²) (force.engaged_cf)
    flute_length_mm: float = math.inf   # the deepest axial depth this tool can cut (validity.within_tool)
    helix_deg: float | None = None      # None: unknown, the straight-flute η (an upper bound)
    cf_fallback: float | None = None    # "auto": [P]'s 1.075 where the model lacks the chip or the engagement

    @property
    def cf_model(self) -> bool:
        return self.cf is None

    @property
    def diameter_mm(self) -> float:
        return 2.0 * self.radius_mm

    @classmethod
    def of(cls, diameter_mm: float, flutes: int, cf: float | str,
           flute_length_mm: float | None = None, helix_deg: float | None = None) -> ToolGeometry:
        length = validity.default_flute_length_mm(diameter_mm) if flute_length_mm is None else float(flute_length_mm)
        return cls(float(diameter_mm) / 2.0, int(flutes), None if isinstance(cf, str) else float(cf), length,
                   None if helix_deg is None else float(helix_deg), P_MEAN_CF if cf == "auto" else None)


def tool_geometries(settings) -> tuple[ToolGeometry, dict[int, ToolGeometry]]:
    """`[tool]` and every `[tools.N]` by number; a `[tools.N]` without `cf` or `helix_deg` takes `[tool]`'s,
    one without `flute_length_mm` twice its own diameter (validity.FLUTE_LENGTH_PER_DIAMETER)."""
    default = settings.tool
    default_helix = getattr(default, "helix_deg", None)
    listed = {
        int(number): ToolGeometry.of(t.diameter_mm, t.flutes, default.cf if t.cf is None else t.cf,
                                     getattr(t, "flute_length_mm", None),
                                     default_helix if getattr(t, "helix_deg", None) is None else t.helix_deg)
        for number, t in (getattr(settings, "tools", None) or {}).items()
    }
    return ToolGeometry.of(default.diameter_mm, default.flutes, default.cf,
                           getattr(default, "flute_length_mm", None), default_helix), listed


@dataclass(frozen=True)
class Gear:
    name: str
    ratio: float
    max_spindle_rpm: float
    friction_torque_nm: float
    viscous_nms: float
    inertia_kgm2: float | None = None   # referred to the spindle; None: unknown, no compensation


class OperationEngagement(NamedTuple):
    """The engagement an operation declares (`[operations]`, constant): what the force's C_f is taken at."""

    mode: str
    radial_depth_mm: float
    axial_depth_mm: float


class _ToolPart(NamedTuple):
    """The tool-dependent columns of some revolutions (nan where none)."""

    feed_per_tooth_mm: np.ndarray
    tangential_n: np.ndarray
    radial_mm: np.ndarray
    axial_mm: np.ndarray
    status: list
    force_n: np.ndarray


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
        self._max_model_rpm = validity.max_spindle_rpm(self._max_rpm[-1])   # eq. (13)'s friction known up to it
        # per-gear columns, indexed by the gear of each revolution
        self._names = [g.name for g in self.gears]
        self._ratios = np.array([g.ratio for g in self.gears])
        self._ratio_list = [g.ratio for g in self.gears]
        self._friction = np.array([g.friction_torque_nm for g in self.gears])
        self._viscous = np.array([g.viscous_nms for g in self.gears])
        self._inertia = np.array([np.nan if g.inertia_kgm2 is None else g.inertia_kgm2 for g in self.gears])
        self.cutoff_hz = float(settings.daq.filter_cutoff_hz or 0.0)
        self.filter_order = int(getattr(settings.daq, "filter_order", 2) or 2)
        pp = getattr(settings.motor, "pole_pairs", None)
        self.pole_pairs = int(pp) if pp else None
        self.tool, self.tools = tool_geometries(settings)
        m = settings.material
        self.material = Material(float(m.ks), float(m.ks_exp), float(m.r1), float(m.r1_exp), float(m.r2), float(m.r2_exp),
                                 float(getattr(m, "edge_t_n_mm", 0.0)), float(getattr(m, "edge_r_n_mm", 0.0)))
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
        self.gains: list[float] = []

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

    def estimate(self, r: RevolutionMeans, tool: int | None = None, cut: OperationEngagement | None = None) -> dict:
        """All physical fields of one good revolution (payload of interfaces.md), on plain floats;
        `tool`: the CNC number of the tool in the spindle (None: unknown, `[tool]`); `cut`: the engagement of
        the operation the CNC reports, where `[operations]` declares it (None: `[cut]`'s, `force_engagement`).

        The live daemon's block closes one revolution: this is its path. The chain is `estimate_many`'s,
        step for step in the same order, through the same physics functions on Python floats (after its
        thread slept, a numpy call on one element costs several times the float arithmetic it stands for:
        docs/performance.md; `physics/numbers.py`). The two forms give the same numbers: tests/estimator/test_one_revolution.py holds them equal over the
        configurations' branches, test_vectorised.py over whole captures cut into blocks of any size.
        """
        rpm = r.spindle_rpm
        f_e = math.nan if r.f_e_hz is None else r.f_e_hz
        has_fe = math.isfinite(f_e)
        gain = self._filter_gain(f_e)
        gi = self._gear_index_of(rpm, r.motor_rpm, f_e)
        gear = self.gears[gi]
        omega = TWO_PI * rpm / 60.0
        p_in_w = r.p_in_meas_w / gain
        p_gap_w = air_gap_power_w(r.p_in_meas_w, r.p_cu_meas_w, gain)                            # eq. (11)
        if self.pole_pairs and has_fe and f_e != 0.0:
            power_omega = synchronous_spindle_omega_rad_s(f_e, self.pole_pairs, gear.ratio)        # eq. (10)
        else:
            power_omega = omega
        torque_nm = cutting_torque_nm(p_gap_w, omega, gear.friction_torque_nm, gear.viscous_nms,
                                      power_omega_rad_s=power_omega)                            # eq. (13)
        steady = self.steady(r.speed_rise_rpm, rpm, r.prev_spindle_rpm)
        p_inertia_w = None
        inertia_nm = 0.0
        if gear.inertia_kgm2 is not None:
            if omega > 0.0 and not steady:
                d_omega = TWO_PI * r.speed_rise_rpm / 60.0
                inertia_nm = inertia_torque_nm(gear.inertia_kgm2, omega - d_omega / 2.0, omega + d_omega / 2.0,
                                               TWO_PI / omega, omega)
            torque_nm = torque_nm - inertia_nm                                                  # eq. (13) + J·dω/dt
            p_inertia_w = inertia_nm * omega
        p_gap_meas = r.p_in_meas_w - r.p_cu_meas_w
        var_w2 = max(r.p_gap_sq_meas_w2 - p_gap_meas * p_gap_meas, 0.0)
        sigma_p_w = math.sqrt(var_w2 / max(r.samples, 1)) / gain                                 # std. error of the mean
        sigma_nm = torque_sigma_nm(sigma_p_w, power_omega)                                      # eq. (20)

        override = r.feed_override_pct
        feed_mm_min = r.feed_rate_mm_min
        if feed_mm_min is None and self.feed_mm_min is not None:
            feed_mm_min = self.feed_mm_min if override is None else self.feed_mm_min * override / 100.0
        force_feed_n = None
        if self.feed_force is not None and r.feed_current_a is not None:
            _, n_per_a, friction_n = self.feed_force
            force_feed_n = n_per_a * r.feed_current_a - friction_n

        # not while the spindle only runs up or brakes (docs/physics.md, "When a depth is published")
        ramp = validity.spindle_ramp(r.speed_rise_rpm, rpm, r.prev_spindle_rpm, p_gap_w, inertia_nm, torque_nm)
        cutting = torque_nm >= self.min_torque_nm and not ramp
        self.feed_check.update(r.feed_rate_mm_min, cutting and steady, 100.0 if override is None else override)
        noise_nm = self.min_torque_nm + self.FORCE_NOISE_SIGMAS * (sigma_nm if math.isfinite(sigma_nm) else 0.0)
        geometry = self.tools.get(tool, self.tool)
        t_c = feed_mm_min / (geometry.flutes * rpm) if feed_mm_min is not None and rpm > 0 else math.nan  # f/(N·n)
        tangential_n = torque_nm / (geometry.radius_mm * 1e-3)                                  # eq. (16)
        radial_mm = axial_mm = None
        status = None
        if self.method != "off":
            status = self._precondition(ramp, cutting, rpm, t_c, geometry)
            if status is None:
                d = self._depth(geometry, torque_nm, tangential_n, force_feed_n, t_c, r.force_x_n, r.force_y_n)
                status, radial_mm, axial_mm = d.status, _known(d.radial_depth_mm), _known(d.axial_depth_mm)
                if not validity.within_tool(radial_mm, axial_mm, geometry.diameter_mm, geometry.flute_length_mm):
                    status, radial_mm, axial_mm = validity.OUTSIDE_TOOL, None, None
        force_n = self._force_one(geometry, torque_nm, t_c, radial_mm, axial_mm, noise_nm, cut)
        self.last_gain = gain
        self.gains = [gain]
        return {
            "spindle_rpm": rpm,
            "gear": gear.name,
            "p_in_w": p_in_w,
            "p_gap_w": p_gap_w,
            "p_inertia_w": p_inertia_w,
            "spindle_accel_rad_s2": TWO_PI / 60.0 * r.speed_rise_rpm * rpm / 60.0,
            "torque_nm": torque_nm,
            "torque_sigma_nm": sigma_nm,
            "force_n": None if math.isnan(force_n) else force_n,
            "force_tangential_n": tangential_n,
            "force_feed_n": force_feed_n,
            "feed_per_tooth_mm": t_c if math.isfinite(t_c) else None,
            "radial_depth_mm": radial_mm,
            "axial_depth_mm": axial_mm,
            "depth_status": status,
            "cutting": cutting,
        }

    def _precondition(self, ramp: bool, cutting: bool, rpm: float, t_c: float, tool: ToolGeometry) -> str | None:
        """Why one revolution gets no depth before any root finding (None: solve it); `_depth_many`'s
        masks in the same order (docs/physics.md, "When a depth is published")."""
        if ramp:
            return validity.SPEED_CHANGING
        if not cutting:
            return depth_mod.AIR_CUT
        if rpm > self._max_model_rpm:
            return validity.SPEED_OUT_OF_RANGE
        if math.isnan(t_c):
            return depth_mod.OUT_OF_RANGE   # no feed known: as before
        return validity.feed_status(t_c, tool.radius_mm)

    def _force_one(self, tool: ToolGeometry, torque_nm: float, t_c: float, radial_mm: float | None,
                   axial_mm: float | None, noise_nm: float, cut: OperationEngagement | None = None) -> float:
        """`_force_many` of one revolution on floats: [P] eq. (18), nan where none."""
        cf = tool.cf
        if tool.cf_model:   # the engaged teeth added as vectors (force.engaged_cf, resultant.py R2)
            mode, radial_mm, axial_mm = self.force_engagement(cut, radial_mm, axial_mm)
            cf = engaged_cf(mode, tool.flutes, tool.radius_mm, tool.helix_deg, t_c, radial_mm, axial_mm,
                            self.material, tool.cf_fallback)
            if math.isnan(cf):
                return math.nan
        return resultant_force_magnitudes_n(torque_nm, tool.radius_mm, cf, noise_nm)            # [P] eq. 18

    def force_engagement(self, cut: OperationEngagement | None, radial_mm, axial_mm):
        """(mode, radial, axial) the force's C_f is taken at: an operation's declared constant cut where the CNC
        reports one (`[operations]`: its mode is the cut's, whatever `[cut]` says, and its programmed depths, not
        depths estimated under `[cut]`'s mode); else `[cut]`'s mode, the estimated depths, else `[cut]`'s."""
        if cut is not None:
            return cut
        return self.mode, _or_known(radial_mm, self.known_radial_mm), _or_known(axial_mm, self.known_axial_mm)

    def estimate_many(self, c: RevolutionColumns, tools: Sequence[int | None] | None = None,
                      cuts: Sequence[OperationEngagement | None] | None = None) -> dict[str, list]:
        """All physical fields of R good revolutions at once: {field: list of R plain values (None: null)}.

        Every formula runs once over the (R,) columns; only the feed check (a state machine over
        consecutive revolutions) and the depth's root finding, when configured, go revolution by revolution.
        `tools`: the CNC tool number in the spindle for each revolution (None: unknown); what depends on
        the tool runs once per tool among them, on its revolutions; `cuts`: each revolution's operation
        engagement (`estimate`'s `cut`), grouped with the tool.
        """
        rpm = c.spindle_rpm
        f_e = c.f_e_hz
        count = len(rpm)
        has_fe = np.isfinite(f_e)
        gain = self._filter_gains(f_e)
        gi = self._gear_indices(c)
        ratio = self._ratios[gi]
        omega = TWO_PI * rpm / 60.0
        p_in_w = c.p_in_meas_w / gain
        p_gap_w = air_gap_power_w(c.p_in_meas_w, c.p_cu_meas_w, gain)                         # eq. (11)
        use_sync = has_fe & (f_e != 0.0) if self.pole_pairs else np.zeros(count, dtype=bool)
        if use_sync.any():
            power_omega = np.where(use_sync, synchronous_spindle_omega_rad_s(
                np.where(use_sync, f_e, 0.0), self.pole_pairs, ratio), omega)                  # eq. (10)
        else:
            power_omega = omega
        torque_nm = cutting_torque_nm(p_gap_w, omega, self._friction[gi], self._viscous[gi],
                                      power_omega_rad_s=power_omega)                            # eq. (13)
        steady = self.steady(c.speed_rise_rpm, rpm, c.prev_spindle_rpm)
        inertia = self._inertia[gi]
        has_j = np.isfinite(inertia)
        inertia_nm = np.zeros(count)
        if has_j.any():
            apply = has_j & (omega > 0.0) & ~steady
            d_omega = TWO_PI * c.speed_rise_rpm / 60.0
            # a revolution's rpm is 60·rate/duration: always finite and > 0, so nothing here divides by 0
            inertia_nm = np.where(apply, inertia_torque_nm(np.where(has_j, inertia, 0.0), omega - d_omega / 2.0,
                                                           omega + d_omega / 2.0, TWO_PI / omega, omega), 0.0)
            torque_nm = torque_nm - inertia_nm                                                  # eq. (13) + J·dω/dt
            p_inertia_w = _optional(inertia_nm * omega, has_j)
        else:
            p_inertia_w = [None] * count
        p_gap_meas = c.p_in_meas_w - c.p_cu_meas_w
        var_w2 = np.maximum(c.p_gap_sq_meas_w2 - p_gap_meas * p_gap_meas, 0.0)
        sigma_p_w = np.sqrt(var_w2 / np.maximum(c.samples, 1)) / gain                            # std. error of the mean
        sigma_nm = torque_sigma_nm(sigma_p_w, power_omega)                                      # eq. (20)

        # The feed the cut ran at: the feed-rate channel when there is one, else the programmed feed times
        # the override the CNC applied (docs/physics.md: feed per tooth t_c = f/(N·n))
        override = c.feed_override_pct
        feed_mm_min = c.feed_rate_mm_min
        if feed_mm_min is None and self.feed_mm_min is not None:
            feed_mm_min = (np.full(count, self.feed_mm_min) if override is None
                           else self.feed_mm_min * override / 100.0)
        force_feed_n = None
        if self.feed_force is not None and c.feed_current_a is not None:
            _, n_per_a, friction_n = self.feed_force
            force_feed_n = n_per_a * c.feed_current_a - friction_n

        ramp = validity.spindle_ramp(c.speed_rise_rpm, rpm, c.prev_spindle_rpm, p_gap_w, inertia_nm, torque_nm)
        cutting = (torque_nm >= self.min_torque_nm) & ~ramp
        self._feed_check_many(c.feed_rate_mm_min, cutting & steady, override)
        noise_nm = self.force_noise_nm(sigma_nm)
        groups = self._tool_groups(tools, count, cuts)
        if len(groups) == 1:   # the usual block: one tool, the whole columns
            t_c, tangential_n, radial_mm, axial_mm, status, force_n = self._with_tool(
                groups[0][0], torque_nm, rpm, feed_mm_min, force_feed_n, c.force_x_n, c.force_y_n, cutting, noise_nm,
                ramp, groups[0][2])
        else:
            t_c, tangential_n, radial_mm, axial_mm, force_n = (np.empty(count) for _ in range(5))
            status: list = [None] * count
            for tool, rows, cut in groups:
                def pick(values):
                    return None if values is None else values[rows]

                part = self._with_tool(tool, torque_nm[rows], rpm[rows], pick(feed_mm_min), pick(force_feed_n),
                                       pick(c.force_x_n), pick(c.force_y_n), cutting[rows], noise_nm[rows],
                                       ramp[rows], cut)
                for whole, piece in zip((t_c, tangential_n, radial_mm, axial_mm), part[:4]):
                    whole[rows] = piece
                force_n[rows] = part.force_n
                for i, st in zip(rows.tolist(), part.status):
                    status[i] = st
        self.last_gain = float(gain[-1])
        self.gains = gain.tolist()   # of each revolution of this call, for the sample-level power after each
        t_c_ok = np.isfinite(t_c)
        return {
            "spindle_rpm": rpm.tolist(),
            "gear": [self._names[g] for g in gi.tolist()],
            "p_in_w": p_in_w.tolist(),
            "p_gap_w": p_gap_w.tolist(),
            "p_inertia_w": p_inertia_w,
            "spindle_accel_rad_s2": (TWO_PI / 60.0 * c.speed_rise_rpm * rpm / 60.0).tolist(),
            "torque_nm": torque_nm.tolist(),
            "torque_sigma_nm": sigma_nm.tolist(),
            "force_n": _optional(force_n, ~np.isnan(force_n)),
            "force_tangential_n": tangential_n.tolist(),
            "force_feed_n": [None] * count if force_feed_n is None else force_feed_n.tolist(),
            "feed_per_tooth_mm": _optional(t_c, t_c_ok),
            "radial_depth_mm": _optional(radial_mm, ~np.isnan(radial_mm)),
            "axial_depth_mm": _optional(axial_mm, ~np.isnan(axial_mm)),
            "depth_status": status,
            "cutting": cutting.tolist(),
        }

    def _tool_groups(self, tools: Sequence[int | None] | None, count: int,
                     cuts: Sequence[OperationEngagement | None] | None = None) -> list[tuple]:
        """(geometry, its revolutions' indices, operation engagement) per tool and engagement among `tools` and
        `cuts`; a number not listed is `[tool]`."""
        if (tools is None or not self.tools) and not (cuts and any(c is not None for c in cuts)):
            return [(self.tool, np.arange(count), None)]
        rows: dict[tuple, list[int]] = {}
        for i in range(count):
            number = None if tools is None else tools[i]
            rows.setdefault((number if number in self.tools else None, None if cuts is None else cuts[i]), []).append(i)
        return [(self.tools.get(number, self.tool), np.array(r, dtype=np.intp), cut)
                for (number, cut), r in rows.items()]

    def _with_tool(self, tool: ToolGeometry, torque_nm, rpm, feed_mm_min, force_feed_n, force_x_n, force_y_n,
                   cutting, noise_nm, ramp, cut: OperationEngagement | None = None) -> _ToolPart:
        """What depends on the tool, for revolutions that all had `tool` in the spindle."""
        if feed_mm_min is not None:
            t_c = np.where(rpm > 0, feed_mm_min / (tool.flutes * rpm), np.nan)                  # t_c = f/(N·n)
        else:
            t_c = np.full(len(rpm), np.nan)
        tangential_n = torque_nm / (tool.radius_mm * 1e-3)                                      # eq. (16)
        radial_mm, axial_mm, status = self._depth_many(tool, torque_nm, tangential_n, force_feed_n, t_c,
                                                       force_x_n, force_y_n, cutting, rpm, ramp)
        force_n = self._force_many(tool, torque_nm, t_c, radial_mm, axial_mm, noise_nm, cut)
        return _ToolPart(t_c, tangential_n, radial_mm, axial_mm, status, force_n)

    def _filter_gains(self, f_e_hz: np.ndarray) -> np.ndarray:
        """|H(f_e)|² of the DAQ's anti-alias filter (physics.md §1); 1 with no filter or no f_e."""
        if self.cutoff_hz <= 0.0:
            return np.ones(len(f_e_hz))
        known = np.isfinite(f_e_hz)
        return np.where(known, butterworth_power_gain(np.where(known, f_e_hz, 0.0), self.cutoff_hz,
                                                      self.filter_order), 1.0)

    def _gear_indices(self, c: RevolutionColumns) -> np.ndarray:
        """Gear from the motor/spindle speed ratio when measurable, else by spindle speed."""
        rpm = c.spindle_rpm
        if len(rpm) == 1:   # the live daemon's batch: one revolution, on plain floats (the same choice)
            return np.array([self._gear_index(c)], dtype=np.intp)
        if c.motor_rpm is not None:
            ratio = np.where(rpm > 0, c.motor_rpm / rpm, np.nan)
        elif self.pole_pairs:
            f_e = c.f_e_hz
            usable = np.isfinite(f_e) & (f_e != 0.0) & (rpm > 0)
            ratio = np.where(usable, (60.0 * f_e / self.pole_pairs) / rpm, np.nan)   # synchronous / spindle
        else:
            ratio = None
        return select_gears(rpm, self._max_rpm, self._ratio_list, motor_to_spindle_ratio=ratio)

    def _filter_gain(self, f_e_hz: float) -> float:
        """`_filter_gains` of one revolution on floats: |H(f_e)|² (physics.md §1), 1 with no f_e
        (`butterworth_power_gain` gives 1 with no filter)."""
        if not math.isfinite(f_e_hz):
            return 1.0
        return butterworth_power_gain(f_e_hz, self.cutoff_hz, self.filter_order)

    def _gear_index(self, c: RevolutionColumns) -> int:
        """`_gear_indices` of a one-revolution batch."""
        return self._gear_index_of(float(c.spindle_rpm[0]), None if c.motor_rpm is None else float(c.motor_rpm[0]),
                                   float(c.f_e_hz[0]))

    def _gear_index_of(self, rpm: float, motor_rpm: float | None, f_e: float) -> int:
        """One revolution's gear: `select_gear` on its floats (test_vectorised.py holds `select_gears` to it),
        with the measured ratio clipped as `select_gears` clips it; `f_e` nan: none."""
        ratio: float | None = None
        if motor_rpm is not None:
            ratio = motor_rpm / rpm if rpm > 0 else math.nan
        elif self.pole_pairs:
            usable = math.isfinite(f_e) and f_e != 0.0 and rpm > 0
            ratio = (60.0 * f_e / self.pole_pairs) / rpm if usable else math.nan
        if ratio is not None and math.isfinite(ratio) and ratio > 0:
            ratio = min(max(ratio, 1e-12), 1e12)
        return select_gear(rpm, self._max_rpm, self._ratio_list, motor_to_spindle_ratio=ratio)

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
    def steady(speed_rise_rpm, spindle_rpm, prev_spindle_rpm):
        """Is the speed's change over each revolution within the speed readings' noise? Plain floats (one
        revolution; prev None: none before) or arrays of revolutions (prev nan: none before)."""
        if isinstance(spindle_rpm, float):
            band = max(RevolutionPhysics.STEADY_STEP_RPM, RevolutionPhysics.STEADY_STEP_PCT / 100.0 * spindle_rpm)
            return abs(speed_rise_rpm) <= RevolutionPhysics.STEADY_RISE_RPM and (
                prev_spindle_rpm is None or abs(spindle_rpm - prev_spindle_rpm) <= band)
        band = np.maximum(RevolutionPhysics.STEADY_STEP_RPM, RevolutionPhysics.STEADY_STEP_PCT / 100.0 * spindle_rpm)
        step_ok = np.isnan(prev_spindle_rpm) | (np.abs(spindle_rpm - prev_spindle_rpm) <= band)
        return (np.abs(speed_rise_rpm) <= RevolutionPhysics.STEADY_RISE_RPM) & step_ok

    # The masses' share of a revolution's mean torque is ½J(ω_end² − ω_start²)/(Δt·ω̄) with Δt = 2π/ω̄
    # exactly (a revolution) and ω_start, ω_end = ω̄ ∓ Δω/2, Δω the speed reading's rise over the
    # revolution: J·Δω/Δt (torque.inertia_torque_nm). Why the rise and not the difference of consecutive
    # revolutions' mean speeds (which is far less noisy): that difference is centred half a revolution
    # earlier, and in a crash the speed turns within a revolution: the lagged term hands the recovering
    # revolution's load to the masses (reads low, the unsafe side). See docs for the noise (J·σ_Δω·ω̄/2π).

    def _feed_check_many(self, measured_mm_min: np.ndarray | None, steady_cutting: np.ndarray,
                         override_pct: np.ndarray | None = None) -> None:
        if measured_mm_min is None or self.feed_check.configured_mm_min is None:
            # nothing to judge: the check only remembers the last measured feed
            self.feed_check.update(None if measured_mm_min is None else float(measured_mm_min[-1]), False)
            return
        overrides = [100.0] * len(measured_mm_min) if override_pct is None else override_pct.tolist()
        for measured, steady, ovr in zip(measured_mm_min.tolist(), steady_cutting.tolist(), overrides):
            self.feed_check.update(measured, steady, ovr)

    def _depth_many(self, tool: ToolGeometry, torque_nm, tangential_n, force_feed_n, t_c, force_x_n, force_y_n,
                    cutting, rpm, ramp):
        """(radial mm, axial mm: nan where none; statuses): root finding only on cutting revolutions inside
        the physics' preconditions (`_precondition`'s order), depths outside the tool taken back."""
        count = len(torque_nm)
        radial = np.full(count, np.nan)
        axial = np.full(count, np.nan)
        if self.method == "off":
            return radial, axial, [None] * count
        fast = rpm > self._max_model_rpm
        no_feed = np.isnan(t_c)
        low, high = validity.feed_masks(t_c, tool.radius_mm)
        status = np.select([ramp, ~cutting, fast, no_feed, low, high],
                           [validity.SPEED_CHANGING, depth_mod.AIR_CUT, validity.SPEED_OUT_OF_RANGE,
                            depth_mod.OUT_OF_RANGE, validity.NOT_FEEDING, validity.FEED_OUT_OF_RANGE],
                           depth_mod.OUT_OF_RANGE).tolist()
        todo = np.flatnonzero(cutting & ~(fast | no_feed | low | high))
        # one revolution (the live daemon's block) goes the scalar way below: numpy's pass over one
        # element costs more than the revolution's floats (test_depth_vector holds the two forms equal)
        if not (len(todo) > 1 and self.method == "torque-only"
                and self._torque_only_many(tool, torque_nm, t_c, todo, radial, axial, status)):
            self._depth_each(tool, todo, torque_nm, tangential_n, force_feed_n, t_c, force_x_n, force_y_n,
                             radial, axial, status)
        outside = ~validity.within_tool(radial, axial, tool.diameter_mm, tool.flute_length_mm)
        if outside.any():
            radial[outside] = np.nan
            axial[outside] = np.nan
            for i in np.flatnonzero(outside).tolist():
                status[i] = validity.OUTSIDE_TOOL
        return radial, axial, status

    def _depth_each(self, tool: ToolGeometry, todo, torque_nm, tangential_n, force_feed_n, t_c, force_x_n,
                    force_y_n, radial, axial, status) -> None:
        """`_depth` revolution by revolution over `todo`, written into radial, axial, status."""
        if len(todo):
            fx = force_x_n.tolist() if force_x_n is not None else None
            fy = force_y_n.tolist() if force_y_n is not None else None
            ff = force_feed_n.tolist() if force_feed_n is not None else None
            tq, tn, tc = torque_nm.tolist(), tangential_n.tolist(), t_c.tolist()
            for i in todo.tolist():
                d = self._depth(tool, tq[i], tn[i], None if ff is None else ff[i], tc[i],
                                None if fx is None else fx[i], None if fy is None else fy[i])
                status[i] = d.status
                if d.radial_depth_mm is not None:
                    radial[i] = d.radial_depth_mm
                if d.axial_depth_mm is not None:
                    axial[i] = d.axial_depth_mm

    def _torque_only_many(self, tool: ToolGeometry, torque_nm, t_c, todo, radial, axial, status) -> bool:
        """Torque-only depths of the `todo` revolutions in one pass over their columns
        (`depth.depth_from_torque_many`), written into radial, axial, status. False (nothing written):
        the configuration is refused (a known depth outside the tool): the revolution-by-revolution
        path words it, as before."""
        known_radial = self.known_radial_mm
        known_axial = self.known_axial_mm if known_radial is None else None
        try:
            r, a, st = depth_mod.depth_from_torque_many(
                torque_nm[todo], t_c[todo], tool.radius_mm, tool.flutes, self.material, self.mode,
                known_radial_mm=known_radial, known_axial_mm=known_axial)
        except ValueError:
            return False
        radial[todo] = r
        axial[todo] = a
        for i, s in zip(todo.tolist(), st):
            status[i] = s
        return True

    def _depth(self, tool: ToolGeometry, torque_nm: float, tangential_n: float, force_feed_n: float | None,
               t_c: float, force_x_n: float | None, force_y_n: float | None) -> depth_mod.DepthResult:
        """One cutting revolution's depths by the configured method ([D] §3), on plain floats; a known
        depth outside this tool's diameter gives `out_of_range`."""
        common = dict(feed_per_tooth_mm=t_c, tool_radius_mm=tool.radius_mm, flutes=tool.flutes,
                      material=self.material, mode=self.mode)
        try:
            if self.method == "dynamometer":
                if force_x_n is None or force_y_n is None:
                    return depth_mod.DepthResult(None, None, depth_mod.NO_SECOND_FORCE)
                return depth_mod.depths_from_forces(fx_n=force_x_n, fy_n=force_y_n, **common)
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

    def force_noise_nm(self, sigma_nm):
        return self.min_torque_nm + self.FORCE_NOISE_SIGMAS * np.where(np.isfinite(sigma_nm), sigma_nm, 0.0)

    def _force_many(self, tool: ToolGeometry, torque_nm: np.ndarray, t_c: np.ndarray, radial_mm: np.ndarray,
                    axial_mm: np.ndarray, noise_nm, cut: OperationEngagement | None = None) -> np.ndarray:
        """Resultant in-plane force magnitude, [P] eq. (18), >= 0, nan where none
        (force.resultant_force_magnitudes_n); C_f constant, or of the engaged teeth (force.engaged_cf):
        the operation's declared cut, else the estimated depths, else the configured ones (`force_engagement`)."""
        if not tool.cf_model:
            return resultant_force_magnitudes_n(torque_nm, tool.radius_mm, tool.cf, noise_nm)
        mode, radial_mm, axial_mm = self.force_engagement(cut, radial_mm, axial_mm)
        cf = engaged_cf(mode, tool.flutes, tool.radius_mm, tool.helix_deg, t_c, radial_mm, axial_mm,
                        self.material, tool.cf_fallback)
        usable = np.isfinite(cf)
        return np.where(usable, resultant_force_magnitudes_n(torque_nm, tool.radius_mm, np.where(usable, cf, 1.0),
                                                             noise_nm), np.nan)


def _or_known(depth_mm, known_mm: float | None):
    """An estimated depth (a float, None, or a column with nan), the configured one where it has none."""
    if known_mm is None:
        return depth_mm
    if isinstance(depth_mm, np.ndarray):
        return np.where(np.isnan(depth_mm), known_mm, depth_mm)
    return known_mm if depth_mm is None else depth_mm


def _known(value: float | None) -> float | None:
    """A plain float, None for nan: as `_optional` gives it from a column (the root finders may hand back a
    numpy float)."""
    return None if value is None or math.isnan(value) else float(value)


def _optional(values: np.ndarray, known: np.ndarray) -> list:
    """Plain values, None where not `known`."""
    if known.all():
        return values.tolist()
    if not known.any():
        return [None] * len(values)
    return [v if k else None for v, k in zip(values.tolist(), known.tolist())]
