"""The operator's actions on learned limits (`cmd/limits`, `millsense limits`). Pure.

Each returns {"ok": true, ...} or {"ok": false, "error": one line}; a refused
action changes nothing. What it changed is recorded on the monitor
(`take_changes`, the next `MonitorStep`) so the runner persists it.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from millsense.daemon.learning.keys import KEY_RE, UINT32_MAX, KeyState, seen_outside
from millsense.daemon.learning.process import finite
from millsense.daemon.learning.wear import ToolWear

if TYPE_CHECKING:
    from millsense.daemon.learning.monitor import ProcessMonitor

ACTIONS = ("list", "show", "accept", "relearn", "widen", "narrow", "false_alarm", "new_tool")
MAX_PCT = 500.0


def run_command(m: "ProcessMonitor", args: Any) -> dict[str, Any]:
    """{"action", "key"?, "pct"?, "tool"?} → {"ok", "error"?, ...}."""
    if not isinstance(args, dict):
        return _refused("arguments must be a JSON object")
    action = args.get("action")
    if action not in ACTIONS:
        return _refused(f"unknown action {action!r} (one of {', '.join(ACTIONS)})")
    if action == "list":
        return {"ok": True, "action": action, **m.limits_summary()}
    if action == "new_tool":
        return _new_tool(m, args.get("tool"))
    key = args.get("key")
    if not isinstance(key, str) or not KEY_RE.match(key):
        return _refused(f"{action} needs a key \"program/tool/operation\", e.g. \"1234/12/3\", not {key!r}")
    ks = m.keys.get(key)
    if ks is None:
        return _refused(f"no learned limits for {key} (known: {', '.join(sorted(m.keys)) or 'none'})")
    if action == "show":
        return {"ok": True, "action": action, **m.show(key)}
    if action == "relearn":
        m.keys[key] = KeyState()
        return _done(m, action, key)
    if ks.envelope is None:
        return _refused(f"{key} is still learning ({len(ks.taught)} of {m.target} processes): nothing to {action}")
    if action == "accept":
        if ks.state != "pending":
            return _refused(f"{key} is {ks.state}, not pending: nothing to accept")
        ks.state = "active"
        return _done(m, action, key)
    if action in ("widen", "narrow"):
        pct = args.get("pct")
        pct = None if isinstance(pct, (bool, str)) else finite(pct)
        top = 99.0 if action == "narrow" else MAX_PCT
        if pct is None or not 0 < pct <= top:
            return _refused(f"{action} needs pct, a number above 0 and at most {top:g}, not {args.get('pct')!r}")
        getattr(ks.envelope, action)(pct)
        return _done(m, action, key, pct=pct)
    return _false_alarm(m, key, ks)


def _false_alarm(m: "ProcessMonitor", key: str, ks: KeyState) -> dict[str, Any]:
    alarms = ks.last_alarms
    proc = m.proc
    if proc is not None and proc.key == key and proc.raised:
        # the alarm is in the process still running: what it has seen so far
        alarms = seen_outside(proc)
    if not alarms:
        return _refused(f"no envelope alarm of {key} to mark false")
    for alarm in alarms:
        ks.envelope.false_alarm(alarm["level"], alarm["quantity"], alarm["observed"])
    ks.last_alarms = []
    return _done(m, "false_alarm", key, alarms=[{k: a[k] for k in ("level", "quantity", "process")} for a in alarms])


def _new_tool(m: "ProcessMonitor", tool: Any) -> dict[str, Any]:
    if isinstance(tool, bool) or not isinstance(tool, int) or not 0 <= tool <= UINT32_MAX:
        return _refused(f"new_tool needs tool, a tool number 0 … {UINT32_MAX}, not {tool!r}")
    m.tools.setdefault(tool, ToolWear()).new_tool()
    m.changed_by_command(tools={tool})
    return {"ok": True, "action": "new_tool", "tool": tool}


def _done(m: "ProcessMonitor", action: str, key: str, **extra: Any) -> dict[str, Any]:
    m.changed_by_command(keys={key})
    return {"ok": True, "action": action, "key": key, "state": m.keys[key].state, **extra}


def _refused(error: str) -> dict[str, Any]:
    return {"ok": False, "error": error}
