"""What every operator command shares (`millsense limits`, `millsense afc`): one way to reach a daemon.

Its options (`--json`, `--machine`, `--local`, `--config`, the Zenoh options, the
token, `--timeout`); at the machine, the daemon's control socket (`--local`);
over Zenoh, a read on a queryable that needs no token, or a command on
`cmd/<name>`, authorised by the challenge–response of docs/zenoh.md exactly like
`millsense reset`. The command module says only what it asks and how its answer
reads. The machine is never guessed (cli_args.Target). Exit 0 when done, 1 when
refused or unanswered (nothing ran), 2 for a bad argument, 3 when the command's
proof went out and no answer came that can be trusted (the outcome is unknown:
the message says how to check), 78 for an unreadable --config.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from millsense.daemon.local_socket import CLIENT_TIMEOUT_S
from millsense.daemon.publish.cli_args import (
    EXIT_UNKNOWN,
    add_config_argument,
    add_token_arguments,
    add_zenoh_arguments,
    command_error_text,
    command_target,
    open_machine_session,
    read_token,
)

ZENOH_TIMEOUT_S = 2.0


@dataclass(frozen=True)
class Read:
    """A request answered by a queryable that needs no token: `millsense/<machine>/<queryable>`."""

    queryable: str
    payload: dict[str, Any] | None = None
    # the queryable's body -> the command's reply (e.g. the `afc` part of the status payload)
    shape: Callable[[dict[str, Any]], dict[str, Any]] = lambda body: body


@dataclass(frozen=True)
class OperatorCommand:
    prog: str       # "millsense afc"
    command: str    # the control socket's command, and cmd/<command> on Zenoh

    @property
    def hints(self) -> tuple[str, str]:
        return ("a longer --timeout", f"at the machine: {self.prog} --local")

    def add_arguments(self, parser: argparse.ArgumentParser) -> None:
        parser.add_argument("--json", action="store_true", help="print the daemon's answer as one JSON object")
        parser.add_argument("--machine", "-m", metavar="ID", default=None,
                            help="the machine id of the daemon (default: --config's; else the only one on "
                                 "--connect with --no-scouting; else the demo's)")
        parser.add_argument("--local", action="store_true",
                            help="ask through the daemon's control socket at the machine (root or the daemon's user)")
        add_config_argument(parser, "its machine id and where to connect")
        add_zenoh_arguments(parser, listen=False)
        add_token_arguments(parser)
        parser.add_argument("--timeout", type=float, default=None, metavar="S",
                            help=f"how long to wait for a reply (default {ZENOH_TIMEOUT_S:g} s; "
                                 f"{CLIENT_TIMEOUT_S:g} s with --local)")

    def fail(self, message: str, code: int = 1) -> int:
        print(f"{self.prog}: {message}", file=sys.stderr)
        return code

    def run(self, args: argparse.Namespace, request: dict[str, Any], read: Read | None,
            report: Callable[[str, dict[str, Any]], int]) -> int:
        """Ask the daemon; `read`: how to answer `request` without a token (None: it is a command).
        `report(machine, reply)` prints the answer and gives the exit code."""
        target = command_target(args, self.prog, ZENOH_TIMEOUT_S, CLIENT_TIMEOUT_S)
        if isinstance(target, int):
            return target
        if args.local:
            return self._local(target.machine, request, args, report)
        token = None
        if read is None:
            try:
                token = read_token(args)
            except ValueError as exc:
                return self.fail(f"error: {exc}")
        return self._over_zenoh(args, target, request, read, token, report)

    def _local(self, machine: str, request: dict[str, Any], args: argparse.Namespace,
               report: Callable[[str, dict[str, Any]], int]) -> int:
        from millsense.daemon.state_dir import daemon_state_dir
        from millsense.daemon.local_socket import LocalControlError, local_command

        try:
            reply = local_command(daemon_state_dir(machine), self.command, args.timeout, args=request)
        except LocalControlError as exc:
            return self.fail(f"error: {exc}")
        return report(machine, reply)

    def _over_zenoh(self, args: argparse.Namespace, target: Any, request: dict[str, Any], read: Read | None,
                    token: str | None, report: Callable[[str, dict[str, Any]], int]) -> int:
        from millsense.daemon.publish.command_auth import CommandError, exchange, others_warning

        opened = open_machine_session(args, target, self.prog, *self.hints)
        if isinstance(opened, int):
            return opened
        machine, session = opened.machine, opened.session
        try:
            left = max(0.2, opened.deadline - time.monotonic())
            if read is not None:
                where = f"millsense/{machine}/{read.queryable}"
                try:
                    body = query_json(session, where, read.payload, left)
                except LookupError:
                    return self.fail(f"no daemon answered on {where} within {args.timeout:g} s\n"
                                     f"{opened.no_daemon_hint}")
                return report(machine, body if body.get("ok") is False else read.shape(body))
            try:
                outcome = exchange(session, machine, self.command, token, args=request, timeout_s=left)
            except CommandError as exc:
                if exc.result is not None and args.json:
                    print(json.dumps(exc.result))
                return self.fail(command_error_text(exc, opened, self.command, args, target.daemon, token),
                                 EXIT_UNKNOWN if exc.unknown else 1)
            if not outcome.verified:
                print(f'{self.prog}: note: {machine} takes commands from anyone (reset = "open"): this answer '
                      "cannot be verified", file=sys.stderr)
            if outcome.others:
                print(others_warning(self.prog, machine, self.command, outcome.others), file=sys.stderr)
            return report(machine, outcome.result)
        finally:
            session.close()


def query_json(session: Any, where: str, payload: dict[str, Any] | None, timeout_s: float) -> dict[str, Any]:
    """The first JSON object a queryable answers; its error reply as `{"ok": false, "error": ...}`.
    LookupError: none came within `timeout_s`."""
    import zenoh

    deadline = time.monotonic() + timeout_s
    querier = session.declare_querier(where, timeout=max(0.1, timeout_s))
    try:
        while not querier.matching_status.matching:  # a fresh session learns remote queryables a moment later
            if time.monotonic() >= deadline:
                raise LookupError(f"no daemon answered on {where} within {timeout_s:g} s")
            time.sleep(0.01)
        data = json.dumps(payload).encode() if payload is not None else None
        for reply in querier.get(payload=data, encoding=zenoh.Encoding.APPLICATION_JSON):
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
