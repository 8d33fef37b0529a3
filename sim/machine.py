"""The simulated machine: motor, gearbox, spindle drive, feed drive, tools and materials.

These are the *plant's* constants, chosen once and documented here; the daemon
must learn them from its own configuration and calibration, never from this
module.  [P] = spindle-power paper, [D] = depth-of-cut paper.

Iron and stray losses of the motor are not modelled separately: like [P], they
are folded into the gearbox friction (T_f', B' of [P] Table 2), which is why an
air-cut calibration of the daemon recovers exactly these friction values.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field


@dataclass(frozen=True)
class Motor:
    """FANUC-class 15 kW induction motor, delta winding ([P] §4: FANUC 15S)."""

    rated_power_w: float = 15_000.0
    pole_pairs: int = 2
    stator_resistance_ohm: float = 0.349  # per phase, [P] Table 2
    base_frequency_hz: float = 50.0  # V/f up to here, constant voltage above (field weakening)
    rated_line_voltage_v: float = 200.0  # rms, at and above base frequency
    rated_slip: float = 0.025  # at rated torque; slip is proportional to torque
    magnetising_current_a: float = 10.0  # phase rms at base frequency (~30 % of rated phase current)
    rotor_inertia_kgm2: float = 0.06
    winding: str = "delta"

    @property
    def base_speed_rad_s(self) -> float:
        """Mechanical speed at base frequency and rated slip."""
        return 2 * math.pi * self.base_frequency_hz / self.pole_pairs * (1 - self.rated_slip)

    @property
    def rated_torque_nm(self) -> float:
        return self.rated_power_w / self.base_speed_rad_s


@dataclass(frozen=True)
class Gear:
    """One gearbox ratio with its friction referred to the spindle ([P] eq. 13, Table 2)."""

    name: str
    ratio: float  # motor speed / spindle speed
    max_spindle_rpm: float
    friction_torque_nm: float  # T_f' (Coulomb), iron/stray loss folded in
    viscous_nms: float  # B' (N·m·s/rad)


@dataclass(frozen=True)
class Drive:
    """Speed-controlled spindle drive: PI on motor speed, first-order torque lag, limits."""

    bandwidth_hz: float = 5.0  # speed-loop crossover
    integral_ratio: float = 0.2  # PI zero at this fraction of the crossover
    torque_lag_s: float = 0.015  # torque command -> torque, first order
    peak_torque_factor: float = 1.5  # x rated torque (constant-torque region)
    peak_power_w: float = 22_000.0  # short-time limit (constant-power region)
    spindle_inertia_kgm2: float = 0.08  # spindle, tool holder, output gears (spindle side)
    ramp_motor_rpm_s: float = 2000.0  # speed-reference ramp (the drive's acceleration setting)


@dataclass(frozen=True)
class FeedDrive:
    """X-axis feed servo: the current that balances the feed-direction force."""

    newton_per_amp: float = 950.0
    friction_n: float = 120.0
    current_bandwidth_hz: float = 40.0
    accel_mm_s2: float = 2500.0  # also the feed-hold deceleration (8000 mm/min stops in 53 ms)


@dataclass(frozen=True)
class Machine:
    motor: Motor = field(default_factory=Motor)
    gears: tuple[Gear, ...] = (
        Gear("low-speed", 4.81, 900.0, 2.6629, 0.0400),  # [P] Table 2 ("high ratio")
        Gear("high-speed", 1.157, 4500.0, 1.6160, 0.0022),  # [P] Table 2 ("low ratio")
    )
    drive: Drive = field(default_factory=Drive)
    feed: FeedDrive = field(default_factory=FeedDrive)

    def gear_for_rpm(self, spindle_rpm: float) -> Gear:
        """Gear chosen by the commanded spindle speed, lowest max first ([P] §2: change at 900 rpm)."""
        for gear in sorted(self.gears, key=lambda g: g.max_spindle_rpm):
            if abs(spindle_rpm) <= gear.max_spindle_rpm:
                return gear
        raise ValueError(f"spindle speed {spindle_rpm} rpm is above every gear's maximum")


@dataclass(frozen=True)
class Tool:
    diameter_mm: float
    flutes: int
    helix_deg: float = 30.0
    name: str = ""
    youngs_gpa: float = 600.0  # the cutter's modulus (solid carbide ~600, HSS ~210): its bending (cut_effects.py)

    @property
    def radius_mm(self) -> float:
        return self.diameter_mm / 2


@dataclass(frozen=True)
class Material:
    """Power laws of [D] eqs. (8)-(9): K_s = ks·t_a^ks_exp (N/mm², t_a in mm), r1, r2 alike."""

    name: str
    ks: float
    ks_exp: float
    r1: float
    r1_exp: float
    r2: float
    r2_exp: float
    assumed: bool = False


MATERIALS = {
    "SB40": Material("SB40", 646.08, -0.4362, 0.2201, -0.2667, 0.1244, 0.1702),  # [D] Table 2
    "SM45C": Material("SM45C", 760.0, -0.40, 0.25, -0.25, 0.12, 0.17, assumed=True),
    "SS41": Material("SS41", 580.0, -0.42, 0.22, -0.27, 0.12, 0.17, assumed=True),
}

TOOL_P = Tool(20.0, 2, 30.0, "phi20 2-flute flat end mill [P]")
TOOL_D = Tool(16.0, 4, 30.0, "phi16 4-flute HSS end mill [D]", youngs_gpa=210.0)
TOOL_F = Tool(8.0, 3, 35.0, "phi8 3-flute carbide finishing end mill")

MCH10 = Machine()
