"""The expected band: an operation's load from the physics, checked from the first part (issue 41). Pure.

A process whose key has an `[operations."P/T/O"]` entry is checked, every part (not only until its envelope
is learned), revolution by revolution against the load the forward model (`physics.expected.expected_load`)
gives for its programmed cut at the revolution's measured spindle speed and applied feed override:

    band = expected × (1 − tol_low, 1 + tol_high),   tol = [learning] physics_tolerance_pct / 100

(× the operator's widening, `ExpectedWidening`; the high side never above the fixed `[alarms]` limit).

Only *steady* revolutions in cut are judged (docs/validation.md's steady): valid, in cut (called cutting, or —
a light cut under `[depth] min_torque_nm` — risen above the air's level by IN_CUT_OF_EXPECTED of the
operation's own expected torque, `_in_cut`), the spindle not changing speed, a tool radius of path past the
(re-)entry into the cut by the end of the revolution (the engagement still growing before it; the entry
counted from the revolutions rising out of the air's noise into the cut, `_entry_credit`), the override and
the measured feed per tooth each held within STEADY_FEED_PCT over the last STEADY_REVOLUTIONS revolutions.
Others neither count nor break a run. An unknown override arms nothing (a note per process,
`learning.expected_unarmed`, which the runner logs once a run; the process payload says
`expected_band: "unarmed"`).

- `expected_high`: `high_revolutions` steady revolutions in a row above the band; holds the feed.
- `expected_low`: `low_revolutions` in a row below it; holds the feed for `engagement = "constant"`, else a
  warning that does not hold (depth steps, corners, ramps). A cut's exit, and any slow decline, goes below the
  band too: a low run counts only when the cut fell below the band in one revolution by at least
  LOW_STEP_OF_TOL × tol of the expected load (a broken flute, a step into missing stock), or — constant
  engagement only — was below it from its first steady revolution (a shallower cut, a wrong tool: with varying
  engagement the cut's own depths lie anywhere below the declared maximum). A gradual decline from inside the
  band is taken for an exit and not judged until the load is back in the band. `limits low-off KEY` turns it
  off like envelope_low.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from typing import Any

from millsense.daemon.events import AlarmEvent, finite
from millsense.daemon.learning.envelope import LOW_MAX_FRACTION, MAX_WIDENING, WideningCapped, setting
from millsense.daemon.physics.expected import ExpectedLoad, expected_load

LEVELS = ("expected_high", "expected_low")
DEFAULT_TOLERANCE_PCT = 34.0   # [learning] physics_tolerance_pct (config/models.py)
STEADY_REVOLUTIONS = 3        # the override and feed held over this many revolutions (this one included)
STEADY_FEED_PCT = 2.0         # "held": within this % of the largest of them
LOW_STEP_OF_TOL = 0.5         # a drop into the low side that counts: at least half the tolerance in one revolution
FALSE_ALARM_MARGIN_PCT = 5.0  # a false alarm widens the band so that what was seen fits with this to spare
KEPT_WARNING_PROCESSES = 3    # processes in a row kept from teaching by the physics: warned once
ENTRY_LOOKBACK = 16           # revolutions before the first one in cut that may be the cutter's first touch
ENTRY_NOISE_SIGMAS = 3.0      # ... each above its own torque scatter (eq. 20) by this, and rising into the cut
IN_CUT_OF_EXPECTED = 0.25     # a light cut is in cut once its torque rose this fraction of its expected one above air
AIR_WINDOW = 8                # the air's torque level: the lowest of the last this many revolutions out of cut ...
AIR_MIN_REVOLUTIONS = 3       # ... of at least this many in the process (before: only a cutting revolution is in cut)
_QUANTITIES = ("torque_nm", "force_n")
_UNITS = {"torque_nm": "N·m", "force_n": "N"}


@dataclass
class ExpectedWidening:
    """The operator's widening of one operation's expected band, per side (1.0: the configured tolerance)."""

    high: float = 1.0
    low: float = 1.0
    adjustments: list[dict[str, Any]] = field(default_factory=list)

    def fractions(self, tol: float) -> tuple[float, float]:
        """(low, high) half-widths as fractions of the expected load, within the bounds."""
        low = min(tol * self.low, max(tol, LOW_MAX_FRACTION), MAX_WIDENING * tol)
        return min(low, 0.99), min(tol * self.high, MAX_WIDENING * tol)

    def widen(self, pct: float) -> None:
        factor = 1.0 + pct / 100.0
        now = max(self.high, self.low)
        if now * factor > MAX_WIDENING * (1.0 + 1e-9):
            room = max(math.floor((MAX_WIDENING / now - 1.0) * 100.0 + 1e-6), 0)
            raise WideningCapped(
                f"the expected band's widening is capped at {MAX_WIDENING:g}× [learning] physics_tolerance_pct "
                f"(now {now:.2f}×, {pct:g} % more would make {now * factor:.2f}×): "
                + (f"at most {room} % more" if room >= 1 else "no more"))
        self.high, self.low = self.high * factor, self.low * factor
        self.adjustments.append({"action": "widen", "pct": float(pct)})

    def narrow(self, pct: float) -> None:
        factor = 1.0 - pct / 100.0   # never below the configured tolerance (the floor)
        self.high, self.low = max(self.high * factor, 1.0), max(self.low * factor, 1.0)
        self.adjustments.append({"action": "narrow", "pct": float(pct)})

    def fit(self, level: str, ratios: list[float], tol: float) -> bool:
        """A false alarm: widen the side of `level` so each measured/expected ratio fits; False if bounded."""
        m = FALSE_ALARM_MARGIN_PCT / 100.0
        ratios = [r for r in ratios if r is not None and math.isfinite(r)]
        if not ratios:
            return True
        if level == "expected_high":
            need = (max(ratios) * (1.0 + m) - 1.0) / tol
            self.high = min(max(self.high, need), MAX_WIDENING)
            fits = self.fractions(tol)[1] >= max(ratios) - 1.0
        else:
            need = (1.0 - min(ratios) * (1.0 - m)) / tol
            self.low = min(max(self.low, need), MAX_WIDENING)
            fits = self.fractions(tol)[0] >= 1.0 - min(ratios)
        self.adjustments.append({"action": "false_alarm", "level": level})
        return fits

    def to_dict(self) -> dict[str, Any]:
        return {"high": self.high, "low": self.low, "adjustments": [dict(a) for a in self.adjustments]}

    @classmethod
    def from_dict(cls, d: Any) -> "ExpectedWidening":
        if not isinstance(d, dict):
            raise ValueError("expected_widening: not an object")
        out = []
        for side in ("high", "low"):
            v = d.get(side, 1.0)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not 1.0 <= v <= MAX_WIDENING * (1 + 1e-9):
                raise ValueError(f"expected_widening.{side}: {v!r} is not a widening 1 … {MAX_WIDENING:g}")
            out.append(float(v))
        adj = d.get("adjustments", [])
        if not isinstance(adj, list) or not all(isinstance(a, dict) for a in adj):
            raise ValueError("expected_widening.adjustments: not a list of objects")
        return cls(out[0], out[1], [dict(a) for a in adj[-100:]])


@dataclass
class _Run:
    """One process's state for the physics check."""

    proc: Any
    path_mm: float = 0.0          # path since (re-)entry into the cut
    overrides: deque = field(default_factory=lambda: deque(maxlen=STEADY_REVOLUTIONS))
    feeds: deque = field(default_factory=lambda: deque(maxlen=STEADY_REVOLUTIONS))
    air: deque = field(default_factory=lambda: deque(maxlen=ENTRY_LOOKBACK))   # (torque, sigma, path) out of cut
    air_torques: deque = field(default_factory=lambda: deque(maxlen=AIR_WINDOW))   # torque out of cut, N·m
    runs: dict[str, int] = field(default_factory=dict)           # level:quantity -> steady revolutions in a row
    prev: dict[str, tuple[float, bool]] = field(default_factory=dict)   # quantity -> (value, below) of the last steady
    low_armed: dict[str, bool] = field(default_factory=dict)
    noted: bool = False           # the override was unknown (said once per process)
    outside: bool = False         # a steady revolution outside the band
    judged: int = 0               # steady revolutions judged

    def leave_cut(self) -> None:
        self.path_mm = 0.0
        self.prev.clear()
        self.low_armed.clear()
        for name in self.runs:
            self.runs[name] = 0


@dataclass
class Judged:
    """What one revolution gave: alarms to raise (each with its observed {process_rev: ratio}) and notes."""

    events: list[tuple[AlarmEvent, dict[int, float]]] = field(default_factory=list)
    notes: list[tuple[str, dict[str, Any]]] = field(default_factory=list)


class ExpectedBand:
    """The physics check of every operation a configuration declares. One owner (the monitor's thread).

    `cuts`: key → the operation as the physics takes it (`config.operations.OperationCut`: cut, tool_radius_mm,
    flutes, material, engagement, spindle_rpm; resolved by the caller, `config.operations.operation_cuts`).
    """

    def __init__(self, cuts: dict[str, Any], learning: Any = None, alarms: Any = None):
        self.tolerance_pct = float(setting(learning, "physics_tolerance_pct", DEFAULT_TOLERANCE_PCT))
        self.high_revolutions = max(1, int(setting(learning, "high_revolutions", 3)))
        self.low_revolutions = max(1, int(setting(learning, "low_revolutions", 3)))
        self.ceilings = {"torque_nm": setting(alarms, "torque_limit_nm", None),
                         "force_n": setting(alarms, "force_limit_n", None)}
        self.cuts: dict[str, Any] = dict(cuts)
        self.last_seen: dict[str, tuple[float, float]] = {}   # key -> (spindle_rpm, override_pct) of its last steady rev
        self._run: _Run | None = None

    @property
    def tol(self) -> float:
        return self.tolerance_pct / 100.0

    def cut(self, key: str) -> Any:
        """The operation of `key`, None when it has none (it behaves as before)."""
        return self.cuts.get(key)

    def expected(self, key: str, spindle_rpm: float | None, override_pct: float | None) -> ExpectedLoad | None:
        op = self.cut(key)
        if op is None or spindle_rpm is None:
            return None
        try:
            exp = expected_load(op.cut, tool_radius_mm=op.tool_radius_mm, flutes=op.flutes, material=op.material,
                                spindle_rpm=spindle_rpm, override_pct=override_pct,
                                helix_deg=getattr(op, "helix_deg", None))
        except (ValueError, ArithmeticError):
            return None   # nothing can be expected: nothing armed (never an error on the estimator thread)
        if exp is None or not (math.isfinite(exp.torque_nm) and math.isfinite(exp.feed_per_tooth_mm)):
            return None
        return exp

    def limits(self, quantity: str, expected: float, widening: ExpectedWidening | None) -> tuple[float, float]:
        low_f, high_f = (widening or ExpectedWidening()).fractions(self.tol)
        high = expected * (1.0 + high_f)
        ceiling = self.ceilings.get(quantity)
        if ceiling is not None:
            high = min(high, float(ceiling))   # the fixed limit trips above it anyway
        return expected * (1.0 - low_f), high

    # -- one revolution ---------------------------------------------------------------------------
    def judge(self, proc: Any, est: dict[str, Any], k: int | None, widening: ExpectedWidening | None,
              low_on: bool) -> Judged:
        out = Judged()
        op = self.cut(proc.key)
        if op is None:
            return out
        run = self._run
        if run is None or run.proc is not proc:
            run = self._run = _Run(proc)
        if not est.get("valid", True):
            return out   # a damaged revolution neither counts nor breaks a run
        rpm, ovr = finite(est.get("spindle_rpm")), finite(est.get("feed_override_pct"))
        if not self._in_cut(run, est, rpm, ovr):
            run.leave_cut()
            run.air.append(self._air_step(proc.key, est, rpm, ovr, op.flutes))
            torque = finite(est.get("torque_nm"))
            if torque is not None and not est.get("accelerating"):
                run.air_torques.append(torque)
            return out
        if ovr is None:
            if not run.noted:
                run.noted = True
                out.notes.append(("learning.expected_unarmed", {
                    "key": proc.key, "process": proc.pid,
                    "reason": "the CNC's applied feed override is unknown: the expected band is not armed"}))
            run.leave_cut()
            return out
        exp = self.expected(proc.key, rpm, ovr)
        if exp is None:
            run.leave_cut()
            return out
        if run.path_mm == 0.0:   # the first revolution in cut: the entry may have begun under its threshold
            run.path_mm = self._entry_credit(run.air, finite(est.get("torque_nm")))
        run.air.clear()
        run.path_mm += exp.feed_per_tooth_mm * op.flutes   # mm of path at this revolution's end
        run.overrides.append(ovr)
        feed = finite(est.get("feed_per_tooth_mm"))
        run.feeds.append(feed)
        # judged from the revolution in which the cutter's centre crosses the part's face (its engagement then
        # within (p/R)²/2 of full): the first touch's revolution is partial and, under the noise, not credited
        if run.path_mm < op.tool_radius_mm or est.get("accelerating") or not self._held(run):
            return out
        self.last_seen[proc.key] = (float(rpm), float(ovr))
        run.judged += 1
        at = k if k is not None else proc.revolutions - 1
        for quantity, expected in (("torque_nm", exp.torque_nm), ("force_n", exp.force_n)):
            value = finite(est.get(quantity))
            if value is None or not expected > 0:
                continue
            low, high = self.limits(quantity, expected, widening)
            self._side(out, run, proc, op, est, exp, at, quantity, "expected_high", value, expected, high,
                       value > high, True)
            self._side(out, run, proc, op, est, exp, at, quantity, "expected_low", value, expected, low,
                       value < low and low_on and self._low_counts(run, quantity, value, expected, low),
                       op.engagement == "constant")
            run.prev[quantity] = (value, value < low)
        return out

    def _in_cut(self, run: _Run, est: dict[str, Any], rpm: float | None, ovr: float | None) -> bool:
        """Is this revolution in cut for the expected band? Called cutting (over `[depth] min_torque_nm`), or a
        light cut under it: its torque risen above the air's level by at least IN_CUT_OF_EXPECTED of the
        operation's expected torque and by ENTRY_NOISE_SIGMAS of its own scatter (eq. 20), the spindle not
        accelerating. The air's level is the lowest torque of the last AIR_WINDOW revolutions out of cut (at
        least AIR_MIN_REVOLUTIONS of them in this process), never below 0.

        `min_torque_nm` is the depth estimator's threshold, set for every cut of the machine: a light finishing
        cut, or a half-depth first part of one, stays under it and was never judged (a half-depth part passed
        unseen). Its own expected torque says how much a cut of this operation takes. Air stays air: the level is
        the air's own, so a friction calibrated a little off does not read as a cut; the lowest, not the mean,
        so the cutter's first touches (out of cut, rising) do not lift it; never below 0, because the air after
        a spindle run-up reads below 0 for some tens of revolutions while it settles (found live: −0.7 N·m
        decaying to 0), and rising from there is not a cut. Nothing marks the part's face ahead (a program's air
        time before the part is not known), so a cut taking under a quarter of its expected load, or whose load
        rises slower than that over AIR_WINDOW revolutions, is taken for air: the fail-safe reading, which never
        calls a correct part's approach missing stock (docs/learning.md, "What it does not see")."""
        if est.get("cutting"):
            return True
        if est.get("accelerating"):
            return False
        torque, sigma = finite(est.get("torque_nm")), finite(est.get("torque_sigma_nm"))
        if torque is None:
            return False
        exp = self.expected(run.proc.key, rpm, ovr)
        if exp is None or not exp.torque_nm > 0.0:
            return False
        if len(run.air_torques) < AIR_MIN_REVOLUTIONS:
            return False   # too little air seen in this process: nothing says where the air's level is
        rise = torque - max(min(run.air_torques), 0.0)
        return rise >= IN_CUT_OF_EXPECTED * exp.torque_nm and rise > ENTRY_NOISE_SIGMAS * (sigma or 0.0)

    def _air_step(self, key: str, est: dict[str, Any], rpm: float | None, ovr: float | None,
                  flutes: int) -> tuple[float, float, float] | None:
        """A revolution out of cut: (torque, its scatter, its path) where it may be the cutter's first touch."""
        torque, sigma = finite(est.get("torque_nm")), finite(est.get("torque_sigma_nm"))
        if torque is None or sigma is None or est.get("accelerating") or ovr is None:
            return None
        exp = self.expected(key, rpm, ovr)
        return None if exp is None else (torque, sigma, exp.feed_per_tooth_mm * flutes)

    @staticmethod
    def _entry_credit(air: deque, first_torque: float | None) -> float:
        """The path already cut when the first revolution in cut came (`_in_cut`): the revolutions just (up to
        ENTRY_LOOKBACK) before it whose torque rose out of the air's noise (above ENTRY_NOISE_SIGMAS of its own
        scatter) and below the next one's, each into the cut. A shallow cut's first touch stays under the threshold; without
        this its steady revolutions were judged that many revolutions late. Flat air credits nothing (a
        revolution not below the next breaks the chain), and a revolution or two credited wrongly moves the
        first judged one by as much of a tool radius of path, where a slot's engagement is within
        (p/R)²/2 of full."""
        credit, above = 0.0, first_torque
        for step in reversed(air):
            if step is None or above is None:
                break
            torque, sigma, path = step
            if not (ENTRY_NOISE_SIGMAS * sigma < torque < above - ENTRY_NOISE_SIGMAS * sigma):
                break
            credit, above = credit + path, torque
        return credit

    @staticmethod
    def _held(run: _Run) -> bool:
        """The override and the measured feed per tooth held over the last STEADY_REVOLUTIONS revolutions."""
        for values in (run.overrides, run.feeds):
            known = [v for v in values if v is not None]
            if not known:
                continue
            if len(known) < len(values):
                return False   # the feed went unknown within the window
            top = max(abs(v) for v in known)
            if top > 0 and (max(known) - min(known)) > STEADY_FEED_PCT / 100.0 * top:
                return False
        return len(run.overrides) >= STEADY_REVOLUTIONS   # a whole window seen

    def _low_counts(self, run: _Run, quantity: str, value: float, expected: float, low: float) -> bool:
        """May this revolution below the band count towards expected_low? (the exit rule, module doc)"""
        prev = run.prev.get(quantity)
        if prev is None:   # below from the cut's first steady revolution: a shallower cut, a wrong tool ...
            # ... unless the engagement varies: the cut's own depths then lie anywhere below the maximum
            run.low_armed.setdefault(quantity, self.cut(run.proc.key).engagement == "constant")
        elif not prev[1]:                                    # it left the band in this revolution
            run.low_armed[quantity] = (prev[0] - value) >= LOW_STEP_OF_TOL * self.tol * expected
        return run.low_armed.get(quantity, False)

    def _side(self, out: Judged, run: _Run, proc: Any, op: Any, est: dict[str, Any], exp: ExpectedLoad,
              at: int, quantity: str, level: str, value: float, expected: float, limit: float, outside: bool,
              hold: bool) -> None:
        name = f"{level}:{quantity}"
        run.runs[name] = run.runs.get(name, 0) + 1 if outside else 0
        if not outside:
            return
        run.outside = True
        proc.outside.setdefault(name, {})[at] = round(value / expected, 4)   # false_alarm fits these ratios
        need = self.high_revolutions if level == "expected_high" else self.low_revolutions
        if run.runs[name] < need or level in proc.raised or any(ev.level == level for ev, _ in out.events):
            return   # at most one of each per process
        reason = self.reason(op, est, exp, quantity, level, value, expected, limit)
        ev = AlarmEvent(level, quantity, round(value, 4), round(limit, 4), proc.last_rev, proc.last_seq, hold=hold,
                        detail=proc.detail(k_or_none(at, proc)) + (("expected", round(expected, 4)),
                                                                     ("reason", reason)))
        out.events.append((ev, dict(proc.outside[name])))

    def reason(self, op: Any, est: dict[str, Any], exp: ExpectedLoad, quantity: str, level: str,
               value: float, expected: float, limit: float) -> str:
        """What the physics expected and what was measured, in one line (the alarm's `reason`)."""
        unit = _UNITS[quantity]
        name = "torque" if quantity == "torque_nm" else "force"
        pct = abs(limit / expected - 1.0) * 100.0
        side = (f"> expected {expected:.4g} {unit} + {pct:.0f} %" if level == "expected_high"
                else f"< expected {expected:.4g} {unit} − {pct:.0f} %")
        c = op.cut
        feed = f"fz {c.feed_per_tooth_mm:g} mm" if c.feed_per_tooth_mm is not None else f"vf {c.feed_mm_min:g} mm/min"
        rpm = finite(est.get("spindle_rpm")) or 0.0
        ovr = finite(est.get("feed_override_pct")) or 0.0
        hold = "" if level == "expected_high" or op.engagement == "constant" else " (varying engagement: a warning)"
        return (f"{name} {value:.4g} {unit} {side} (ae {c.radial_depth_mm:g} mm, ap {c.axial_depth_mm:g} mm, "
                f"{feed} ({exp.feed_per_tooth_mm:.3g} mm/tooth cut), {c.mode}, at {rpm:.0f} rpm, {ovr:g} %){hold}")

    def summary(self, proc: Any) -> dict[str, Any]:
        """The process payload's `expected_band` (additive): "armed" (steady revolutions were judged; how many in
        `expected_revolutions`), "unarmed" (the override was unknown), "not_steady" (no revolution was steady)."""
        run = self._run if self._run is not None and self._run.proc is proc else None
        judged = 0 if run is None else run.judged
        state = "armed" if judged else ("unarmed" if run is not None and run.noted else "not_steady")
        return {"expected_band": state, "expected_revolutions": judged}

    # -- `limits show` ----------------------------------------------------------------------------
    def show(self, key: str, learned: dict[str, float | None], widening: ExpectedWidening | None) -> dict[str, Any] | None:
        """The operation's expected load at its last steady speed and override (or the programmed speed at
        100 %), its band, the learned mean beside it and their ratio (learned / expected)."""
        op = self.cut(key)
        if op is None:
            return None
        seen = self.last_seen.get(key)
        rpm, ovr, where = (seen[0], seen[1], "last steady revolution") if seen else (op.spindle_rpm, 100.0, "programmed")
        exp = self.expected(key, rpm, ovr)
        # the learned band is at the programmed feed (process.py): its ratio is to the expectation at 100 %
        at_programmed = self.expected(key, rpm, 100.0)
        out: dict[str, Any] = {"operation_cut": {"ae_mm": op.cut.radial_depth_mm, "ap_mm": op.cut.axial_depth_mm,
                                                 "fz_mm": op.cut.feed_per_tooth_mm, "vf_mm_min": op.cut.feed_mm_min,
                                                 "mode": op.cut.mode, "engagement": op.engagement},
                               "expected_at": {"spindle_rpm": rpm, "feed_override_pct": ovr, "from": where},
                               "physics_tolerance_pct": self.tolerance_pct}
        if widening is not None:
            out["expected_widening"] = {"high": round(widening.high, 3), "low": round(widening.low, 3)}
        for quantity in _QUANTITIES:
            value = None if exp is None else getattr(exp, quantity)
            mean = learned.get(quantity)
            out[f"expected_{quantity}"] = None if value is None else round(value, 4)
            if value is not None:
                low, high = self.limits(quantity, value, widening)
                out[f"expected_low_{quantity}"], out[f"expected_high_{quantity}"] = round(low, 4), round(high, 4)
            out[f"learned_mean_{quantity}"] = None if mean is None else round(mean, 4)
            base = None if at_programmed is None else getattr(at_programmed, quantity)
            out[f"learned_to_expected_{quantity.split('_')[0]}"] = (
                None if mean is None or not base else round(mean / base, 4))
        if exp is None:
            out["expected_note"] = ("no speed seen yet and none programmed (spindle_rpm in the operation)"
                                    if rpm is None else "nothing can be expected at this speed and override")
        return out


def k_or_none(at: int, proc: Any) -> int | None:
    """The process_rev of an alarm when the process has entered (else None, as an envelope alarm's entry)."""
    return at if proc.entry_rev is not None else None
