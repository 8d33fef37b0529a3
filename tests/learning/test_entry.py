"""The entry of a process: one revolution over the cutting threshold in the air is not a cut.

Found on the simulated part program: after the spindle came up to speed, one
revolution read 0.5 N·m with `cutting` true two revolutions before the tool
touched the part; taken as the entry, it shifted the process's revolutions by
two against the envelope and raised `envelope_low` on a good part.
"""

from __future__ import annotations

import pytest

from millsense.daemon.learning.monitor import ProcessMonitor
from tests.learning.synth import CUTTING_NM, Shape, Shop, learning

pytestmark = pytest.mark.quick


def blip_before_entry(k_blip: int = 4) -> Shape:
    """Air with one revolution just over the cutting threshold, two revolutions before the real entry."""
    shape = Shape(air_before=10)
    base = shape.torques

    def torques() -> list[float]:
        out = base()
        out[k_blip] = 2.5 * CUTTING_NM
        return out

    shape.torques = torques  # type: ignore[method-assign]
    return shape


def test_a_single_revolution_over_the_threshold_in_the_air_is_not_the_entry():
    shop = Shop(ProcessMonitor(learning()), noise_pct=1.0)
    shop.learn()
    shop.process(blip_before_entry())
    (summary,) = shop.processes()[-1:]
    assert summary["entry_rev"] == 10  # the real entry, not the blip at 4
    assert shop.events("envelope_low") == [] and shop.events("envelope_high") == []


def test_the_entry_revolution_is_process_rev_zero():
    shop = Shop(ProcessMonitor(learning()), noise_pct=0.0)
    shop.process(Shape(air_before=7))
    revs = [e.get("process_rev") for e in shop.estimates]
    entry = next(i for i, k in enumerate(revs) if k is not None)
    assert revs[entry] == 1 and revs[entry - 1] is None  # known one revolution later
    assert shop.processes()[0]["entry_rev"] == 7
