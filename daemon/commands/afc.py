"""`millsense afc`: switch a daemon's adaptive feed control on or off, or see its state (docs/afc.md).

    millsense afc status       the controller's state, target, commanded and applied override
    millsense afc on           hold each allowed cut at its target load through the feed override
    millsense afc off          back to the programmed feed: the override returns to 100 % at once

`status` reads the `status` queryable (no token), as `millsense limits list`
reads `limits`; `on` and `off` are commands on `cmd/afc`, authorised and
audited exactly like `millsense reset` (the challenge–response of
docs/zenoh.md; the token from `--token-file`, `--token` or
MILLSENSE_RESET_TOKEN), or through the daemon's control socket with `--local`.
AFC is off at every start of the daemon. `--machine`, `--config`, `--connect`,
`--timeout` find the daemon as `reset` does. Human lines by default, one JSON
object with `--json`. Exit 0 when done, 1 when refused or unanswered, 2 for a
bad argument, 78 for an unreadable --config.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from typing import Any

from millsense.daemon.pipeline.local_control import CLIENT_TIMEOUT_S
from millsense.daemon.publish.cli_args import (
    DaemonConfig,
    add_config_argument,
    add_token_arguments,
    add_zenoh_arguments,
    command_error_text,
    command_target,
    open_machine_session,
    read_token,
)

PROG = "millsense afc"
ACTIONS = ("on", "off", "status")
ZENOH_TIMEOUT_S = 2.0
LOCAL_TIMEOUT_S = CLIENT_TIMEOUT_S
HINT_MORE = ("a longer --timeout", "at the machine: millsense afc --local")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("action", choices=list(ACTIONS), help="on, off, or status")
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


def run(args: argparse.Namespace) -> int:
    request = {"action": args.action}
    target = command_target(args, PROG, ZENOH_TIMEOUT_S, LOCAL_TIMEOUT_S)
    if isinstance(target, int):
        return target
    if args.local:
        return _local(target.machine, request, args)
    token = None
    if args.action != "status":
        try:
            token = read_token(args)
        except ValueError as exc:
            return _fail(f"error: {exc}")
    return _over_zenoh(args, target.machine, target.daemon, request, token)


def _local(machine: str, request: dict[str, str], args: argparse.Namespace) -> int:
    from millsense.daemon.pipeline.latch_store import daemon_state_dir
    from millsense.daemon.pipeline.local_control import LocalControlError, local_command

    try:
        reply = local_command(daemon_state_dir(machine), "afc", args.timeout, args=request)
    except LocalControlError as exc:
        return _fail(f"error: {exc}")
    return _report(machine, request["action"], reply, args.json)


def _over_zenoh(args: argparse.Namespace, machine: str | None, daemon: DaemonConfig | None,
                request: dict[str, str], token: str | None) -> int:
    from millsense.daemon.publish.command_auth import CommandError, exchange

    opened = open_machine_session(args, daemon, machine, PROG, *HINT_MORE)
    if isinstance(opened, int):
        return opened
    machine, session = opened.machine, opened.session
    try:
        left = max(0.2, opened.deadline - time.monotonic())
        if request["action"] == "status":
            try:
                reply = _read_status(session, machine, left)
            except LookupError:
                return _fail(f"no daemon answered on millsense/{machine}/status within {args.timeout:g} s\n"
                             f"{opened.no_daemon_hint}")
            return _report(machine, "status", reply, args.json)
        try:
            outcome = exchange(session, machine, "afc", token, args=request, timeout_s=left)
        except CommandError as exc:
            if exc.result is not None and args.json:
                print(json.dumps(exc.result))
            return _fail(command_error_text(exc, opened, "afc", args, daemon, token))
        if not outcome.verified:
            print(f'{PROG}: note: {machine} takes commands from anyone (reset = "open"): this answer cannot be '
                  "verified", file=sys.stderr)
        return _report(machine, request["action"], outcome.result, args.json)
    finally:
        session.close()


def _read_status(session: Any, machine: str, timeout_s: float) -> dict[str, Any]:
    """`{"ok", "afc"}` from the `status` queryable; LookupError when none came in time."""
    where = f"millsense/{machine}/status"
    deadline = time.monotonic() + timeout_s
    querier = session.declare_querier(where, timeout=max(0.1, timeout_s))
    try:
        while not querier.matching_status.matching:  # a fresh session learns remote queryables a moment later
            if time.monotonic() >= deadline:
                raise LookupError(where)
            time.sleep(0.01)
        for reply in querier.get():
            sample = reply.ok if reply.ok is not None else reply.err
            try:
                body = json.loads(sample.payload.to_bytes())
            except (UnicodeDecodeError, ValueError):
                continue
            if not isinstance(body, dict):
                continue
            if reply.ok is None:
                return {"ok": False, "error": body.get("error") or body}
            if not isinstance(body.get("afc"), dict):
                return {"ok": False, "error": "its status carries no \"afc\": a daemon without adaptive feed control"}
            return {"ok": True, "action": "status", "afc": body["afc"]}
        raise LookupError(where)
    finally:
        try:
            querier.undeclare()
        except Exception:  # noqa: BLE001 - the session may be closing
            pass


# ---- what the user reads ----------------------------------------------------------------------
def _report(machine: str, action: str, reply: dict[str, Any], as_json: bool) -> int:
    refused = reply.get("ok") is False
    if as_json:
        print(json.dumps(reply))
    elif not refused:
        print("\n".join(status_lines(machine, action, reply.get("afc"))))
    if refused:
        reason = reply.get("error") or reply.get("reason") or reply
        return _fail(f"{machine} refused afc {action}: {reason}")
    return 0


def _pct(value: Any) -> str:
    return f"{value:.1f} %" if isinstance(value, (int, float)) and not isinstance(value, bool) else "–"


def status_lines(machine: str, action: str, afc: Any) -> list[str]:
    """The controller's state in a few lines (what `on`/`off` did first)."""
    afc = afc if isinstance(afc, dict) else {}
    head = {"on": "adaptive feed control switched on", "off": "adaptive feed control switched off"}.get(action)
    enabled = afc.get("enabled")
    lines = [f"{machine}: {head}" if head else
             f"{machine}: adaptive feed control {'on' if enabled else 'off' if enabled is False else '?'}"]
    state = str(afc.get("state", "–")) + (f" ({afc['reason']})" if afc.get("reason") else "")
    lines.append(f"  state: {state}")
    if afc.get("available") is False:
        lines.append("  this DAQ has no feed-override output (protocol version 1): no adaptive feed control")
    target = afc.get("target")
    quantity = afc.get("quantity") or "load"
    lines.append(f"  target: {_num(target)} ({quantity})" if target is not None else f"  target: none ({quantity})")
    lines.append(f"  override: commanded {_pct(afc.get('override_pct'))}, applied {_pct(afc.get('applied_pct'))}"
                 f", bounds {_pct(afc.get('min_pct'))} … {_pct(afc.get('max_pct'))}")
    return lines


def _num(value: Any) -> str:
    return f"{value:.4g}" if isinstance(value, (int, float)) and not isinstance(value, bool) else str(value)
