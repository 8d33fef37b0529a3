"""`millsense limits`: see and change the limits a daemon learned, per process (program/tool/operation).

    millsense limits list                      every key: learning, pending or active; the tools' life and wear
    millsense limits show KEY                  one key's envelope
    millsense limits accept KEY                activate a learned envelope waiting for it ([learning] confirm)
    millsense limits relearn KEY               forget it; the next good processes teach it again
    millsense limits widen KEY --pct N         widen its band by N %
    millsense limits narrow KEY --pct N        narrow it by N % (never below the configured floors)
    millsense limits false-alarm KEY           the last alarm of KEY was false: widen the band where it fired
    millsense limits new-tool TOOL             a new cutter in T<TOOL>: its life count and wear start again

KEY is "program/tool/operation", e.g. 1234/12/3. `list` and `show` read the
`limits` queryable (no token); the others are commands on `cmd/limits`,
authorised and audited exactly like `millsense reset` (the challenge–response
of docs/zenoh.md; the token from `--token-file`, `--token` or
MILLSENSE_RESET_TOKEN), or through the daemon's control socket with `--local`.
`--machine`, `--config`, `--connect`, `--timeout` find the daemon as `reset`
does. Human lines by default, one JSON object with `--json`. Exit 0 when done,
1 when refused or unanswered, 2 for a bad argument, 78 for an unreadable --config.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from typing import Any

from millsense.daemon.pipeline.local_control import CLIENT_TIMEOUT_S
from millsense.daemon.publish.cli_args import (
    EXIT_USAGE,
    DaemonConfig,
    add_config_argument,
    add_token_arguments,
    add_zenoh_arguments,
    command_error_text,
    command_target,
    open_machine_session,
    read_token,
)
from millsense.daemon.publish.limits_args import READS, check_args

PROG = "millsense limits"
ZENOH_TIMEOUT_S = 2.0
LOCAL_TIMEOUT_S = CLIENT_TIMEOUT_S
HINT_MORE = ("a longer --timeout", "at the machine: millsense limits --local")
# The CLI's words (hyphens, as the other subcommands) -> the action of cmd/limits.
ACTIONS = {"list": "list", "show": "show", "accept": "accept", "relearn": "relearn", "widen": "widen",
           "narrow": "narrow", "false-alarm": "false_alarm", "new-tool": "new_tool"}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("action", choices=list(ACTIONS), help="what to do (see below)")
    parser.add_argument("target", nargs="?", default=None, metavar="KEY|TOOL",
                        help="the process key program/tool/operation (e.g. 1234/12/3); for new-tool the tool number")
    parser.add_argument("--pct", type=int, default=None, metavar="N",
                        help="widen / narrow: by how many whole percent of the band")
    parser.add_argument("--json", action="store_true", help="print the daemon's answer as one JSON object")
    parser.add_argument("--machine", "-m", metavar="ID", default=None,
                        help="the machine id of the daemon (default: the only one alive)")
    parser.add_argument("--local", action="store_true",
                        help="ask through the daemon's control socket at the machine (root or the daemon's user)")
    add_config_argument(parser, "its machine id and where to connect")
    add_zenoh_arguments(parser, listen=False)
    add_token_arguments(parser)
    parser.add_argument("--timeout", type=float, default=None, metavar="S",
                        help=f"how long to wait for a reply (default {ZENOH_TIMEOUT_S:g} s; "
                             f"{LOCAL_TIMEOUT_S:g} s with --local)")
    parser.epilog = __doc__.split("\n\n")[1]
    parser.formatter_class = argparse.RawDescriptionHelpFormatter


def _fail(message: str, code: int = 1) -> int:
    print(f"{PROG}: {message}", file=sys.stderr)
    return code


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
    try:
        request = request_args(args.action, args.target, args.pct)
    except ValueError as exc:
        return _fail(f"error: {exc}", EXIT_USAGE)
    target = command_target(args, PROG, ZENOH_TIMEOUT_S, LOCAL_TIMEOUT_S)
    if isinstance(target, int):
        return target
    if args.local:
        return _local(target.machine, request, args)
    token = None
    if request["action"] not in READS:
        try:
            token = read_token(args)
        except ValueError as exc:
            return _fail(f"error: {exc}")
    return _over_zenoh(args, target.machine, target.daemon, request, token)


def _local(machine: str, request: dict[str, Any], args: argparse.Namespace) -> int:
    from millsense.daemon.pipeline.latch_store import daemon_state_dir
    from millsense.daemon.pipeline.local_control import LocalControlError, local_command

    try:
        reply = local_command(daemon_state_dir(machine), "limits", args.timeout, args=request)
    except LocalControlError as exc:
        return _fail(f"error: {exc}")
    return _report(machine, request, reply, args.json)


def _over_zenoh(args: argparse.Namespace, machine: str | None, daemon: DaemonConfig | None,
                request: dict[str, Any], token: str | None) -> int:
    from millsense.daemon.publish.command_auth import CommandError, exchange

    opened = open_machine_session(args, daemon, machine, PROG, *HINT_MORE)
    if isinstance(opened, int):
        return opened
    machine, session, no_daemon_hint = opened.machine, opened.session, opened.no_daemon_hint
    try:
        left = max(0.2, opened.deadline - time.monotonic())
        if request["action"] in READS:
            try:
                reply = _read(session, machine, request.get("key"), left)
            except LookupError:
                return _fail(f"no daemon answered on millsense/{machine}/limits within {args.timeout:g} s\n"
                             f"{no_daemon_hint}")
            return _report(machine, request, reply, args.json)
        try:
            outcome = exchange(session, machine, "limits", token, args=request, timeout_s=left)
        except CommandError as exc:
            if exc.result is not None and args.json:
                print(json.dumps(exc.result))
            return _fail(command_error_text(exc, opened, "limits", args, daemon, token))
        if not outcome.verified:
            print(f'{PROG}: note: {machine} takes commands from anyone (reset = "open"): this answer cannot be '
                  "verified", file=sys.stderr)
        return _report(machine, request, outcome.result, args.json)
    finally:
        session.close()


def _read(session: Any, machine: str, key: str | None, timeout_s: float) -> dict[str, Any]:
    """The `limits` queryable's answer (`{"key": K}` for one key). LookupError: none came; the daemon's
    error reply comes back as `{"ok": false, "error": ...}`."""
    import zenoh

    where = f"millsense/{machine}/limits"
    deadline = time.monotonic() + timeout_s
    querier = session.declare_querier(where, timeout=max(0.1, timeout_s))
    try:
        while not querier.matching_status.matching:  # a fresh session learns remote queryables a moment later
            if time.monotonic() >= deadline:
                raise LookupError(f"no daemon answered on {where} within {timeout_s:g} s")
            time.sleep(0.01)
        payload = json.dumps({"key": key}).encode() if key is not None else None
        for reply in querier.get(payload=payload, encoding=zenoh.Encoding.APPLICATION_JSON):
            sample = reply.ok if reply.ok is not None else reply.err
            try:
                body = json.loads(sample.payload.to_bytes())
            except (UnicodeDecodeError, ValueError):
                continue
            if not isinstance(body, dict):
                continue
            if reply.ok is None:
                body = {"ok": False, "error": body.get("error") or body}
            return body
        raise LookupError(f"no daemon answered on {where} within {timeout_s:g} s")
    finally:
        try:
            querier.undeclare()
        except Exception:  # noqa: BLE001 - the session may be closing
            pass


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
                             if k not in ("key", "program", "tool", "operation", "state", "envelope", "learned", "learn_target")
                             and not isinstance(v, (list, dict)))
            lines.append(f"  {e.get('key')!s:<18} {state:<9}{progress}  {rest}".rstrip())
    tools = reply.get("tools")
    if isinstance(tools, dict) and tools:
        lines.append("  tools:")
        for number, t in sorted(tools.items(), key=lambda kv: str(kv[0])):
            if isinstance(t, dict):
                wear = t.get("wear_pct", t.get("tool_wear_pct"))
                life = t.get("processes", t.get("tool_processes"))
                lines.append(f"    T{number}: {_value(life)} process(es), wear {_value(wear)} %")
    return lines


def _show_lines(machine: str, key: str, reply: dict[str, Any]) -> list[str]:
    body = reply.get("limits") if isinstance(reply.get("limits"), dict) else reply
    lines = [f"{machine}: limits of {key}"]
    for name, value in body.items():
        if name not in ("ok", "action", "key", "machine"):
            lines.append(f"  {name}: {_value(value)}")
    return lines


def _change_lines(machine: str, request: dict[str, Any], reply: dict[str, Any]) -> list[str]:
    action = request["action"]
    what = f"T{request['tool']}" if action == "new_tool" else request["key"]
    done = {"accept": "accepted: its envelope is active", "relearn": "forgotten: the next good processes teach it",
            "widen": f"widened by {request.get('pct')} %", "narrow": f"narrowed by {request.get('pct')} %",
            "false_alarm": "alarm marked false: the band widens where it fired",
            "new_tool": "new tool: life and wear start again"}[action]
    lines = [f"{machine}: {what} {done}"]
    for name, value in reply.items():
        if name not in ("ok", "action", "key", "pct", "tool", "machine"):
            lines.append(f"  {name}: {_value(value)}")
    return lines
