"""The plant under the CNC's feed override (issue 15): the programmed feed times the override, a feed
hold winning over any override, a part program's cycle shortened by an override above 100 %,
adaptive feed allowed per operation, and the AFC scenarios."""

from __future__ import annotations

import numpy as np
import pytest

from millsense.drivers.protocol import CTX_AFC_ALLOWED, CTX_MONITOR
from millsense.sim import SCENARIOS, Plant
from millsense.sim.program import PROGRAMS
from millsense.sim.program_plant import ProgramPlant

pytestmark = pytest.mark.quick


def _settled(revs, pct):
    """Revolutions at ``pct`` throughout, the one before too, no hold: the feed has settled."""
    return [r for prev, r in zip(revs, revs[1:], strict=False)
            if all(x["feed_override_pct"] == pct and not x["feed_hold"] for x in (prev, r))]


@pytest.mark.parametrize("pct", [60.0, 135.0])
def test_the_feed_is_the_programmed_one_times_the_override(pct):
    plant = Plant("afc-step", seed=0, noise_scale=0)
    plant.feed_override_pct = pct
    plant.step(4000)
    feed = plant.scenario.feed_segments[0][1]
    settled = _settled(plant.truth.revolutions(), pct)
    assert len(settled) > 20
    assert all(r["feed_mm_min"] == pytest.approx(feed * pct / 100.0, rel=1e-6) for r in settled)
    # and the chip with it: the feed per tooth of the machine's feed (t_c = feed / (N n))
    cutting = [r for r in settled if r["cutting"]]
    assert cutting
    flutes = plant.geometry.tool.flutes
    for r in cutting:
        assert r["feed_per_tooth_mm"] == pytest.approx(r["feed_mm_min"] / (flutes * r["spindle_rpm"]), rel=2e-3)


def test_a_feed_hold_wins_over_150_percent():
    plant = Plant("afc-step", seed=0, noise_scale=0)
    plant.feed_override_pct = 150.0
    plant.step(2000)
    plant.feed_hold = True
    plant.step(1500)
    after = [r for r in plant.truth.revolutions() if r["index_end"] > 2500]
    assert after and all(r["feed_mm_min"] == 0.0 and r["feed_override_pct"] == 150.0 for r in after)


def test_a_per_sample_override_must_fit_the_step():
    plant = Plant("afc-step", seed=0, noise_scale=0)
    plant.feed_override_pct = np.full(10, 120.0)
    with pytest.raises(ValueError, match="10 values for a step of 20"):
        plant.step(20)
    plant.feed_override_pct = np.linspace(100.0, 120.0, 20)
    assert plant.step(20).shape == (20, len(plant.descriptor.channels))


def _process_samples(pct: float) -> dict[int, int]:
    plant = ProgramPlant(parts=1, seed=0, noise_scale=0)
    plant.feed_override_pct = pct
    plant.step(round(plant.scenario.duration_s * 1000))
    return {p["operation"]: p["last_index"] - p["first_index"] + 1 for p in plant.processes()}


def test_a_part_programs_cycle_is_shorter_above_100_percent():
    base, fast = _process_samples(100.0), _process_samples(125.0)
    prog = PROGRAMS["part-program"]
    assert set(base) == set(fast) == {op.number for op in prog.operations}
    for op in prog.operations:
        start, end = prog.feed_travel_mm(op)
        feed_s = (end - start) / (op.feed_mm_min / 60.0)  # the feed phase at the programmed feed
        saved = (base[op.number] - fast[op.number]) / 1000.0
        # program time runs by position: the feed phase takes 1/1.25 of its time (the servo's few-ms
        # accelerations aside), the retract its own
        assert saved == pytest.approx(feed_s * (1 - 1 / 1.25), abs=0.01), op.number


def test_adaptive_feed_is_allowed_per_operation_and_never_in_the_finishing_one():
    prog = PROGRAMS["part-program"]
    assert any(op.afc_allowed for op in prog.operations) and not all(op.afc_allowed for op in prog.operations)
    plant = ProgramPlant(parts=1, seed=0, noise_scale=0)
    plant.step(round(plant.scenario.duration_s * 1000))
    cuts = {ctx[2]: ctx[3] for _, ctx in plant.drain_context() if ctx[3] & CTX_MONITOR}
    assert cuts == {op.number: cuts[op.number] for op in prog.operations}
    for op in prog.operations:
        assert bool(cuts[op.number] & CTX_AFC_ALLOWED) == op.afc_allowed, op.number


@pytest.mark.parametrize("name, rpm", [("afc-step-300", 300), ("afc-step", 600), ("afc-step-1500", 1500),
                                       ("afc-step-3000", 3000)])
def test_the_afc_step_scenarios(name, rpm):
    sc = SCENARIOS[name]
    assert sc.spindle_schedule == ((0.0, rpm),) and sc.mode == "slot"
    _ = sc.gear  # one gear: else ValueError
    depths = [d for _, d in sc.axial_profile]
    assert depths[::2] == [2.0, 3.0, 2.5]
    edges = [x for x, _ in sc.axial_profile]
    assert edges[1] - edges[0] == pytest.approx(25.0) and edges[-1] == pytest.approx(75.0)
    taper = SCENARIOS["afc-taper"]
    assert [d for _, d in taper.axial_profile] == [1.0, 3.0] and taper.axial_profile[-1][0] == 75.0
