"""The published force against the plant's where several teeth cut at once (issue 41).

[P] eq. (17) sizes one tooth's force, √(1 + r₁²)·F_T. With 3–4 flutes in a slot, or a wide
immersion, the engaged teeth's forces point different ways and their vector sum is smaller:
the plant (sim/cutting.py) adds every edge element's (F_x, F_y) and writes the revolution mean
of |(F_x, F_y)| to its truth. The daemon's C_f (``cf = "model"``, and the default ``"auto"``)
is η·√(1 + r₁(t_a)²) with η of physics/resultant.py, from the mode, the radial depth, the
helix and the axial depth (estimated, else configured), each tooth's force at its instantaneous
chip (Kienzle's law, R1a). The slot and up-milling plants here take that law and nothing else
(``LOCAL_LAW``); [D]'s Fig. 5 keeps [D]'s own plant (K_s, r₁ at the average chip), where the two
laws differ by well under the torque's budget (down milling, 1-8 mm of 16).

Bounds, from the physics, never from a measured error:

* the torque: docs/accuracy.md's 2 % + 0.03 N·m, carried through C_f/R;
* η's table: bilinear interpolation and 6-point Gauss pieces, within ETA_TABLE_REL of a fine
  quadrature (tests/physics/test_resultant.py holds that);
* the helix lag ψ comes from the estimated axial depth, as off as the torque; its effect on η is
  not given an allowance of its own (η moves slowly with ψ: C_f alone stays within 0.1 % of the
  plant's in these cases, bench/force_accuracy.py), so a wrong ψ would show here.

Cases: the [P] step cut at 1200 rpm (SS41, 300 mm/min, 1/2/3 mm steps) with the [D] φ16
4-flute and a φ8 3-flute end mill instead of [P]'s 2-flute one (η = π/4 and 0.83–0.85, where
√(1 + r₁²) alone is 20–27 % high); [D]'s Fig. 5 (4-flute down milling, radial depth 1 → 8 mm
estimated from the feed drive, d_a 16 mm: η 0.94–1); [D]'s Fig. 6 as up milling at a radial depth
of 12 mm, configured (600 rpm, the low gear; d_a 6/11/16 mm estimated from the torque: η 0.88–0.91).
"""

from __future__ import annotations

import math
from dataclasses import replace

import pytest

from millsense.sim.cut_effects import NONE

from . import configs, simcase

# the plant with Kienzle's law at each instantaneous chip and nothing else (no edge forces, runout or
# deflection; the clamp h_min below every chip cut): the law η models (resultant.py R1a). The full plant of
# the first-part programs: tests/estimator/test_force_first_part.py.
LOCAL_LAW = replace(NONE, size_effect=True, min_chip_mm=1e-6)
TORQUE_REL = 0.02     # docs/accuracy.md: steady torque within 2 % + 0.03 N·m
TORQUE_ABS_NM = 0.03
ETA_TABLE_REL = 0.001  # physics/resultant.py's table against a fine quadrature (test_resultant.py)


def _slot_with(tool_name: str):
    from millsense.sim.machine import TOOL_D, TOOL_F
    from millsense.sim.scenarios import SCENARIOS

    tool = {"D": TOOL_D, "F": TOOL_F}[tool_name]
    base = SCENARIOS["step-1200"]
    return replace(base, name=f"step-1200-{tool_name}-local", tool=tool, effects=LOCAL_LAW)


@pytest.fixture(scope="module")
def tmp(tmp_path_factory):
    return tmp_path_factory.mktemp("force-vector")


def _capture(tmp, scenario, seed):
    from millsense.sim import write_capture
    from tests import captures

    def build(d):
        write_capture(scenario, str(d / "capture.bin"), str(d / "truth.jsonl"), seed=seed)

    d = captures.shared(f"force-vector {scenario.name} s{seed}", build)
    return d / "capture.bin", d / "truth.jsonl"


def _settings(tmp, scenario, cf):
    m = scenario.material
    return configs.load(
        tmp, name=f"{scenario.name}-{cf}.toml", tool=(scenario.tool.diameter_mm, scenario.tool.flutes,
                                                      scenario.tool.helix_deg),
        material=(m.ks, m.ks_exp, m.r1, m.r1_exp, m.r2, m.r2_exp), mode=scenario.mode, cf=cf,
        feed_mm_min=scenario.feed_segments[0][1], method="auto")


def _bound_n(e, t, radius_mm):
    """|F_est − F_true| allowed: the torque's budget through C_f/R, plus η's table error."""
    cf_est = e["force_n"] / e["force_tangential_n"]
    torque_bound_nm = TORQUE_REL * abs(t["torque_nm"]) + TORQUE_ABS_NM
    return cf_est * torque_bound_nm / (radius_mm * 1e-3) + ETA_TABLE_REL * t["force_n"]


@pytest.mark.parametrize("cf", ["model", "auto"])
@pytest.mark.parametrize("tool_name", ["D", "F"])
def test_slot_with_several_teeth_in_cut_matches_the_plants_resultant(tmp, tool_name, cf):
    """3- and 4-flute slots at 1200 rpm: each steady revolution's |F| within the torque's budget."""
    scenario = _slot_with(tool_name)
    cap, truth_path = _capture(tmp, scenario, seed=11)
    est, _ = simcase.run(cap, _settings(tmp, scenario, cf))
    truth = simcase.read_truth(truth_path)
    pairs = [(e, t) for e, t in simcase.match(est, truth, 1) if t["steady"] and t["cutting"] and e["valid"]]
    assert len(pairs) >= 60, len(pairs)
    depths = {round(t["axial_depth_mm"], 3) for _, t in pairs}
    assert depths == {1.0, 2.0, 3.0}, depths
    for e, t in pairs:
        assert e["force_n"] is not None, e
        assert abs(e["force_n"] - t["force_n"]) <= _bound_n(e, t, scenario.tool.radius_mm), (
            e["force_n"], t["force_n"], t["axial_depth_mm"])


def test_fig5_wide_immersion_with_the_radial_depth_estimated(tmp):
    """[D] Fig. 5 (4 flutes, down milling, d_r 1 → 8 mm from the feed drive): |F| of each settled
    revolution whose depth was estimated, within the torque's budget."""
    cap, truth_path = simcase.capture(tmp, "fig5", seed=11)
    settings = simcase.settings_for("fig5", tmp, method="feed-drive", cf="model",
                                    ix_offset_counts=simcase.zero_feed_current(cap, "fig5", tmp),
                                    tool=(16.0, 4, 30.0))
    est, _ = simcase.run(cap, settings)
    truth = simcase.read_truth(truth_path)
    settled = simcase.settled(truth, "fig5")
    pairs = [(e, t) for e, t in simcase.match(est, truth) if t["rev"] in settled and e["depth_status"] == "ok"]
    assert len(pairs) >= 100, len(pairs)
    assert max(t["radial_depth_mm"] for _, t in pairs) > 7.0       # reaches the wide immersions
    for e, t in pairs:
        assert abs(e["force_n"] - t["force_n"]) <= _bound_n(e, t, 8.0), (
            e["force_n"], t["force_n"], t["radial_depth_mm"])


def test_up_milling_with_the_radial_depth_configured(tmp):
    """[D] Fig. 6's cut as up milling, R_r = 1.5 (three teeth's arcs overlap), the radial depth given in
    `[cut]` and the axial depth estimated from the torque: each steady revolution within the budget."""
    from millsense.sim.scenarios import SCENARIOS

    scenario = replace(SCENARIOS["fig6"], name="fig6-up-12-local", mode="up", radial_profile=((0.0, 12.0), (150.0, 12.0)),
                       extra_channels=(), effects=LOCAL_LAW)
    cap, truth_path = _capture(tmp, scenario, seed=11)
    m = scenario.material
    settings = configs.load(tmp, name="fig6-up-12.toml", tool=(16.0, 4, 30.0),
                            material=(m.ks, m.ks_exp, m.r1, m.r1_exp, m.r2, m.r2_exp), mode="up", cf="auto",
                            feed_mm_min=scenario.feed_segments[0][1], method="torque-only", radial_depth_mm=12.0)
    est, _ = simcase.run(cap, settings)
    truth = simcase.read_truth(truth_path)
    pairs = [(e, t) for e, t in simcase.match(est, truth, 1) if t["steady"] and t["cutting"] and e["valid"]
             and e["depth_status"] == "ok"]
    assert len(pairs) >= 100, len(pairs)
    assert {round(t["axial_depth_mm"]) for _, t in pairs} == {6, 11, 16}
    for e, t in pairs:
        assert abs(e["force_n"] - t["force_n"]) <= _bound_n(e, t, 8.0), (e["force_n"], t["force_n"], t["axial_depth_mm"])
