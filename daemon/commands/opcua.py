"""`millsense opcua`: an OPC UA server showing every millsense daemon it sees on Zenoh.

A machine appears (by its liveliness token `millsense/<m>/alive`) as an object with its spindle
speed, power, torque, force, depths, alarm and interlock state, program, tool and operation,
process count and wear, AFC state where the daemon has it; its alarm changes are OPC UA events.
Security: Sign & Encrypt only (Basic256Sha256, Aes128_Sha256_RsaOaep, Aes256_Sha256_RsaPss), client
certificates from a trust directory, anonymous sessions only with `--allow-anonymous`. With
`--nodesets DIR` the OPC Foundation's companion specifications are loaded and each configured machine
is an OPC 40501 MachineToolType. Options left out come from the `[opcua]` section of `--config`.
docs/opcua.md has the address space and the certificates.

Needs the `opcua` extra (asyncua); the live daemon never imports it.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from millsense.daemon.publish.cli_args import (
    EXIT_CONFIG,
    EXIT_USAGE,
    add_config_argument,
    add_zenoh_arguments,
    check_machine,
    client_settings,
    hint,
    strip_rust,
)

PROG = "millsense opcua"
DEFAULT_ENDPOINT = "opc.tcp://127.0.0.1:4840"
EXTRA_MISSING = (f"{PROG}: error: the OPC UA server needs the 'opcua' extra (asyncua), not installed here: "
                 "pip install 'millsense[opcua]'")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    # Left out, each option takes the --config file's [opcua] key (issue 42), then its default.
    parser.add_argument("--endpoint", default=None, metavar="opc.tcp://HOST:PORT",
                        help=f"where to listen (default [opcua] endpoint, else {DEFAULT_ENDPOINT}: this host only; "
                             "give the address of the plant network's interface to serve it)")
    parser.add_argument("--cert", metavar="FILE", default=None,
                        help="the server's application certificate (PEM or DER, RSA 2048-4096, its application "
                             "URI in subjectAltName; default [opcua] cert)")
    parser.add_argument("--key", metavar="FILE", default=None,
                        help="its private key (PEM or DER, unencrypted; default [opcua] key)")
    parser.add_argument("--trust-dir", metavar="DIR", default=None,
                        help="directory of trusted client certificates (one file each, read at every new session; "
                             "default [opcua] trust_dir)")
    parser.add_argument("--operators-dir", metavar="DIR", default=None,
                        help="certificates of the clients that may acknowledge and confirm alarms (each also in "
                             "--trust-dir; default [opcua] operators_dir, else nobody)")
    parser.add_argument("--allow-anonymous", action="store_true",
                        help="also accept anonymous sessions (still over the encrypted channel, from a client whose "
                             "certificate is trusted; or [opcua] allow_anonymous = true)")
    parser.add_argument("--nodesets", metavar="DIR", default=None,
                        help="folder of the OPC Foundation's NodeSet2 files (DI, IA, Machinery, ISA-95 Job Control, "
                             "Machinery Jobs, MachineTool): one MachineToolType object per machine (docs/opcua.md)")
    parser.add_argument("--machine", "-m", metavar="ID", default=None, help="only this machine (default: every one seen)")
    add_config_argument(parser, "where to connect, its [opcua] section and its machine's identification")
    add_zenoh_arguments(parser, listen=False)
    parser.add_argument("--log-format", choices=("auto", "json", "console"), default="auto",
                        help="log lines: JSON under systemd or into a pipe, readable on a terminal (auto)")


def _fail(message: str, code: int) -> int:
    print(f"{PROG}: error: {message}", file=sys.stderr)
    return code


def _named(message: str, from_section: dict[str, str]) -> str:
    """A setup error names the option it is about; when the value came from [opcua], name that key instead."""
    option = message.split(" ", 1)[0]
    return from_section[option] + message[len(option):] if option in from_section else message


def run(args: argparse.Namespace) -> int:
    if check_machine(args.machine, PROG):
        return EXIT_USAGE
    try:
        import asyncua  # noqa: F401 - only to say clearly that the extra is missing
    except ImportError:
        print(EXTRA_MISSING, file=sys.stderr)
        return 1
    from millsense.daemon.opcua.security import OpcuaSetupError, TrustList, load_server_identity
    from millsense.daemon.opcua.server import Options, parse_endpoint
    from millsense.daemon.opcua.settings import OpcuaConfigError, identification_of, read_opcua_section

    identities, tools = {}, []
    from_section: dict[str, str] = {}  # option -> `opcua.key (FILE)`: an error names where the value came from
    if args.config:
        try:
            from_file = read_opcua_section(Path(args.config))
        except OpcuaConfigError as exc:
            return _fail(str(exc), EXIT_CONFIG)
        section = from_file.opcua
        for option, key in (("endpoint", "endpoint"), ("cert", "cert"), ("key", "key"), ("trust_dir", "trust_dir"),
                            ("operators_dir", "operators_dir"), ("nodesets", "nodesets_dir")):
            if getattr(args, option) is None and getattr(section, key):
                setattr(args, option, getattr(section, key))  # the command line first, then the file
                from_section[f"--{option.replace('_', '-')}"] = f"opcua.{key} ({args.config})"
        args.allow_anonymous = args.allow_anonymous or section.allow_anonymous
        identity_of_machine = identification_of(section)
        if from_file.machine and identity_of_machine is not None:
            identities[from_file.machine] = identity_of_machine
        tools = from_file.tools
    args.endpoint = args.endpoint or DEFAULT_ENDPOINT
    if args.nodesets and not identities:
        # 40001-1's Identification is mandatory and only the configuration knows it: nothing could be typed
        return _fail(f"{from_section.get('--nodesets', '--nodesets')}: no machine to show as a MachineToolType: give "
                     "--config FILE whose [opcua] has manufacturer, serial_number and product_instance_uri "
                     "(docs/opcua.md)", EXIT_CONFIG)
    try:
        parse_endpoint(args.endpoint)
    except ValueError as exc:
        return _fail(f"--endpoint {exc}", EXIT_USAGE)
    missing = [o for o, v in (("--cert", args.cert), ("--key", args.key), ("--trust-dir", args.trust_dir)) if not v]
    if missing:
        return _fail(f"{', '.join(missing)} required: the server offers only signed and encrypted sessions "
                     "(docs/opcua.md, Certificates)", EXIT_CONFIG)
    try:
        identity = load_server_identity(Path(args.cert), Path(args.key))
        trust = TrustList(Path(args.trust_dir))
        trusted = trust.check()
        operators = TrustList(Path(args.operators_dir), option="--operators-dir") if args.operators_dir else None
        if operators is not None:
            operators.check()
    except OpcuaSetupError as exc:
        return _fail(_named(str(exc), from_section), EXIT_CONFIG)
    connection = client_settings(args, PROG)
    if isinstance(connection, int):
        return connection
    daemon, settings = connection

    from millsense.daemon.logging_setup import configure_logging

    configure_logging("info", args.log_format, stream=sys.stderr)
    import structlog

    log = structlog.get_logger("millsense.opcua")
    if trusted == 0:
        log.warning("opcua.trust_list_empty", directory=str(trust.directory),
                    detail="no client can open a session until its certificate is copied there")

    from millsense.daemon.publish.session import ZenohConfigError, ZenohUnavailable, open_session

    try:
        session = open_session(settings, retry_for_s=30.0)
    except ZenohConfigError as exc:
        return _fail(strip_rust(str(exc)), 1)
    except ZenohUnavailable as exc:
        return _fail(f"{strip_rust(str(exc))}\n{hint(settings, daemon)}", 1)
    options = Options(endpoint=args.endpoint, identity=identity, trust=trust,
                      allow_anonymous=args.allow_anonymous, machine=args.machine or "*",
                      nodesets=Path(args.nodesets) if args.nodesets else None, identities=identities, tools=tools,
                      operators=operators)
    try:
        return _serve(options, session)
    except OpcuaSetupError as exc:
        return _fail(_named(str(exc), from_section), EXIT_CONFIG)
    finally:
        session.close()


def _serve(options: object, session: object) -> int:
    import asyncio
    import signal

    from millsense.daemon import sdnotify
    from millsense.daemon.opcua.server import serve

    async def main() -> None:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, stop.set)
        await serve(options, session, stop, on_ready=lambda: sdnotify.notify(ready=True, status="serving OPC UA"))
        sdnotify.notify(stopping=True)

    asyncio.run(main())
    return 0
