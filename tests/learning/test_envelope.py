"""Envelope statistics checked against numbers computed here, independently, in plain loops."""

from __future__ import annotations

import json
import math
import statistics

import numpy as np
import pytest

from millsense.daemon.learning.envelope import Envelope, Taught, learn
from tests.learning.synth import learning

pytestmark = pytest.mark.quick

SETTINGS = learning()
SIGMA, PCT, LOW_PCT, FLOOR_NM, FLOOR_N = 4.0, 25.0, 12.5, 0.5, 50.0


def _taught(seed: int = 3) -> list[Taught]:
    rng = np.random.default_rng(seed)
    out = []
    for i, length in enumerate((40, 44, 41, 38, 47)):
        torque = 3.0 + np.sin(np.arange(length) / 5.0) + rng.normal(0.0, 0.2, length)
        torque[length // 2:] += 2.0   # a depth step
        force = 150.0 * torque
        torque[7 + i] = np.nan         # one invalid revolution each, at different places
        force[7 + i] = np.nan
        if i == 2:
            force[20] = np.nan         # process 2 did not know its force at k = 20
        out.append(Taught(torque, force, 9 + i % 3, float(2 * math.pi * np.nansum(torque))))
    return out


def _by_hand(rows: list[list[float]], length: int, pct: float, low_pct: float, floor: float):
    mean, std, h_hi, h_lo = [], [], [], []
    for k in range(length):
        xs = [r[k] for r in rows if k < len(r) and math.isfinite(r[k])]
        m = sum(xs) / len(xs)
        s = math.sqrt(sum((x - m) ** 2 for x in xs) / (len(xs) - 1)) if len(xs) > 1 else 0.0
        mean.append(m)
        std.append(s)
        h_hi.append(max(SIGMA * s, pct / 100 * abs(m), floor))
        h_lo.append(max(SIGMA * s, low_pct / 100 * abs(m), floor))
    high = [max(mean[j] + h_hi[j] for j in range(max(k - 1, 0), min(k + 2, length))) for k in range(length)]
    low = [max(0.0, min(mean[j] - h_lo[j] for j in range(max(k - 1, 0), min(k + 2, length)))) for k in range(length)]
    return mean, std, high, low


def test_torque_band_matches_the_definition():
    taught = _taught()
    env = learn(taught, SETTINGS)
    assert env.length == 41    # median_low of 38, 40, 41, 44, 47 (their mean is 42)
    mean, std, high, low = _by_hand([list(t.torque_nm) for t in taught], 41, PCT, LOW_PCT, FLOOR_NM)
    np.testing.assert_allclose(env.torque.mean, mean, rtol=1e-12)
    np.testing.assert_allclose(env.torque.std, std, rtol=1e-12)
    np.testing.assert_allclose(env.torque.high, high, rtol=1e-12)
    np.testing.assert_allclose(env.torque.low, low, rtol=1e-12)


def test_force_band_only_where_every_process_knew_its_force():
    taught = _taught()
    env = learn(taught, SETTINGS)
    assert env.force.high[20] is None and env.force.low[20] is None
    assert math.isnan(env.force.mean[20])
    rows = [list(t.force_n) for t in taught]
    mean, _, high, _ = _by_hand(rows, 41, PCT, LOW_PCT, FLOOR_N)
    for k in (5, 18, 30):   # away from k = 20 (its neighbours see the missing mean)
        assert env.force.mean[k] == pytest.approx(mean[k], rel=1e-12)
        assert env.force.high[k] == pytest.approx(high[k], rel=1e-12)


def test_no_force_band_when_no_process_knew_force():
    taught = [Taught(t.torque_nm, np.full_like(t.force_n, np.nan), t.entry_rev, t.energy_j) for t in _taught()]
    assert learn(taught, SETTINGS).force is None


def test_entry_and_energy_statistics():
    taught = _taught()
    env = learn(taught, SETTINGS)
    entries = [t.entry_rev for t in taught]
    energies = [t.energy_j for t in taught]
    assert env.entry_mean == pytest.approx(sum(entries) / 5)
    assert env.entry_std == pytest.approx(statistics.stdev(entries))
    assert env.entry_max == max(entries)
    assert env.energy_mean_j == pytest.approx(sum(energies) / 5)
    assert env.energy_std_j == pytest.approx(statistics.stdev(energies))
    e_mean = sum(energies) / 5
    assert env.energy_low_j == pytest.approx(e_mean - max(SIGMA * statistics.stdev(energies), LOW_PCT / 100 * e_mean))
    margin = max(3, SIGMA * statistics.stdev(entries), PCT / 100 * sum(entries) / 5)
    assert env.entry_deadline == math.ceil(max(entries) + margin)


def test_a_process_one_revolution_off_at_a_depth_step_stays_inside():
    flat = [Taught(np.array([2.0] * 10 + [4.0] * 10), np.full(20, np.nan), 5, 1.0) for _ in range(5)]
    env = learn(flat, learning(min_width_pct=5.0, min_width_nm=0.1))
    early = [2.0] * 9 + [4.0] * 11
    late = [2.0] * 11 + [4.0] * 9
    for k in range(20):
        for seen in (early[k], late[k]):
            assert env.torque.low[k] <= seen <= env.torque.high[k]


def test_widen_and_narrow_scale_the_half_width_and_narrow_stops_at_the_floors():
    env = learn(_taught(), SETTINGS)
    k = 10
    mean, h = env.torque.mean[k], env.torque.h_high.copy()
    env.widen(20.0)
    np.testing.assert_allclose(env.torque.h_high, h * 1.2)
    env.narrow(90.0)
    floor = np.maximum(PCT / 100 * np.abs(env.torque.mean), FLOOR_NM)
    np.testing.assert_allclose(env.torque.h_high, np.maximum(h * 1.2 * 0.1, floor))
    assert env.torque.high[k] >= mean + floor[k] - 1e-12
    assert [a["action"] for a in env.adjustments] == ["widen", "narrow"]


def test_false_alarm_widens_where_the_values_were_seen():
    env = learn(_taught(), SETTINGS)
    seen = {12: env.torque.high[12] * 1.3, 13: env.torque.high[13] * 1.3}
    before_far = env.torque.high[30]
    env.false_alarm("envelope_high", "torque_nm", seen)
    for k, v in seen.items():
        assert env.torque.high[k] >= v * 1.1 - 1e-9
    assert env.torque.high[30] == before_far
    low_seen = {25: env.torque.mean[25] * 0.9}      # 10 % under the mean: within the low side's bound
    assert env.false_alarm("envelope_low", "torque_nm", low_seen)
    assert env.torque.low[25] <= low_seen[25] * 0.9 + 1e-9
    deadline = env.entry_deadline
    assert env.false_alarm("envelope_low", "entry", {0: deadline + 2.0})
    assert env.entry_deadline > deadline + 2
    assert env.false_alarm("envelope_low", "cutting_energy_j", {0: env.energy_mean_j * 0.9})
    assert env.energy_low_j <= env.energy_mean_j * 0.9 * 0.9 + 1e-9


def test_a_false_alarm_never_takes_the_band_past_its_bounds():
    """A value far outside (a broken tool marked false) widens only to the bounds, and says so: the low side
    stays at least 80 % of the mean, the high side within 4x the learned width, the entry margin and the
    energy band too. Before, marking a broken tool's alarm false took the low side to 0: envelope_low off."""
    env = learn(_taught(), SETTINGS)
    k = 25
    mean, low_before = env.torque.mean, env.torque.low[k]
    assert not env.false_alarm("envelope_low", "torque_nm", {k: 0.0})
    # never more than 20 % under the mean, unless it was learned lower (a noisy process: sigma · std)
    assert env.torque.low[k] >= min(low_before, 0.8 * min(mean[k - 1: k + 2])) - 1e-9 > 0
    assert not env.false_alarm("envelope_high", "torque_nm", {k: 1e6})
    assert env.torque.h_high[k] <= 4.0 * max(SIGMA * env.torque.std[k], env.torque.floor_high[k]) + 1e-9
    margin = env.entry_margin
    assert not env.false_alarm("envelope_low", "entry", {0: 1e6})
    assert env.entry_margin <= 4.0 * margin + 1e-9
    energy_low = env.energy_low_j
    assert not env.false_alarm("envelope_low", "cutting_energy_j", {0: 0.0})
    assert env.energy_low_j >= min(energy_low, 0.8 * env.energy_mean_j) - 1e-9 > 0


def test_round_trip_through_json_keeps_every_number():
    env = learn(_taught(), SETTINGS)
    env.widen(10.0)
    env.false_alarm("envelope_high", "torque_nm", {5: 50.0})
    text = json.dumps(env.to_dict(), allow_nan=False)
    back = Envelope.from_dict(json.loads(text))
    assert back.to_dict() == env.to_dict()
    assert back.torque.high == env.torque.high and back.force.low == env.force.low
    assert back.entry_deadline == env.entry_deadline and back.energy_low_j == env.energy_low_j
    t = _taught()[0]
    assert Taught.from_dict(json.loads(json.dumps(t.to_dict(), allow_nan=False))).to_dict() == t.to_dict()
