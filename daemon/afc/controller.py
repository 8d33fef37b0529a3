"""Adaptive feed control: hold a cut's load at its target through the CNC's feed override (issue 15).

Pure: no I/O, no threads, time passed in. The supervisor (`supervisor.py`) feeds it one estimate per
revolution and writes what it decides (`output.py`); faults reach it
through `safe()`. Tuning and its reasons: docs/afc.md.

The plant, seen from the override: the load follows feed^gain (torque ~ t^(1+p),
[D] eq. 8, with the feed per tooth t proportional to the feed), so in log space
it is a static gain `gain` behind a delay (one revolution's mean, the
estimator's batching) and the CNC's first-order lag. The PI works on
ln(target/load): a multiplicative plant becomes additive, and a step up and an
equal step down in load are answered alike.

The delay is taken out by a predictor (Smith's): every estimate carries the
override the CNC really applied during its revolution (`feed_override_pct`), so
the load that the override commanded *now* will give is the measured load ×
(commanded / applied)^gain. The PI works on that predicted load, which
answers at once; what is left of the loop's delay only matters through a
wrong `gain` (docs/afc.md, "The tuning").
"""

from __future__ import annotations

import collections
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from millsense.daemon.config.models import AFC_MIN_GAIN as MIN_GAIN  # config.checks refuses a gain below it
from millsense.daemon.config.models import AfcSettings

STATES = ("unavailable", "off", "idle", "air", "armed", "saturated", "safe")

NEUTRAL_PCT = 100.0          # the programmed feed
WIRE_STEP_PCT = 0.1          # the override's step on the wire (daq-protocol.md: uint16 in 0.1 %)
LAMBDA_REVOLUTIONS = 1.0     # default lambda: one revolution (63 % of the predicted error per update) ...
DAMPED_DELAY_REVOLUTIONS = 6.0  # ... up to this many revolutions of delay; beyond, lambda grows with the delay
                                # (docs/afc.md, "The tuning": a gain 0.6-1.6x the assumed one stays damped)
MIN_REV_S = 0.001            # a revolution's duration is bounded: a glitched speed cannot make dt absurd
MAX_REV_S = 1.0
STALE_REVOLUTIONS = 3.0
STALE_MIN_S = 0.3
# A sensor that fails mid-cut reads a lighter load for a revolution or two before the daemon declares the
# fault (docs/afc.md, "The safety path"). So a sudden drop is confirmed before the feed rises for it, and the
# fault path takes back what was raised within that window.
DROP_CONFIRM = 0.8           # the load at the programmed feed below 80 % of the revolution before's: confirm first
SUSPECT_REVOLUTIONS = 3.0    # safe() goes to the lowest command of the last 3 revolutions ...
SUSPECT_MIN_S = 0.3          # ... or 0.3 s
ESTIMATE_KEYS = {"torque": "torque_nm", "force": "force_n", "power": "p_gap_w"}
TARGET_KEYS = {"torque": "torque_nm", "force": "force_n", "power": "power_w"}


@dataclass(frozen=True)
class Decision:
    override_pct: float | None   # to command now (None: leave the DAQ as it is)
    state: str                   # one of STATES
    reason: str | None = None    # why (safe: the fault; idle: "no target" / "not allowed" / ...)


@dataclass(frozen=True)
class Tuning:
    delay_s: float
    lambda_s: float
    kp: float
    ki_per_s: float
    gain: float


def tune(revolution_s: float, *, batch_s: float, cnc_lag_s: float, gain: float, closed_loop_s: float = 0.0) -> Tuning:
    """Lambda tuning of the PI on the predicted load (docs/afc.md, "The tuning").

    delay = one revolution (the estimate is its mean, published at its close) + the estimator's batching + the
    CNC's lag. The predictor takes the delay out of the loop the PI sees, which is then the static gain alone:
    an integral action ki = 1/(gain·lambda) makes it a first-order loop of time constant lambda, with no
    proportional part needed (kp = 0: there is no lag left for it to answer). The delay still sets lambda: it is
    what a wrong gain turns into ringing. Default lambda: LAMBDA_REVOLUTIONS revolutions while the delay is at
    most DAMPED_DELAY_REVOLUTIONS revolutions, longer in proportion beyond.
    """
    gain = max(gain, MIN_GAIN)
    delay_s = revolution_s + batch_s + cnc_lag_s
    lambda_s = closed_loop_s if closed_loop_s > 0 else max(LAMBDA_REVOLUTIONS * revolution_s,
                                                          delay_s / DAMPED_DELAY_REVOLUTIONS)
    return Tuning(delay_s=delay_s, lambda_s=lambda_s, kp=0.0, ki_per_s=1.0 / (gain * lambda_s), gain=gain)


def _wire(pct: float) -> float:
    """`pct` rounded to the wire's 0.1 % step."""
    return round(round(pct / WIRE_STEP_PCT) * WIRE_STEP_PCT, 1)


class FeedController:
    """One machine's adaptive feed controller. Off at start; `switch(True)` arms it."""

    def __init__(self, afc_settings: Any, material_settings: Any = None, *, batch_s: float = 0.05) -> None:
        if afc_settings is None:  # a config without [afc] (or settings built in code): the defaults, off
            afc_settings = AfcSettings()
        self.settings = afc_settings
        self.batch_s = batch_s
        if afc_settings.process_gain > 0:
            self.gain = afc_settings.process_gain
        else:
            ks_exp = material_settings.ks_exp if material_settings is not None else -0.4362  # [D] Table 2
            self.gain = 1.0 + ks_exp  # torque ~ t^(1+p), [D] eq. (8)
        self.quantity_key = ESTIMATE_KEYS[afc_settings.quantity]
        self.enabled = bool(getattr(afc_settings, "enabled", False))
        self.available = True
        self.target: float | None = None
        self.reason: str | None = None
        self.state = "air" if self.enabled else "off"
        self.tuning = tune(0.1, batch_s=batch_s, cnc_lag_s=self._lag_s(), gain=self.gain,
                           closed_loop_s=afc_settings.closed_loop_s)
        self._commanded = NEUTRAL_PCT
        self._xi = 0.0               # the integrator: ln(override / 100)
        self._latched = False        # safe() until release()
        self._last_rev_s = 0.1
        self._last_now: float | None = None
        self._recent: collections.deque[tuple[float, float]] = collections.deque(maxlen=64)  # (now_s, commanded)
        self._last_load_ln: float | None = None  # ln(load at the programmed feed) of the revolution before

    # ----------------------------------------------------------------- what the DAQ holds
    @property
    def commanded_pct(self) -> float:
        return self._commanded

    @commanded_pct.setter
    def commanded_pct(self, pct: float) -> None:
        """What the DAQ holds, set from outside (a DAQ that restarted is back at 100 %): the integrator follows."""
        self._commanded = float(pct)
        self._xi = math.log(max(self._commanded, WIRE_STEP_PCT) / NEUTRAL_PCT)  # a DAQ reporting 0 % must not raise
        self._recent.clear()

    def _lag_s(self) -> float:
        return self.settings.cnc_lag_ms / 1000.0

    def _command(self, pct: float) -> float | None:
        """Take `pct` (rounded to the wire) as the commanded override; the value to send, None if unchanged."""
        pct = _wire(pct)
        if pct == self._commanded:
            return None
        self._commanded = pct
        return pct

    def _decide(self, state: str, pct: float | None, reason: str | None = None) -> Decision:
        self.state, self.reason = state, reason
        return Decision(None if pct is None else self._command(pct), state, reason)

    # ----------------------------------------------------------------- switches
    def set_available(self, available: bool) -> None:
        """False: a version-1 DAQ or one without an override output; the controller can do nothing."""
        self.available = available
        if not available:
            self.state, self.reason = "unavailable", "the DAQ has no feed-override output"
        elif self.state == "unavailable":
            self.state, self.reason = ("air" if self.enabled else "off"), None

    def switch(self, on: bool, now_s: float) -> Decision:
        """On: armed from the next cut. Off: the programmed feed at once."""
        self.enabled = on
        self._recent.clear()  # what was commanded before a switch is no suspect of what comes after
        self._last_load_ln = None
        if not self.available:
            return Decision(None, "unavailable", self.reason)
        if not on:
            self._xi = 0.0
            self._command(NEUTRAL_PCT)
            self.state, self.reason = "off", None
            return Decision(NEUTRAL_PCT, "off")
        if self._latched:  # a fault or a hold came while it was off: on, but safe until it is gone
            self.state = "safe"
            return Decision(None, "safe", self.reason)
        self._xi = math.log(self._commanded / NEUTRAL_PCT)
        self.state, self.reason = "air", None
        return Decision(None, "air")

    # ----------------------------------------------------------------- the fault path
    def safe(self, reason: str) -> Decision:
        """A fault, blind signals or a trip: min(commanded, 100 %) at once, and no rise until `release()`."""
        self._latched = True
        return self._to_safe(reason)

    def _to_safe(self, reason: str) -> Decision:
        """min(commanded, 100 %, the lowest command of the last few revolutions): what a failing sensor made the
        controller raise before the fault was seen is taken back too."""
        new = min(self._commanded, NEUTRAL_PCT, self._lowest_recent())
        self._last_load_ln = None
        self._xi = math.log(new / NEUTRAL_PCT)
        if not self.available:
            self.reason = reason
            return Decision(None, "unavailable", reason)
        if not self.enabled:  # off: nothing to make safe beyond what is on the DAQ (switching off sent 100 %)
            self.reason = reason
            return Decision(self._command(new), "off", reason)
        self.state, self.reason = "safe", reason
        return Decision(self._command(new), "safe", reason)

    def _lowest_recent(self) -> float:
        if self._last_now is None or not self._recent:
            return self._commanded
        window_s = max(SUSPECT_REVOLUTIONS * self._last_rev_s, SUSPECT_MIN_S)
        return min([self._commanded, *(pct for t, pct in self._recent if t >= self._last_now - window_s)])

    def release(self) -> None:
        """The condition is gone: the next revolution starts from air (at most where safe() left it)."""
        self._latched = False
        self._xi = math.log(self._commanded / NEUTRAL_PCT)
        self._recent.clear()
        if self.available and self.state == "safe":
            self.state, self.reason = ("air" if self.enabled else "off"), None

    def on_idle(self, now_s: float) -> Decision | None:
        """No revolution for stale_s while above the programmed feed: back to min(commanded, 100 %)."""
        if self._last_now is None or self._commanded <= NEUTRAL_PCT:
            return None
        stale_s = max(STALE_REVOLUTIONS * self._last_rev_s, STALE_MIN_S)
        if now_s - self._last_now < stale_s:
            return None
        self._xi = 0.0
        return self._decide("idle", NEUTRAL_PCT, "no revolution")

    # ----------------------------------------------------------------- targets
    def _entries(self, tool: int | None, operation: int | None) -> list[Any]:
        """The `[afc.targets]` entries for this tool and operation, most specific first."""
        if tool is None:
            return []
        keys = ([f"{tool}/{operation}"] if operation is not None else []) + [f"{tool}/*"]
        return [self.settings.targets[k] for k in keys if k in self.settings.targets]

    def target_for(self, tool: int | None, operation: int | None, learned_mean: float | None) -> float | None:
        """The target: `[afc.targets]` (tool/operation, then tool/*), the machine-wide one, else factor × learned."""
        key = TARGET_KEYS[self.settings.quantity]
        for entry in self._entries(tool, operation):
            if getattr(entry, key) is not None:
                return float(getattr(entry, key))
        machine_wide = getattr(self.settings, f"target_{key}")
        if machine_wide is not None:
            return float(machine_wide)
        if learned_mean is not None and learned_mean > 0:
            return self.settings.target_factor * learned_mean
        return None

    def allowed(self, tool: int | None, operation: int | None, ctx_flag: bool | None) -> bool:
        """An entry's `allow` decides (false: never); else the CONTEXT flag; else `[afc] allow`."""
        for entry in self._entries(tool, operation):
            if entry.allow is not None:
                return entry.allow
        return bool(ctx_flag) or self.settings.allow

    # ----------------------------------------------------------------- the loop
    def _toward(self, goal_pct: float, dt_s: float) -> float:
        step = self.settings.rate_pct_s * dt_s
        return self._commanded + min(max(goal_pct - self._commanded, -step), step)

    def on_revolution(self, est: Mapping[str, Any], *, target: float | None, allowed: bool, now_s: float,
                      suspect: str | None = None, untrusted: str | None = None) -> Decision:
        """One revolution's estimate in, the override to command out. `suspect`: why the newest samples may
        come from a failing sensor (a channel that stopped moving): no feed is raised on this revolution.
        `untrusted`: why the context in force may not steer the feed (a Zenoh put nobody vouches for, issue
        36): idle, and the override at most 100 % from this revolution on, whatever the context says."""
        rpm = est.get("spindle_rpm") or 0.0
        rev_s = 60.0 / rpm if rpm > 0 else (now_s - self._last_now if self._last_now is not None else 0.1)
        dt_s = min(max(rev_s, MIN_REV_S), MAX_REV_S)
        self._last_rev_s, self._last_now = dt_s, now_s
        if not self.available:
            return Decision(None, "unavailable", self.reason)
        if not self.enabled:
            self.state, self.reason = "off", None
            return Decision(None, "off")
        if self._latched:
            return Decision(None, "safe", self.reason)
        if not est.get("valid", True):
            return self._to_safe("invalid revolution")  # this revolution only: the next valid one resumes
        self.target = target
        s = self.settings
        if untrusted is not None:
            return self._ceiling(dt_s, untrusted)
        if target is None or not allowed:
            return self._coast("idle", dt_s, "no target" if target is None else "not allowed")
        load = est.get(self.quantity_key)
        if not est.get("cutting") or load is None or load <= 0 or load < s.arm_pct / 100.0 * target:
            self._last_load_ln = None
            return self._remember(now_s, self._coast("air", dt_s))
        self.tuning = tune(dt_s, batch_s=self.batch_s, cnc_lag_s=self._lag_s(), gain=self.gain,
                           closed_loop_s=s.closed_loop_s)
        error = math.log(target / load)
        applied = est.get("feed_override_pct")
        load_ln = math.log(load)
        if applied is not None and applied > 0:
            # the predictor: this revolution ran at `applied`; the override commanded now gives the load
            # × (commanded / applied)^gain once the CNC has followed (what the delay still hides)
            error -= self.gain * math.log(self._commanded / float(applied))
            load_ln -= self.gain * math.log(float(applied) / NEUTRAL_PCT)  # the load at the programmed feed
        dropped = self._last_load_ln is not None and load_ln < self._last_load_ln + math.log(DROP_CONFIRM)
        self._last_load_ln = load_ln
        if dropped and error > 0:
            # a sudden drop (a sensor failing, a flute breaking, not a cut's floor): no more feed for it until
            # the next revolution confirms it; the fault or the breakage check has that long to see it
            return self._remember(now_s, self._decide("armed", self._commanded, "confirming a drop"))
        if suspect is not None and error > 0:
            # a sensor that failed in this revolution's last samples lightens it by a little, below the drop
            # above: the newest samples show it (signal_check.newest_pinned), so no more feed for it
            return self._remember(now_s, self._decide("armed", self._commanded, f"a signal stopped: {suspect}"))
        return self._remember(now_s, self._pi(error, dt_s))

    def _remember(self, now_s: float, decision: Decision) -> Decision:
        self._recent.append((now_s, self._commanded))
        return decision

    def _coast(self, state: str, dt_s: float, reason: str | None = None) -> Decision:
        """Not controlling: toward the air override, rate limited; the integrator follows the command."""
        d = self._decide(state, self._toward(self.settings.air_override_pct, dt_s), reason)
        self._xi = math.log(self._commanded / NEUTRAL_PCT)
        return d

    def _ceiling(self, dt_s: float, reason: str) -> Decision:
        """Idle under a context without authority: at most 100 % at once (an unauthenticated put can never
        keep the feed raised), then toward the air override if it lies lower; the integrator follows."""
        goal = min(self.settings.air_override_pct, NEUTRAL_PCT)
        d = self._decide("idle", min(self._toward(goal, dt_s), NEUTRAL_PCT), reason)
        self._last_load_ln = None
        self._xi = math.log(self._commanded / NEUTRAL_PCT)
        return d

    def _pi(self, error: float, dt_s: float) -> Decision:
        """PI in log space on the predicted error, clamped, rate limited, with back-calculation so the
        integrator never winds up. The integral step is the exact one of a first-order loop over dt:
        a share 1 − exp(−dt/lambda) of the error per revolution (ki·dt for dt << lambda)."""
        s, t = self.settings, self.tuning
        self._xi += (1.0 - math.exp(-dt_s / t.lambda_s)) * error / t.gain
        wanted = NEUTRAL_PCT * math.exp(self._xi + t.kp * error)
        clamped = min(max(wanted, s.min_override_pct), s.max_override_pct)
        limited = self._toward(clamped, dt_s)
        at_max = clamped >= s.max_override_pct and error > 0
        at_min = clamped <= s.min_override_pct and error < 0
        state = "saturated" if (at_max or at_min) and limited == clamped else "armed"
        d = self._decide(state, limited)
        # back-calculation: the integrator is what, with this error, gives the override actually commanded
        self._xi = math.log(self._commanded / NEUTRAL_PCT) - t.kp * error
        return d

    def status(self) -> dict[str, Any]:
        s, t = self.settings, self.tuning
        return {
            "enabled": self.enabled, "state": self.state, "reason": self.reason,
            "override_pct": self._commanded, "target": self.target, "quantity": self.quantity_key,
            "min_pct": s.min_override_pct, "max_pct": s.max_override_pct,
            "tuning": {"delay_s": t.delay_s, "lambda_s": t.lambda_s, "kp": t.kp, "ki_per_s": t.ki_per_s,
                       "gain": t.gain},
        }
