"""`millsense afc`: switch a daemon's adaptive feed control on or off, or see its state (docs/afc.md).

Its actions are listed in ACTIONS_HELP below, which `--help` prints.
`status` reads the `status` queryable (no token), as `millsense limits list`
reads `limits`; `on` and `off` are commands on `cmd/afc`, authorised by the
token's proof and audited like `millsense reset` (the challenge–response of
docs/zenoh.md; the token from `--token-file`, `--token` or
MILLSENSE_RESET_TOKEN), or through the daemon's control socket with `--local`;
never open: under `reset = "open"` only `--local` takes them.
AFC starts as `[afc] enabled` says (default off). `--machine`, `--config`, `--connect`,
`--timeout` find the daemon as `reset` does. Human lines by default, one JSON
object with `--json`. Exit 0 when done, 1 when refused or unanswered (nothing
ran), 2 for a bad argument, 3 when the outcome is unknown (docs/zenoh.md), 78
for an unreadable --config.
"""

from __future__ import annotations

import argparse
import json
from typing import Any

from millsense.daemon.publish.operator_command import OperatorCommand, Read

COMMAND = OperatorCommand("millsense afc", "afc")
PROG = COMMAND.prog

# The actions as `--help` prints them (a constant, not the docstring: the service runs with -OO)
ACTIONS_HELP = """\
    millsense afc status       the controller's state, target, commanded and applied override
    millsense afc on           hold each allowed cut at its target load through the feed override
    millsense afc off          back to the programmed feed: the override returns to 100 % at once
"""
ACTIONS = ("on", "off", "status")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("action", choices=list(ACTIONS), help="on, off, or status")
    COMMAND.add_arguments(parser)
    parser.epilog = ACTIONS_HELP
    parser.formatter_class = argparse.RawDescriptionHelpFormatter


def _fail(message: str, code: int = 1) -> int:
    return COMMAND.fail(message, code)


def run(args: argparse.Namespace) -> int:
    request = {"action": args.action}
    # status: the `status` queryable's `afc`, no token (as `limits list` reads `limits`)
    read = Read("status", None, _status_afc) if args.action == "status" else None
    return COMMAND.run(args, request, read, lambda machine, reply: _report(machine, args.action, reply, args.json))


def _status_afc(body: dict[str, Any]) -> dict[str, Any]:
    """The status payload's `afc` as the command's reply."""
    if not isinstance(body.get("afc"), dict):
        return {"ok": False, "error": "its status carries no \"afc\": a daemon without adaptive feed control"}
    return {"ok": True, "action": "status", "afc": body["afc"]}


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
