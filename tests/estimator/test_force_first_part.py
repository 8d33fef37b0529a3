"""The force estimate within 2 % on the first-part programs' plant (issue 41), 3- and 4-flute slots first.

The plant of the first-part programs (sim/cut_effects.py: Kienzle's law at the instantaneous chip, edge
forces, 5 µm runout, deflection) cuts a few operations of each program; per steady revolution in cut the
daemon's C_f (``force.engaged_cf``, resultant.py R2: the engaged teeth's forces added as vectors, each
tooth's force at its instantaneous chip) at the operation's programmed cut and the revolution's feed per
tooth, times the true torque over R ([P] eq. 18), against the plant's true mean resultant; and the forward
model's force (``expected_load``, the same C_f) against the plant's C_f. Before η took the size effect,
the 3- and 4-flute slots were 7–13 % high (bench/force_accuracy.py).

2 % is the issue's figure, not a measured error. The φ8 3-flute slots at 0.04–0.05 mm a tooth (4101/3/70,
/80) are 2.1–2.2 % high on the full plant with the law alone, from the edge forces: they are held to 2 % with
the material's edge coefficients (physics/edge.py; docs/accuracy.md).

From the estimate: [P]'s step cut at 1200 rpm (1/2/3 mm) with the φ16 4-flute and the φ8 3-flute end mill,
on the plant with every effect: each steady revolution's |F| within 2 % plus the torque's own budget
(docs/accuracy.md: 2 % + 0.03 N·m) carried through C_f/R.
"""

from __future__ import annotations

from dataclasses import replace

import pytest

from millsense.daemon.physics.expected import ProgrammedCut, expected_load
from millsense.daemon.physics.force import P_MEAN_CF, engaged_cf
from millsense.daemon.physics.materials import STEEL_EDGE_N_MM
from millsense.daemon.physics.milling import Material
from millsense.sim.cut_effects import CutEffects
from millsense.sim.first_part import FIRST_PART_PROGRAMS, programmed_cut
from millsense.sim.program_plant import ProgramPlant

from . import configs, simcase

FORCE_REL = 0.02       # the "force estimate within 2 %"
TORQUE_REL = 0.02      # docs/accuracy.md: steady torque within 2 % + 0.03 N·m
TORQUE_ABS_NM = 0.03


def _revolutions(program):
    """(operation, its programmed cut, its steady revolutions in cut) for each operation of ``program``."""
    plant = ProgramPlant(program, noise_scale=0.0)
    while not plant.done:
        plant.step(1000)
    revs = [r for r in plant.truth.revolutions() if r["steady"] and r["cutting"]]
    out = []
    for proc in plant.processes():
        op = next(o for o in program.operations if o.number == proc["operation"])
        mine = [r for r in revs if proc["first_index"] <= r["index_end"] <= proc["last_index"]]
        out.append((op, programmed_cut(program, op), mine))
    return out


def _check(program, edge_n_mm: tuple[float, float] = (0.0, 0.0)) -> int:
    m = program.material
    material = Material(m.ks, m.ks_exp, m.r1, m.r1_exp, m.r2, m.r2_exp, *edge_n_mm)
    checked = 0
    for op, cut, revs in _revolutions(program):
        tool = op.tool
        assert len(revs) >= 10, (op.number, len(revs))
        programmed = ProgrammedCut(cut["ae_mm"], cut["ap_mm"], cut["mode"], cut.get("fz_mm"), cut.get("vf_mm_min"))
        for r in revs:
            cf = engaged_cf(cut["mode"], tool.flutes, tool.radius_mm, tool.helix_deg, float(r["feed_per_tooth_mm"]),
                            cut["ae_mm"], cut["ap_mm"], material, P_MEAN_CF)
            force_n = cf * r["torque_nm"] / (tool.radius_mm * 1e-3)                         # [P] eq. 18
            assert force_n == pytest.approx(r["force_n"], rel=FORCE_REL), (op.number, force_n, r["force_n"])
            load = expected_load(programmed, tool_radius_mm=tool.radius_mm, flutes=tool.flutes, material=material,
                                 spindle_rpm=r["spindle_rpm"], override_pct=r["feed_override_pct"],
                                 helix_deg=tool.helix_deg)
            expected_cf = load.force_n / (load.torque_nm / (tool.radius_mm * 1e-3))
            true_cf = r["force_n"] / (r["torque_nm"] / (tool.radius_mm * 1e-3))
            assert expected_cf == pytest.approx(true_cf, rel=FORCE_REL), (op.number, expected_cf, true_cf)
            checked += 1
    return checked


def test_three_and_four_flute_slots_of_the_first_part_within_two_percent():
    """first-part-slot's 4-flute (φ16) and 3-flute (φ12) slots, and a 2-flute one, on the full plant."""
    assert _check(FIRST_PART_PROGRAMS["first-part-slot"].only(10, 40, 50, 60, 90, 100)) >= 60


def test_the_thin_chip_three_flute_slots_within_two_percent_with_the_material_s_edge_coefficients():
    """4101/3/70 and /80 (φ8 3-flute, 0.04 and 0.05 mm a tooth) on the plant with every effect: 2.1-2.2 % high
    with the law alone (its edge forces taken for chip); within 2 % with the material's edge coefficients of the
    round steel pair (unverified: physics.md §5b; not the plant's own: docs/accuracy.md)."""
    assert _check(FIRST_PART_PROGRAMS["first-part-slot"].only(70, 80), STEEL_EDGE_N_MM) >= 20


def test_up_and_down_cuts_that_held_before_still_hold():
    """The cases within 2 % before η took the size effect stay so (3- and 4-flute up and down milling)."""
    assert _check(FIRST_PART_PROGRAMS["first-part-up"].only(60, 80)) >= 20
    assert _check(FIRST_PART_PROGRAMS["first-part-down"].only(90)) >= 10


@pytest.fixture(scope="module")
def tmp(tmp_path_factory):
    return tmp_path_factory.mktemp("force-first-part")


def _capture(scenario, seed):
    from millsense.sim import write_capture
    from tests import captures

    def build(d):
        write_capture(scenario, str(d / "capture.bin"), str(d / "truth.jsonl"), seed=seed)

    d = captures.shared(f"force-first-part {scenario.name} s{seed}", build)
    return d / "capture.bin", d / "truth.jsonl"


@pytest.mark.parametrize("tool_name", ["D", "F"])
def test_the_estimate_in_three_and_four_flute_slots_on_the_full_plant(tmp, tool_name):
    from millsense.sim.machine import TOOL_D, TOOL_F
    from millsense.sim.scenarios import SCENARIOS

    tool = {"D": TOOL_D, "F": TOOL_F}[tool_name]
    scenario = replace(SCENARIOS["step-1200"], name=f"step-1200-{tool_name}-effects", tool=tool, effects=CutEffects())
    cap, truth_path = _capture(scenario, seed=11)
    m = scenario.material
    settings = configs.load(tmp, name=f"{scenario.name}.toml", tool=(tool.diameter_mm, tool.flutes, tool.helix_deg),
                            material=(m.ks, m.ks_exp, m.r1, m.r1_exp, m.r2, m.r2_exp), mode=scenario.mode, cf="auto",
                            feed_mm_min=scenario.feed_segments[0][1], method="auto")
    est, _ = simcase.run(cap, settings)
    truth = simcase.read_truth(truth_path)
    pairs = [(e, t) for e, t in simcase.match(est, truth, 1) if t["steady"] and t["cutting"] and e["valid"]]
    assert len(pairs) >= 60, len(pairs)
    assert {round(t["axial_depth_mm"], 3) for _, t in pairs} == {1.0, 2.0, 3.0}
    for e, t in pairs:
        assert e["force_n"] is not None, e
        cf_est = e["force_n"] / e["force_tangential_n"]
        torque_bound_n = cf_est * (TORQUE_REL * abs(t["torque_nm"]) + TORQUE_ABS_NM) / (tool.radius_mm * 1e-3)
        assert abs(e["force_n"] - t["force_n"]) <= FORCE_REL * t["force_n"] + torque_bound_n, (
            e["force_n"], t["force_n"], t["axial_depth_mm"])
