"""`millsense test-trip`: proof test of the feed-hold path, then a reset.

Asks the running daemon to assert feed hold through the same path as a real
trip (reason "test-trip"), prints how long the DAQ took to show it in its
STATUS and, on a protocol-2 DAQ that reports the CNC's context, how long the
CNC took to report "feed held". Then it asks for a reset.

- `--local`: through the daemon's control socket at the machine (root or the
  daemon's user; the state directory from `--config` or `--machine`);
- else over Zenoh (`cmd/test-trip`, then `cmd/reset`), authorised like
  `millsense reset` (`--token-file`, or the environment variable
  MILLSENSE_RESET_TOKEN).

Exit 0 when the daemon confirmed the hold (the DAQ's status, and the CNC's
flag where the DAQ reports it) and granted the reset; 3 when a command's proof
went out and no answer came that can be trusted (its outcome unknown); 1
otherwise. When the test itself failed, no reset is sent: the feed stays held
until someone has looked at the path and runs `millsense reset`.

The machine is never guessed, as for every command (publish/cli_args.py,
`Target`): `--machine`, `--config`'s, the only daemon on a network named by
`--connect` with scouting off, or the demo's; the one not named is said.
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

from millsense.daemon.local_socket import CLIENT_TIMEOUT_S
from millsense.daemon.publish.cli_args import (
    EXIT_UNKNOWN,
    Target,
    add_config_argument,
    add_token_arguments,
    add_zenoh_arguments,
    command_target,
    open_machine_session,
    read_token,
)

PROG = "millsense test-trip"
DEFAULT_TIMEOUT_S = 6.0  # the daemon waits up to 2 s for each confirmation
# At the machine nothing else can answer, and a loaded box answers late: wait (the error says
# when the daemon does not answer at all).
LOCAL_TIMEOUT_S = CLIENT_TIMEOUT_S


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--machine", "-m", metavar="ID", default=None,
                        help="the machine id of the daemon (default: --config's; else the only one on "
                             "--connect with --no-scouting; else the demo's)")
    parser.add_argument("--local", action="store_true",
                        help="ask through the daemon's control socket at the machine (root or the daemon's user)")
    add_config_argument(parser, "its machine id and where to connect")
    add_token_arguments(parser, inline=False)
    parser.add_argument("--timeout", type=float, default=None, metavar="S",
                        help=f"how long to wait for each answer (default {DEFAULT_TIMEOUT_S:g} s; "
                             f"{LOCAL_TIMEOUT_S:g} s with --local)")
    add_zenoh_arguments(parser, listen=False)


def _fail(message: str, code: int = 1) -> int:
    print(f"{PROG}: {message}", file=sys.stderr)
    return code


def run(args: argparse.Namespace) -> int:
    target = command_target(args, PROG, DEFAULT_TIMEOUT_S, LOCAL_TIMEOUT_S)
    if isinstance(target, int):
        return target
    if args.local:
        return _local(target.machine, args.timeout)
    return _zenoh(args, target)


def _local(machine: str, timeout_s: float) -> int:
    from millsense.daemon.state_dir import daemon_state_dir
    from millsense.daemon.local_socket import LocalControlError, local_command

    directory = daemon_state_dir(machine)
    try:
        trip = local_command(directory, "test-trip", timeout_s)
    except LocalControlError as exc:
        return _fail(f"error: {exc}")
    if not _report_trip(machine, trip):
        return 1
    try:
        reset = local_command(directory, "reset", timeout_s)
    except LocalControlError as exc:
        return _fail(f"error: the reset after the test was not answered: {exc}; the feed stays held")
    return _report_reset(machine, reset)


def _zenoh(args: argparse.Namespace, target: Target) -> int:
    try:
        from millsense.daemon.publish.command_auth import CommandError, send_command
    except ImportError:
        return _fail("error: this build has no authorised Zenoh commands; use --local at the machine")
    try:
        token = read_token(args)
    except ValueError as exc:
        return _fail(f"error: {exc}")
    opened = open_machine_session(args, target, PROG, "at the machine: --local")
    if isinstance(opened, int):
        return opened
    machine, session, no_daemon_hint = opened.machine, opened.session, opened.no_daemon_hint
    try:
        try:
            trip = send_command(session, machine, "test-trip", token, timeout_s=args.timeout)
        except CommandError as exc:
            more = f"\n{no_daemon_hint}" if str(exc).startswith("no daemon answered") else ""
            return _fail(f"error: {machine}: test-trip: {exc}{more}", EXIT_UNKNOWN if exc.unknown else 1)
        if not _report_trip(machine, trip):
            return 1
        try:
            reset = send_command(session, machine, "reset", token, timeout_s=args.timeout)
        except CommandError as exc:
            return _fail(f"error: {machine}: the reset after the test was refused or not answered: {exc}; "
                         "the feed stays held", EXIT_UNKNOWN if exc.unknown else 1)
        return _report_reset(machine, reset)
    finally:
        session.close()


def _ms(value: Any) -> str:
    return "–" if value is None else f"{float(value):.1f} ms"


def _report_trip(machine: str, reply: dict[str, Any]) -> bool:
    """Print the measured times; True if the test passed (then the reset is sent)."""
    daq_ms, cnc_ms = reply.get("daq_confirm_ms"), reply.get("cnc_confirm_ms")
    print(f"{machine}: feed hold asserted (reason test-trip)" if daq_ms is not None or reply.get("ok")
          else f"{machine}: test-trip")
    print(f"  DAQ status shows feed hold after: {_ms(daq_ms)}")
    if reply.get("cnc_reports_hold"):
        print(f"  CNC reports feed held after:      {_ms(cnc_ms)}")
    else:
        print("  CNC confirmation: not measured (the DAQ reports no CNC context; protocol 1)")
    if not reply.get("ok"):
        held = reply.get("interlock") == "feed_hold"
        print(f"{PROG}: {machine}: the test failed: {reply.get('error') or reply}"
              + ("; the feed stays held: check the path, then `millsense reset`" if held else ""), file=sys.stderr)
        return False
    return True


def _report_reset(machine: str, reply: dict[str, Any]) -> int:
    if reply.get("ok"):
        print(f"{machine}: reset granted; interlock {reply.get('interlock')}")
        return 0
    print(f"{PROG}: {machine}: the reset after the test was refused: {reply.get('error') or reply}; "
          "the feed stays held", file=sys.stderr)
    return 1
