"""The operator's actions on learned limits (`cmd/limits`, `millsense limits`). Pure.

Each returns {"ok": true, ...} or {"ok": false, "error": one line}; a refused
action changes nothing. What it changed is recorded on the monitor
(`take_changes`, the next `MonitorStep`) so the runner persists it.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from millsense.daemon.events import finite
from millsense.daemon.learning.envelope import LOW_MAX_FRACTION, MAX_WIDENING, WideningCapped
from millsense.daemon.learning.expected import LEVELS as EXPECTED_LEVELS
from millsense.daemon.learning.expected import ExpectedWidening
from millsense.daemon.learning.keys import KEY_RE, UINT32_MAX, KeyState, seen_outside
from millsense.daemon.learning.wear import ToolWear

if TYPE_CHECKING:
    from millsense.daemon.learning.monitor import ProcessMonitor

# The one list of actions: `cmd/limits`, `millsense limits` and the local socket check against it
# (publish/limits_args.py imports it). `low_off` / `low_on`: envelope_low off or on for one key.
ACTIONS = ("list", "show", "accept", "relearn", "widen", "narrow", "false_alarm", "new_tool", "low_off", "low_on")
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
    operation = m.has_operation(key)
    if ks is None and operation and action == "show":
        return {"ok": True, "action": action, **m.show(key)}
    if ks is None and operation and action in ("widen", "narrow", "low_off", "low_on", "false_alarm", "accept"):
        if len(m.keys) >= MAX_KEYS_FOR_ACTIONS:
            return _refused(f"{key}: no room for another key ({len(m.keys)} kept)")
        m.keys[key] = KeyState()   # an operation's expected band, before anything was learned
        reply = _on_key(m, action, key, m.keys[key], operation, args)
        if not reply.get("ok"):
            del m.keys[key]   # refused: nothing changed, not even a key made for it
        return reply
    if ks is None:
        return _refused(f"no learned limits for {key} (known: {', '.join(sorted(m.keys)) or 'none'})")
    return _on_key(m, action, key, ks, operation, args)


def _on_key(m: "ProcessMonitor", action: str, key: str, ks: KeyState, operation: bool,
            args: dict[str, Any]) -> dict[str, Any]:
    """An action on one key's state."""
    if action == "show":
        return {"ok": True, "action": action, **m.show(key)}
    if action == "relearn":   # the operator's low-off stays (its own command turns it on); a set-aside row is kept
        m.keys[key] = KeyState(low_check=ks.low_check, set_aside_row=ks.set_aside_row)
        return _done(m, action, key)
    if action in ("low_off", "low_on"):
        return _low_check(m, action, key, ks)
    if action == "accept" and ks.held_back is not None and ks.state == "learning":
        m.teach_held_back(key)   # the process kept from teaching by the expected band: accepted, it teaches
        return _done(m, action, key, taught="the process kept from teaching by the expected band")
    if operation and action in ("widen", "narrow", "false_alarm"):
        return _expected_action(m, action, key, ks, args)
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
            return _refused(f"{action} needs pct, a finite number above 0 and at most {top:g}, not {args.get('pct')!r}")
        try:
            getattr(ks.envelope, action)(pct)
        except WideningCapped as exc:
            return _refused(f"{key}: {exc}")
        return _done(m, action, key, pct=pct, widening=round(ks.envelope.widening(), 3))
    return _false_alarm(m, key, ks)


def _low_check(m: "ProcessMonitor", action: str, key: str, ks: KeyState) -> dict[str, Any]:
    """envelope_low off (or on again) for one key: the one way to stop it (widening never reaches 0)."""
    on = action == "low_on"
    if ks.low_check == on:
        return _refused(f"envelope_low is already {'on' if on else 'off'} for {key}: nothing to change")
    ks.low_check = on
    return _done(m, action, key, low_check=on)


def _pct(action: str, args: dict[str, Any]) -> float | None:
    pct = args.get("pct")
    pct = None if isinstance(pct, (bool, str)) else finite(pct)
    top = 99.0 if action == "narrow" else MAX_PCT
    return pct if pct is not None and 0 < pct <= top else None


def _expected_action(m: "ProcessMonitor", action: str, key: str, ks: KeyState, args: dict[str, Any]) -> dict[str, Any]:
    """widen / narrow / false-alarm of a key with an operation: its expected band (expected.py), and its learned
    envelope too where there is one; every bound checked before anything changes (refused: nothing changed)."""
    if action == "false_alarm":
        return _false_alarm(m, key, ks)
    pct = _pct(action, args)
    if pct is None:
        top = 99.0 if action == "narrow" else MAX_PCT
        return _refused(f"{action} needs pct, a finite number above 0 and at most {top:g}, not {args.get('pct')!r}")
    widening = ks.expected_widening or ExpectedWidening()
    trial = ExpectedWidening(widening.high, widening.low, list(widening.adjustments))
    try:
        getattr(trial, action)(pct)
        if ks.envelope is not None and action == "widen":
            env_now = ks.envelope.widening()
            if env_now * (1.0 + pct / 100.0) > MAX_WIDENING * (1.0 + 1e-9):
                ks.envelope.widen(pct)   # raises WideningCapped with the envelope's own words
    except WideningCapped as exc:
        return _refused(f"{key}: {exc}")
    ks.expected_widening = trial
    extra: dict[str, Any] = {"expected_widening": {"high": round(trial.high, 3), "low": round(trial.low, 3)}}
    if ks.envelope is not None:
        getattr(ks.envelope, action)(pct)
        extra["widening"] = round(ks.envelope.widening(), 3)
    return _done(m, action, key, pct=pct, **extra)


def _false_alarm(m: "ProcessMonitor", key: str, ks: KeyState) -> dict[str, Any]:
    alarms = ks.last_alarms
    proc = m.proc
    if proc is not None and proc.key == key and proc.raised:
        # the alarm is in the process still running: what it has seen so far
        alarms = seen_outside(proc)
    if not alarms:
        return _refused(f"no envelope or expected alarm of {key} to mark false")
    bounded = []
    for a in alarms:
        if a["level"] in EXPECTED_LEVELS:   # the expected band: what was seen, as ratios to the expected load
            ks.expected_widening = ks.expected_widening or ExpectedWidening()
            tol = m.expected.tol if m.expected is not None else 0.25
            if not ks.expected_widening.fit(a["level"], list(a["observed"].values()), tol):
                bounded.append(f"{a['level']} {a['quantity']}")
        elif ks.envelope is not None and not ks.envelope.false_alarm(a["level"], a["quantity"], a["observed"]):
            bounded.append(a["quantity"])
    extra: dict[str, Any] = {}
    if ks.held_back is not None:
        m.teach_held_back(key)   # the alarm was false: the process it kept from teaching teaches
        extra["taught"] = "the process kept from teaching by the expected band"
    ks.last_alarms = []
    if ks.expected_widening is not None:
        extra["expected_widening"] = {"high": round(ks.expected_widening.high, 3),
                                      "low": round(ks.expected_widening.low, 3)}
    if bounded:   # what was seen does not fit within the bounds: say so, the alarm may come again
        extra["bounded"] = (
            f"{', '.join(sorted(set(bounded)))}: the band reached its bounds (at most {MAX_WIDENING:g}× the learned "
            f"width, the high side under the fixed [alarms] limit, the low side at most {LOW_MAX_FRACTION:.0%} below "
            f"the mean; an expected band at most {MAX_WIDENING:g}× [learning] physics_tolerance_pct, its low side at "
            f"most max(tolerance, {LOW_MAX_FRACTION:.0%}) below the expected load); the same alarm may come again: "
            f"relearn {key}, check its [operations] entry, or low-off {key} for envelope_low and expected_low")
    return _done(m, "false_alarm", key, alarms=[{k: a[k] for k in ("level", "quantity", "process")} for a in alarms],
                 **extra)


MAX_KEYS_FOR_ACTIONS = 2000   # monitor.MAX_KEYS (not imported: the monitor imports this module)


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
