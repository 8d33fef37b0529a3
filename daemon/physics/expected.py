"""The load a programmed cut should take: [D]'s average forces run forwards ([D] eqs. 7–9, [P] eqs. 16–18).

The estimator runs the milling model backwards (torque → depth of cut). Here the same model runs
forwards: from an operation's programmed cut (radial and axial depth, feed, mode), the tool and the
material, the expected mean cutting torque and resultant force at the spindle speed and feed override
of one revolution. This is what guards a first part before anything is learned (docs/learning.md).

The feed per tooth a revolution actually cuts follows the override in both ways of programming a feed:
per tooth (``fz``, like G95: the feed rate follows the spindle speed) it is ``fz·u``; as a feed rate
(``vf``, like G94) it is ``vf·u/(n·N)``, u = override/100. An unknown override gives no expectation:
nothing is armed on a guess.
"""

from __future__ import annotations

import math
from typing import NamedTuple

from millsense.daemon.physics.force import P_MEAN_CF, engaged_cf
from millsense.daemon.physics.milling import Material, average_forces_n, check_mode


class ProgrammedCut(NamedTuple):
    """An operation's cut as programmed: depths in mm, one of the two feeds, the milling mode."""

    radial_depth_mm: float                  # ae (a slot: the tool's diameter)
    axial_depth_mm: float                   # ap
    mode: str                               # "slot", "up" or "down"
    feed_per_tooth_mm: float | None = None  # fz, per tooth (G95-like)
    feed_mm_min: float | None = None        # vf, feed rate (G94-like)


class ExpectedLoad(NamedTuple):
    """The mean load one revolution of a programmed cut should take."""

    torque_nm: float
    force_n: float
    feed_per_tooth_mm: float   # the feed per tooth cut at this speed and override


def cut_feed_per_tooth_mm(cut: ProgrammedCut, spindle_rpm: float, flutes: int, override_pct: float | None) -> float | None:
    """Feed per tooth actually cut, mm: ``fz·u`` or ``vf·u/(n·N)``; None where it cannot be known.

    None for an unknown or non-positive override, a spindle not turning, or a cut with neither feed.
    """
    if override_pct is None or not math.isfinite(override_pct) or override_pct <= 0.0:
        return None
    if not math.isfinite(spindle_rpm) or spindle_rpm <= 0.0 or flutes < 1:
        return None
    u = override_pct / 100.0
    if cut.feed_per_tooth_mm is not None:
        return cut.feed_per_tooth_mm * u
    if cut.feed_mm_min is not None:
        return cut.feed_mm_min * u / (spindle_rpm * flutes)
    return None


def expected_load(
    cut: ProgrammedCut,
    *,
    tool_radius_mm: float,
    flutes: int,
    material: Material,
    spindle_rpm: float,
    override_pct: float | None,
    helix_deg: float | None = None,
) -> ExpectedLoad | None:
    """Expected mean cutting torque (N·m) and resultant force (N) of one revolution, or None.

    Torque: ``T = F_at·R`` ([P] eq. 16) with F_at the average tangential force of [D] eq. (7) at the
    chip thickness of eq. (8) and the coefficients of eq. (9). Force: ``C_f·F_at`` ([P] eq. 18) with
    the estimator's C_f of the engaged teeth, ``η·√(1 + r₁(t_a)²)`` (``force.engaged_cf``: [P] eq. 17,
    [D] eq. 9, the teeth's forces added as vectors, each at its instantaneous chip with the material's
    exponents: resultant.py eqs. R1a–R2) at the programmed depths;
    ``helix_deg`` None (unknown) takes straight flutes, the largest force the cut can have. A feed per
    tooth outside the chip model's range (validity.py) takes [P]'s mean 1.075 for √(1 + r₁²).
    None where nothing can be expected (unknown override, spindle stopped, no feed, a radial depth the
    mode cannot have).
    """
    check_mode(cut.mode)
    t_c = cut_feed_per_tooth_mm(cut, spindle_rpm, flutes, override_pct)
    if t_c is None or tool_radius_mm <= 0.0:
        return None
    radial_ratio = cut.radial_depth_mm / tool_radius_mm
    axial_ratio = cut.axial_depth_mm / tool_radius_mm
    forces = average_forces_n(radial_ratio, axial_ratio, t_c, tool_radius_mm, flutes, material, cut.mode)
    tangential_n = float(forces.tangential_n)
    if not math.isfinite(tangential_n):
        return None
    cf = float(engaged_cf(cut.mode, flutes, tool_radius_mm, helix_deg, float(t_c), cut.radial_depth_mm,
                          cut.axial_depth_mm, material, P_MEAN_CF))
    return ExpectedLoad(
        torque_nm=tangential_n * tool_radius_mm * 1e-3,   # [P] eq. 16, R in metres
        force_n=cf * tangential_n,                        # [P] eq. 18
        feed_per_tooth_mm=t_c,
    )
