"""`millsense reset`: ask a running daemon to clear a latched interlock.

Over Zenoh (`millsense/<machine>/cmd/reset`) by the challenge–response of
docs/zenoh.md: the token never leaves this process, and the daemon's answer is
believed only when its MAC proves that it knows the token too. Prints the
daemon's result (the new interlock state) as one JSON line. Exit 0 when the
daemon cleared the hold, 1 when it refused or nobody answered (nothing ran),
3 when the proof went out and no answer came that can be trusted (none, or
one that fails the daemon's MAC): the outcome is unknown, and the message
says how to check.

The machine is never guessed (publish/cli_args.py, `Target`): `--machine`,
or `--config`'s; without either, on a network named by `--connect` with
scouting off, the one daemon alive there (with several, it names them and
asks to choose); else the default config's, the demo's (`mch10-demo`). The
machine not named is said on stderr.

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

from millsense.daemon.local_socket import CLIENT_TIMEOUT_S
from millsense.daemon.publish.cli_args import (
    EXIT_UNKNOWN,
    Target,
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
    parser.add_argument("--machine", "-m", metavar="ID", default=None, help="the machine id of the daemon (default: --config's; else the only one on "
                        "--connect with --no-scouting; else the demo's)")
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
    if args.local:
        return _local(target.machine, args.timeout)
    try:
        token = read_token(args)
    except ValueError as exc:
        return _fail(f"error: {exc}")
    return _over_zenoh(args, target, token)


def _local(machine: str, timeout_s: float) -> int:
    from millsense.daemon.state_dir import daemon_state_dir
    from millsense.daemon.local_socket import LocalControlError, local_command

    try:
        result = local_command(daemon_state_dir(machine), "reset", timeout_s)
    except LocalControlError as exc:
        return _fail(f"error: {exc}")
    print(json.dumps(result))
    if result.get("ok") is False:
        return _fail(f"{machine} refused the reset: {result.get('error') or result}")
    return 0


def _over_zenoh(args: argparse.Namespace, target: Target, token: str | None) -> int:
    from millsense.daemon.publish.command_auth import CommandError, exchange, others_warning

    opened = open_machine_session(args, target, PROG, *HINT_MORE)
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
            return _fail(command_error_text(exc, opened, "reset", args, target.daemon, token),
                         EXIT_UNKNOWN if exc.unknown else 1)
        print(json.dumps(outcome.result))
        if not outcome.verified:
            print(f'{PROG}: note: {machine} takes commands from anyone (reset = "open"): this answer cannot be '
                  "verified", file=sys.stderr)
        if outcome.others:
            print(others_warning(PROG, machine, "reset", outcome.others), file=sys.stderr)
        if outcome.result.get("ok") is False:
            return _fail(f"{machine} refused the reset: {outcome.result.get('error') or outcome.result}")
        return 0
    finally:
        session.close()
