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

from tests.learning.test_expected import ENTRY_REVS, Cell, first_event_rev

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
    assert low.rev - first_touch == ENTRY_REVS + need - 1


def test_flat_air_before_the_cut_credits_nothing():
    """Air whose torque sits above its noise (a friction calibrated a little off) but does not rise into the cut
    is not the entry: the band is judged a tool radius past the first cutting revolution, as before."""
    cell = _cell_with([0.2, 0.2, 0.2, 0.2, 0.2], 0.5, 0)
    need = cell.cfg.learning.low_revolutions
    assert first_event_rev(cell, "expected_low") == ENTRY_REVS + need - 1
