"""The state of one process key, and what is shown of it (the `limits` queryable, `limits show`). Pure."""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from typing import Any

from millsense.daemon.learning.envelope import Envelope, Taught, Widths, json_list
from millsense.daemon.learning.expected import ExpectedWidening
from millsense.daemon.learning.process import ProcessRun

# A key's fields are the CONTEXT frame's (docs/protocol.md): program and tool uint32, operation uint16.
UINT32_MAX = 2**32 - 1
UINT16_MAX = 2**16 - 1
# "program/tool/operation" in ASCII digits and nothing after: `$` would take a final newline, `\d` any script's digits.
KEY_RE = re.compile(r"^([0-9]{1,10})/([0-9]{1,10})/([0-9]{1,5})\Z")


LEVELS = ("envelope_high", "envelope_low", "expected_high", "expected_low")
QUANTITIES = ("torque_nm", "force_n", "entry", "cutting_energy_j")


@dataclass
class KeyState:
    """One process key: learning, pending or active."""

    state: str = "learning"
    taught: list[Taught] = field(default_factory=list)
    envelope: Envelope | None = None
    last_alarms: list[dict[str, Any]] = field(default_factory=list)   # the last alarmed process's, for false_alarm
    low_check: bool = True          # envelope_low checked (`limits low-off KEY` / `low-on KEY`, audited)
    set_aside: str | None = None    # why its stored state was set aside at start (shown until it is learned again)
    set_aside_row: Any = None       # that stored state as it was read (kept, so nothing is lost)
    # issue 41 (expected.py): the operator's widening of the key's expected band; the last process kept from
    # teaching by it (accept / false-alarm teach it); how many in a row were kept
    expected_widening: ExpectedWidening | None = None
    held_back: Taught | None = None
    kept: int = 0

    def to_dict(self) -> dict[str, Any]:
        out = {"state": self.state, "taught": [t.to_dict() for t in self.taught],
               "envelope": None if self.envelope is None else self.envelope.to_dict(),
               "last_alarms": [dict(a, observed={str(k): v for k, v in a["observed"].items()})
                               for a in self.last_alarms],
               "low_check": self.low_check}
        if self.set_aside is not None or self.set_aside_row is not None:
            out["set_aside"] = {"reason": self.set_aside, "row": self.set_aside_row}
        if self.expected_widening is not None:
            out["expected_widening"] = self.expected_widening.to_dict()
        if self.held_back is not None:
            out["held_back"] = self.held_back.to_dict()
        if self.kept:
            out["kept"] = self.kept
        return out

    @classmethod
    def from_dict(cls, d: Any, widths: Widths | None = None) -> "KeyState":
        """A stored key, every value checked: ValueError naming what is wrong (never another error)."""
        if not isinstance(d, dict):
            raise ValueError(f"not an object ({'null' if d is None else type(d).__name__})")
        state = d.get("state", "learning")
        if state not in ("learning", "pending", "active"):
            raise ValueError(f"unknown envelope state {state!r}")
        env = d.get("envelope")
        envelope = None if env is None else Envelope.from_dict(env, widths)
        if (envelope is None) != (state == "learning"):
            raise ValueError(f"state {state} {'without' if envelope is None else 'with'} an envelope")
        taught = d.get("taught", [])
        if not isinstance(taught, list):
            raise ValueError("taught: not a list")
        low_check = d.get("low_check", True)
        if not isinstance(low_check, bool):
            raise ValueError(f"low_check: {low_check!r} is not true or false")
        aside = d.get("set_aside")
        if aside is not None and not (isinstance(aside, dict) and isinstance(aside.get("reason"), (str, type(None)))):
            raise ValueError("set_aside: not an object with a reason")
        widening = d.get("expected_widening")
        held = d.get("held_back")
        kept = d.get("kept", 0)
        if isinstance(kept, bool) or not isinstance(kept, int) or not 0 <= kept <= 10**9:
            raise ValueError(f"kept: {kept!r} is not a count")
        return cls(state, [Taught.from_dict(t, f"taught[{i}]") for i, t in enumerate(taught)], envelope,
                   _last_alarms(d.get("last_alarms", [])), low_check,
                   None if aside is None else aside.get("reason"), None if aside is None else aside.get("row"),
                   None if widening is None else ExpectedWidening.from_dict(widening),
                   None if held is None else Taught.from_dict(held, "held_back"), kept)


def _last_alarms(alarms: Any) -> list[dict[str, Any]]:
    """The stored last alarms (what `false_alarm` widens by), checked."""
    if not isinstance(alarms, list):
        raise ValueError("last_alarms: not a list")
    out = []
    for i, a in enumerate(alarms):
        where = f"last_alarms[{i}]"
        if not isinstance(a, dict) or a.get("level") not in LEVELS or a.get("quantity") not in QUANTITIES:
            raise ValueError(f"{where}: not an envelope or expected alarm (level, quantity)")
        observed = a.get("observed")
        if not isinstance(observed, dict):
            raise ValueError(f"{where}.observed: not an object")
        values = {}
        for k, v in observed.items():
            if not str(k).isdigit() or len(str(k)) > 9:
                raise ValueError(f"{where}.observed: {k!r} is not a process_rev")
            if isinstance(v, bool) or not isinstance(v, (int, float)) or abs(v) > 1e9 or not math.isfinite(v):
                raise ValueError(f"{where}.observed[{k}]: {v!r} is not a finite number")
            values[int(k)] = float(v)
        out.append(dict(a, observed=values))
    return out


def key_summary(key: str, ks: KeyState, target: int) -> dict[str, Any]:
    """One key as `limits list` shows it."""
    program, tool, operation = (int(p) for p in key.split("/"))
    env = ks.envelope
    out: dict[str, Any] = {
        "key": key, "program": program, "tool": tool, "operation": operation, "state": ks.state,
        "learned": env.n if env is not None else len(ks.taught), "learn_target": target,
        "length": None, "energy_baseline_j": None, "energy_std_j": None, "entry_rev": None, "adjustments": [],
        "low_check": ks.low_check, "widening": None, "set_aside": ks.set_aside,
    }
    if ks.kept:   # (issue 41, additive) processes in a row kept from teaching by the expected band
        out["kept_from_teaching"] = ks.kept
    if env is not None:
        out.update({"length": env.length, "energy_baseline_j": round(env.energy_mean_j, 3),
                    "energy_std_j": round(env.energy_std_j, 3), "entry_rev": round(env.entry_mean, 2),
                    "adjustments": [dict(a) for a in env.adjustments], "widening": round(env.widening(), 3)})
    return out


def key_show(key: str, ks: KeyState, target: int) -> dict[str, Any]:
    """One key's summary and its band along process_rev (None where there is none)."""
    out = key_summary(key, ks, target)
    env = ks.envelope
    if env is not None:
        out.update({"torque_mean_nm": _rounded(json_list(env.torque.mean)), "torque_std_nm": _rounded(json_list(env.torque.std)),
                    "torque_low_nm": _rounded(env.torque.low), "torque_high_nm": _rounded(env.torque.high),
                    "entry_deadline_rev": env.entry_deadline, "energy_low_j": round(env.energy_low_j, 3)})
        if env.force is not None:
            out.update({"force_mean_n": _rounded(json_list(env.force.mean)), "force_low_n": _rounded(env.force.low),
                        "force_high_n": _rounded(env.force.high)})
    return out


def seen_outside(proc: ProcessRun) -> list[dict[str, Any]]:
    """What a process showed outside its band, per alarm level raised and quantity (for `false_alarm`).

    Every quantity outside on the side of a raised alarm, not only the one that
    raised it: torque and force leave the band together, and widening one alone
    would let the other raise the same alarm next time.
    """
    out = []
    for level in proc.raised:
        for name, observed in proc.outside.items():
            seen_level, quantity = name.split(":", 1)
            if seen_level != level:
                continue
            if quantity == "entry":  # how late it really entered (or how long it ran without)
                # as progress along the path, like the deadline (the plain count at 100 %)
                late = proc.entry_progress if proc.entry_progress is not None else round(proc.progress, 2)
                observed = {0: float(late)}
            out.append({"level": level, "quantity": quantity, "process": proc.pid, "observed": dict(observed)})
    return out


def _rounded(values: list[float | None]) -> list[float | None]:
    return [None if v is None else round(v, 4) for v in values]
