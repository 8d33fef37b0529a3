"""The expected band's entry: the path to a steady revolution counts from where the cutter touched, not from the
first revolution over `[depth] min_torque_nm`.

A cut shallower than programmed stays under the "cutting" threshold for its first revolutions in the part; counted
from the first revolution called cutting, the band was judged a revolution or two after the plant's first steady
one, and a half-depth slot tripped `expected_low` on the fourth steady revolution instead of the third (found live:
tests/e2e/test_first_part_acceptance.py, docs/validation.md). Revolutions rising out of the air's noise just before
the first cutting one are the entry too. Air that does not rise into the cut credits nothing.
"""

from __future__ import annotations

import pytest

from tests.learning.test_expected import FIRST_JUDGED, Cell, first_event_rev

pytestmark = pytest.mark.quick

SIGMA_NM = 0.01   # the revolution's own torque scatter (eq. 20), as a live estimate carries it


def _cell_with(air_torques: list[float], factor: float, touching: int) -> Cell:
    """A cell fed: air at `air_torques` (not cutting), then the cut entering over a tool radius of path, its
    first `touching` revolutions under the cutting threshold (not cutting, torque rising), then steady."""
    cell = Cell(noise_pct=0.0)
    cut = cell.cut(factor)
    exp = cell.expected()
    for t in air_torques:
        est = cell.est(0.0, cutting=False)
        est.update(torque_nm=t, torque_sigma_nm=SIGMA_NM)
        cell.feed(est)
    for i, f in enumerate(cut):
        est = cell.est(f)
        est["torque_sigma_nm"] = SIGMA_NM
        if i < touching:
            est["cutting"] = False
            est["force_n"] = None
        cell.feed(est)
    return cell


def test_a_shallow_cut_entering_under_the_threshold_trips_on_the_third_steady_revolution():
    touching = 2
    cell = _cell_with([0.0] * 5, 0.5, touching)
    need = cell.cfg.learning.low_revolutions
    # counted from the cutter's first touch (the first revolution of cell.cut), as for a cut seen at once
    first_touch = next(e["rev"] for e in cell.estimates if e["torque_nm"] > 3 * SIGMA_NM)
    low = cell.events("expected_low")[0]
    assert low.rev - first_touch == FIRST_JUDGED + need - 1


def test_flat_air_before_the_cut_credits_nothing():
    """Air whose torque sits above its noise (a friction calibrated a little off) but does not rise into the cut
    is not the entry: the band is judged a tool radius past the first cutting revolution, as before."""
    cell = _cell_with([0.2, 0.2, 0.2, 0.2, 0.2], 0.5, 0)
    need = cell.cfg.learning.low_revolutions
    assert first_event_rev(cell, "expected_low") == FIRST_JUDGED + need - 1


# A light cut: its whole load under `[depth] min_torque_nm`, so the estimator never calls it cutting. The expected
# band takes it in cut from its own expected torque (learning/expected.py `_in_cut`): found live, a half-depth
# φ8 slot took 0.499 N·m, under the 0.5 N·m threshold, and a half-depth first part passed unseen
# (docs/validation.md, "The expected load of a first part, live").

def _light_cell(air_torques: list[float], factor: float) -> Cell:
    """Air, then a cut at `factor` of the expected load entering over a tool radius of path, none of it called
    cutting (every revolution under the estimator's threshold), then air again."""
    cell = _cell_with(air_torques, factor, touching=10**6)
    for _ in range(5):
        est = cell.est(0.0, cutting=False)
        est.update(torque_nm=air_torques[-1] if air_torques else 0.0, torque_sigma_nm=SIGMA_NM)
        cell.feed(est)
    return cell


def test_a_half_depth_cut_under_the_cutting_threshold_trips_on_the_third_steady_revolution():
    cell = _light_cell([0.0] * 5, 0.5)
    assert not any(e["cutting"] for e in cell.estimates)
    need = cell.cfg.learning.low_revolutions
    first_touch = next(e["rev"] for e in cell.estimates if e["torque_nm"] > 3 * SIGMA_NM)
    low = cell.events("expected_low")[0]
    assert low.hold and low.quantity == "torque_nm"
    assert low.rev - first_touch == FIRST_JUDGED + need - 1


def test_a_correct_light_cut_is_judged_and_raises_nothing():
    cell = _light_cell([0.0] * 5, 1.0)
    assert cell.events() == []
    assert cell.band.summary(cell.monitor.proc)["expected_band"] == "armed"


def test_air_above_the_cutting_fraction_but_flat_is_air():
    """A process that never cuts, its air read at 0.3 of the cut's expected torque (a friction calibrated off,
    more than IN_CUT_OF_EXPECTED of the load): the air's own level, not a cut missing its stock."""
    level = 0.3 * Cell().expected().torque_nm
    cell = Cell(noise_pct=0.0)
    for _ in range(40):
        est = cell.est(0.0, cutting=False)
        est.update(torque_nm=level, torque_sigma_nm=SIGMA_NM)
        cell.feed(est)
    assert cell.events() == []
    assert cell.band.summary(cell.monitor.proc)["expected_band"] == "not_steady"


def test_air_settling_up_from_below_zero_after_a_run_up_is_air():
    """After a spindle run-up the air's torque reads below 0 and settles back over tens of revolutions (found live:
    −0.7 N·m decaying to 0). Measured from that, the settling rose by more than a light cut's threshold: it is air,
    not a cut whose stock is missing."""
    exp = Cell().expected().torque_nm
    cell = Cell(noise_pct=0.0)
    for i in range(60):
        est = cell.est(0.0, cutting=False)
        est.update(torque_nm=-0.4 * exp * max(0.0, 1.0 - i / 10.0), torque_sigma_nm=SIGMA_NM)
        cell.feed(est)
    assert cell.events() == []
    assert cell.band.summary(cell.monitor.proc)["expected_band"] == "not_steady"
