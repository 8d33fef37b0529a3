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
(its `[zenoh]` mode, endpoints, scouting, config_file); the token comes from
`--token-file`, `--token`, the environment variable `MILLSENSE_RESET_TOKEN`, or
the config's `reset_token_file` when this user may read it.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

from millsense.daemon.publish.cli_args import add_zenoh_arguments, check_machine, zenoh_settings_from_args

PROG = "millsense reset"
TOKEN_ENV = "MILLSENSE_RESET_TOKEN"
NO_DAEMON_HINT = ("try: is the daemon running (systemctl status millsense)? Does --connect name its endpoint or "
                  "router (or give --config with its config file)? A longer --timeout? At the machine: "
                  "millsense reset --local")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--machine", "-m", metavar="ID", default=None, help="the machine id of the daemon (default: the only one alive)")
    parser.add_argument("--local", action="store_true",
                        help="ask through the daemon's control socket at the machine (root or the daemon's user)")
    parser.add_argument("--config", "-c", metavar="FILE", default=None,
                        help="the daemon's config: its machine id, where to connect, and its token file if readable")
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
    if check_machine(args.machine, PROG):
        return 2
    if not (0 < args.timeout < 3600):
        return _fail("error: --timeout must be between 0 and 3600 seconds", 2)
    daemon_cfg: dict[str, Any] = {}
    if args.config:
        try:
            daemon_cfg = _read_daemon_config(Path(args.config))
        except ValueError as exc:
            return _fail(f"error: {exc}", 2)
    machine = args.machine or daemon_cfg.get("machine")
    if machine is not None and check_machine(machine, PROG):
        return 2
    if args.local:
        if machine is None:
            return _fail("error: --local needs --machine or --config (to find the daemon's state directory)", 2)
        return _local(machine, args.timeout)
    try:
        token = _token(args, daemon_cfg)
    except ValueError as exc:
        return _fail(f"error: {exc}")
    return _over_zenoh(args, machine, token, daemon_cfg)


def _token(args: argparse.Namespace, daemon_cfg: dict[str, Any]) -> str | None:
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
    return daemon_cfg.get("token")


def _read_daemon_config(path: Path) -> dict[str, Any]:
    """From the daemon's TOML only the machine id, where to connect, and the token if readable.

    Not the whole validated config: this user may not read everything it names,
    and nothing of the daemon's own identity is taken (its listen endpoints are
    where to connect to, not where to listen).
    """
    import tomllib

    try:
        raw = tomllib.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise ValueError(f"--config {path}: cannot be read: {exc.strerror or exc}") from None
    except (UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise ValueError(f"--config {path}: not a TOML file: {exc}") from None
    out: dict[str, Any] = {}
    if isinstance(raw.get("machine"), str):
        out["machine"] = raw["machine"]
    z = raw.get("zenoh") if isinstance(raw.get("zenoh"), dict) else {}
    connect = [str(e) for e in z.get("connect") or []]
    connect += [_loopback(str(e)) for e in z.get("listen") or []]  # the daemon listens there: we are on its host
    out["zenoh"] = SimpleNamespace(
        mode="client" if z.get("mode") == "client" else "peer",
        connect=connect, listen=[],
        multicast_scouting=bool(z.get("multicast_scouting", True)),
        config_file=str(z.get("config_file") or ""),
    )
    il = raw.get("interlock") if isinstance(raw.get("interlock"), dict) else {}
    if isinstance(il.get("reset_token"), str):
        out["token"] = il["reset_token"].strip()
    elif isinstance(il.get("reset_token_file"), str):
        try:
            out["token"] = Path(il["reset_token_file"]).read_text(encoding="utf-8").strip() or None
        except (OSError, UnicodeDecodeError):
            pass  # not ours to read: --token-file or the environment then
    return out


def _loopback(endpoint: str) -> str:
    for any_addr, loop in (("0.0.0.0", "127.0.0.1"), ("[::]", "[::1]")):
        endpoint = endpoint.replace(f"/{any_addr}:", f"/{loop}:")
    return endpoint


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


def _over_zenoh(args: argparse.Namespace, machine: str | None, token: str | None, daemon_cfg: dict[str, Any]) -> int:
    from millsense.daemon.publish.command_auth import CommandError, exchange
    from millsense.daemon.publish.session import ZenohConfigError, ZenohUnavailable, open_session

    settings = zenoh_settings_from_args(args)
    given = settings.model_fields_set
    if "zenoh" in daemon_cfg and not (args.connect or args.zenoh_config):
        settings = daemon_cfg["zenoh"]  # the command line wins; else where the daemon is
        if "mode" in given:
            settings.mode = args.mode
        if "multicast_scouting" in given:
            settings.multicast_scouting = False
    started = time.monotonic()
    try:
        session = open_session(settings, retry_for_s=args.timeout)
    except (ZenohUnavailable, ZenohConfigError) as exc:
        return _fail(f"error: {exc}")
    try:
        deadline = started + args.timeout
        if machine is None:
            machine, code = _only_machine_alive(session, deadline, args.timeout)
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
                return _fail(f"{message}\n{NO_DAEMON_HINT}")
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
        return None, _fail(f"no daemon alive on millsense/*/alive within {_seconds(timeout_s)}\n{NO_DAEMON_HINT}")
    if len(machines) > 1:
        names = ", ".join(sorted(machines))
        return None, _fail(f"several daemons are alive ({names}); choose one with --machine")
    return machines.pop(), 0
