"""The physics' expected band (issue 41) on the process monitor, from synthetic revolutions: which revolutions
are judged, expected_high / expected_low, the teaching gate, the operator's actions, and a key without an
operation behaving as before. The load of a synthetic revolution is the forward model's own expectation times a
factor (the cut deeper, shallower, ...), with noise."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from millsense.daemon.config.load import load_config_text
from millsense.daemon.learning.expected import KEPT_WARNING_PROCESSES
from millsense.daemon.pipeline.run_core import expected_band
from millsense.daemon.learning.envelope import MAX_WIDENING
from millsense.daemon.learning.monitor import ProcessMonitor
from tests.config.helpers import base, dumps
from tests.learning.synth import ctx

pytestmark = pytest.mark.quick

KEY = "1001/5/1"
RPM = 2000.0
FLUTES = 3
FZ_MM = 0.1
RADIUS_MM = 4.0
# revolutions in cut before the first steady one: a tool radius of path at fz·N per revolution
ENTRY_REVS = int(np.ceil(RADIUS_MM / (FZ_MM * FLUTES)))
# the first judged revolution: the one in which the cutter's centre crosses the part's face (its path ends a tool
# radius past the first touch)
FIRST_JUDGED = ENTRY_REVS - 1


def settings(engagement: str = "constant", operations: dict | None = None, **learning):
    d = base()
    d["tools"] = {"5": {"diameter_mm": 2 * RADIUS_MM, "flutes": FLUTES}}
    d["operations"] = operations if operations is not None else {
        KEY: {"ap_mm": 2.0, "fz_mm": FZ_MM, "mode": "slot", "engagement": engagement, "spindle_rpm": RPM}}
    d.setdefault("learning", {}).update(learning)
    return load_config_text(dumps(d))


REFERENCE = expected_band(settings())
TOL = REFERENCE.tolerance_pct / 100.0   # the settings' tolerance (the lead sets its default): factors follow it


class Cell:
    """A monitor with the physics of `settings()`, fed processes of KEY."""

    def __init__(self, cfg=None, noise_pct: float = 1.0, seed: int = 3):
        self.cfg = cfg or settings()
        self.band = expected_band(self.cfg)
        self.monitor = ProcessMonitor(self.cfg.learning, alarms=self.cfg.alarms, expected=self.band)
        self.rng = np.random.default_rng(seed)
        self.noise = noise_pct / 100.0
        self.rev = 0
        self.steps = []
        self.estimates = []

    def expected(self, override_pct: float = 100.0):
        """KEY's expected load as `settings()` declares it (the synthetic loads are made from it)."""
        return REFERENCE.expected(KEY, RPM, override_pct)

    def est(self, factor: float, override_pct: float | None = 100.0, cutting: bool = True) -> dict:
        self.rev += 1
        exp = self.expected(override_pct if override_pct is not None else 100.0)
        n = 1.0 + self.noise * self.rng.standard_normal()
        torque, force = (exp.torque_nm * factor * n, exp.force_n * factor * n) if cutting else (0.01, None)
        return {"rev": self.rev, "seq_end": self.rev * 100, "samples": 100, "torque_nm": torque, "force_n": force,
                "cutting": cutting, "valid": True, "spindle_rpm": RPM, "feed_override_pct": override_pct,
                "feed_per_tooth_mm": None}

    def feed(self, est: dict, context=None) -> None:
        self.steps.append(self.monitor.on_revolution(est, context or ctx(1001, 5, 1)))
        self.estimates.append(est)

    def process(self, factors: list[float], override=100.0, air: int = 5, key_ctx=None) -> None:
        """Air, the cut (one factor per revolution; `override` one value or one per revolution), air, cycle off."""
        context = key_ctx or ctx(1001, 5, 1)
        overrides = override if isinstance(override, list) else [override] * len(factors)
        for _ in range(air):
            self.feed(self.est(0.0, overrides[0], cutting=False), context)
        for f, o in zip(factors, overrides):
            self.feed(self.est(f, o), context)
        for _ in range(air):
            self.feed(self.est(0.0, overrides[-1], cutting=False), context)
        self.steps.append(self.monitor.on_context(replace(context, cycle=False), self.rev * 100))

    def cut(self, factor: float, revs: int = 60) -> list[float]:
        """A cut entering over a tool radius of path (the load growing), then steady at `factor`."""
        return [factor * (i + 1) / ENTRY_REVS for i in range(ENTRY_REVS)] + [factor] * (revs - ENTRY_REVS)

    def events(self, level: str | None = None) -> list:
        return [e for s in self.steps for e in s.events if level is None or e.level == level]

    def notes(self, name: str) -> list:
        return [n for s in self.steps for n in s.notes if n[0] == name]

    def processes(self) -> list[dict]:
        return [p for s in self.steps for p in s.processes]


def first_event_rev(cell: Cell, level: str) -> int:
    """The revolution (counted from the cut's first) that raised `level`."""
    ev = cell.events(level)[0]
    first_cut = next(e["rev"] for e in cell.estimates if e["cutting"])
    return ev.rev - first_cut


def test_correct_first_parts_raise_nothing_and_teach():
    cell = Cell()
    for _ in range(6):
        cell.process(cell.cut(1.0))
    assert cell.events() == []
    verdicts = [p["verdict"] for p in cell.processes()]
    assert verdicts[:5] == ["learning"] * 5 and verdicts[5] == "good"


def test_a_deeper_cut_trips_expected_high_within_three_steady_revolutions_and_latches():
    cell = Cell()
    cell.process(cell.cut(1.8))
    highs = cell.events("expected_high")
    assert len(highs) == 1
    ev = highs[0]
    need = cell.cfg.learning.high_revolutions
    # the first judged revolution is FIRST_JUDGED into the cut; `need` of them in a row trip
    assert first_event_rev(cell, "expected_high") == FIRST_JUDGED + need - 1
    assert ev.trips and ev.quantity == "torque_nm"
    detail = dict(ev.detail)
    exp = cell.expected()
    assert detail["expected"] == pytest.approx(exp.torque_nm, rel=1e-3)
    tol = cell.cfg.learning.physics_tolerance_pct / 100.0
    assert ev.limit == pytest.approx(exp.torque_nm * (1 + tol), rel=1e-3)
    assert "> expected" in detail["reason"] and "ap 2 mm" in detail["reason"] and "2000 rpm" in detail["reason"]
    assert cell.processes()[0]["verdict"] == "expected_high"
    # latched: no clear at the end of the process, only the reset clears it
    assert not [e for e in cell.events("clear") if e.level == "clear"]
    assert "expected_high" in cell.monitor.active()
    cleared = cell.monitor.reset()
    assert [c.level for c in cleared] == ["clear", "clear"] or [c.level for c in cleared] == ["clear"]
    assert cell.monitor.active() == {}


def test_the_entry_is_not_judged_even_far_above_the_band():
    """Within a tool radius of the entry nothing is judged: an overshoot there raises nothing."""
    cell = Cell()
    cut = [3.0] * FIRST_JUDGED + [1.0] * 40
    cell.process(cut)
    assert cell.events() == []


def test_a_varying_operation_cut_shallower_than_its_maximum_raises_nothing():
    cell = Cell(settings("varying"))
    cell.process(cell.cut(0.5))
    cell.process(cell.cut(0.6) + [1.0] * 30 + [1.0 - 0.6 * TOL] * 30)   # a depth step up, then a step down within the band
    assert cell.events() == []


def test_constant_engagement_low_holds_the_feed_varying_only_warns():
    for engagement, holds in (("constant", True), ("varying", False)):
        cell = Cell(settings(engagement))
        # constant: shallower from the start; varying: a sudden loss (a flute) from inside the band
        below = 1.0 - 2.0 * TOL
        cell.process(cell.cut(below) if holds else cell.cut(1.0) + [below] * 20)
        lows = cell.events("expected_low")
        assert len(lows) == 1, engagement
        assert lows[0].trips is holds
        at = FIRST_JUDGED + cell.cfg.learning.low_revolutions - 1 + (0 if holds else 60 - FIRST_JUDGED)
        assert first_event_rev(cell, "expected_low") == at
        assert "< expected" in dict(lows[0].detail)["reason"]
        cleared = [e for e in cell.events("clear")]
        assert bool(cleared) is (not holds)   # a warning clears when its process ends; a hold latches


def test_a_flute_lost_mid_cut_trips_low_but_a_gradual_exit_does_not():
    cell = Cell()
    # the engagement shrinking as the tool leaves: a fraction of the tolerance per revolution, down to nothing
    exit_ramp = [1.0 - 0.16 * TOL * i for i in range(1, int(1 / (0.16 * TOL)))]
    cell.process(cell.cut(1.0) + exit_ramp)
    assert cell.events("expected_low") == []
    cell.process(cell.cut(1.0) + [1.0 - 1.8 * TOL] * 10)  # one revolution from inside the band to far below it
    assert len(cell.events("expected_low")) == 1


def test_an_unknown_override_arms_nothing_and_says_so_once_per_process():
    cell = Cell()
    cell.process(cell.cut(1.8), override=None)
    cell.process(cell.cut(1.8), override=None)
    assert cell.events() == []
    notes = cell.notes("learning.expected_unarmed")
    assert len(notes) == 2 and "override is unknown" in notes[0][1]["reason"]


def test_the_expectation_follows_the_override_and_a_moving_override_is_not_judged():
    cell = Cell()
    # the feed override at 60 %: the load of a right cut is what the physics expects at 60 % (lower)
    low_ratio = cell.expected(60.0).torque_nm / cell.expected(100.0).torque_nm
    assert low_ratio < 0.8   # else this test would not tell the two apart
    cell.process(cell.cut(1.0), override=60.0)   # est() scales the load by the expectation at 60 %
    assert cell.events() == []
    # the override stepping every revolution: nothing is steady, so a load far off is not judged
    n = 60
    steps = [100.0 if i % 2 else 90.0 for i in range(n)]
    cell.process(cell.cut(1.8, n), override=steps)
    assert cell.events() == []


def test_a_process_outside_the_band_does_not_teach_and_accept_teaches_it():
    cell = Cell(settings(processes=2))
    for _ in range(KEPT_WARNING_PROCESSES):
        cell.process(cell.cut(1.8))
        cell.monitor.reset()
    assert [p["verdict"] for p in cell.processes()] == ["expected_high"] * KEPT_WARNING_PROCESSES
    assert [p["learned"] for p in cell.processes()] == [0] * KEPT_WARNING_PROCESSES
    warned = cell.notes("learning.kept_from_teaching")
    assert len(warned) == 1 and warned[0][1]["key"] == KEY
    summary = cell.monitor.limits_summary()["limits"][0]
    assert summary["kept_from_teaching"] == KEPT_WARNING_PROCESSES
    reply = cell.monitor.command({"action": "accept", "key": KEY})
    assert reply["ok"] and reply["changed_keys"] == [KEY]
    assert len(cell.monitor.keys[KEY].taught) == 1 and cell.monitor.keys[KEY].held_back is None


def test_false_alarm_widens_the_expected_band_and_teaches_the_process():
    cell = Cell()
    above = 1.0 + 1.6 * TOL   # outside the band, within what a false alarm may widen it to (4x)
    cell.process(cell.cut(above))
    assert len(cell.events("expected_high")) == 1
    cell.monitor.reset()
    reply = cell.monitor.command({"action": "false_alarm", "key": KEY})
    assert reply["ok"], reply
    assert len(cell.monitor.keys[KEY].taught) == 1
    n = len(cell.events())
    cell.process(cell.cut(above))
    assert cell.events()[n:] == []
    assert cell.processes()[-1]["verdict"] == "learning"


def test_widen_and_narrow_keep_the_bounds():
    cell = Cell()
    assert cell.monitor.command({"action": "widen", "key": KEY, "pct": 100})["ok"]
    refused = cell.monitor.command({"action": "widen", "key": KEY, "pct": 150})
    assert not refused["ok"] and f"{MAX_WIDENING:g}×" in refused["error"]
    assert cell.monitor.keys[KEY].expected_widening.high == pytest.approx(2.0)
    assert cell.monitor.command({"action": "narrow", "key": KEY, "pct": 90})["ok"]
    assert cell.monitor.keys[KEY].expected_widening.high == 1.0   # never below the configured tolerance
    assert not cell.monitor.command({"action": "widen", "key": KEY, "pct": 0})["ok"]


def test_low_off_stops_expected_low_too():
    cell = Cell()
    assert cell.monitor.command({"action": "low_off", "key": KEY})["ok"]
    cell.process(cell.cut(0.5))
    assert cell.events("expected_low") == []


def test_show_gives_the_expected_load_beside_the_learned_mean_and_their_ratio():
    cell = Cell(settings(processes=2), noise_pct=0.0)
    shown = cell.monitor.show(KEY)   # before anything: at the programmed speed, 100 %
    exp = cell.expected()
    assert shown["expected_torque_nm"] == pytest.approx(exp.torque_nm, rel=1e-3)
    assert shown["expected_at"]["from"] == "programmed" and shown["learned_mean_torque_nm"] is None
    for _ in range(2):   # long cuts: the learned mean is over the whole cut, its entry's growing load included
        cell.process(cell.cut(1.0 + 0.4 * TOL, 400))
    shown = cell.monitor.command({"action": "show", "key": KEY})
    assert shown["ok"] and shown["state"] == "active"
    assert shown["expected_at"]["from"] == "last steady revolution"
    assert shown["learned_to_expected_torque"] == pytest.approx(1.0 + 0.4 * TOL, rel=0.03)


def test_a_key_without_an_operation_behaves_as_before():
    """The same revolutions through a monitor with operations for another key and one without any physics:
    the same events, processes and estimates."""
    other = settings(operations={"1001/5/9": {"ap_mm": 2.0, "fz_mm": FZ_MM, "mode": "slot", "engagement": "constant"}})
    with_physics = Cell(other)
    plain = Cell(other)
    plain.monitor = ProcessMonitor(other.learning, alarms=other.alarms)
    for cell in (with_physics, plain):
        for _ in range(7):
            cell.process(cell.cut(1.0))
        cell.process(cell.cut(1.8))
    assert [(e.level, e.quantity, e.value) for e in with_physics.events()] == \
        [(e.level, e.quantity, e.value) for e in plain.events()]
    assert with_physics.processes() == plain.processes()
    assert with_physics.estimates == plain.estimates
    assert with_physics.events("envelope_high")   # the learned envelope still guards it


def test_each_process_says_whether_its_expected_band_was_armed():
    cell = Cell()
    cell.process(cell.cut(1.0))
    cell.process(cell.cut(1.0), override=None)
    cell.process(cell.cut(1.0)[:FIRST_JUDGED])   # never a tool radius past its entry
    states = [(p["expected_band"], p["expected_revolutions"] > 0) for p in cell.processes()]
    assert states == [("armed", True), ("unarmed", False), ("not_steady", False)]


def test_the_expected_state_of_a_key_is_kept_and_a_bad_one_set_aside():
    cell = Cell(settings(processes=3))
    cell.process(cell.cut(1.8))
    cell.monitor.reset()
    assert cell.monitor.command({"action": "widen", "key": KEY, "pct": 50})["ok"]
    stored = cell.monitor.export_limits(KEY)
    again = ProcessMonitor(cell.cfg.learning, limits={KEY: stored}, alarms=cell.cfg.alarms, expected=cell.band)
    ks = again.keys[KEY]
    assert ks.expected_widening.high == pytest.approx(1.5) and ks.held_back is not None and ks.kept == 1
    assert again.command({"action": "accept", "key": KEY})["ok"] and len(again.keys[KEY].taught) == 1
    bad = dict(stored, expected_widening={"high": 1e9, "low": 1.0})
    aside = ProcessMonitor(cell.cfg.learning, limits={KEY: bad}, alarms=cell.cfg.alarms, expected=cell.band)
    assert "expected_widening.high" in aside.keys[KEY].set_aside


def test_a_process_with_a_fixed_alarm_too_is_not_kept_for_accept():
    """accept teaches a process kept back by the physics only: one a fixed limit also fired in never teaches."""
    from millsense.daemon.events import AlarmEvent

    cell = Cell()
    context = ctx(1001, 5, 1)
    for _ in range(3):
        cell.feed(cell.est(0.0, cutting=False), context)
    for i, f in enumerate(cell.cut(1.8)):
        cell.feed(cell.est(f), context)
        if i == ENTRY_REVS + 5:
            cell.monitor.note_alarm(AlarmEvent("overload", "torque_nm", 9.5, 9.0))
    cell.steps.append(cell.monitor.on_context(replace(context, cycle=False), cell.rev * 100))
    assert cell.processes()[-1]["verdict"] == "expected_high"
    assert cell.monitor.keys.get(KEY) is None or cell.monitor.keys[KEY].held_back is None


def test_a_refused_action_on_an_operation_makes_no_key():
    cell = Cell()
    for args in ({"action": "accept", "key": KEY}, {"action": "false_alarm", "key": KEY},
                 {"action": "low_on", "key": KEY}, {"action": "widen", "key": KEY, "pct": 900}):
        reply = cell.monitor.command(args)
        assert not reply["ok"] and reply["changed_keys"] == [], (args, reply)
        assert KEY not in cell.monitor.keys
    assert cell.monitor.command({"action": "show", "key": KEY})["ok"] and KEY not in cell.monitor.keys

