"""Learned limits and breakage while the CNC's feed override moves (issue 15).

Processes are built here along the programmed path: a profile of torque per
programmed revolution (air, an entry, depth steps 2 -> 3 -> 2.5 mm as torque
levels, an exit, air). A process run at override u (= ovr/100) advances u
programmed revolutions per revolution and cuts with u^gain times the torque
(torque ~ t^(1+p), [D] eq. 8). Learned at 100 %, judged at 130 % (or while the
override ramps at a controller's rate): no false alarm; a broken flute at
130 % is still caught; energy (wear) stays at the learned baseline.
"""

from __future__ import annotations

import math
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from millsense.daemon.learning.monitor import ProcessMonitor
from millsense.daemon.pipeline.alarms import AlarmEngine
from tests.learning.synth import CUTTING_NM, FORCE_PER_NM, SAMPLES_PER_REV, ctx, learning

pytestmark = pytest.mark.quick

GAIN = 1.0 - 0.4362          # 1 + ks_exp of SM45C ([D] Table 2), as the daemon derives it
KEY = "1001/12/1"
AIR_NM = 0.03
# programmed revolutions of each part of the path, and its torque at the programmed feed
PATH = ((10, AIR_NM), (1, 2.0), (20, 4.0), (20, 6.0), (20, 5.0), (1, 2.5), (6, AIR_NM))


def profile(x: float) -> float:
    """Torque at the programmed feed at path position x (programmed revolutions)."""
    start = 0.0
    for length, level in PATH:
        if x < start + length:
            return level
        start += length
    return AIR_NM


def path_length() -> float:
    return float(sum(length for length, _ in PATH))


class Run:
    """Feeds processes to a monitor the way the estimator thread would."""

    def __init__(self, monitor: ProcessMonitor, seed: int = 1, noise_pct: float = 2.0):
        self.monitor = monitor
        self.rng = np.random.default_rng(seed)
        self.noise_pct = noise_pct
        self.rev = 0
        self.events: list = []
        self.processes: list[dict] = []
        self.estimates: list[dict] = []

    def process(self, override, flute_broken_at: float | None = None) -> None:
        """One process; `override(i)` gives revolution i's override in %; a flute breaks at path position x."""
        x, i, context = 0.0, 0, ctx()
        while x < path_length():
            pct = float(override(i))
            u = pct / 100.0
            # the revolution's mean of the profile over [x, x + u] (a step inside it is shared)
            points = np.linspace(x, x + u, 9)
            nominal = float(np.mean([profile(p) for p in points]))
            torque = nominal * u ** GAIN if nominal > AIR_NM else nominal
            if flute_broken_at is not None and x >= flute_broken_at and nominal > AIR_NM:
                torque *= 0.78          # [D] eq. 9: the next flute takes a double chip at a lower K_s
            torque = torque * (1.0 + self.noise_pct / 100.0 * self.rng.standard_normal())
            self.rev += 1
            est = {"rev": self.rev, "seq_end": self.rev * SAMPLES_PER_REV, "samples": SAMPLES_PER_REV,
                   "torque_nm": torque, "force_n": torque * FORCE_PER_NM if torque >= CUTTING_NM else None,
                   "cutting": torque >= CUTTING_NM, "valid": True, "feed_override_pct": pct}
            step = self.monitor.on_revolution(est, context)
            self.estimates.append(est)
            self.events += step.events
            self.processes += step.processes
            x += u
            i += 1
        step = self.monitor.on_context(replace(context, cycle=False), self.rev * SAMPLES_PER_REV)
        self.events += step.events
        self.processes += step.processes


def learned(gain: float = GAIN, seed: int = 1) -> Run:
    run = Run(ProcessMonitor(learning(), gain=gain), seed=seed)
    for _ in range(5):
        run.process(lambda i: 100.0)
    assert run.processes[-1]["envelope"] == "active" and run.events == []
    return run


def ramp(start: float, stop: float, per_rev: float, from_rev: int):
    """An override held at `start`, then moving towards `stop` by `per_rev` % a revolution (a rate limit)."""
    def at(i: int) -> float:
        if i < from_rev:
            return start
        step = (i - from_rev + 1) * per_rev
        return min(stop, start + step) if stop >= start else max(stop, start - step)
    return at


def test_learned_at_100_judged_at_130_through_the_same_depth_steps_no_false_alarm():
    run = learned()
    n = len(run.estimates)
    run.process(lambda i: 130.0)
    assert run.events == [], [(e.level, e.quantity, e.detail) for e in run.events]
    last = run.processes[-1]
    assert last["verdict"] == "good"
    # the energy of the same cut at the programmed feed: the wear figure does not move with the override
    assert last["energy_ratio"] == pytest.approx(1.0, abs=0.03)
    # the band published with each estimate is in the revolution's own terms: its torque sits inside
    checked = [e for e in run.estimates[n:] if e["envelope_high_nm"] is not None and e["cutting"]]
    assert len(checked) >= 40
    for e in checked:
        assert e["envelope_low_nm"] <= e["torque_nm"] <= e["envelope_high_nm"], e
    # the path is 78 programmed revolutions: at 130 % the process indexes reach its end, not 78/1.3
    assert max(e["process_rev"] for e in run.estimates[n:] if e["process_rev"] is not None) >= 60


def test_a_controller_ramp_through_the_steps_raises_nothing():
    run = learned()
    # up at 10 %/rev (100 %/s at 600 rpm) to 140, then down to 70 mid-cut, as the AFC would in a deeper step
    moves = [ramp(100.0, 140.0, 10.0, 12), ramp(140.0, 70.0, 10.0, 30)]
    run.process(lambda i: moves[0](i) if i < 30 else moves[1](i))
    assert run.events == [], [(e.level, e.quantity, e.detail) for e in run.events]
    assert run.processes[-1]["verdict"] == "good"
    assert run.processes[-1]["energy_ratio"] == pytest.approx(1.0, abs=0.03)


def test_a_broken_flute_at_130_is_still_caught():
    run = learned()
    run.process(lambda i: 130.0, flute_broken_at=45.0)   # in the 6.0 N·m step
    lows = [e for e in run.events if e.level == "envelope_low"]
    assert lows and lows[0].quantity in ("torque_nm", "force_n"), [(e.level, e.quantity) for e in run.events]
    assert dict(lows[0].detail)["process_rev"] >= 34   # after the break, on the path (45 - 11 at entry)
    assert not [e for e in run.events if e.level == "envelope_high"]


def test_energy_at_130_without_normalisation_would_read_as_a_different_tool():
    """The premise of the normalisation: at 130 % the raw energy is 1.3^(gain-1) = 0.89 of the learned."""
    run = learned()
    n = len(run.estimates)
    run.process(lambda i: 130.0)
    raw = 2 * math.pi * sum(e["torque_nm"] for e in run.estimates[n:])
    # the summary's energy is the normalised one; the raw one is what a count of revolutions would give
    assert raw / run.processes[-1]["energy_j"] == pytest.approx(1.3 ** (GAIN - 1.0), rel=0.02)
    assert 1.3 ** (GAIN - 1.0) < 1.0 - 0.1   # outside the energy band's 12.5 % floor with noise: an alarm


def test_at_100_the_progress_index_is_the_revolution_count():
    run = Run(ProcessMonitor(learning(), gain=GAIN))
    run.process(lambda i: 100.0)
    ks = [e["process_rev"] for e in run.estimates if e["process_rev"] is not None]
    # the entry revolution itself is known as such one revolution later: the published ones start at 1
    assert ks == list(range(1, len(ks) + 1))


def test_learned_mean_is_the_band_mean_over_the_cut():
    run = Run(ProcessMonitor(learning(), gain=GAIN), noise_pct=0.0)
    assert run.monitor.learned_mean(KEY, "torque_nm") is None
    for _ in range(5):
        run.process(lambda i: 100.0)
    mean = run.monitor.learned_mean(KEY, "torque_nm")
    # the cut is 20 revolutions each at 4, 6 and 5 N·m (the entry and exit halves are not "the cut")
    assert mean == pytest.approx(5.0, rel=0.02)
    assert run.monitor.learned_mean(KEY, "force_n") == pytest.approx(5.0 * FORCE_PER_NM, rel=0.02)
    assert run.monitor.learned_mean("9/9/9", "torque_nm") is None


def test_learned_mean_waits_for_accept_when_confirm_is_set():
    run = Run(ProcessMonitor(learning(confirm=True), gain=GAIN), noise_pct=0.0)
    for _ in range(5):
        run.process(lambda i: 100.0)
    assert run.monitor.learned_mean(KEY, "torque_nm") is None
    run.monitor.command({"action": "accept", "key": KEY})
    assert run.monitor.learned_mean(KEY, "torque_nm") == pytest.approx(5.0, rel=0.02)


# -- breakage while the feed moves (alarms.BreakageTrack) ---------------------------------------------

PROGRAMMED_FPT_MM = 0.1


def _engine(drop_pct: float) -> AlarmEngine:
    engine = AlarmEngine(SimpleNamespace(breakage_drop_pct=drop_pct, breakage_min_torque_nm=1.0))
    engine.breakage.gain = GAIN
    return engine


def _breakage(engine: AlarmEngine, overrides: list[float], torque_at_100: list[float], fpt: bool = True) -> list:
    """Estimates as the estimator makes them now: feed per tooth = programmed x override."""
    events = []
    for i, (pct, t100) in enumerate(zip(overrides, torque_at_100)):
        u = pct / 100.0
        est = {"rev": i + 1, "seq_end": (i + 1) * 100, "valid": True, "cutting": True, "spindle_rpm": 600.0,
               "torque_nm": t100 * u ** GAIN, "feed_per_tooth_mm": PROGRAMMED_FPT_MM * u if fpt else None,
               "feed_override_pct": pct}
        events += [e for e in engine.on_revolution(est) if e.level == "tool_breakage"]
    return events


def test_an_override_ramp_down_is_not_a_breakage():
    # no feed per tooth known (no configured feed): a ramp at <= 10 %/rev drops the raw torque 17 % in
    # steps each within the steadiness tolerance, which a 15 % drop limit took for a broken flute
    overrides = [100.0] * 4 + [93.0, 84.0, 75.0, 70.0] + [70.0] * 6
    assert _breakage(_engine(15.0), overrides, [10.0] * len(overrides), fpt=False) == []


def test_a_flute_breaking_during_an_override_ramp_up_is_caught():
    overrides = [100.0] * 4 + [110.0, 120.0, 130.0, 130.0, 130.0, 130.0]
    torque = [10.0] * 6 + [7.5] * 4          # the flute breaks at revolution 7, while the override ramps
    events = _breakage(_engine(20.0), overrides, torque)
    assert [e.level for e in events] == ["tool_breakage"]
    # the limit is in the revolution's terms (the learned level at 100 % times 1.3^gain), like the torque
    assert events[0].limit == pytest.approx(10.0 * 0.8 * 1.3 ** GAIN, rel=1e-6)


def test_a_flute_breaking_at_a_steady_130_is_caught_and_the_override_alone_is_not():
    steady = [130.0] * 10
    assert _breakage(_engine(20.0), steady, [10.0] * 10) == []
    assert len(_breakage(_engine(20.0), steady, [10.0] * 5 + [7.5] * 5)) == 1
