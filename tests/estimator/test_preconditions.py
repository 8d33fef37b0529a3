"""Issue 36, finding 4: a depth is published only where the physics' preconditions hold, and `cutting`
is not claimed while the spindle only runs up or brakes (docs/physics.md, "When a depth is published").

Each rule at its boundary, a hair inside and a hair outside, on both forms of the chain: one
revolution on plain floats (`RevolutionPhysics.estimate`, the live path) and the columns
(`estimate_many`, replay's), which must agree (`_differences` of test_one_revolution.py).

The revolutions are built backwards from the torque they should read: with no anti-alias filter and
no pole pairs, eq. (11) is P_g = p_in − p_cu and eq. (13) T_c = P_g/ω − T_f' − B'·ω (− T_J), so
p_in = (T_c + T_f' + B'·ω + T_J)·ω gives exactly the torque wanted.
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from millsense.daemon.config.load import load_config
from millsense.daemon.physics import validity
from millsense.daemon.pipeline.per_revolution import RevolutionMeans, RevolutionPhysics
from tests.estimator import configs
from tests.estimator.test_one_revolution import _columns, _differences

pytestmark = pytest.mark.quick

HAIR = 1e-6          # relative step either side of a boundary
LOW_GEAR = (2.6629, 0.0400)    # T_f' N·m, B' N·m·s/rad of configs.GEARS, up to 900 rpm
HIGH_GEAR = (1.6160, 0.0022)   # up to 4500 rpm
FLUTES = 2
SMALL_TOOL = "\n[tools.6]\ndiameter_mm = 6.0\nflutes = 2\nflute_length_mm = 9.0\n"


def _physics(tmp_path: Path, **kwargs) -> tuple[RevolutionPhysics, RevolutionPhysics]:
    """Two physics of one configuration (no filter, no pole pairs: the torque is set exactly), one per path."""
    extra = kwargs.pop("extra_toml", "")
    path = tmp_path / "pre.toml"
    path.write_text(configs.toml_text(filter_cutoff_hz=0.0, pole_pairs=None, **kwargs) + extra)
    settings = load_config(path)
    return (RevolutionPhysics(settings, has_dynamometer=False, feed_force=None),
            RevolutionPhysics(settings, has_dynamometer=False, feed_force=None))


def _rev(torque_nm: float, *, rpm: float = 600.0, feed_mm_min: float | None = 200.0, rise_rpm: float = 0.0,
         inertia_nm: float = 0.0, gear: tuple[float, float] = LOW_GEAR, prev_rpm: float | None = None) -> RevolutionMeans:
    omega = 2 * math.pi * rpm / 60.0
    friction_nm, viscous_nms = gear
    p_in_w = (torque_nm + friction_nm + viscous_nms * omega + inertia_nm) * omega
    return RevolutionMeans(spindle_rpm=rpm, p_in_meas_w=p_in_w, p_cu_meas_w=0.0, p_gap_sq_meas_w2=p_in_w * p_in_w,
                           samples=100, f_e_hz=None, motor_rpm=None, feed_rate_mm_min=feed_mm_min,
                           feed_current_a=None, force_x_n=None, force_y_n=None, speed_rise_rpm=rise_rpm,
                           prev_spindle_rpm=rpm if prev_rpm is None else prev_rpm)


def _both(pair, r: RevolutionMeans, tool: int | None = None) -> dict:
    """The revolution through both paths; they must agree; the float path's fields."""
    one, many = pair
    got = one.estimate(r, tool)
    ref = {k: v[0] for k, v in many.estimate_many(_columns(r), None if tool is None else [tool]).items()}
    diffs = _differences(got, ref)
    assert not diffs, "; ".join(diffs)
    return got


def _has_depth(e: dict) -> bool:
    return e["depth_status"] == "ok" and e["axial_depth_mm"] is not None and e["radial_depth_mm"] is not None


# --- feed per tooth ---------------------------------------------------------------------------------
def test_a_feed_per_tooth_under_the_chip_models_range_gets_no_depth(tmp_path):
    pair = _physics(tmp_path)
    at_min = validity.FEED_PER_TOOTH_MIN_MM * FLUTES * 600.0           # mm/min giving t_c = 0.01 mm
    inside = _both(pair, _rev(5.0, feed_mm_min=at_min * (1 + HAIR)))
    below = _both(pair, _rev(5.0, feed_mm_min=at_min * (1 - HAIR)))
    stopped = _both(pair, _rev(5.0, feed_mm_min=0.0))                  # the axes stand
    assert _has_depth(inside) and inside["cutting"]
    for e in (below, stopped):
        assert e["depth_status"] == validity.NOT_FEEDING
        assert e["axial_depth_mm"] is None and e["radial_depth_mm"] is None
        # torque and force do not depend on the feed per tooth ([P] eqs. 13, 18 with a constant C_f)
        assert e["torque_nm"] == pytest.approx(5.0) and e["force_n"] == pytest.approx(inside["force_n"])
        assert e["cutting"]


@pytest.mark.parametrize("tool, radius_mm", [(None, 10.0), (6, 3.0)])
def test_a_feed_per_tooth_over_the_chip_models_range_for_the_tool_gets_no_depth(tmp_path, tool, radius_mm):
    pair = _physics(tmp_path, extra_toml=SMALL_TOOL)
    limit = min(validity.FEED_PER_TOOTH_MAX_MM, validity.FEED_PER_TOOTH_MAX_PER_RADIUS * radius_mm)
    at_max = limit * FLUTES * 600.0
    inside = _both(pair, _rev(1.0, feed_mm_min=at_max * (1 - HAIR)), tool)
    above = _both(pair, _rev(1.0, feed_mm_min=at_max * (1 + HAIR)), tool)
    assert _has_depth(inside)
    assert above["depth_status"] == validity.FEED_OUT_OF_RANGE and above["axial_depth_mm"] is None


def test_with_cf_from_the_chip_the_force_follows_the_feed_rule(tmp_path):
    """C_f = √(1 + r_1(t_a)²) ([D] eq. 9) needs a chip in the model's range: outside it no force either."""
    pair = _physics(tmp_path, cf="model")
    at_min = validity.FEED_PER_TOOTH_MIN_MM * FLUTES * 600.0
    inside = _both(pair, _rev(5.0, feed_mm_min=at_min * (1 + HAIR)))
    below = _both(pair, _rev(5.0, feed_mm_min=at_min * (1 - HAIR)))
    assert inside["force_n"] is not None and below["force_n"] is None
    assert below["torque_nm"] == pytest.approx(5.0)


# --- spindle speed ------------------------------------------------------------------------------------
def test_a_speed_over_the_gear_table_gets_no_depth(tmp_path):
    pair = _physics(tmp_path)
    top = validity.max_spindle_rpm(4500.0)
    for rpm, has in ((top * (1 - HAIR), True), (top * (1 + HAIR), False)):
        e = _both(pair, _rev(3.0, rpm=rpm, feed_mm_min=0.1 * FLUTES * rpm, gear=HIGH_GEAR))
        assert _has_depth(e) is has, e
        assert e["cutting"] and e["torque_nm"] == pytest.approx(3.0)
        if not has:
            assert e["depth_status"] == validity.SPEED_OUT_OF_RANGE


# --- geometry -----------------------------------------------------------------------------------------
@pytest.mark.parametrize("tool, flute_mm", [(None, 2.0 * 20.0), (6, 9.0)])
def test_an_axial_depth_past_the_flute_length_is_not_published(tmp_path, tool, flute_mm):
    """[tool] without flute_length_mm: twice its diameter; [tools.6] gives its own."""
    pair = _physics(tmp_path, extra_toml=SMALL_TOOL)
    probe = _both(pair, _rev(1.0), tool)          # a slot: the axial depth is linear in the torque (eq. 13 of [D])
    per_nm = probe["axial_depth_mm"] / 1.0
    inside = _both(pair, _rev(flute_mm / per_nm * (1 - HAIR)), tool)
    outside = _both(pair, _rev(flute_mm / per_nm * (1 + HAIR)), tool)
    assert _has_depth(inside) and inside["axial_depth_mm"] <= flute_mm
    assert outside["depth_status"] == validity.OUTSIDE_TOOL
    assert outside["axial_depth_mm"] is None and outside["radial_depth_mm"] is None
    assert outside["cutting"] and outside["force_n"] is not None   # the cut is real; its depth is not this


def test_a_radial_depth_wider_than_the_tool_is_not_published():
    """The solvers never return R_r > 2; the check is a guard on what reaches the payload."""
    assert validity.within_tool(20.0, 40.0, 20.0, 40.0)
    assert not validity.within_tool(20.0 * (1 + HAIR), 1.0, 20.0, 40.0)
    assert not validity.within_tool(1.0, 40.0 * (1 + HAIR), 20.0, 40.0)
    assert validity.within_tool(None, None, 20.0, 40.0)


# --- run-up and braking: no cut claimed -----------------------------------------------------------------
def test_a_speed_rise_over_one_percent_is_a_run_up_not_a_cut(tmp_path):
    """No inertia known: the speed rule alone (1 % of 600 rpm = 6 rpm within the revolution)."""
    pair = _physics(tmp_path)
    edge = validity.RAMP_RISE_FRAC * 600.0
    steady = _both(pair, _rev(5.0, rise_rpm=edge * (1 - HAIR)))
    ramp = _both(pair, _rev(5.0, rise_rpm=edge * (1 + HAIR)))
    assert steady["cutting"] and _has_depth(steady)
    assert not ramp["cutting"] and ramp["depth_status"] == validity.SPEED_CHANGING
    assert ramp["axial_depth_mm"] is None
    # torque and force stay: they are what the alarms judge as load
    assert ramp["torque_nm"] == pytest.approx(5.0) and ramp["force_n"] == pytest.approx(steady["force_n"])


def test_a_drive_catching_up_with_a_spindle_its_load_slowed_still_cuts(tmp_path):
    """The same rise while the mean speed fell against the revolution before (a crash, a stall)."""
    pair = _physics(tmp_path)
    rise = 2 * validity.RAMP_RISE_FRAC * 600.0
    slowed = 600.0 * (1 + validity.RAMP_SLOWING_FRAC) * (1 + HAIR)    # the revolution before was faster
    barely = 600.0 * (1 + validity.RAMP_SLOWING_FRAC) * (1 - HAIR)
    assert _both(pair, _rev(5.0, rise_rpm=rise, prev_rpm=slowed))["cutting"]
    assert not _both(pair, _rev(5.0, rise_rpm=rise, prev_rpm=barely))["cutting"]


def _inertia_nm(pair, rise_rpm: float) -> float:
    """T_J of a revolution at 600 rpm with this rise (from its published p_inertia_w = T_J·ω)."""
    e = _both(pair, _rev(5.0, rise_rpm=rise_rpm))
    return e["p_inertia_w"] / (2 * math.pi * 600.0 / 60.0)


def test_when_the_masses_take_more_than_the_cut_it_is_a_run_up(tmp_path):
    """J known: a rise under 1 % (4 rpm at 600 rpm) but over the steady gate; T_J against T_c."""
    pair = _physics(tmp_path, gears=configs.GEARS_WITH_INERTIA)
    t_j = _inertia_nm(pair, 4.0)
    assert t_j > 1.0
    cut = _both(pair, _rev(t_j * (1 + HAIR), rise_rpm=4.0, inertia_nm=t_j))
    run_up = _both(pair, _rev(t_j * (1 - HAIR), rise_rpm=4.0, inertia_nm=t_j))
    assert cut["cutting"] and _has_depth(cut)
    assert not run_up["cutting"] and run_up["depth_status"] == validity.SPEED_CHANGING


def test_a_spindle_braking_or_coasting_is_not_cutting(tmp_path):
    """J known, the speed falling 4 rpm: the masses give T_J < 0. With no air-gap power from the drive
    (P_g ≤ 0) what is left of eq. (13) is no cut; a drive still motoring (P_g > 0) keeps it."""
    pair = _physics(tmp_path, gears=configs.GEARS_WITH_INERTIA)
    t_j = _inertia_nm(pair, -4.0)
    omega = 2 * math.pi * 600.0 / 60.0
    # P_g = 0 exactly: T_c = −T_f' − B'ω − T_J, above the cutting threshold here
    zero = -(LOW_GEAR[0] + LOW_GEAR[1] * omega + t_j)
    assert zero > 0.5 + 0.1
    motoring = _both(pair, _rev(zero + 1e-6, rise_rpm=-4.0, inertia_nm=t_j))
    braking = _both(pair, _rev(zero - 1e-6, rise_rpm=-4.0, inertia_nm=t_j))
    assert motoring["p_gap_w"] > 0 and motoring["cutting"]
    assert braking["p_gap_w"] < 0 and not braking["cutting"] and braking["depth_status"] == validity.SPEED_CHANGING


def test_depth_method_off_still_judges_cutting(tmp_path):
    pair = _physics(tmp_path, method="off")
    e = _both(pair, _rev(5.0, rise_rpm=2 * validity.RAMP_RISE_FRAC * 600.0))
    assert not e["cutting"] and e["depth_status"] is None
