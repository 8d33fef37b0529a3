"""The operator's actions on learned limits are bounded on both sides, and every value stays finite (issue 36).

Through the same dispatch as `cmd/limits`, `millsense limits` and the local socket: the arguments checked by
`publish/limits_args.check_args`, then `ProcessMonitor.command` (what `Runner.limits_command` calls).
Finding 1: about 400 `widen --pct 500` overflowed the band, the entry margin and the energy band to inf, stored
as null; `limits show` raised OverflowError and the daemon never started again.
"""

from __future__ import annotations

import json
import math
from types import SimpleNamespace

import numpy as np
import pytest

from millsense.daemon.learning.envelope import LOW_MAX_FRACTION, MAX_WIDENING
from millsense.daemon.learning.monitor import ProcessMonitor
from millsense.daemon.publish.limits_args import ACTIONS, check_args
from tests.learning.synth import LEVELS_NM, Shape, Shop, learning

pytestmark = pytest.mark.quick

KEY = "1001/12/1"


def shop(alarms=None, **over) -> Shop:
    return Shop(ProcessMonitor(learning(**over), alarms=alarms), rng=np.random.default_rng(1), noise_pct=2.0)


def command(m: ProcessMonitor, args: dict) -> dict:
    """As every transport does: the one argument check, then the monitor's dispatch."""
    return m.command(check_args(args))


def numbers(value, where="") -> list[tuple[str, float]]:
    """Every number in a JSON-like value, with where it is."""
    if isinstance(value, bool) or value is None or isinstance(value, str):
        return []
    if isinstance(value, (int, float)):
        return [(where, float(value))]
    if isinstance(value, dict):
        return [n for k, v in value.items() for n in numbers(v, f"{where}.{k}")]
    return [n for i, v in enumerate(value) for n in numbers(v, f"{where}[{i}]")]


def restored(m: ProcessMonitor, **kw) -> ProcessMonitor:
    """A monitor restored from `m`'s exports as the history stores them (strict JSON text)."""
    limits = json.loads(json.dumps({k: m.export_limits(k) for k in m.keys}, allow_nan=False))
    tools = json.loads(json.dumps(m.export_tools(), allow_nan=False))
    return ProcessMonitor(m.learning, limits=limits, tools=tools, **kw)


def test_the_one_list_of_actions_is_shared_by_the_argument_check_and_the_dispatch():
    from millsense.daemon.learning import actions

    assert ACTIONS is actions.ACTIONS and {"low_off", "low_on"} <= set(ACTIONS)


def test_a_thousand_widens_leave_every_value_finite_and_the_key_restorable():
    s = shop()
    s.learn(5)
    m = s.monitor
    replies = [command(m, {"action": "widen", "key": KEY, "pct": 500}) for _ in range(1000)]
    assert all(r["ok"] is False for r in replies)   # 6x at once is past the cap: refused, nothing changed
    assert m.keys[KEY].envelope.widening() == pytest.approx(1.0)
    granted = 0
    for pct in (100, 50, 10, 5, 1) * 200:          # 1 000 more, each granted until the cap
        reply = command(m, {"action": "widen", "key": KEY, "pct": pct})
        granted += reply["ok"]
        if not reply["ok"]:
            assert "capped at 4× the learned width since the last relearn" in reply["error"], reply
    assert 0 < granted < 1000
    stored = m.export_limits(KEY)
    json.dumps(stored, allow_nan=False)
    found = numbers(stored)
    assert found and all(math.isfinite(v) and abs(v) < 1e6 for _, v in found), [n for n in found if not math.isfinite(n[1])]
    assert m.keys[KEY].envelope.widening() == pytest.approx(MAX_WIDENING, rel=0.02)
    # `limits show` and `list` answer; a restart restores it as it was, and it still checks
    shown = m.command({"action": "show", "key": KEY})
    json.dumps(shown, allow_nan=False)
    assert all(math.isfinite(v) for _, v in numbers(shown))
    twin = restored(m)
    assert twin.keys[KEY].state == "active" and twin.learned_limits_status()["set_aside"] == []
    assert twin.show(KEY) == m.show(KEY)
    s2 = Shop(twin, rng=np.random.default_rng(2), noise_pct=2.0)
    s2.process(Shape(levels_nm=(0.03, 0.03)))      # the tool broke before this part: no torque at all
    assert [e.level for e in s2.events()] == ["envelope_low"]


def test_widening_is_capped_since_the_last_relearn_and_the_refusal_says_the_cap():
    s = shop()
    s.learn(5)
    m = s.monitor
    assert command(m, {"action": "widen", "key": KEY, "pct": 100})["widening"] == pytest.approx(2.0)
    assert command(m, {"action": "widen", "key": KEY, "pct": 100})["widening"] == pytest.approx(4.0)
    refused = command(m, {"action": "widen", "key": KEY, "pct": 1})
    assert refused["ok"] is False and refused["changed_keys"] == []
    assert refused["error"].startswith(f"{KEY}: widening is capped at 4× the learned width since the last relearn")
    assert "no more" in refused["error"] and "relearn" in refused["error"]
    assert command(m, {"action": "narrow", "key": KEY, "pct": 50})["ok"]
    room = command(m, {"action": "widen", "key": KEY, "pct": 150})
    assert room["ok"] is False and "(now 2.00×" in room["error"] and "at most 100 % more" in room["error"]
    assert command(m, {"action": "widen", "key": KEY, "pct": 100})["ok"]
    assert m.limits_summary()["limits"][0]["widening"] == pytest.approx(4.0)
    assert command(m, {"action": "relearn", "key": KEY})["ok"]
    s.learn(5)
    assert command(m, {"action": "widen", "key": KEY, "pct": 300})["ok"]    # from the new learning: 4x again


def test_the_high_side_never_passes_the_fixed_limit():
    """[alarms] torque_limit_nm / force_limit_n trip every cut: a band above them would only be a number."""
    torque_limit = LEVELS_NM[1] * 1.4               # above the learned high side (mean + 25 %), under 4x wider
    force_limit = torque_limit * 150.0
    s = shop(alarms=SimpleNamespace(torque_limit_nm=torque_limit, force_limit_n=force_limit))
    s.learn(5)
    m = s.monitor
    before = m.show(KEY)["torque_high_nm"]
    assert max(h for h in before if h is not None) < torque_limit
    assert command(m, {"action": "widen", "key": KEY, "pct": 300})["ok"]
    after = m.show(KEY)
    assert max(h for h in after["torque_high_nm"] if h is not None) == pytest.approx(torque_limit, abs=1e-4)
    assert max(h for h in after["force_high_n"] if h is not None) <= force_limit + 1e-6
    # a false alarm far over it too (the fixed limit itself trips there)
    s.process(Shape(scale=3.0))
    reply = command(m, {"action": "false_alarm", "key": KEY})
    assert reply["ok"] and "bounded" in reply
    assert max(h for h in m.show(KEY)["torque_high_nm"] if h is not None) <= torque_limit + 1e-4
    # a restart under a lower limit holds the band under it (the config rules)
    twin = restored(m, alarms=SimpleNamespace(torque_limit_nm=LEVELS_NM[1] * 1.1, force_limit_n=None))
    assert max(h for h in twin.show(KEY)["torque_high_nm"] if h is not None) <= LEVELS_NM[1] * 1.1 + 1e-4


def test_the_low_side_never_drops_below_its_floor_so_a_broken_flute_is_still_caught():
    s = shop(noise_pct=0.0)
    s.learn(5)
    m = s.monitor
    learned = m.show(KEY)
    assert command(m, {"action": "widen", "key": KEY, "pct": 300})["ok"]
    shown = m.show(KEY)
    for k, (mean, low0, low) in enumerate(zip(shown["torque_mean_nm"], learned["torque_low_nm"], shown["torque_low_nm"])):
        if low0 is not None and low0 > 0:
            means = [v for v in shown["torque_mean_nm"][max(k - 1, 0): k + 2] if v is not None]
            assert low >= min(low0, (1 - LOW_MAX_FRACTION) * min(means)) - 1e-3 > 0, (k, low0, low)
    env = m.keys[KEY].envelope
    assert env.energy_low_j >= (1 - LOW_MAX_FRACTION) * env.energy_mean_j - 1e-6
    # a flute breaks in the deeper cut: 25 % less torque from process_rev 30 on (a two-flute cutter, [D] eq. 9)
    s.process(Shape(change=lambda k, t: t * 0.75 if k >= 30 else t))
    assert [(e.level, e.quantity) for e in s.events()] == [("envelope_low", "torque_nm")]


def test_low_off_is_its_own_command_shown_everywhere_and_low_on_turns_it_back():
    s = shop()
    s.learn(5)
    m = s.monitor
    reply = command(m, {"action": "low_off", "key": KEY})
    assert reply == {"ok": True, "action": "low_off", "key": KEY, "state": "active", "low_check": False,
                     "changed_keys": [KEY], "tools_changed": []}
    again = command(m, {"action": "low_off", "key": KEY})
    assert again["ok"] is False and "already off" in again["error"]
    assert m.limits_summary()["limits"][0]["low_check"] is False
    assert m.show(KEY)["low_check"] is False
    assert m.learned_limits_status() == {"set_aside": [], "low_off": [KEY]}
    # no envelope_low of any kind while off: a broken tool, a missing part; envelope_high still checks
    n = len(s.estimates)
    s.process(Shape(change=lambda k, t: 0.03 if k >= 20 else t))
    s.process(Shape(missing_part=True))
    assert s.events() == []
    assert all(e["envelope_low_nm"] is None for e in s.estimates[n:])
    s.process(Shape(scale=1.5))
    assert [e.level for e in s.events()] == ["envelope_high"]
    # kept across a restart and a relearn; low_on checks again
    twin = restored(m)
    assert twin.learned_limits_status()["low_off"] == [KEY]
    assert command(m, {"action": "relearn", "key": KEY})["ok"]
    assert m.learned_limits_status()["low_off"] == [KEY]
    s.learn(5)
    assert command(m, {"action": "low_on", "key": KEY})["low_check"] is True
    s.process(Shape(missing_part=True))
    assert [(e.level, e.quantity) for e in s.events()][-1] == ("envelope_low", "entry")
    assert m.learned_limits_status()["low_off"] == []


def test_low_off_needs_a_known_key_and_nothing_else_turns_envelope_low_off():
    s = shop()
    s.learn(5)
    m = s.monitor
    assert "no learned limits for 9/9/9" in command(m, {"action": "low_off", "key": "9/9/9"})["error"]
    with pytest.raises(ValueError, match="low_off takes no pct"):
        check_args({"action": "low_off", "key": KEY, "pct": 10})
    with pytest.raises(ValueError, match="key must be"):
        check_args({"action": "low_on"})
    # widening as far as it goes, and marking a broken tool's alarm false, leave the low side checking
    assert command(m, {"action": "widen", "key": KEY, "pct": 300})["ok"]
    s.process(Shape(change=lambda k, t: 0.03 if k >= 20 else t))
    assert [e.level for e in s.events()] == ["envelope_low"]
    reply = command(m, {"action": "false_alarm", "key": KEY})
    assert reply["ok"] and "low-off" in reply["bounded"]
    assert m.keys[KEY].low_check is True
    s.process(Shape(change=lambda k, t: 0.03 if k >= 20 else t))
    assert [e.level for e in s.events()] == ["envelope_low", "envelope_low"]


@pytest.mark.parametrize("pct", [float("nan"), float("inf"), float("-inf"), 1e400, 10.0, "10", True, None])
def test_json_nan_infinity_and_fractions_are_refused_as_pct(pct):
    args = json.loads(json.dumps({"action": "widen", "key": KEY, "pct": pct}))   # NaN and Infinity as JSON has them
    with pytest.raises(ValueError, match="pct must be a (finite )?whole number"):
        check_args(args)


def test_the_monitor_itself_refuses_a_non_finite_pct():
    """A caller that skipped the argument check (the runner's own) still changes nothing."""
    s = shop()
    s.learn(5)
    for pct in (math.nan, math.inf, 1e400):
        reply = s.monitor.command({"action": "widen", "key": KEY, "pct": pct})
        assert reply["ok"] is False and "finite number" in reply["error"]
    assert s.monitor.keys[KEY].envelope.widening() == pytest.approx(1.0)
