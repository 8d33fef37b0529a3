"""Alarm state machines, revolution by revolution."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from millsense.daemon.pipeline.alarms import AlarmEngine, alarm_payload

pytestmark = pytest.mark.quick


def cfg(**kw):
    base = dict(
        torque_warn_nm=20.0,
        torque_limit_nm=30.0,
        force_limit_n=None,
        power_limit_w=None,
        revolutions=2,
        crash_power_w=15000.0,
        hysteresis_pct=10.0,
        breakage_drop_pct=50.0,
        breakage_min_torque_nm=1.0,
    )
    base.update(kw)
    return SimpleNamespace(**base)


def rev(i, torque, valid=True, cutting=True, **extra):
    return {"rev": i, "seq_end": 100 * i + 99, "torque_nm": torque, "valid": valid, "cutting": cutting, **extra}


def feed(engine, torques, **kw):
    out = []
    for i, t in enumerate(torques):
        out.append([(e.level, e.quantity) for e in engine.on_revolution(rev(i, t, **kw))])
    return out


def test_overload_needs_n_consecutive_revolutions():
    e = AlarmEngine(cfg(revolutions=3, torque_warn_nm=None, breakage_drop_pct=0))
    got = feed(e, [10, 31, 31, 10, 31, 31, 31, 31])
    assert got[:6] == [[]] * 6
    assert got[6] == [("overload", "torque_nm")]
    assert got[7] == []


def test_single_spike_neither_raises_nor_clears():
    e = AlarmEngine(cfg(breakage_drop_pct=0))
    assert feed(e, [5, 35, 5]) == [[], [], []]
    e = AlarmEngine(cfg(breakage_drop_pct=0))
    got = feed(e, [35, 35, 5, 35, 5, 5])
    assert got[1] == [("overload", "torque_nm")]
    assert got[2:5] == [[], [], []]
    assert got[5] == [("clear", "torque_nm")]


def test_hysteresis_band_holds_the_level():
    e = AlarmEngine(cfg(hysteresis_pct=10.0, breakage_drop_pct=0))
    # 28 is below the 30 limit but inside the band (>= 27): overload stays.
    got = feed(e, [31, 31, 28, 28, 28, 26.5, 26.5])
    assert got[1] == [("overload", "torque_nm")]
    assert got[2:5] == [[], [], []]
    # 26.5 is under the band of 30 but above the warning limit: back to warning.
    assert got[6] == [("warning", "torque_nm")]


def test_event_payload_carries_value_and_limit_of_new_level():
    e = AlarmEngine(cfg(breakage_drop_pct=0))
    e.on_revolution(rev(1, 22.0))
    (ev,) = e.on_revolution(rev(2, 23.0))
    assert (ev.level, ev.value, ev.limit, ev.rev, ev.seq, ev.trips) == ("warning", 23.0, 20.0, 2, 299, False)
    p = alarm_payload(ev, "m1", 12.5, None)
    assert list(p) == ["machine", "t", "rev", "level", "quantity", "value", "limit", "interlock"]
    assert p["machine"] == "m1" and p["t"] == 12.5 and p["interlock"] is None


def test_damaged_revolutions_never_raise_clear_or_break_a_run():
    e = AlarmEngine(cfg(breakage_drop_pct=0))
    assert feed(e, [99, 99, 99], valid=False) == [[], [], []]
    e = AlarmEngine(cfg(breakage_drop_pct=0))
    seq = [rev(0, 35), rev(1, 0.0, valid=False), rev(2, 35)]
    events = [e.on_revolution(r) for r in seq]
    assert events[1] == [] and [x.level for x in events[2]] == ["overload"]
    events = [e.on_revolution(r) for r in (rev(3, 1.0, valid=False), rev(4, 1.0, valid=False), rev(5, 1.0, valid=False))]
    assert events == [[], [], []] and e.summary() == "overload"


def test_force_and_power_limits_use_their_own_fields():
    e = AlarmEngine(cfg(torque_warn_nm=None, torque_limit_nm=None, force_limit_n=3000.0, power_limit_w=7500.0, revolutions=1, breakage_drop_pct=0))
    evs = e.on_revolution(rev(0, 5.0, force_n=3100.0, p_gap_w=100.0))
    assert [(x.level, x.quantity) for x in evs] == [("overload", "force_n")]
    evs = e.on_revolution(rev(1, 5.0, force_n=3100.0, p_gap_w=8000.0))
    assert [(x.level, x.quantity) for x in evs] == [("overload", "p_gap_w")]
    # None / NaN values are "cannot be estimated": no decision either way.
    assert e.on_revolution(rev(2, 5.0, force_n=None, p_gap_w=float("nan"))) == []


def test_unarmed_limits_raise_nothing():
    e = AlarmEngine(SimpleNamespace())
    assert e.on_revolution(rev(0, 1e6)) == [] and e.on_revolution(rev(1, 1e6)) == []
    assert e.on_revolution(rev(2, 1.0)) == []  # breakage not armed either
    assert e.on_power(np.full(10, 1e9), 0) == []


def test_breakage_on_a_step_between_steady_levels():
    """Three steady revolutions, one of transition, two that agree: alarm on the second."""
    e = AlarmEngine(cfg(torque_warn_nm=None, torque_limit_nm=None, breakage_drop_pct=20.0))
    got = feed(e, [10, 10.2, 9.9, 8.6, 7.5, 7.6])  # -24 %: a 2-flute cutter lost a flute
    assert got == [[], [], [], [], [], [("tool_breakage", "torque_nm")]]
    assert feed(e, [0.1, 0.1]) == [[], []]  # latched: said once
    assert [x.level for x in e.reset()] == ["clear"]
    e = AlarmEngine(cfg(torque_warn_nm=None, torque_limit_nm=None, breakage_drop_pct=20.0))
    assert feed(e, [10, 10, 10, 11, 12.6, 12.7])[-1] == []  # +26 %: a rise is load, never a breakage
    e = AlarmEngine(cfg(torque_warn_nm=None, torque_limit_nm=None, breakage_drop_pct=20.0))
    assert feed(e, [10, 10, 10, 4, 0.2, 0.1])[-1] == [("tool_breakage", "torque_nm")]  # snapped off: to air at once


def test_no_breakage_from_entry_exit_ramps_or_small_steps():
    def quiet(torques, **kw):
        e = AlarmEngine(cfg(torque_warn_nm=None, torque_limit_nm=None, breakage_drop_pct=20.0))
        return all(got == [] for got in feed(e, torques, **kw))

    assert quiet([10, 10, 10, 9, 7, 5, 3, 1.5, 0.5, 0.1, 0.0])  # leaving the part: never settles
    assert quiet([0.0, 0.3, 1.5, 4, 7, 9.5, 10, 10])  # entering
    assert quiet([10, 10, 10, 9, 8.5, 8.5])  # -15 %: below the threshold
    assert quiet([10, 10.2, 9.8, 8, 7.0, 8.0, 7.5])  # no settled level after
    assert quiet([10, 13, 8, 6, 7.5, 7.6])  # no steady level before


def test_no_breakage_when_speed_or_feed_changes():
    e = AlarmEngine(cfg(torque_warn_nm=None, torque_limit_nm=None, breakage_drop_pct=20.0))
    rpms = [600, 600, 600, 900, 900, 900]
    got = [e.on_revolution(rev(i, t, spindle_rpm=r)) for i, (t, r) in enumerate(zip([10, 10, 10, 8, 7.5, 7.5], rpms))]
    assert all(g == [] for g in got)
    e = AlarmEngine(cfg(torque_warn_nm=None, torque_limit_nm=None, breakage_drop_pct=20.0))
    feeds = [0.2, 0.2, 0.2, 0.15, 0.1, 0.1]  # a programmed feed change, seen on a feed-rate channel
    got = [e.on_revolution(rev(i, t, feed_per_tooth_mm=f)) for i, (t, f) in enumerate(zip([10, 10, 10, 8, 7.0, 7.0], feeds))]
    assert all(g == [] for g in got)


@settings(max_examples=200, deadline=None)
@given(st.floats(1.5, 100.0), st.lists(st.floats(-0.03, 0.03), min_size=12, max_size=60))
def test_no_breakage_from_noise_on_a_steady_cut(level_nm, noise):
    e = AlarmEngine(cfg(torque_warn_nm=None, torque_limit_nm=None, breakage_drop_pct=20.0))
    assert all(got == [] for got in feed(e, [level_nm * (1 + n) for n in noise]))


def test_no_breakage_from_air_cut_or_small_torque():
    e = AlarmEngine(cfg(torque_warn_nm=None, torque_limit_nm=None))
    assert all(g == [] for g in feed(e, [0.1, 0.1, 0.1, 10.0, 10.0, 10.0], cutting=False))
    e = AlarmEngine(cfg(torque_warn_nm=None, torque_limit_nm=None, breakage_min_torque_nm=2.0))
    assert all(g == [] for g in feed(e, [1.5, 1.5, 1.5, 0.5, 0.1, 0.1]))


def test_breakage_not_across_a_link_outage():
    e = AlarmEngine(cfg(torque_warn_nm=None, torque_limit_nm=None))
    for i in range(4):
        e.on_revolution(rev(i, 10.0))
    e.on_daq(False)
    e.on_daq(True)
    assert all(e.on_revolution(rev(i, 1.0)) == [] for i in range(4, 9))


def test_crash_trips_at_the_first_sample_over_the_limit():
    e = AlarmEngine(cfg())
    p = np.full(10, 1000.0)
    assert e.on_power(p, 500) == []
    p[6:] = 16000.0
    p[3] = np.nan
    (ev,) = e.on_power(p, 510)
    assert (ev.level, ev.seq, ev.value, ev.limit, ev.trips) == ("crash", 516, 16000.0, 15000.0, True)
    assert e.on_power(p, 520) == []  # latched
    assert e.summary() == "crash"
    assert [(x.level, x.quantity) for x in e.reset()] == [("clear", "p_gap_w")]
    assert [x.level for x in e.on_power(p, 530)] == ["crash"]


def test_daq_lost_only_on_change():
    e = AlarmEngine(cfg())
    assert e.on_daq(True) == []
    assert [x.level for x in e.on_daq(False)] == ["daq_lost"]
    assert e.on_daq(False) == []
    assert [(x.level, x.quantity) for x in e.on_daq(True)] == [("clear", "daq")]


@settings(max_examples=60, deadline=None)
@given(
    st.lists(st.floats(0.0, 50.0) | st.none(), min_size=1, max_size=60),
    st.integers(1, 4),
)
def test_overload_only_after_n_values_over_and_no_repeats(values, n):
    e = AlarmEngine(cfg(revolutions=n, torque_warn_nm=None, hysteresis_pct=0.0, breakage_drop_pct=0))
    history: list[float] = []
    last_level = None
    for i, v in enumerate(values):
        valid = v is not None
        events = e.on_revolution(rev(i, v if valid else 0.0, valid=valid))
        if valid:
            history.append(v)
        for ev in events:
            assert ev.level != last_level, "a state change must change the state"
            if ev.level == "overload":
                assert len(history) >= n and all(x > 30.0 for x in history[-n:])
            else:
                assert ev.level == "clear" and all(x <= 30.0 for x in history[-n:])
            last_level = ev.level


def test_reset_rearms_levels_so_a_persisting_overload_trips_again():
    e = AlarmEngine(cfg(torque_warn_nm=None, breakage_drop_pct=0))
    assert [x.level for x in e.on_revolution(rev(0, 35)) + e.on_revolution(rev(1, 35))] == ["overload"]
    assert [(x.level, x.quantity) for x in e.reset()] == [("clear", "torque_nm")]
    assert e.summary() == "ok"
    assert e.on_revolution(rev(2, 35)) == []
    assert [x.level for x in e.on_revolution(rev(3, 35))] == ["overload"]


def test_a_torque_rise_is_an_overload_and_never_a_breakage():
    """Issue 10, finding 6: a rise 10 -> 40 N·m raised `tool_breakage` beside the overload."""
    for drop in (None, 20.0):   # not armed (the default now), and armed: rises never fire it
        e = AlarmEngine(cfg(torque_warn_nm=None, breakage_drop_pct=drop))
        levels = [x.level for got in [e.on_revolution(rev(i, t)) for i, t in enumerate([10, 10, 10, 25, 40, 40, 40])]
                  for x in got]
        assert levels == ["overload"], (drop, levels)
        assert "tool_breakage" not in e.active()


def test_breakage_not_armed_by_the_default_config():
    from millsense.daemon.config.models import AlarmSettings

    defaults = AlarmSettings()
    assert defaults.breakage_drop_pct is None
    e = AlarmEngine(defaults)
    assert not e.breakage.armed
    assert all(g == [] for g in feed(e, [10, 10.2, 9.9, 8.6, 5.0, 5.0, 0.1, 0.1]))  # even a real drop: not armed
    armed = AlarmEngine(AlarmSettings(breakage_drop_pct=20.0))
    assert feed(armed, [10, 10.2, 9.9, 8.6, 5.0, 5.0])[-1] == [("tool_breakage", "torque_nm")]


def test_accelerating_revolutions_count_like_any_other():
    """`accelerating` is information only: the estimator takes the masses' share out of the torque."""
    e = AlarmEngine(cfg(torque_warn_nm=None, breakage_drop_pct=None))
    assert feed(e, [35, 35], accelerating=True)[-1] == [("overload", "torque_nm")]


def test_the_power_limit_compares_the_power_less_what_went_into_the_masses():
    e = AlarmEngine(cfg(torque_warn_nm=None, torque_limit_nm=None, power_limit_w=2000.0, revolutions=1,
                        breakage_drop_pct=None))
    # a speed step in air: 6 kW of air-gap power, 5.8 kW of it into the rotating masses
    assert e.on_revolution(rev(0, 1.0, p_gap_w=6000.0, p_inertia_w=5800.0)) == []
    assert e.over_limits(rev(0, 1.0, p_gap_w=6000.0, p_inertia_w=5800.0)) == []
    # slowing under load: the masses give 1 kW to the cut, on top of 1.5 kW from the motor
    evs = e.on_revolution(rev(1, 1.0, p_gap_w=1500.0, p_inertia_w=-1000.0))
    assert [(x.level, x.quantity) for x in evs] == [("overload", "p_gap_w")]
    # J unknown: p_inertia_w null, the air-gap power as measured (the safe side)
    assert AlarmEngine(cfg(torque_limit_nm=None, power_limit_w=2000.0)).over_limits(
        rev(2, 1.0, p_gap_w=6000.0, p_inertia_w=None)) == ["p_gap_w"]


def _saturated(i):
    """What the estimator publishes when a current clipped while high: invalid, no numbers."""
    return {"rev": i, "seq_end": 100 * i + 99, "valid": False, "invalid": "signals", "saturated": True,
            "torque_nm": None, "force_n": None, "p_gap_w": None, "cutting": False, "accelerating": False}


def test_saturated_revolutions_count_as_over_every_armed_limit():
    e = AlarmEngine(cfg(force_limit_n=3000.0, power_limit_w=7500.0, breakage_drop_pct=None))
    assert e.on_revolution(_saturated(0)) == []          # one revolution: not yet (revolutions = 2)
    evs = e.on_revolution(_saturated(1))
    assert sorted((x.level, x.quantity) for x in evs) == [
        ("overload", "force_n"), ("overload", "p_gap_w"), ("overload", "torque_nm")]
    assert all(x.trips and x.value is None for x in evs)
    assert sorted(e.over_limits(_saturated(2))) == ["force_n", "p_gap_w", "torque_nm"]
    # a saturated revolution after a valid over-limit one completes the run
    e = AlarmEngine(cfg(torque_warn_nm=None, breakage_drop_pct=None))
    assert e.on_revolution(rev(0, 35.0)) == []
    assert [(x.level, x.quantity) for x in e.on_revolution(_saturated(1))] == [("overload", "torque_nm")]
    # only armed limits; an invalid revolution that is not saturated stays over nothing
    e = AlarmEngine(cfg(torque_warn_nm=None, breakage_drop_pct=None))
    assert e.over_limits(_saturated(0)) == ["torque_nm"]
    assert e.over_limits(dict(_saturated(0), saturated=False)) == []
    assert AlarmEngine(SimpleNamespace()).on_revolution(_saturated(0)) == []
