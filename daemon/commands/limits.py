"""`millsense limits`: see and change the limits a daemon learned, per process (program/tool/operation).

Its actions are listed in ACTIONS_HELP below, which `--help` prints.
KEY is "program/tool/operation", e.g. 1234/12/3. `list` and `show` read the
`limits` queryable (no token); the others are commands on `cmd/limits`,
authorised by the token's proof and audited like `millsense reset` (the
challenge–response of docs/zenoh.md; the token from `--token-file`, `--token` or
MILLSENSE_RESET_TOKEN), or through the daemon's control socket with `--local`;
never open: under `reset = "open"` only `--local` takes them.
`--machine`, `--config`, `--connect`, `--timeout` find the daemon as `reset`
does. Human lines by default, one JSON object with `--json`. Exit 0 when done,
1 when refused or unanswered (nothing ran), 2 for a bad argument, 3 when the
outcome is unknown (docs/zenoh.md), 78 for an unreadable --config.
"""

from __future__ import annotations

import argparse
import json
from typing import Any

from millsense.daemon.publish.cli_args import EXIT_USAGE
from millsense.daemon.publish.limits_args import READS, check_args
from millsense.daemon.publish.operator_command import OperatorCommand, Read

COMMAND = OperatorCommand("millsense limits", "limits")
PROG = COMMAND.prog

# The actions as `--help` prints them (a constant, not the docstring: the service runs with -OO)
ACTIONS_HELP = """\
    millsense limits list                      every key: learning, pending or active; the tools' life and wear
    millsense limits show KEY                  one key's envelope
    millsense limits accept KEY                activate a learned envelope waiting for it ([learning] confirm)
    millsense limits relearn KEY               forget it; the next good processes teach it again
    millsense limits widen KEY --pct N         widen its band by N % (in all at most 4x the learned width
                                               since the last relearn, never above the fixed [alarms] limits)
    millsense limits narrow KEY --pct N        narrow it by N % (never below the configured floors)
    millsense limits false-alarm KEY           the last alarm of KEY was false: widen the band where it fired
    millsense limits new-tool TOOL             a new cutter in T<TOOL>: its life count and wear start again
    millsense limits low-off KEY               stop checking KEY's envelope_low and expected_low (a broken flute
                                               or a missing tool then goes unseen by them; audited); low-on KEY:
                                               check them again
    millsense limits import-operations FILE --config CONFIG [--print]
                                               a CSV sheet of operations (program,tool,operation,ae_mm,ap_mm,
                                               fz_mm,vf_mm_min,mode,engagement,material,spindle_rpm) merged into
                                               CONFIG's [learning] operations_file; checked as check-config
                                               (exit 78); restart the daemon to arm them
With an [operations] entry for KEY, widen / narrow / false-alarm also act on its expected band (the physics'),
accept / false-alarm teach the process it kept from teaching, and show gives the expected load beside the
learned one.
"""
# The CLI's words (hyphens, as the other subcommands) -> the action of cmd/limits.
ACTIONS = {"list": "list", "show": "show", "accept": "accept", "relearn": "relearn", "widen": "widen",
           "narrow": "narrow", "false-alarm": "false_alarm", "new-tool": "new_tool", "low-off": "low_off",
           "low-on": "low_on", "import-operations": "import_operations"}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("action", choices=list(ACTIONS), help="what to do (see below)")
    parser.add_argument("target", nargs="?", default=None, metavar="KEY|TOOL|FILE",
                        help="the process key program/tool/operation (e.g. 1234/12/3); for new-tool the tool number; "
                             "for import-operations the CSV file")
    parser.add_argument("--pct", type=int, default=None, metavar="N",
                        help="widen / narrow: by how many whole percent of the band")
    parser.add_argument("--print", action="store_true",
                        help="import-operations: print the merged operations file instead of writing it")
    COMMAND.add_arguments(parser)
    parser.epilog = ACTIONS_HELP
    parser.formatter_class = argparse.RawDescriptionHelpFormatter


def _fail(message: str, code: int = 1) -> int:
    return COMMAND.fail(message, code)


def request_args(action_word: str, target: str | None, pct: int | None) -> dict[str, Any]:
    """The `cmd/limits` args for the command line's words; ValueError (a usage error) otherwise."""
    action = ACTIONS[action_word]
    args: dict[str, Any] = {"action": action}
    if action == "new_tool":
        if target is None or not target.isdigit():
            raise ValueError(f"new-tool needs the tool number, e.g. `{PROG} new-tool 12`")
        args["tool"] = int(target)
    elif action != "list":
        if target is None:
            raise ValueError(f"{action_word} needs a KEY program/tool/operation, e.g. `{PROG} {action_word} 1234/12/3`")
        args["key"] = target
    elif target is not None:
        raise ValueError("list takes no KEY (use show KEY)")
    if action in ("widen", "narrow"):
        if pct is None:
            raise ValueError(f"{action_word} needs --pct N (whole percent)")
        args["pct"] = pct
    elif pct is not None:
        raise ValueError(f"--pct is for widen and narrow, not {action_word}")
    return check_args(args)


def run(args: argparse.Namespace) -> int:
    if args.action == "import-operations":   # a local file, not a command to the daemon
        from millsense.daemon.commands import operations_import
        return operations_import.run(args)
    if args.print:
        return _fail("error: --print is for import-operations", EXIT_USAGE)
    try:
        request = request_args(args.action, args.target, args.pct)
    except ValueError as exc:
        return _fail(f"error: {exc}", EXIT_USAGE)
    read = None
    if request["action"] in READS:  # the `limits` queryable, `{"key": K}` for one key: no token
        read = Read("limits", {"key": request["key"]} if request.get("key") is not None else None)
    return COMMAND.run(args, request, read, lambda machine, reply: _report(machine, request, reply, args.json))


# ---- what the user reads ----------------------------------------------------------------------
def _report(machine: str, request: dict[str, Any], reply: dict[str, Any], as_json: bool) -> int:
    refused = reply.get("ok") is False
    if as_json:
        print(json.dumps(reply))
    elif not refused:
        action = request["action"]
        lines = _list_lines(machine, reply) if action == "list" else (
            _show_lines(machine, request["key"], reply) if action == "show" else _change_lines(machine, request, reply))
        print("\n".join(lines))
    if refused:
        what = request["action"].replace("_", "-")
        return _fail(f"{machine} refused {what}: {reply.get('error') or reply}")
    return 0


def _entries(limits: Any) -> list[dict[str, Any]]:
    """The daemon's per-key summaries as a list, whether it sends a list or an object by key."""
    if isinstance(limits, dict):
        return [{"key": k, **v} if isinstance(v, dict) else {"key": k, "value": v} for k, v in limits.items()]
    return [e for e in limits or [] if isinstance(e, dict)]


def _value(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, list):
        nums = [v for v in value if isinstance(v, (int, float)) and not isinstance(v, bool)]
        if nums and len(nums) == len(value) and len(nums) > 6:
            return f"[{len(nums)} values, {min(nums):.4g} … {max(nums):.4g}]"
    if isinstance(value, (dict, list)):
        return json.dumps(value, separators=(", ", ": "))
    return "–" if value is None else str(value)


def _list_lines(machine: str, reply: dict[str, Any]) -> list[str]:
    entries = _entries(reply.get("limits"))
    aside = [a for a in reply.get("set_aside") or [] if isinstance(a, dict)]
    if reply.get("enabled") is False:
        lines = [f"{machine}: learning is off ([learning] enabled = false): fixed limits only"]
    elif not entries:
        lines = [f"{machine}: no learned limits yet (a process needs context: program, tool, operation)"]
    else:
        lines = [f"{machine}: {len(entries)} process key(s)"]
        for e in sorted(entries, key=lambda e: str(e.get("key"))):
            state = e.get("state") or e.get("envelope") or "?"
            learned, target = e.get("learned"), e.get("learn_target")
            progress = f" {learned}/{target} learned" if learned is not None and target is not None else ""
            rest = "  ".join(f"{k} {_value(v)}" for k, v in e.items()
                             if k not in ("key", "program", "tool", "operation", "state", "envelope", "learned", "learn_target",
                                          "set_aside", "low_check")   # those two: a warning line of their own
                             and not isinstance(v, (list, dict)))
            lines.append(f"  {e.get('key')!s:<18} {state:<9}{progress}  {rest}".rstrip())
            lines += _warnings(e)
    listed = {str(e.get("key")) for e in entries}
    for a in aside:   # a stored row whose key is no process key: only here
        if str(a.get("key")) not in listed:
            lines.append(f"  ! {a.get('key')!s}: stored limits set aside: {a.get('reason')}")
    tools = reply.get("tools")
    if isinstance(tools, dict) and tools:
        lines.append("  tools:")
        for number, t in sorted(tools.items(), key=lambda kv: str(kv[0])):
            if isinstance(t, dict):
                wear = t.get("wear_pct", t.get("tool_wear_pct"))
                life = t.get("processes", t.get("tool_processes"))
                lines.append(f"    T{number}: {_value(life)} process(es), wear {_value(wear)} %")
    return lines


def _warnings(entry: dict[str, Any]) -> list[str]:
    """What an operator must not miss about one key: its stored limits set aside, envelope_low off."""
    out = []
    if entry.get("set_aside"):
        out.append(f"    ! stored limits set aside ({entry['set_aside']}): learning afresh, the fixed limits apply")
    if entry.get("low_check") is False:
        out.append("    ! envelope_low is off for this key (limits low-on KEY turns it on)")
    return out


def _show_lines(machine: str, key: str, reply: dict[str, Any]) -> list[str]:
    body = reply.get("limits") if isinstance(reply.get("limits"), dict) else reply
    lines = [f"{machine}: limits of {key}"] + _warnings(body) + _expected_lines(body)
    for name, value in body.items():
        if name not in ("ok", "action", "key", "machine"):
            lines.append(f"  {name}: {_value(value)}")
    return lines


def _expected_lines(body: dict[str, Any]) -> list[str]:
    """An operation's expected load beside the learned mean, and their ratio (issue 41), in one line each."""
    out = []
    at = body.get("expected_at") if isinstance(body.get("expected_at"), dict) else {}
    for quantity, unit, name in (("torque_nm", "N·m", "torque"), ("force_n", "N", "force")):
        if f"expected_{quantity}" not in body:
            continue
        exp, mean = body.get(f"expected_{quantity}"), body.get(f"learned_mean_{quantity}")
        ratio = body.get(f"learned_to_expected_{name}")
        out.append(f"  expected {name} {_value(exp)} {unit} (at {_value(at.get('spindle_rpm'))} rpm, "
                   f"{_value(at.get('feed_override_pct'))} %, {at.get('from', '?')}); learned mean {_value(mean)} "
                   f"{unit}; learned/expected {_value(ratio)}")
    return out


def _change_lines(machine: str, request: dict[str, Any], reply: dict[str, Any]) -> list[str]:
    action = request["action"]
    what = f"T{request['tool']}" if action == "new_tool" else request["key"]
    done = {"accept": "accepted: its envelope is active", "relearn": "forgotten: the next good processes teach it",
            "widen": f"widened by {request.get('pct')} %", "narrow": f"narrowed by {request.get('pct')} %",
            "false_alarm": "alarm marked false: the band widens where it fired",
            "new_tool": "new tool: life and wear start again",
            "low_off": "envelope_low is off: not checked until low-on",
            "low_on": "envelope_low is on again"}[action]
    lines = [f"{machine}: {what} {done}"]
    for name, value in reply.items():
        if name not in ("ok", "action", "key", "pct", "tool", "machine"):
            lines.append(f"  {name}: {_value(value)}")
    return lines
