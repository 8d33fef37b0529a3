"""The adaptive feed controller (daemon/afc/controller.py), alone and in a simple closed loop.

The loop (tests/pipeline/loop_model.py) is the cut as the controller sees it:
a static gain between ln(feed) and ln(load), one revolution's averaging, the
estimator's batching as dead time, and the CNC's first-order lag and rate
limit. The plant's gain runs over 0.4 … 0.9 while the controller assumes
0.56 (1 + [material] ks_exp of the default material): the tuning must hold with
that mismatch, at 300, 600, 1500 and 3000 rpm.
"""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from millsense.daemon.config.models import AfcSettings, AfcTargetSettings, MaterialSettings
from millsense.daemon.afc.controller import STATES, FeedController, tune
from tests.pipeline.loop_model import Cut, run

pytestmark = pytest.mark.quick

SETTLE_BAND = 0.05        # issue 15: within ±5 % of the target ...
OVERSHOOT_MAX = 0.15      # ... overshoot at most 15 %
CNC_LAG_S = 0.04
SPEEDS = [(300, 100.0), (600, 200.0), (1500, 300.0), (3000, 600.0)]  # rpm, programmed feed mm/min
GAINS = [0.4, 0.56, 0.9]
TOOL_D_MM = 20.0          # [P]'s end mill: a wall in the floor passes under it over its diameter


def controller(**afc) -> FeedController:
    return FeedController(AfcSettings(**{"enabled": True, "allow": True, **afc}))


def est(load: float, *, rpm: float = 600.0, valid: bool = True, cutting: bool = True) -> dict:
    return {"valid": valid, "cutting": cutting, "spindle_rpm": rpm, "torque_nm": load, "feed_override_pct": 100.0}


def step_outcome(revs, target: float) -> tuple[int | None, float, float]:
    """(revolutions until the load stays within the band, overshoot beyond the target, spread over the last half)."""
    ratio = [r.load / target - 1.0 for r in revs]
    settle = next((k for k in range(len(ratio)) if all(abs(x) <= SETTLE_BAND for x in ratio[k:])), None)
    sign = -1.0 if ratio[0] > 0 else 1.0
    overshoot = max([0.0, *(sign * x for x in ratio)])
    return settle, overshoot, max(abs(x) for x in ratio[len(ratio) // 2:])


def reach(cut: Cut, level_mm: float, target: float, afc: AfcSettings) -> str:
    """"in": the bounds bring this level's load to the target with room to spare; "out": beyond them; "edge"."""
    needed = 100.0 * (target / (cut.load_per_mm * level_mm)) ** (1.0 / cut.gain)
    if afc.min_override_pct * 1.02 <= needed <= afc.max_override_pct / 1.02:
        return "in"
    return "out" if not afc.min_override_pct <= needed <= afc.max_override_pct else "edge"


# ----------------------------------------------------------------------------- the tuning
def test_the_tuning_starts_from_the_loops_delay():
    t = tune(0.1, batch_s=0.05, cnc_lag_s=CNC_LAG_S, gain=0.56)
    assert t.delay_s == pytest.approx(0.1 + 0.05 + CNC_LAG_S)
    # the predictor takes the delay out: a first-order loop of one revolution, integral action only
    assert t.lambda_s == pytest.approx(0.1) and t.kp == 0.0
    assert t.ki_per_s == pytest.approx(1.0 / (0.56 * t.lambda_s))
    # a delay beyond DAMPED_DELAY_REVOLUTIONS revolutions slows the loop in proportion
    fast = tune(0.01, batch_s=0.05, cnc_lag_s=CNC_LAG_S, gain=0.56)
    assert fast.lambda_s == pytest.approx(fast.delay_s / 6.0) and fast.lambda_s > 0.01
    slow = tune(0.2, batch_s=0.05, cnc_lag_s=CNC_LAG_S, gain=0.56)
    assert slow.ki_per_s < t.ki_per_s                              # a slower spindle, a slower loop
    assert tune(0.1, batch_s=0.05, cnc_lag_s=CNC_LAG_S, gain=0.56, closed_loop_s=2.0).lambda_s == 2.0


def test_the_gain_comes_from_the_material_unless_given():
    c = FeedController(AfcSettings(), MaterialSettings(ks_exp=-0.3))
    assert c.gain == pytest.approx(0.7)                            # torque ~ t^(1+p), [D] eq. (8)
    assert FeedController(AfcSettings(process_gain=0.8), MaterialSettings(ks_exp=-0.3)).gain == 0.8


# ----------------------------------------------------------------------------- the closed loop
@pytest.mark.parametrize("rpm,feed", SPEEDS)
@pytest.mark.parametrize("gain", GAINS)
def test_depth_steps_settle_within_the_acceptance(rpm, feed, gain):
    """2 -> 3 -> 2.5 mm under [P]'s 20 mm end mill, target = the load at 2.5 mm and the programmed feed."""
    cut = Cut(rpm, feed, levels_mm=(0.0, 2.0, 3.0, 2.5), tool_diameter_mm=TOOL_D_MM, gain=gain, cnc_lag_s=CNC_LAG_S)
    c = controller()
    target = cut.load_per_mm * 2.5
    result = run(cut, c, target, start_mm=cut.level_len_mm - TOOL_D_MM / 2 - 1.0)
    rev_s = 60.0 / rpm
    allowed = max(5, math.ceil(3 * CNC_LAG_S / rev_s))
    checked = 0
    for k, level in enumerate(cut.levels_mm[1:], start=1):
        revs = result.level(k)
        assert len(revs) > allowed + 3, (k, len(revs))
        where = reach(cut, level, target, c.settings)
        if where == "out":
            assert {r.state for r in revs[allowed:]} == {"saturated"}, (level, {r.state for r in revs})
        if where != "in":
            continue
        settle, overshoot, spread = step_outcome(revs, target)
        assert settle is not None and settle <= allowed, (level, settle, allowed)
        assert overshoot <= OVERSHOOT_MAX, (level, overshoot)
        assert spread <= SETTLE_BAND, (level, spread)
        checked += 1
    assert checked >= 2


@pytest.mark.parametrize("rpm,feed", SPEEDS)
@pytest.mark.parametrize("gain", GAINS)
def test_an_abrupt_step_neither_overshoots_nor_oscillates(rpm, feed, gain):
    """The worst case: the load steps within one revolution (no tool to cross the wall)."""
    cut = Cut(rpm, feed, levels_mm=(2.0, 3.0, 2.5), gain=gain, cnc_lag_s=CNC_LAG_S)
    c = controller()
    target = cut.load_per_mm * 2.5
    result = run(cut, c, target)
    for k, level in enumerate(cut.levels_mm[1:], start=1):
        revs = result.level(k)
        if reach(cut, level, target, c.settings) != "in":
            continue
        settle, overshoot, spread = step_outcome(revs, target)
        assert settle is not None and settle < len(revs) // 2, (level, settle, len(revs))
        assert overshoot <= OVERSHOOT_MAX, (level, overshoot)
        assert spread <= SETTLE_BAND / 5, (level, spread)        # it settles, it does not ring
        commanded = [r.commanded_pct for r in revs[len(revs) // 2:]]
        assert max(commanded) - min(commanded) <= 0.5, (level, min(commanded), max(commanded))


def test_a_target_beyond_reach_sits_at_the_bound_and_says_saturated():
    c = controller()
    states = [c.on_revolution(est(40.0), target=100.0, allowed=True, now_s=0.1 * k).state for k in range(100)]
    assert states[-1] == "saturated" and c.commanded_pct == c.settings.max_override_pct
    assert c.status()["state"] == "saturated"
    c2 = controller()
    for k in range(100):
        c2.on_revolution(est(500.0), target=100.0, allowed=True, now_s=0.1 * k)
    assert c2.state == "saturated" and c2.commanded_pct == c2.settings.min_override_pct


def test_the_integrator_does_not_run_away_at_a_bound():
    """After long at the upper bound, the first revolution that asks for less feed gets less feed."""
    c = controller()
    for k in range(2000):
        c.on_revolution(est(40.0), target=100.0, allowed=True, now_s=0.1 * k)
    assert c.commanded_pct == 150.0
    c.on_revolution(est(150.0), target=100.0, allowed=True, now_s=200.1)
    assert c.commanded_pct < 150.0 and c.state == "armed"


# ----------------------------------------------------------------------------- arming, air, idle
def test_arming_needs_a_target_permission_and_load_above_the_arm_level():
    c = controller(air_override_pct=90.0)
    d = c.on_revolution(est(50.0), target=None, allowed=True, now_s=0.1)
    assert (d.state, d.reason) == ("idle", "no target")
    d = c.on_revolution(est(50.0), target=100.0, allowed=False, now_s=0.2)
    assert (d.state, d.reason) == ("idle", "not allowed")
    d = c.on_revolution(est(29.0), target=100.0, allowed=True, now_s=0.3)  # below 30 % of the target
    assert d.state == "air"
    d = c.on_revolution(est(60.0, cutting=False), target=100.0, allowed=True, now_s=0.4)
    assert d.state == "air"
    d = c.on_revolution(est(31.0), target=100.0, allowed=True, now_s=0.5)
    # controlling: the load is a third of the target, far beyond the bounds' reach, so at once at the bound
    assert d.state in ("armed", "saturated") and d.override_pct is not None
    assert d.override_pct > c.settings.air_override_pct


def test_in_air_the_override_returns_to_the_air_value_rate_limited_and_stays():
    c = controller(rate_pct_s=100.0)
    for k in range(50):
        c.on_revolution(est(40.0), target=100.0, allowed=True, now_s=0.1 * k)
    assert c.commanded_pct == 150.0
    seen = [c.commanded_pct]
    for k in range(50, 60):
        c.on_revolution(est(0.0, cutting=False), target=100.0, allowed=True, now_s=0.1 * k)
        seen.append(c.commanded_pct)
    assert all(0 <= a - b <= 100.0 * 0.1 + 0.05 for a, b in zip(seen, seen[1:])), seen
    assert seen[-1] == 100.0 and c.state == "air"
    d = c.on_revolution(est(0.0, cutting=False), target=100.0, allowed=True, now_s=6.1)
    assert d.override_pct is None                                  # unchanged: nothing to send


def test_switch_off_commands_the_programmed_feed_at_once_and_on_does_not_move_it():
    c = controller()
    for k in range(20):
        c.on_revolution(est(50.0), target=100.0, allowed=True, now_s=0.1 * k)
    assert c.commanded_pct > 100.0
    d = c.switch(False, now_s=2.1)
    assert (d.override_pct, d.state) == (100.0, "off") and c.commanded_pct == 100.0
    assert c.on_revolution(est(50.0), target=100.0, allowed=True, now_s=2.2).override_pct is None
    d = c.switch(True, now_s=2.3)
    assert d.override_pct is None and c.state == "air"


def test_a_stale_loop_above_programmed_returns_to_100():
    c = controller()
    for k in range(20):
        c.on_revolution(est(50.0), target=100.0, allowed=True, now_s=0.1 * k)
    last = 1.9
    assert c.on_idle(last + 0.29) is None                          # max(3 revolutions, 0.3 s) not yet
    d = c.on_idle(last + 0.31)
    assert d is not None and d.override_pct == 100.0 and c.commanded_pct == 100.0
    assert c.on_idle(last + 1.0) is None                           # already at 100


def test_a_daq_without_an_override_output_is_unavailable():
    c = controller()
    c.set_available(False)
    assert c.state == "unavailable"
    assert c.on_revolution(est(50.0), target=100.0, allowed=True, now_s=0.1) == \
        c.on_revolution(est(50.0), target=100.0, allowed=True, now_s=0.2)
    assert c.on_revolution(est(50.0), target=100.0, allowed=True, now_s=0.3).override_pct is None
    assert c.switch(True, 0.4).state == "unavailable" and c.commanded_pct == 100.0


# ----------------------------------------------------------------------------- the safety path
def _above_100() -> FeedController:
    """Armed above 100 %: a load of 85 % of the target wants (1/0.85)^(1/0.56) = 134 %, within the bounds."""
    c = controller()
    for k in range(20):
        c.on_revolution(est(85.0), target=100.0, allowed=True, now_s=0.1 * k)
    assert c.commanded_pct > 110.0
    return c


def test_safe_brings_the_override_to_100_at_once_and_holds_until_release():
    c = _above_100()
    d = c.safe("blind")
    assert (d.override_pct, d.state, d.reason) == (100.0, "safe", "blind")
    for k in range(20):
        d = c.on_revolution(est(85.0), target=100.0, allowed=True, now_s=3.0 + 0.1 * k)
        assert d.state == "safe" and d.override_pct is None and c.commanded_pct == 100.0
    c.release()
    d = c.on_revolution(est(85.0), target=100.0, allowed=True, now_s=6.0)
    assert d.state == "armed" and c.commanded_pct > 100.0


def test_safe_below_100_leaves_the_override_where_it_is():
    c = controller()
    for k in range(30):
        c.on_revolution(est(200.0), target=100.0, allowed=True, now_s=0.1 * k)
    low = c.commanded_pct
    assert low < 100.0
    d = c.safe("trip")
    assert d.override_pct is None and d.state == "safe" and c.commanded_pct == low


def test_an_invalid_revolution_is_safe_for_itself_and_control_resumes_from_100():
    c = _above_100()
    d = c.on_revolution(est(85.0, valid=False), target=100.0, allowed=True, now_s=3.0)
    assert (d.override_pct, d.state, d.reason) == (100.0, "safe", "invalid revolution")
    d = c.on_revolution(est(85.0), target=100.0, allowed=True, now_s=3.1)
    assert d.state == "armed"
    assert 100.0 < c.commanded_pct <= 100.0 + c.settings.rate_pct_s * 0.1 + 0.05


# ----------------------------------------------------------------------------- targets and permission
def test_targets_come_from_the_table_then_the_machine_then_learning():
    afc = AfcSettings(target_factor=0.9, targets={"12/3": AfcTargetSettings(torque_nm=18.0),
                                                  "12/*": AfcTargetSettings(torque_nm=15.0),
                                                  "7/1": AfcTargetSettings(allow=False)})
    c = FeedController(afc)
    assert c.target_for(12, 3, 30.0) == 18.0
    assert c.target_for(12, 4, 30.0) == 15.0
    assert c.target_for(7, 1, 30.0) == pytest.approx(27.0)         # factor × learned mean
    assert c.target_for(7, 1, None) is None
    machine = FeedController(AfcSettings(target_torque_nm=11.0, targets={"12/3": AfcTargetSettings(torque_nm=18.0)}))
    assert machine.target_for(12, 3, 30.0) == 18.0 and machine.target_for(5, 5, 30.0) == 11.0
    force = FeedController(AfcSettings(quantity="force", targets={"12/3": AfcTargetSettings(torque_nm=18.0)}))
    assert force.quantity_key == "force_n" and force.target_for(12, 3, None) is None


def test_permission_a_table_entry_decides_then_the_context_flag_then_the_config():
    afc = AfcSettings(targets={"12/3": AfcTargetSettings(allow=False), "12/*": AfcTargetSettings(allow=True)})
    c = FeedController(afc)
    assert c.allowed(12, 3, True) is False                          # tapping: never, flag or not
    assert c.allowed(12, 9, None) is True
    assert c.allowed(5, 1, True) is True and c.allowed(5, 1, False) is False and c.allowed(None, None, None) is False
    assert FeedController(AfcSettings(allow=True)).allowed(5, 1, False) is True


# ----------------------------------------------------------------------------- properties
step = st.one_of(
    st.tuples(st.just("rev"), st.floats(0.0, 300.0), st.booleans() | st.just(True), st.booleans() | st.just(True),
              st.sampled_from([300.0, 600.0, 1500.0, 3000.0, 0.0]), st.sampled_from([None, 50.0, 100.0, 200.0]),
              st.booleans() | st.just(True)),
    st.tuples(st.just("safe")), st.tuples(st.just("release")), st.tuples(st.just("idle")),
    st.tuples(st.just("switch"), st.booleans()),
)


@settings(max_examples=300, deadline=None)
@given(st.lists(step, max_size=80), st.floats(51.0, 99.0), st.floats(100.0, 200.0), st.floats(5.0, 500.0))
def test_bounds_rate_and_safety_hold_for_any_sequence(steps, lo, hi, rate):
    c = controller(min_override_pct=lo, max_override_pct=hi, rate_pct_s=rate, enabled=len(steps) % 2 == 0)
    now, latched, last_rev = 0.0, False, None
    for s in steps:
        before = c.commanded_pct
        now += 0.05
        if s[0] == "rev":
            _, load, valid, cutting, rpm, target, allowed = s
            d = c.on_revolution(est(load, rpm=rpm, valid=valid, cutting=cutting), target=target, allowed=allowed,
                                now_s=now)
            since = now - last_rev if last_rev is not None else 0.1
            dt = min(max(60.0 / rpm if rpm > 0 else since, 0.001), 1.0)
            last_rev = now
            assert abs(c.commanded_pct - before) <= rate * dt + 0.05 or c.commanded_pct <= min(before, 100.0)
            if latched or not valid:
                assert c.commanded_pct <= before
        elif s[0] == "safe":
            d = c.safe("fault")
            latched = True
            assert c.commanded_pct <= min(before, 100.0)  # and what the last revolutions raised is taken back
        elif s[0] == "release":
            c.release()
            latched = False
            d = None
        elif s[0] == "idle":
            d = c.on_idle(now + 1.0)
        else:
            d = c.switch(s[1], now)
        assert lo - 0.05 <= c.commanded_pct <= max(hi, 100.0) + 0.05 or c.commanded_pct == 100.0
        assert c.state in STATES
        if d is not None:
            assert d.state in STATES
            if d.override_pct is not None:
                assert d.override_pct == c.commanded_pct
                assert abs(d.override_pct * 10 - round(d.override_pct * 10)) < 1e-9   # the wire's 0.1 % step
        if latched:
            assert c.commanded_pct <= 100.0


def test_a_daq_back_at_100_after_a_restart_is_where_control_resumes():
    c = _above_100()
    c.commanded_pct = 100.0                                        # the runner: the link came back, the DAQ restarted
    c.on_revolution(est(100.0), target=100.0, allowed=True, now_s=3.0)  # on target: nothing to change
    assert c.commanded_pct == 100.0
    c.on_revolution(est(85.0), target=100.0, allowed=True, now_s=3.1)
    assert 100.0 < c.commanded_pct <= 100.0 + c.settings.rate_pct_s * 0.1 + 0.05


def test_status_reports_the_state_the_command_and_the_tuning():
    c = _above_100()
    s = c.status()
    assert {"enabled", "state", "reason", "override_pct", "target", "quantity", "min_pct", "max_pct", "tuning"} <= set(s)
    assert (s["enabled"], s["state"], s["override_pct"], s["target"], s["quantity"]) == \
        (True, c.state, c.commanded_pct, 100.0, "torque_nm")
    assert c.state in ("armed", "saturated")
    assert s["tuning"]["delay_s"] == pytest.approx(0.1 + 0.05 + CNC_LAG_S)


def test_a_fault_while_off_says_off_and_switching_on_waits_for_the_release():
    c = controller(enabled=False)
    d = c.safe("fault: signals")
    assert d.state == "off" and d.override_pct is None and c.state == "off"
    d = c.switch(True, now_s=1.0)
    assert d.state == "safe" and c.state == "safe"
    assert c.on_revolution(est(85.0), target=100.0, allowed=True, now_s=1.1).state == "safe"
    c.release()
    assert c.state == "air"
    assert c.on_revolution(est(85.0), target=100.0, allowed=True, now_s=1.2).state == "armed"



def test_a_sudden_drop_is_confirmed_before_the_feed_rises_for_it():
    """A sensor failing mid-cut reads a lighter load before the fault is seen: one revolution waits."""
    c = _above_100()
    held = c.commanded_pct
    d = c.on_revolution(est(40.0), target=100.0, allowed=True, now_s=3.0)   # 85 -> 40: more than 20 % down
    assert (d.override_pct, d.reason) == (None, "confirming a drop") and c.commanded_pct == held
    d = c.on_revolution(est(40.0), target=100.0, allowed=True, now_s=3.1)   # it stays: a lighter cut after all
    assert c.commanded_pct > held
    rising = c.commanded_pct
    d = c.on_revolution(est(200.0), target=100.0, allowed=True, now_s=3.2)  # a rise is answered at once
    assert c.commanded_pct < rising


def test_no_feed_is_raised_while_a_signal_has_stopped_in_the_newest_samples():
    """A sensor that fails in a revolution's last samples lightens it by a few %, below the drop rule: the
    runner passes what the signal check saw in the newest samples, and the feed is not raised on it."""
    c = _above_100()
    held = c.commanded_pct
    d = c.on_revolution(est(82.0), target=100.0, allowed=True, now_s=3.0, suspect="i_u")   # 85 -> 82: 4 % down
    assert (d.override_pct, d.reason) == (None, "a signal stopped: i_u") and c.commanded_pct == held
    c.on_revolution(est(120.0), target=100.0, allowed=True, now_s=3.1, suspect="i_u")      # a fall still goes out
    assert c.commanded_pct < held
    lowered = c.commanded_pct
    for k in range(2):  # nothing suspect: the drop from 120 is confirmed, then the feed rises
        c.on_revolution(est(82.0), target=100.0, allowed=True, now_s=3.2 + 0.1 * k)
    assert c.commanded_pct > lowered


def test_the_fault_path_takes_back_what_the_last_revolutions_raised():
    """A fault seen a revolution or two after its onset: the commands made on its readings are suspect."""
    c = controller()
    for k in range(30):
        c.on_revolution(est(125.0), target=100.0, allowed=True, now_s=0.1 * k)   # a heavy cut: below 100 %
    heavy = c.commanded_pct
    assert heavy < 95.0
    c.on_revolution(est(110.0), target=100.0, allowed=True, now_s=3.0)           # readings going light ...
    c.on_revolution(est(95.0), target=100.0, allowed=True, now_s=3.1)
    assert c.commanded_pct > heavy
    d = c.safe("fault: signals")                                                 # ... then the fault is seen
    assert d.override_pct == heavy and c.commanded_pct == heavy
