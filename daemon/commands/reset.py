"""`millsense reset`: ask a running daemon to clear a latched interlock.

Over Zenoh (`millsense/<machine>/cmd/reset`) by the challenge–response of
docs/zenoh.md: the token never leaves this process, and the daemon's answer is
believed only when its MAC proves that it knows the token too. Prints the
daemon's result (the new interlock state) as one JSON line. Exit 0 when the
daemon cleared the hold, 1 when it refused, nobody answered, or the answer
could not be trusted.

Without `--machine`, the one daemon whose liveliness token `millsense/*/alive`
is visible is asked; with several, it names them and asks to choose, since
clearing a feed hold on the wrong machine is not a guess to make.

`--local` asks through the daemon's control socket at the machine instead (root
or the daemon's user): it works with `reset = "off"`, with the network down, and
while network commands are paused after failed proofs.

`--config FILE` (the daemon's TOML) gives the machine id and where to connect
(its `[zenoh]` mode, endpoints and scouting, and the same from the JSON5 file
it names), never the daemon's TLS identity nor its token (publish/cli_args.py).
The token comes from `--token-file`, `--token` or the environment variable
`MILLSENSE_RESET_TOKEN`.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

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

PROG = "millsense reset"
HINT_MORE = ("a longer --timeout", "at the machine: millsense reset --local")
ZENOH_TIMEOUT_S = 2.0
# At the machine nothing else can answer, and a loaded box answers late: wait (the error says
# when the daemon does not answer at all).
LOCAL_TIMEOUT_S = CLIENT_TIMEOUT_S


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--machine", "-m", metavar="ID", default=None, help="the machine id of the daemon (default: the only one alive)")
    parser.add_argument("--local", action="store_true",
                        help="ask through the daemon's control socket at the machine (root or the daemon's user)")
    add_config_argument(parser, "its machine id and where to connect")
    add_zenoh_arguments(parser, listen=False)
    add_token_arguments(parser)
    parser.add_argument("--timeout", type=float, default=None, metavar="S",
                        help=f"how long to wait for a reply (default {ZENOH_TIMEOUT_S:g} s; "
                             f"{LOCAL_TIMEOUT_S:g} s with --local)")


def _fail(message: str, code: int = 1) -> int:
    print(f"{PROG}: {message}", file=sys.stderr)
    return code


def run(args: argparse.Namespace) -> int:
    target = command_target(args, PROG, ZENOH_TIMEOUT_S, LOCAL_TIMEOUT_S)
    if isinstance(target, int):
        return target
    daemon, machine = target.daemon, target.machine
    if args.local:
        return _local(machine, args.timeout)
    try:
        token = read_token(args)
    except ValueError as exc:
        return _fail(f"error: {exc}")
    return _over_zenoh(args, machine, token, daemon)


def _local(machine: str, timeout_s: float) -> int:
    from millsense.daemon.pipeline.latch_store import daemon_state_dir
    from millsense.daemon.pipeline.local_control import LocalControlError, local_command

    try:
        result = local_command(daemon_state_dir(machine), "reset", timeout_s)
    except LocalControlError as exc:
        return _fail(f"error: {exc}")
    print(json.dumps(result))
    if result.get("ok") is False:
        return _fail(f"{machine} refused the reset: {result.get('error') or result}")
    return 0


def _over_zenoh(args: argparse.Namespace, machine: str | None, token: str | None, daemon: DaemonConfig | None) -> int:
    from millsense.daemon.publish.command_auth import CommandError, exchange

    opened = open_machine_session(args, daemon, machine, PROG, *HINT_MORE)
    if isinstance(opened, int):
        return opened
    machine, session = opened.machine, opened.session
    try:
        left = max(0.2, opened.deadline - time.monotonic())
        try:
            outcome = exchange(session, machine, "reset", token, timeout_s=left)
        except CommandError as exc:
            if exc.result is not None:
                print(json.dumps(exc.result))
            return _fail(command_error_text(exc, opened, "reset", args, daemon, token))
        print(json.dumps(outcome.result))
        if not outcome.verified:
            print(f'{PROG}: note: {machine} takes commands from anyone (reset = "open"): this answer cannot be '
                  "verified", file=sys.stderr)
        if outcome.result.get("ok") is False:
            return _fail(f"{machine} refused the reset: {outcome.result.get('error') or outcome.result}")
        return 0
    finally:
        session.close()
