"""ToolWear: the mean of the last window of energy ratios, one warning, re-armed by a new tool."""

from __future__ import annotations

import json

import pytest

from millsense.daemon.learning.wear import ToolWear

pytestmark = pytest.mark.quick


def test_wear_is_the_mean_rise_of_the_last_window():
    w = ToolWear()
    assert w.wear_pct is None
    for r in (1.00, 1.10, 1.20, 1.30):
        w.add_ratio(r, window=3, rise_pct=50.0)
    assert w.ratios == [1.10, 1.20, 1.30]
    assert w.wear_pct == pytest.approx((1.10 + 1.20 + 1.30) / 3 * 100 - 100)


def test_the_warning_waits_for_a_full_window_and_comes_once():
    w = ToolWear()
    assert w.add_ratio(1.5, window=3, rise_pct=15.0) is False     # one process is not a trend
    assert w.add_ratio(1.5, window=3, rise_pct=15.0) is False
    assert w.add_ratio(1.5, window=3, rise_pct=15.0) is True
    assert w.add_ratio(1.6, window=3, rise_pct=15.0) is False     # said once
    assert w.warned


def test_below_the_rise_no_warning():
    w = ToolWear()
    assert not any(w.add_ratio(1.149, window=3, rise_pct=15.0) for _ in range(10))


def test_new_tool_restarts_everything_and_round_trips():
    w = ToolWear()
    w.count_process()
    w.count_process()
    for _ in range(3):
        w.add_ratio(1.2, window=3, rise_pct=15.0)
    back = ToolWear.from_dict(json.loads(json.dumps(w.to_dict())))
    assert back == w and back.processes == 2 and back.warned
    w.new_tool()
    assert (w.processes, w.ratios, w.warned) == (0, [], False)
    assert [w.add_ratio(1.2, window=3, rise_pct=15.0) for _ in range(3)] == [False, False, True]
