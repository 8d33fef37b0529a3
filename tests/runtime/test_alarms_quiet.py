"""The threshold tracks' quiet shortcut (issue 13: most revolutions sit below every level) decides
exactly what the full rule decides, revolution by revolution, whatever the values."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from millsense.daemon.pipeline.alarms import AlarmEngine, ThresholdTrack

pytestmark = pytest.mark.quick

# values around both levels and their hysteresis bands (warn 20, limit 30, 10 %: 18 and 27), None: saturated
values = st.lists(st.one_of(st.sampled_from([0.0, 17.9, 18.0, 19.99, 20.0, 20.01, 26.9, 27.0, 30.0, 30.5, None]),
                            st.floats(-5.0, 40.0)), max_size=80)


def _full_rule(track: ThresholdTrack) -> ThresholdTrack:
    track._lowest = -math.inf   # the shortcut never applies: every revolution takes the full rule
    return track


def _events(track: ThresholdTrack, seq: list, rearm_at: int | None) -> list:
    out = []
    for i, v in enumerate(seq):
        if i == rearm_at:
            out.append(("rearm", track.rearm()))
        out.append(track.update(v, i, 10 * i))
    return out


@settings(max_examples=300, deadline=None)
@given(seq=values, n=st.integers(1, 3), warn=st.sampled_from([20.0, None]), rearm_at=st.one_of(st.none(), st.integers(0, 80)))
def test_shortcut_decides_as_the_full_rule(seq, n, warn, rearm_at):
    fast = ThresholdTrack("torque_nm", warn, 30.0, n, 10.0)
    full = _full_rule(ThresholdTrack("torque_nm", warn, 30.0, n, 10.0))
    assert _events(fast, seq, rearm_at) == _events(full, seq, rearm_at)
    assert (fast.rank, fast._above, fast._below) == (full.rank, full._above, full._below)


def test_a_level_is_still_entered_and_left():
    """The shortcut must not swallow the revolutions that count towards a level (n = 2)."""
    t = ThresholdTrack("torque_nm", 20.0, 30.0, 2, 10.0)
    got = [t.update(v, i, i) for i, v in enumerate([5.0, 21.0, 5.0, 21.0, 22.0, 5.0, 5.0, 5.0])]
    assert [(e.level, e.rev) for e in got if e is not None] == [("warning", 4), ("clear", 6)]


def test_unarmed_tracks_and_breakage_are_skipped_but_armed_ones_decide():
    alarms = SimpleNamespace(torque_warn_nm=None, torque_limit_nm=None, force_warn_n=None, force_limit_n=None,
                             power_warn_w=None, power_limit_w=1000.0, revolutions=1, hysteresis_pct=5.0,
                             breakage_drop_pct=None, crash_power_w=None)
    e = AlarmEngine(alarms)
    est = {"rev": 1, "seq_end": 99, "valid": True, "torque_nm": 50.0, "force_n": 5000.0, "p_gap_w": 1500.0,
           "p_inertia_w": None, "cutting": True}
    assert [(ev.level, ev.quantity) for ev in e.on_revolution(est)] == [("overload", "p_gap_w")]


ENGINE = SimpleNamespace(torque_warn_nm=20.0, torque_limit_nm=30.0, force_warn_n=None, force_limit_n=1000.0,
                         power_warn_w=None, power_limit_w=2000.0, revolutions=2, hysteresis_pct=10.0,
                         breakage_drop_pct=None, crash_power_w=None)
estimates = st.lists(st.tuples(st.one_of(values, st.none()), st.floats(0.0, 1500.0), st.floats(0.0, 2600.0),
                               st.sampled_from(["valid", "valid", "valid", "invalid", "saturated"])), max_size=60)


@settings(max_examples=200, deadline=None)
@given(revs=estimates)
def test_engine_decides_as_with_the_full_rule(revs):
    """The engine applies the shortcut itself (no call per quiet track): the same events as without it."""
    fast, full = AlarmEngine(ENGINE), AlarmEngine(ENGINE)
    for track in full.tracks:
        _full_rule(track)
    for i, (torque, force, power, kind) in enumerate(revs):
        est = {"rev": i, "seq_end": 100 * i, "valid": kind == "valid", "saturated": kind == "saturated",
               "torque_nm": torque, "force_n": force, "p_gap_w": power, "p_inertia_w": 50.0, "cutting": True}
        assert fast.on_revolution(est) == full.on_revolution(est)
