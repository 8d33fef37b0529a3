"""The arguments of a limits command, checked the same way wherever they come from.

`millsense limits` checks them before anything is sent, and the daemon checks
them again as they arrive on `cmd/limits` or the local socket, before the
Runner sees them: one clear sentence for a bad argument, never a guess.

args: `{"action": ..., "key": "program/tool/operation", "pct": int, "tool": int}`
(docs/zenoh.md, "cmd/limits"). `pct` is a whole number of percent: the MAC's
canonical JSON takes no fractional numbers (command_auth.canonical_json).
"""

from __future__ import annotations

import math
from typing import Any

from millsense.daemon.learning.actions import ACTIONS  # the one list (learning/actions.py dispatches them)
from millsense.daemon.learning.keys import KEY_RE, UINT16_MAX, UINT32_MAX

READS = ("list", "show")  # change nothing: the `limits` queryable answers them without a token
NEEDS_KEY = ("show", "accept", "relearn", "widen", "narrow", "false_alarm", "low_off", "low_on")
NEEDS_PCT = ("widen", "narrow")
PCT_RANGE = {"widen": (1, 500), "narrow": (1, 90)}  # narrowing by 100 % would leave no band at all


def parse_key(text: Any) -> str:
    """A process key "program/tool/operation" in its one spelling (no leading zeros); ValueError otherwise."""
    m = KEY_RE.match(text) if isinstance(text, str) else None
    if m is None:
        raise ValueError(f"key must be program/tool/operation in whole numbers, e.g. 1234/12/3 (got {text!r})")
    program, tool, operation = (int(g) for g in m.groups())
    if program > UINT32_MAX or tool > UINT32_MAX or operation > UINT16_MAX:
        raise ValueError(f"key {text}: program and tool are at most {UINT32_MAX}, operation at most {UINT16_MAX}")
    return f"{program}/{tool}/{operation}"


def _whole(value: Any, name: str) -> int:
    if isinstance(value, float) and not math.isfinite(value):   # JSON's NaN and Infinity parse as floats
        raise ValueError(f"{name} must be a finite whole number, not {value!r}")
    if isinstance(value, bool) or not isinstance(value, int):
        raise ValueError(f"{name} must be a whole number (got {value!r})")
    return value


def check_args(args: Any) -> dict[str, Any]:
    """`args` checked and normalised (the key in its one spelling); ValueError naming what is wrong."""
    if not isinstance(args, dict):
        raise ValueError("args must be an object")
    action = args.get("action")
    if action not in ACTIONS:
        raise ValueError(f"action must be one of {', '.join(ACTIONS)} (got {action!r})")
    allowed = {"action"}
    out: dict[str, Any] = {"action": action}
    if action in NEEDS_KEY:
        allowed.add("key")
        out["key"] = parse_key(args.get("key"))
    if action in NEEDS_PCT:
        allowed.add("pct")
        low, high = PCT_RANGE[action]
        pct = _whole(args.get("pct"), "pct")
        if not low <= pct <= high:
            raise ValueError(f"{action}: pct must be between {low} and {high} (got {pct})")
        out["pct"] = pct
    if action == "new_tool":
        allowed.add("tool")
        tool = _whole(args.get("tool"), "tool")
        if not 0 <= tool <= UINT32_MAX:
            raise ValueError(f"tool must be between 0 and {UINT32_MAX} (got {tool})")
        out["tool"] = tool
    extra = sorted(set(args) - allowed)
    if extra:
        raise ValueError(f"{action} takes no {', '.join(extra)}")
    return out
