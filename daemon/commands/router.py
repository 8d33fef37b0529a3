"""`millsense router`: Zenoh's own router, from the eclipse-zenoh package, for a plant's machines.

A Zenoh session opened in mode "router" is a complete router (routing between
peers and clients, mutual TLS, access control by certificate): the same Rust
code `zenohd` runs, minus its plugins. So a plant needs nothing beyond pip for
the cell router that every daemon, HMI and console connects to. Its
configuration is a Zenoh JSON5 file (config/zenoh-router.json5: TLS and the
ACL that stops spoofing); `--listen` replaces the file's listen endpoints.

Exit codes: 78 for a configuration that cannot work (the message names the
file's key); 69 when it cannot listen (an address in use: systemd retries);
2 for a bad option; 0 after SIGTERM / SIGINT. It logs as the daemon does
(JSON lines under systemd, on stdout) and tells systemd READY=1 once listening.
docs/router.md has the plant's set-up.
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
from pathlib import Path
from typing import Any

from millsense.daemon.publish.cli_args import CliUsageError, checked_endpoints, strip_rust
from millsense.daemon.stop_signals import stop_on_signals

PROG = "millsense router"
EXIT_UNAVAILABLE = 69
EXIT_CONFIG = 78
EXIT_USAGE = 2
# Certificate and key files a TLS (or QUIC) link reads when it starts: checked first, so a wrong path
# is named by its key instead of Zenoh's "Cannot create a new TLS listener".
TLS_FILE_KEYS = ("root_ca_certificate", "listen_private_key", "listen_certificate",
                 "connect_private_key", "connect_certificate")
ENCRYPTED = ("tls", "quic")


class RouterConfigError(ValueError):
    """The router's configuration cannot work; the message names the file and the key."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", "-c", metavar="ROUTER.json5", default=None,
                        help="the router's Zenoh JSON5 file: TLS, access control (config/zenoh-router.json5); "
                             "without it: plain TCP, no access control, for a bench only")
    parser.add_argument("--listen", "-l", action="append", metavar="ENDPOINT", default=[],
                        help="endpoint to listen on, e.g. tls/0.0.0.0:7447 (repeatable, or comma-separated); "
                             "replaces the file's listen endpoints (default: the file's, else Zenoh's tcp/[::]:7447)")
    parser.add_argument("--log-format", choices=("auto", "json", "console"), default="auto",
                        help="log lines: JSON under systemd or into a pipe, readable on a terminal (auto)")


def router_config(config_file: str | None, listen: list[str]) -> Any:
    """The `zenoh.Config` to run: the file, mode "router", `listen` over its endpoints. Raises RouterConfigError."""
    import zenoh

    if config_file:
        path = Path(config_file)
        if not path.is_file():
            raise RouterConfigError(f"--config {path}: does not exist (a Zenoh JSON5 file, e.g. config/zenoh-router.json5)")
        try:
            conf = zenoh.Config.from_file(str(path))
        except Exception as exc:  # noqa: BLE001 - zenoh.ZError: a JSON5 syntax error or an unknown key, with its place
            raise RouterConfigError(f"--config {path}: not a Zenoh configuration: {strip_rust(str(exc))}") from None
        mode = json.loads(conf.get_json("mode"))
        if mode not in (None, "router"):
            raise RouterConfigError(f"--config {path}: mode: {mode!r}, but this file is run as a router: "
                                    "write mode: \"router\" (or leave it out)")
    else:
        conf = zenoh.Config()
        # Explicit endpoints are the project's way; a router without a file is for a bench.
        conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("mode", '"router"')
    if listen:
        conf.insert_json5("listen/endpoints", json.dumps(listen))
    # Off whatever the file says (Zenoh's default is on, so silence cannot be told apart): with it on, any
    # local node that sends a large message makes this process map that node's segment (docs/security.md).
    conf.insert_json5("transport/shared_memory/enabled", "false")
    _check_tls_files(conf, config_file or "")
    return conf


def _check_tls_files(conf: Any, config_file: str) -> None:
    tls = json.loads(conf.get_json("transport/link/tls"))
    for key in TLS_FILE_KEYS:
        value = tls.get(key)
        if not value:
            continue
        try:
            with open(value, "rb"):
                pass
        except OSError as exc:
            raise RouterConfigError(f"--config {config_file}: transport.link.tls.{key}: {value}: "
                                    f"{exc.strerror or exc}") from None


def listen_endpoints(conf: Any) -> list[str]:
    """The endpoints the router listens on (Zenoh's value may be per mode)."""
    value = json.loads(conf.get_json("listen/endpoints"))
    if isinstance(value, dict):
        value = value.get("router", [])
    return [str(e) for e in value or []]


def describe(conf: Any, config_file: str | None) -> dict[str, Any]:
    """Log fields: where it listens, whether links are encrypted, whether access control is on."""
    listen = listen_endpoints(conf)
    acl = json.loads(conf.get_json("access_control/enabled")) is True
    return {
        "listen": listen,
        "encrypted": bool(listen) and all(e.split("/", 1)[0] in ENCRYPTED for e in listen),
        "access_control": acl,
        "config_file": config_file,
    }


def classify_open_error(message: str, config_file: str | None) -> tuple[int, str]:
    """Exit code and message for a failed `zenoh.open` of a router."""
    where = f"--config {config_file}: " if config_file else ""
    if "Access control" in message:
        # e.g. "Access control not enabled due to: Rule 'x' in policy #0 does not exist in rules list"
        return EXIT_CONFIG, f"{where}access_control: {message}"
    if "TLS" in message and ("key" in message or "certificate" in message):
        # a file that exists but is not a PEM key or certificate of the right kind
        return EXIT_CONFIG, f"{where}transport.link.tls: {message}"
    if "listener" in message or "in use" in message:
        return EXIT_UNAVAILABLE, f"cannot listen: {message}"
    return 1, message


def _fail(message: str, code: int) -> int:
    print(f"{PROG}: error: {message}", file=sys.stderr)
    return code


def run(args: argparse.Namespace) -> int:
    try:
        listen = checked_endpoints(args.listen, "--listen")
    except CliUsageError as exc:
        return _fail(str(exc), EXIT_USAGE)
    try:
        conf = router_config(args.config, listen)
    except RouterConfigError as exc:
        return _fail(str(exc), EXIT_CONFIG)

    from millsense.daemon.logging_setup import configure_logging, flush_logs

    configure_logging("info", args.log_format, stream=sys.stdout)  # as the daemon: stdout is the journal
    import structlog

    log = structlog.get_logger("millsense.router")
    fields = describe(conf, args.config)
    stop = threading.Event()
    stop_on_signals(stop, hangup=True)

    import zenoh

    try:
        session = zenoh.open(conf)
    except Exception as exc:  # noqa: BLE001 - zenoh.ZError; its text names what failed
        code, message = classify_open_error(strip_rust(str(exc)), args.config)
        log.error("router.failed", error=message, **fields)
        flush_logs()
        return _fail(message, code)
    try:
        _serve(session, stop, log, fields)
    finally:
        session.close()
    log.info("router.stopped")
    flush_logs()
    return 0


def _serve(session: Any, stop: threading.Event, log: Any, fields: dict[str, Any]) -> None:
    from millsense.daemon import sdnotify

    if not fields["access_control"]:
        log.warning("router.no_access_control",
                    detail="any node that reaches this router may publish under any machine's keys (docs/router.md)")
    if not fields["encrypted"]:
        log.warning("router.unencrypted", detail="links without TLS: nodes are not authenticated by certificate")
    log.info("router.started", zid=str(session.info.zid()), **fields)
    sdnotify.notify(ready=True, status=f"routing on {', '.join(fields['listen']) or 'Zenoh defaults'}")
    while not stop.wait(1.0):  # a timed wait: signal handlers run between waits
        pass
    sdnotify.notify(stopping=True)
    log.info("router.stopping")
