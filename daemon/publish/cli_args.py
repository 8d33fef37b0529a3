"""Zenoh options shared by `millsense watch`, `reset`, `test-trip`, `limits` and `afc`.

They are short-lived tools, not the daemon: they take the session settings from
the command line (or the operator's own Zenoh JSON5 file for TLS) and, given
`--config FILE` (the daemon's TOML), where to find the daemon. From that file
they take only where to connect: the machine id, `[zenoh]` mode, endpoints and
scouting, and the same from the JSON5 `config_file` it points at. Never the
daemon's TLS identity (its certificate and private key stay in its file, which
is not handed to Zenoh) and never its reset token: a secret is given on purpose
(`--token-file`, the environment), not picked up because a file was readable.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import Any

from millsense.daemon.publish.session import endpoints_arg

MACHINE_RE = re.compile(r"^[A-Za-z0-9_-]+\Z")
EXIT_USAGE = 2
# A command's proof went out and no answer came back that can be trusted (none, or one that fails the daemon's
# MAC): it may have run. Distinct from 1 (refused, or nothing sent) so that a script does not take it for either.
EXIT_UNKNOWN = 3
EXIT_CONFIG = 78

class CliUsageError(ValueError):
    """A bad option value; the message is one line, the exit code 2."""


class DaemonConfigError(ValueError):
    """The `--config` file cannot be read for where the daemon is; the message names the key; exit 78."""


def add_zenoh_arguments(parser: argparse.ArgumentParser, *, listen: bool = True) -> None:
    g = parser.add_argument_group("Zenoh")
    g.add_argument(
        "--connect", "-e", action="append", metavar="ENDPOINT", default=[],
        help="endpoint to connect to, e.g. tcp/10.0.0.5:7447 (repeatable, or comma-separated); wins over --config",
    )
    if listen:
        g.add_argument("--listen", "-l", action="append", metavar="ENDPOINT", default=[], help="endpoint to listen on (repeatable)")
    g.add_argument("--mode", choices=("peer", "client"), default=None, help="Zenoh mode (default: peer)")
    g.add_argument("--no-scouting", action="store_true", help="turn multicast scouting off (then give --connect)")
    g.add_argument("--zenoh-config", metavar="FILE", default="",
                   help="your own Zenoh JSON5 file (TLS identity, auth); the options above override it")


def add_config_argument(parser: argparse.ArgumentParser, what: str) -> None:
    parser.add_argument("--config", "-c", metavar="FILE", default=None,
                        help=f"the daemon's configuration: {what} (never its keys or token)")


def endpoint_problem(endpoint: str) -> str | None:
    """Why `endpoint` cannot be a Zenoh endpoint, or None: the config's own rule (`[zenoh] connect`).

    Zenoh itself takes `tcp/garbage` and fails later, quietly for a peer, and
    what it says about `garbage` carries a Rust source path: so check first.
    """
    from millsense.daemon.config.models import endpoint_problem as problem

    return problem(endpoint)


def checked_endpoints(values: list[str] | None, option: str) -> list[str]:
    endpoints = endpoints_arg(values)
    for e in endpoints:
        problem = endpoint_problem(e)
        if problem:
            raise CliUsageError(f"{option}: {problem}")
    return endpoints


def zenoh_settings_from_args(args: argparse.Namespace) -> SimpleNamespace:
    """A settings object for `open_session`, with only what the user gave marked explicit.

    Raises CliUsageError for an endpoint that is not one.
    """
    zs = SimpleNamespace(
        connect=checked_endpoints(args.connect, "--connect"),
        listen=checked_endpoints(getattr(args, "listen", []), "--listen"),
        config_file=args.zenoh_config or "",
    )
    fields_set = {"connect", "listen", "config_file"}
    zs.mode = args.mode or "peer"
    if args.mode:
        fields_set.add("mode")
    zs.multicast_scouting = not args.no_scouting
    if args.no_scouting:
        fields_set.add("multicast_scouting")
    zs.model_fields_set = fields_set  # read by session._explicit: defaults never override the JSON5 file
    return zs


@dataclass
class DaemonConfig:
    """What a CLI tool takes from the daemon's TOML: who it is and where to find it."""

    path: Path
    machine: str | None = None
    mode: str = "peer"
    connect: list[str] = field(default_factory=list)
    multicast_scouting: bool = True
    tls: bool = False  # the daemon's links are TLS/QUIC: connecting needs the operator's own JSON5
    token_file: str | None = None  # named in hints, never read


def read_daemon_config(path_text: str) -> DaemonConfig:
    """Where the daemon of `path_text` can be reached. Raises DaemonConfigError.

    Not the whole validated config: this user may not read everything it names.
    The daemon's listen endpoints become endpoints to connect to (on its host: a
    wildcard address becomes loopback); its own connect endpoints (a router, a
    peer) are where it is reachable too.
    """
    import tomllib

    path = Path(path_text)
    try:
        raw = tomllib.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise DaemonConfigError(f"--config {path}: cannot be read: {exc.strerror or exc}") from None
    except (UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise DaemonConfigError(f"--config {path}: not a TOML file: {exc}") from None
    out = DaemonConfig(path=path)
    if isinstance(raw.get("machine"), str):
        out.machine = raw["machine"]
    z = raw.get("zenoh") if isinstance(raw.get("zenoh"), dict) else {}
    json5 = _json5_connection(path, z.get("config_file"))
    mode = z.get("mode", json5.get("mode"))
    out.mode = "client" if mode == "client" else "peer"
    connect = z.get("connect") if "connect" in z else json5.get("connect", [])
    listen = z.get("listen") if "listen" in z else json5.get("listen", [])
    endpoints = [str(e) for e in connect or []] + [_loopback(str(e)) for e in listen or []]
    out.connect = [e for e in dict.fromkeys(endpoints) if endpoint_problem(e) is None]
    scouting = z.get("multicast_scouting", json5.get("multicast_scouting", True))
    out.multicast_scouting = scouting is not False
    out.tls = any(e.split("/", 1)[0] in ("tls", "quic") for e in out.connect)
    il = raw.get("interlock") if isinstance(raw.get("interlock"), dict) else {}
    if isinstance(il.get("reset_token_file"), str):
        out.token_file = str(_relative_to(path, il["reset_token_file"]))
    return out


def _relative_to(config_path: Path, name: str) -> Path:
    p = Path(name)
    return p if p.is_absolute() else config_path.resolve().parent / p


def _json5_connection(config_path: Path, config_file: Any) -> dict[str, Any]:
    """Mode, endpoints and scouting from the daemon's Zenoh JSON5 file, nothing else of it."""
    if not config_file:
        return {}
    import zenoh

    path = _relative_to(config_path, str(config_file))
    try:
        conf = zenoh.Config.from_file(str(path))
    except Exception as exc:  # noqa: BLE001 - zenoh's error carries a Rust source path
        reason = "does not exist" if not path.is_file() else f"is not a Zenoh config ({strip_rust(str(exc))})"
        raise DaemonConfigError(f"--config {config_path}: zenoh.config_file: {path} {reason}") from None
    default = zenoh.Config()
    out: dict[str, Any] = {}
    mode = json.loads(conf.get_json("mode"))
    if mode in ("peer", "client"):
        out["mode"] = mode
    for name in ("connect", "listen"):
        key = f"{name}/endpoints"
        value = json.loads(conf.get_json(key))
        if value == json.loads(default.get_json(key)):
            continue  # Zenoh's default (listen on port 0): not where the daemon is
        if isinstance(value, dict):  # per-mode endpoints
            value = value.get(mode or "peer", [])
        out[name] = value if isinstance(value, list) else []
    scouting = json.loads(conf.get_json("scouting/multicast/enabled"))
    if isinstance(scouting, bool):
        out["multicast_scouting"] = scouting
    return out


def _loopback(endpoint: str) -> str:
    for any_addr, loop in (("0.0.0.0", "127.0.0.1"), ("[::]", "[::1]")):
        endpoint = endpoint.replace(f"/{any_addr}:", f"/{loop}:")
    return endpoint


def session_settings(args: argparse.Namespace, daemon: DaemonConfig | None) -> SimpleNamespace:
    """The command line over the daemon's config: `--connect` or `--zenoh-config` replace its endpoints.

    Raises CliUsageError.
    """
    zs = zenoh_settings_from_args(args)
    if daemon is None or args.connect or args.zenoh_config:
        return zs
    zs.connect = list(daemon.connect)
    if not args.mode:
        zs.mode = daemon.mode
    if not args.no_scouting:
        zs.multicast_scouting = daemon.multicast_scouting
    zs.model_fields_set = zs.model_fields_set | {"mode", "multicast_scouting"}
    return zs


def client_settings(args: argparse.Namespace, prog: str) -> tuple[DaemonConfig | None, SimpleNamespace] | int:
    """A reading client's connection (`watch`, `dashboard`, `opcua`): the daemon's config (`--config`) under the
    Zenoh options; or the exit code, said on stderr, when they make none (78: the config; 2: the options)."""
    try:
        daemon = read_daemon_config(args.config) if args.config else None
    except DaemonConfigError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return EXIT_CONFIG
    try:
        return daemon, session_settings(args, daemon)
    except CliUsageError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return EXIT_USAGE


def hint(settings: Any, daemon: DaemonConfig | None, *extra: str) -> str:
    """One `try:` line for "found nothing": what to give next, with the endpoints tried."""
    tried = ", ".join(getattr(settings, "connect", []) or []) or None
    scouting = getattr(settings, "multicast_scouting", True)
    parts: list[str] = []
    if daemon is not None:
        where = tried or "no endpoint (its [zenoh] names none)"
        parts.append(f"is the daemon of {daemon.path} running (systemctl status millsense)? "
                     f"Tried {where} (from --config)")
        if daemon.tls:
            parts.append("its links are TLS: add --zenoh-config with your own TLS file "
                         "(config/zenoh-operator.json5)")
        parts.append("or give --connect ENDPOINT (its host's address, e.g. tcp/10.0.0.5:7447)")
    elif tried:
        parts.append(f"is the daemon running, and is {tried} (your --connect) where it listens? Or give --config "
                     "with its config file (-c /etc/millsense/MACHINE.toml)")
    else:
        parts.append("give --config with the daemon's config file (-c /etc/millsense/MACHINE.toml), or "
                     "--connect ENDPOINT (e.g. tcp/10.0.0.5:7447)")
        if scouting:
            parts.append("the shipped configs turn multicast scouting off, so scouting alone finds no daemon")
    parts.extend(extra)
    return f"try: {'; '.join(parts)}"


def strip_rust(message: str) -> str:
    """Zenoh's errors end with ` at /root/.cargo/...rs:86.`: not for a user's eyes."""
    return re.sub(r" at /\S+\.rs:\d+\.?", "", message).strip()


def check_machine(machine: str | None, prog: str) -> str | None:
    """A clear usage error for a machine id that cannot be a key chunk (no '/', '*', '$')."""
    if machine is not None and not MACHINE_RE.match(machine):
        print(f"{prog}: error: --machine {machine!r}: use letters, digits, '_' and '-' only", file=sys.stderr)
        return "bad"
    return None


@dataclass(frozen=True)
class Target:
    """Which daemon a command (`reset`, `test-trip`, `limits`, `afc`) is for: its config if given, and its machine.

    Never a guess (issue 36, finding 5): the machine is `--machine`, or `--config`'s; else, on a network the
    user named (`network`: endpoints given and multicast scouting off), the only daemon alive there, found
    once the session is open (`machine` None); else the default config's, the demo's (`millsense run` with
    no config runs it), `why` saying so. Whatever was not named is said in the output.
    """

    daemon: DaemonConfig | None
    machine: str | None
    why: str = ""       # how the machine was chosen when it was not named: said on stderr
    network: str = ""   # the endpoints of a named network, where the only daemon alive is taken


def default_machine() -> str:
    """The default config's machine: the built-in demo's (`millsense run` with no `--config`)."""
    import tomllib
    from importlib import resources

    text = resources.files("millsense.daemon").joinpath("demo.toml").read_text(encoding="utf-8")
    return str(tomllib.loads(text)["machine"])


def named_network(args: argparse.Namespace) -> str:
    """The endpoints the user named, when only they are searched (multicast scouting off); "" otherwise.

    On a network found by scouting, "the only daemon alive" is whatever scouting met first: on a host where
    scouting found another daemon, `limits list` answered for the wrong machine.
    """
    try:
        endpoints = checked_endpoints(getattr(args, "connect", None), "--connect")
    except CliUsageError:
        return ""  # said when the session is opened
    scouting = not getattr(args, "no_scouting", False)
    if getattr(args, "zenoh_config", ""):
        try:
            own = _json5_connection(Path.cwd() / "-", str(Path(args.zenoh_config).resolve()))
        except DaemonConfigError:
            return ""  # said when the session is opened
        if not endpoints:
            endpoints = [str(e) for e in own.get("connect", []) or []]
        if not getattr(args, "no_scouting", False):
            scouting = own.get("multicast_scouting", True) is not False
    return ", ".join(endpoints) if endpoints and not scouting else ""


def command_target(args: argparse.Namespace, prog: str, zenoh_timeout_s: float, local_timeout_s: float) -> Target | int:
    """`--machine`, `--config`, `--timeout` and `--local`, checked once: the target, or the exit code after
    printing why. Sets `args.timeout` to its default for `--local` or Zenoh when it was not given."""
    if check_machine(args.machine, prog):
        return EXIT_USAGE
    if args.timeout is None:
        args.timeout = local_timeout_s if args.local else zenoh_timeout_s
    if not (0 < args.timeout < 3600):
        print(f"{prog}: error: --timeout must be between 0 and 3600 seconds", file=sys.stderr)
        return EXIT_USAGE
    try:
        daemon = read_daemon_config(args.config) if args.config else None
    except DaemonConfigError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return EXIT_CONFIG
    machine = args.machine or (daemon.machine if daemon else None)
    if machine is not None and check_machine(machine, prog):
        return EXIT_USAGE
    if args.local and machine is None:
        print(f"{prog}: error: --local needs --machine or --config (to find the daemon's state directory)",
              file=sys.stderr)
        return EXIT_USAGE
    if machine is not None:
        return Target(daemon, machine)
    network = named_network(args)
    if network:
        return Target(daemon, None, network=network)
    return Target(daemon, default_machine(), why="the demo's, the default config: no --machine or --config given")


# ---- the commands' token and session (`reset`, `test-trip`, `limits`, `afc`): one copy -------------------
TOKEN_ENV = "MILLSENSE_RESET_TOKEN"


def add_token_arguments(parser: argparse.ArgumentParser, *, inline: bool = True) -> None:
    """`--token-file FILE` (and, with `inline`, `--token`, which other users see in ps)."""
    tok = parser.add_mutually_exclusive_group()
    if inline:
        tok.add_argument("--token", default=None,
                         help="reset token, if the daemon requires one (other users see it in ps: "
                              f"prefer --token-file or the environment variable {TOKEN_ENV})")
    tok.add_argument("--token-file", metavar="FILE", default=None,
                     help=f"read the token from FILE (first line; or the environment variable {TOKEN_ENV})")


def read_token(args: argparse.Namespace) -> str | None:
    """The token given on purpose: `--token-file`, `--token`, else $MILLSENSE_RESET_TOKEN; None if none.

    Raises ValueError (one sentence) when the file cannot be read.
    """
    import os

    if getattr(args, "token_file", None):
        try:
            lines = Path(args.token_file).read_text(encoding="utf-8").splitlines()
        except (OSError, UnicodeDecodeError) as exc:
            raise ValueError(f"cannot read --token-file {args.token_file}: {exc}") from None
        return lines[0].strip() if lines else ""
    if getattr(args, "token", None) is not None:
        return args.token
    if os.environ.get(TOKEN_ENV):
        return os.environ[TOKEN_ENV].strip()
    return None


@dataclass
class CommandSession:
    """An open Zenoh session for one command, with the `try:` line to print when nobody answers;
    `open_machine_session` adds the machine it is for and the deadline of the user's `--timeout`."""

    session: Any
    settings: Any
    no_daemon_hint: str
    machine: str | None = None
    deadline: float = 0.0


def open_machine_session(args: argparse.Namespace, target: Target, prog: str, *hint_more: str) -> CommandSession | int:
    """`open_command_session`, then the machine of `target`, said on stderr when it was not named: the only
    daemon alive on the named network, or the default config's when it is alive (closed and the exit code,
    after saying who is alive, otherwise)."""
    import time

    started = time.monotonic()
    opened = open_command_session(args, target.daemon, prog, *hint_more)
    if isinstance(opened, int):
        return opened
    opened.deadline = started + args.timeout
    machine = target.machine
    if machine is None:
        machine, code = only_machine_alive(opened.session, opened.deadline, args.timeout, opened.no_daemon_hint,
                                           prog, target.network)
        if machine is None:
            opened.session.close()
            return code
        print(f"{prog}: machine {machine} (the only daemon on {target.network})", file=sys.stderr)
    elif target.why:
        alive = machines_alive(opened.session, opened.deadline, lambda seen: machine in seen)
        if machine not in alive:
            opened.session.close()
            if alive:
                print(f"{prog}: no daemon {machine} alive ({target.why}); alive: {', '.join(sorted(alive))}: "
                      "choose one with --machine, or give its --config", file=sys.stderr)
            else:
                print(f"{prog}: no daemon {machine} alive within {args.timeout:g} s ({target.why})\n"
                      f"{opened.no_daemon_hint}", file=sys.stderr)
            return 1
        print(f"{prog}: machine {machine} ({target.why})", file=sys.stderr)
    opened.machine = machine
    return opened


def command_error_text(exc: Any, opened: CommandSession, command: str, args: argparse.Namespace,
                       daemon: DaemonConfig | None, token: str | None) -> str:
    """What to print when `exchange` raised `CommandError`: nobody answered (with the `try:` line), no
    token where the daemon's config names a token file (with that file), or the daemon's refusal."""
    if exc.unknown:
        return str(exc)   # the proof went out: the message says the outcome is unknown and how to check
    if exc.no_answer:
        message = str(exc)
        if message.startswith("no daemon answered"):  # the user's timeout, not what was left of it
            message = f"no daemon answered on millsense/{opened.machine}/cmd/{command} within {args.timeout:g} s"
        return f"{message}\n{opened.no_daemon_hint}"
    if token is None and daemon is not None and daemon.token_file and "none was given" in str(exc):
        return f"{exc}\ntry: --token-file {daemon.token_file} (the token file its config names, if you may read it)"
    return str(exc)


def open_command_session(args: argparse.Namespace, daemon: DaemonConfig | None, prog: str,
                         *hint_more: str) -> CommandSession | int:
    """The session `args` and the daemon's config say, waiting up to `args.timeout`; or, after printing
    why on stderr, the exit code (2 for a bad option, 1 when Zenoh cannot be opened)."""
    from millsense.daemon.publish.session import ZenohConfigError, ZenohUnavailable, open_session

    try:
        settings = session_settings(args, daemon)
    except CliUsageError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    no_daemon_hint = hint(settings, daemon, *hint_more)
    try:
        session = open_session(settings, retry_for_s=args.timeout)
    except ZenohConfigError as exc:
        print(f"{prog}: error: {strip_rust(str(exc))}", file=sys.stderr)
        return 1
    except ZenohUnavailable as exc:
        print(f"{prog}: error: {strip_rust(str(exc))}\n{no_daemon_hint}", file=sys.stderr)
        return 1
    return CommandSession(session, settings, no_daemon_hint + acl_hint(settings))


def acl_hint(settings: Any) -> str:
    """A second line for "nobody answered" when a router or a Zenoh file is on the way (issue 39): an access
    control that denies a query drops it, so the user hears nothing, as from a stopped daemon. Not on a plain
    peer session (the demo's): no ACL there to blame. Not for a session that could not open (an ACL does
    not refuse a link)."""
    endpoints = [str(e) for e in getattr(settings, "connect", None) or []]
    routed = (bool(getattr(settings, "config_file", "")) or getattr(settings, "mode", "peer") == "client"
              or any(e.split("/", 1)[0] in ("tls", "quic") for e in endpoints))
    if not routed:
        return ""
    return ("\nor: a router's access control (ACL) may deny this identity: what it denies is dropped, and nothing "
            "answers; ask whoever keeps the router's config whether your certificate's name may send this "
            "(docs/security.md, the shop-network example)")


def machines_alive(session: Any, deadline: float, enough: Any) -> set[str]:
    """The machines whose `millsense/*/alive` token is visible, asked until `enough(seen)` holds and two rounds
    agree (a session still learning its peers sees one daemon before it sees two), or until `deadline`."""
    import time

    machines: set[str] = set()
    before: set[str] | None = None
    while True:
        left = deadline - time.monotonic()
        for reply in session.liveliness().get("millsense/*/alive", timeout=max(0.1, min(left, 0.5))):
            if reply.ok is not None:
                parts = str(reply.ok.key_expr).split("/")
                if len(parts) == 3:
                    machines.add(parts[1])
        if (enough(machines) and machines == before) or deadline - time.monotonic() <= 0.05:
            break
        before = set(machines)
        time.sleep(0.05)
    return machines


def only_machine_alive(session: Any, deadline: float, timeout_s: float, no_daemon_hint: str,
                       prog: str, network: str = "") -> tuple[str | None, int]:
    """The one machine whose `millsense/*/alive` token is visible by `deadline`; with none or several,
    (None, 1) after saying so: a command is not sent to a guessed machine."""
    machines = machines_alive(session, deadline, bool)
    where = f" on {network}" if network else ""
    if not machines:
        print(f"{prog}: no daemon alive on millsense/*/alive{where} within {timeout_s:g} s\n{no_daemon_hint}",
              file=sys.stderr)
        return None, 1
    if len(machines) > 1:
        print(f"{prog}: several daemons are alive ({', '.join(sorted(machines))}); choose one with --machine "
              "(or give its --config)", file=sys.stderr)
        return None, 1
    return machines.pop(), 0
