"""The state of one process key, and what is shown of it (the `limits` queryable, `limits show`). Pure."""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Any

from millsense.daemon.learning.envelope import Envelope, Taught, json_list
from millsense.daemon.learning.process import ProcessRun

# A key's fields are the CONTEXT frame's (docs/protocol.md): program and tool uint32, operation uint16.
UINT32_MAX = 2**32 - 1
UINT16_MAX = 2**16 - 1
# "program/tool/operation" in ASCII digits and nothing after: `$` would take a final newline, `\d` any script's digits.
KEY_RE = re.compile(r"^([0-9]{1,10})/([0-9]{1,10})/([0-9]{1,5})\Z")


@dataclass
class KeyState:
    """One process key: learning, pending or active."""

    state: str = "learning"
    taught: list[Taught] = field(default_factory=list)
    envelope: Envelope | None = None
    last_alarms: list[dict[str, Any]] = field(default_factory=list)   # the last alarmed process's, for false_alarm

    def to_dict(self) -> dict[str, Any]:
        return {"state": self.state, "taught": [t.to_dict() for t in self.taught],
                "envelope": None if self.envelope is None else self.envelope.to_dict(),
                "last_alarms": [dict(a, observed={str(k): v for k, v in a["observed"].items()})
                                for a in self.last_alarms]}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "KeyState":
        state = str(d.get("state", "learning"))
        if state not in ("learning", "pending", "active"):
            raise ValueError(f"unknown envelope state {state!r}")
        env = d.get("envelope")
        return cls(state, [Taught.from_dict(t) for t in d.get("taught", [])],
                   None if env is None else Envelope.from_dict(env),
                   [dict(a, observed={int(k): float(v) for k, v in a["observed"].items()})
                    for a in d.get("last_alarms", [])])


def key_summary(key: str, ks: KeyState, target: int) -> dict[str, Any]:
    """One key as `limits list` shows it."""
    program, tool, operation = (int(p) for p in key.split("/"))
    env = ks.envelope
    out: dict[str, Any] = {
        "key": key, "program": program, "tool": tool, "operation": operation, "state": ks.state,
        "learned": env.n if env is not None else len(ks.taught), "learn_target": target,
        "length": None, "energy_baseline_j": None, "energy_std_j": None, "entry_rev": None, "adjustments": [],
    }
    if env is not None:
        out.update({"length": env.length, "energy_baseline_j": round(env.energy_mean_j, 3),
                    "energy_std_j": round(env.energy_std_j, 3), "entry_rev": round(env.entry_mean, 2),
                    "adjustments": [dict(a) for a in env.adjustments]})
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
