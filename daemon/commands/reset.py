"""`millsense reset`: ask a running daemon, over Zenoh, to clear a latched interlock.

Queries `millsense/<machine>/cmd/reset` with the JSON payload `{"token": ...}`
(`{}` without a token) and prints the daemon's reply, the new interlock state.
Exit 0 when the daemon accepted, 1 when it refused or nobody answered.

Without `--machine`, the one daemon whose liveliness token `millsense/*/alive`
is visible is asked; with several, it names them and asks to choose, since
clearing a feed hold on the wrong machine is not a guess to make.

The token comes from `--token-file`, `--token`, or else the environment
variable `MILLSENSE_RESET_TOKEN` (a command line is visible to every user).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

from millsense.daemon.publish.cli_args import add_zenoh_arguments, check_machine, zenoh_settings_from_args

PROG = "millsense reset"
TOKEN_ENV = "MILLSENSE_RESET_TOKEN"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--machine", "-m", metavar="ID", default=None, help="the machine id of the daemon (default: the only one alive)")
    add_zenoh_arguments(parser, listen=False)
    tok = parser.add_mutually_exclusive_group()
    tok.add_argument("--token", default=None,
                     help="reset token, if the daemon requires one (other users see it in ps: "
                          f"prefer --token-file or the environment variable {TOKEN_ENV})")
    tok.add_argument("--token-file", metavar="FILE", default=None, help="read the token from FILE (first line)")
    parser.add_argument("--timeout", type=float, default=2.0, metavar="S", help="how long to wait for a reply (default 2 s)")


def _fail(message: str, code: int = 1) -> int:
    print(f"{PROG}: {message}", file=sys.stderr)
    return code


def _seconds(s: float) -> str:
    return f"{s:g} s"


def run(args: argparse.Namespace) -> int:
    from millsense.daemon.publish.session import ZenohConfigError, ZenohUnavailable, open_session

    if check_machine(args.machine, PROG):
        return 2
    if not (0 < args.timeout < 3600):
        return _fail("error: --timeout must be between 0 and 3600 seconds", 2)
    token = args.token
    if args.token_file:
        try:
            lines = Path(args.token_file).read_text(encoding="utf-8").splitlines()
        except (OSError, UnicodeDecodeError) as exc:
            return _fail(f"error: cannot read --token-file {args.token_file}: {exc}")
        token = lines[0].strip() if lines else ""
    if token is None and os.environ.get(TOKEN_ENV):
        token = os.environ[TOKEN_ENV].strip()
    payload = json.dumps({"token": token} if token is not None else {}).encode()

    started = time.monotonic()
    try:
        session = open_session(zenoh_settings_from_args(args), retry_for_s=args.timeout)
    except (ZenohUnavailable, ZenohConfigError) as exc:
        return _fail(f"error: {exc}")
    try:
        deadline = started + args.timeout
        machine = args.machine
        if machine is None:
            machine, code = _only_machine_alive(session, deadline, args.timeout)
            if machine is None:
                return code
        return _ask(session, machine, payload, deadline, args.timeout)
    finally:
        session.close()


def _only_machine_alive(session: Any, deadline: float, timeout_s: float) -> tuple[str | None, int]:
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
        return None, _fail(f"no daemon alive on millsense/*/alive within {_seconds(timeout_s)}")
    if len(machines) > 1:
        names = ", ".join(sorted(machines))
        return None, _fail(f"several daemons are alive ({names}); choose one with --machine")
    return machines.pop(), 0


def _ask(session: Any, machine: str, payload: bytes, deadline: float, timeout_s: float) -> int:
    import zenoh

    key = f"millsense/{machine}/cmd/reset"
    no_answer = f"no daemon answered on {key} within {_seconds(timeout_s)}"
    querier = session.declare_querier(key)
    try:
        # A fresh session learns remote queryables a moment after it opens: wait until
        # one matches rather than sending a query that nobody is known to receive.
        while not querier.matching_status.matching:
            if time.monotonic() >= deadline:
                return _fail(no_answer)
            time.sleep(0.01)
        left = max(0.05, deadline - time.monotonic())
        replies = list(session.get(key, payload=payload, encoding=zenoh.Encoding.APPLICATION_JSON, timeout=left))
    finally:
        querier.undeclare()
    if not replies:
        return _fail(no_answer)
    code = 0
    for reply in replies:
        if reply.ok is not None:
            body = _parse(reply.ok.payload.to_bytes())
            print(json.dumps(body))
            if isinstance(body, dict) and body.get("ok") is False:
                code = 1
                print(f"{PROG}: {machine} refused the reset: {body.get('error') or body.get('reason') or body}", file=sys.stderr)
        else:
            body = _parse(reply.err.payload.to_bytes())
            reason = body.get("error", body) if isinstance(body, dict) else body
            print(f"{PROG}: {machine} refused the reset: {reason}", file=sys.stderr)
            code = 1
    return code


def _parse(data: bytes) -> Any:
    try:
        return json.loads(data)
    except (UnicodeDecodeError, ValueError):
        return data.decode("utf-8", "replace")
