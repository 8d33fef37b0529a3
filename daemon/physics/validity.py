"""When the physics' preconditions hold: where a depth (and a cut) may be claimed at all.

[P] eq. (13) is a steady-state balance and [D] eqs. (7)–(13) describe a tooth
cutting a chip of feed per tooth t_c with a flute of the tool's geometry. A
revolution outside those premises still yields numbers from the formulas
(a spindle running up with its axes stopped gave t_c = 2·10⁻⁵ mm and an
"axial depth" of 936 mm on a φ20 cutter); they are not measurements and are
not published as such. docs/physics.md, "When a depth is published", states
every rule here with its reason.

Each function takes one revolution's plain floats (the live path) or numpy
arrays of a block's revolutions (replay), as the other physics modules do
(`numbers.py`); the array forms are the float forms element by element
(tests/physics/test_validity.py holds them equal). Plain comparisons only:
this runs on every revolution.
"""

from __future__ import annotations

import numpy as np

# --- statuses (depth_status values added to depth.py's; docs/zenoh.md, docs/physics.md) -----------
SPEED_CHANGING = "speed_changing"          # the spindle runs up or brakes: nothing is claimed cut
SPEED_OUT_OF_RANGE = "speed_out_of_range"  # faster than the gears' table (friction of eq. 13 unknown)
NOT_FEEDING = "not_feeding"                # t_c below the chip model's range: the axes stand or creep
FEED_OUT_OF_RANGE = "feed_out_of_range"    # t_c above the chip model's range for this tool
OUTSIDE_TOOL = "outside_tool"              # the estimated depth does not fit the tool's geometry

# --- feed per tooth ([D] eqs. 1, 8–9) ---------------------------------------------------------
# Lower bound: the power laws K_s = k_s·t_a^p_s, r_1 = k_1·t_a^p_1 ([D] eq. 9) have negative exponents
# and grow without bound as the chip thins; below t_c = 0.01 mm the mean chip (2·t_c/π in a slot,
# [D] eq. 8) is a few µm, thinner than a cutting edge's radius, where the tool rubs instead of cutting
# (the same reasoning as depth.MIN_RADIAL_RATIO). 0.01–0.7 mm is also the range over which the ratio
# f_xt is checked strictly monotone in R_r (docs/physics.md §6). [P]'s trial grid reaches 0.02 mm
# (100 mm/min, 2500 rpm, 2 flutes), [D] validated 0.104–0.467 mm.
FEED_PER_TOOTH_MIN_MM = 0.01
FEED_PER_TOOTH_MAX_MM = 0.7
# Upper bound from the tool: the chip h = t_c·sin φ ([D] eq. 1) takes the tooth's path as a circle,
# the first term of the trochoid in t_c/R; a feed per tooth over a tenth of the radius is outside
# that approximation (and far outside any end mill's rating: φ8 → 0.4 mm).
FEED_PER_TOOTH_MAX_PER_RADIUS = 0.1

# --- spindle speed ([P] eq. 13, Table 2) -----------------------------------------------------------
# Friction T_f', B' is known per gear up to its max_spindle_rpm; above the fastest gear eq. (13)
# extrapolates it. The margin covers a speed reading's scatter at the top speed. No lower bound is
# needed beyond revolutions.STOP_RPM (nothing is published below it): while the axes feed, t_c = f/(N·n)
# rises past FEED_PER_TOOTH_MAX_MM as n falls, and eq. (20) gives the torque's scatter at every speed.
SPEED_MARGIN_FRAC = 0.02

# --- the spindle runs up or brakes (eq. 13 is steady-state; [P] eq. 2's inertia term) ---------------
# A run-up: the speed rises within the revolution by more than 1 % of its mean (and more than the
# readings' 2 rpm of noise, RevolutionPhysics.STEADY_RISE_RPM), while the mean did not fall against
# the revolution before by more than 0.5 % (that is a drive catching up with a spindle its load
# slowed: a crash, a stall; the estimator's `accelerating` rule says the same). A load change swings
# the speed by 0.12 % at most within a simulated revolution; a run-up by 2.6–36 % (1500–2000 rpm).
RAMP_RISE_FRAC = 0.01
RAMP_RISE_MIN_RPM = 2.0
RAMP_SLOWING_FRAC = 0.005
# With the inertia J known (eq. 13 + J·dω/dt): the masses take at least the torque the cut is said
# to take (T_J ≥ T_c > 0: the torque left is a residual of a large term), or the drive supplies no
# air-gap power at all (P_g ≤ 0: it brakes, or the spindle coasts on its own momentum). A cut, a
# crash or a stall slows the spindle while the drive motors (P_g > 0), so neither rule takes their
# load away.

# --- geometry ---------------------------------------------------------------------------------
# `flute_length_mm` of [tool] / [tools.N] when not given: a regular-length end mill's cutting length
# is about twice its diameter (DIN 6527 L / DIN 844 N: φ8 19 mm, φ16 32 mm, φ20 38 mm).
FLUTE_LENGTH_PER_DIAMETER = 2.0


def default_flute_length_mm(diameter_mm: float) -> float:
    """The flute length taken when `[tool]` / `[tools.N]` gives none."""
    return FLUTE_LENGTH_PER_DIAMETER * float(diameter_mm)


def max_feed_per_tooth_mm(radius_mm: float) -> float:
    """The largest feed per tooth the chip model holds for a tool of this radius (float)."""
    return min(FEED_PER_TOOTH_MAX_MM, FEED_PER_TOOTH_MAX_PER_RADIUS * radius_mm)


def max_spindle_rpm(top_gear_rpm: float) -> float:
    """The fastest spindle speed eq. (13)'s friction is known for (float)."""
    return top_gear_rpm * (1.0 + SPEED_MARGIN_FRAC)


def spindle_ramp(speed_rise_rpm, spindle_rpm, prev_spindle_rpm, p_gap_w, inertia_nm, torque_nm):
    """Does the spindle only run up or brake over this revolution? (module notes above.)

    Floats (one revolution; `prev_spindle_rpm` None or nan: none before; `inertia_nm` 0.0 when J is
    unknown or inside the steady gate) or arrays (prev nan: none).
    """
    if isinstance(spindle_rpm, float):
        slowing = (prev_spindle_rpm is not None and spindle_rpm - prev_spindle_rpm < -RAMP_SLOWING_FRAC * spindle_rpm)
        run_up = speed_rise_rpm > max(RAMP_RISE_FRAC * spindle_rpm, RAMP_RISE_MIN_RPM) and not slowing
        return run_up or (0.0 < inertia_nm and torque_nm <= inertia_nm) or p_gap_w <= 0.0
    slowing = spindle_rpm - prev_spindle_rpm < -RAMP_SLOWING_FRAC * spindle_rpm      # nan: False
    run_up = (speed_rise_rpm > np.maximum(RAMP_RISE_FRAC * spindle_rpm, RAMP_RISE_MIN_RPM)) & ~slowing
    return run_up | ((0.0 < inertia_nm) & (torque_nm <= inertia_nm)) | (p_gap_w <= 0.0)


def feed_status(t_c: float, radius_mm: float) -> str | None:
    """None: the feed per tooth is in the chip model's range for this tool; else the status saying why
    not. `t_c` nan (no feed known) is the caller's (depth.OUT_OF_RANGE, as before)."""
    if t_c < FEED_PER_TOOTH_MIN_MM:
        return NOT_FEEDING
    if t_c > max_feed_per_tooth_mm(radius_mm):
        return FEED_OUT_OF_RANGE
    return None


def feed_masks(t_c: np.ndarray, radius_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """`feed_status` over an array: (below the range, above it); nan is neither."""
    return t_c < FEED_PER_TOOTH_MIN_MM, t_c > max_feed_per_tooth_mm(radius_mm)


def within_tool(radial_mm, axial_mm, diameter_mm: float, flute_length_mm: float):
    """Do the depths fit the tool: radial ≤ diameter, axial ≤ flute length? Floats (None: no depth,
    fits) or arrays (nan: fits)."""
    if isinstance(radial_mm, np.ndarray):
        return ~((radial_mm > diameter_mm) | (axial_mm > flute_length_mm))
    return not ((radial_mm is not None and radial_mm > diameter_mm)
                or (axial_mm is not None and axial_mm > flute_length_mm))


__all__ = [
    "FEED_OUT_OF_RANGE", "FEED_PER_TOOTH_MAX_MM", "FEED_PER_TOOTH_MAX_PER_RADIUS", "FEED_PER_TOOTH_MIN_MM",
    "FLUTE_LENGTH_PER_DIAMETER", "NOT_FEEDING", "OUTSIDE_TOOL", "RAMP_RISE_FRAC", "RAMP_RISE_MIN_RPM",
    "RAMP_SLOWING_FRAC", "SPEED_CHANGING", "SPEED_MARGIN_FRAC", "SPEED_OUT_OF_RANGE", "default_flute_length_mm",
    "feed_masks", "feed_status", "max_feed_per_tooth_mm", "max_spindle_rpm", "spindle_ramp", "within_tool",
]
