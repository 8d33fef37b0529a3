"""Every scenario runs to its end and its truth makes physical sense."""

from __future__ import annotations

import math

import numpy as np
import pytest

from millsense.sim import SCENARIOS, Plant, list_scenarios, machine_config
from millsense.sim.scenarios import _travel_s

from .helpers import steady_cut_revs


def _closed_form_torque_nm(sc, tc, d_a, d_r):
    """Mean cutting torque of a steady cut, [D] eqs. (7)-(9) written out: R·K_s·t_c·d_a·R_r·N/(2π)."""
    r = sc.tool.radius_mm
    rr = d_r / r
    if sc.mode == "slot":
        ta = 2 * tc / math.pi
    else:  # down milling: t_a = t_c·R_r/(π − φ_r)
        ta = tc * rr / (math.pi - math.acos(rr - 1))
    ks = sc.material.ks * ta**sc.material.ks_exp
    return ks * tc * d_a * rr * sc.tool.flutes / (2 * math.pi) * r / 1000


def test_catalogue():
    names = list_scenarios()
    for required in ("step", "taper", "step-1200", "taper-1800", "diagonal-step", "diagonal-taper", "breakage",
                     "crash", "fig5", "fig6", "fig7", "aircut-low", "aircut-high"):
        assert required in names
    for sc in SCENARIOS.values():
        assert sc.description and 5 <= sc.duration_s <= 60
    assert {SCENARIOS[n].gear.name for n in names} == {"low-speed", "high-speed"}
    cfg = machine_config("fig6")
    assert cfg["motor"] == {"winding": "delta", "stator_resistance_ohm": 0.349, "pole_pairs": 2}
    assert [g["name"] for g in cfg["gears"]] == ["low-speed", "high-speed"]
    assert cfg["tool"] == {"diameter_mm": 16.0, "flutes": 4}
    assert cfg["cut"]["mode"] == "down" and cfg["cut"]["radial_depth_mm"] == 2.0
    assert cfg["feed_force"]["ix_feed"] == {"newton_per_amp": 950.0, "friction_n": 120.0}


RAMPS = ("taper", "taper-1200", "taper-1800", "diagonal-taper", "fig5", "fig7", "afc-taper")


def _inside_ramp(sc, revs):
    """Revolutions with the whole engagement inside the part, away from feed changes (±0.2 s)."""
    start, r = sc.start_mm, sc.tool.radius_mm
    part_end = sc.axial_profile[-1][0]
    t_in = _travel_s(start, 0.5, sc.feed_segments) + 0.2
    t_out = _travel_s(start, part_end - r - 0.5, sc.feed_segments)
    changes = [_travel_s(start, x, sc.feed_segments) for x, _ in sc.feed_segments[1:]]
    return [x for x in revs if x["cutting"] and t_in < x["t_end_s"] - 60 / x["spindle_rpm"] and x["t_end_s"] < t_out
            and all(abs(x["t_end_s"] - c) > 0.2 for c in changes)]


@pytest.mark.parametrize("name", list(SCENARIOS))
def test_scenario_runs_with_sensible_truth(name):
    sc = SCENARIOS[name]
    plant = Plant(name)
    counts = plant.step(round(sc.duration_s * 1000))
    assert plant.done and counts.shape == (round(sc.duration_s * 1000), plant.descriptor.channel_count)
    revs = plant.truth.revolutions()
    cmd = [rpm for _, rpm in sc.spindle_schedule]
    expected_revs = sum(rpm / 60 * (t1 - t0) for (t0, rpm), t1 in
                        zip(sc.spindle_schedule, [t for t, _ in sc.spindle_schedule[1:]] + [sc.duration_s]))
    assert len(revs) == pytest.approx(expected_revs, rel=0.02)
    assert all(r["gear"] == sc.gear.name for r in revs)
    for r in revs:
        if r["steady"]:
            assert min(abs(r["spindle_rpm"] - c) for c in cmd) < 0.01 * max(cmd)
        assert r["torque_nm"] >= 0 and r["force_n"] >= 0
        assert r["torque_nm"] > 0 if r["cutting"] else r["torque_nm"] < 1e-4
    steady = steady_cut_revs(revs)
    if name.startswith("aircut"):
        assert not any(r["cutting"] for r in revs)
        assert sum(r["steady"] for r in revs) > 0.8 * len(revs)
        return
    if name == "crash":
        assert steady
        return
    ramp = name in RAMPS
    assert ramp or steady, "a cut with no steady revolution"
    broken_at = plant.truth.events()[0]["t_s"] if sc.breakage else math.inf
    checked = steady if not ramp else _inside_ramp(sc, revs)
    assert len(checked) > 20
    for r in checked:
        if r["t_end_s"] > broken_at:
            continue
        d_a = r["axial_depth_mm"]
        if ramp and sc.mode == "slot":
            # taper of slope k under a slot: the cutting edge at x = s + R·sin φ sees d_a + R·k·sin φ,
            # chip-weighted by sin φ over [0, π]: mean depth d_a + π·R·k/4
            (x0, d0), (x1, d1) = sc.axial_profile
            d_a += math.pi * sc.tool.radius_mm * (d1 - d0) / (x1 - x0) / 4
        expect = _closed_form_torque_nm(sc, r["feed_per_tooth_mm"], d_a, r["radial_depth_mm"])
        assert r["torque_nm"] == pytest.approx(expect, rel=5e-3), r
        nominal_tc = sc.feed_segments[0][1] / (sc.tool.flutes * cmd[0])
        if len(sc.feed_segments) == 1:
            assert r["feed_per_tooth_mm"] == pytest.approx(nominal_tc, rel=2e-3)
    assert np.isfinite([r["airgap_power_w"] for r in revs]).all()
