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
import os
import sys
import time
from pathlib import Path
from typing import Any

from millsense.daemon.pipeline.local_control import CLIENT_TIMEOUT_S
from millsense.daemon.publish.cli_args import (
    EXIT_USAGE,
    CliUsageError,
    DaemonConfig,
    add_config_argument,
    add_zenoh_arguments,
    command_target,
    hint,
    session_settings,
    strip_rust,
)

PROG = "millsense reset"
TOKEN_ENV = "MILLSENSE_RESET_TOKEN"
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
    tok = parser.add_mutually_exclusive_group()
    tok.add_argument("--token", default=None,
                     help="reset token, if the daemon requires one (other users see it in ps: "
                          f"prefer --token-file or the environment variable {TOKEN_ENV})")
    tok.add_argument("--token-file", metavar="FILE", default=None, help="read the token from FILE (first line)")
    parser.add_argument("--timeout", type=float, default=None, metavar="S",
                        help=f"how long to wait for a reply (default {ZENOH_TIMEOUT_S:g} s; "
                             f"{LOCAL_TIMEOUT_S:g} s with --local)")


def _fail(message: str, code: int = 1) -> int:
    print(f"{PROG}: {message}", file=sys.stderr)
    return code


def _seconds(s: float) -> str:
    return f"{s:g} s"


def run(args: argparse.Namespace) -> int:
    target = command_target(args, PROG, ZENOH_TIMEOUT_S, LOCAL_TIMEOUT_S)
    if isinstance(target, int):
        return target
    daemon, machine = target.daemon, target.machine
    if args.local:
        return _local(machine, args.timeout)
    try:
        token = _token(args)
    except ValueError as exc:
        return _fail(f"error: {exc}")
    return _over_zenoh(args, machine, token, daemon)


def _token(args: argparse.Namespace) -> str | None:
    if args.token_file:
        try:
            lines = Path(args.token_file).read_text(encoding="utf-8").splitlines()
        except (OSError, UnicodeDecodeError) as exc:
            raise ValueError(f"cannot read --token-file {args.token_file}: {exc}") from None
        return lines[0].strip() if lines else ""
    if args.token is not None:
        return args.token
    if os.environ.get(TOKEN_ENV):
        return os.environ[TOKEN_ENV].strip()
    return None


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
    from millsense.daemon.publish.session import ZenohConfigError, ZenohUnavailable, open_session

    try:
        settings = session_settings(args, daemon)
    except CliUsageError as exc:
        return _fail(f"error: {exc}", EXIT_USAGE)
    no_daemon_hint = hint(settings, daemon, *HINT_MORE)
    started = time.monotonic()
    try:
        session = open_session(settings, retry_for_s=args.timeout)
    except ZenohConfigError as exc:
        return _fail(f"error: {strip_rust(str(exc))}")
    except ZenohUnavailable as exc:
        return _fail(f"error: {strip_rust(str(exc))}\n{no_daemon_hint}")
    try:
        deadline = started + args.timeout
        if machine is None:
            machine, code = _only_machine_alive(session, deadline, args.timeout, no_daemon_hint)
            if machine is None:
                return code
        left = max(0.2, deadline - time.monotonic())
        try:
            outcome = exchange(session, machine, "reset", token, timeout_s=left)
        except CommandError as exc:
            if exc.result is not None:
                print(json.dumps(exc.result))
            if exc.no_answer:
                message = str(exc)
                if message.startswith("no daemon answered"):  # the user's timeout, not what was left of it
                    message = f"no daemon answered on millsense/{machine}/cmd/reset within {_seconds(args.timeout)}"
                return _fail(f"{message}\n{no_daemon_hint}")
            if token is None and daemon is not None and daemon.token_file and "none was given" in str(exc):
                return _fail(f"{exc}\ntry: --token-file {daemon.token_file} (the token file its config names, "
                             "if you may read it)")
            return _fail(str(exc))
        print(json.dumps(outcome.result))
        if not outcome.verified:
            print(f'{PROG}: note: {machine} takes commands from anyone (reset = "open"): this answer cannot be '
                  "verified", file=sys.stderr)
        if outcome.result.get("ok") is False:
            return _fail(f"{machine} refused the reset: {outcome.result.get('error') or outcome.result}")
        return 0
    finally:
        session.close()


def _only_machine_alive(session: Any, deadline: float, timeout_s: float, no_daemon_hint: str) -> tuple[str | None, int]:
    machines: set[str] = set()
    while True:
        left = deadline - time.monotonic()
        for reply in session.liveliness().get("millsense/*/alive", timeout=max(0.1, min(left, 0.5))):
            if reply.ok is not None:
                parts = str(reply.ok.key_expr).split("/")
                if len(parts) == 3:
                    machines.add(parts[1])
        if machines or deadline - time.monotonic() <= 0.05:
            break
        time.sleep(0.05)  # the session may still be learning its peers' tokens
    if not machines:
        return None, _fail(f"no daemon alive on millsense/*/alive within {_seconds(timeout_s)}\n{no_daemon_hint}")
    if len(machines) > 1:
        names = ", ".join(sorted(machines))
        return None, _fail(f"several daemons are alive ({names}); choose one with --machine")
    return machines.pop(), 0
