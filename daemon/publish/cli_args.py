"""Zenoh options shared by `millsense watch` and `millsense reset`.

Both are short-lived tools, not the daemon: they take the session settings from
the command line (or a Zenoh JSON5 file for TLS) instead of the TOML config.
"""

from __future__ import annotations

import argparse
import re
import sys
from types import SimpleNamespace

from millsense.daemon.publish.session import endpoints_arg

MACHINE_RE = re.compile(r"^[A-Za-z0-9_-]+$")


def add_zenoh_arguments(parser: argparse.ArgumentParser, *, listen: bool = True) -> None:
    g = parser.add_argument_group("Zenoh")
    g.add_argument(
        "--connect", "-e", action="append", metavar="ENDPOINT", default=[],
        help="endpoint to connect to, e.g. tcp/10.0.0.5:7447 (repeatable, or comma-separated)",
    )
    if listen:
        g.add_argument("--listen", "-l", action="append", metavar="ENDPOINT", default=[], help="endpoint to listen on (repeatable)")
    g.add_argument("--mode", choices=("peer", "client"), default=None, help="Zenoh mode (default: peer)")
    g.add_argument("--no-scouting", action="store_true", help="turn multicast scouting off (then give --connect)")
    g.add_argument("--zenoh-config", metavar="FILE", default="", help="a Zenoh JSON5 file (TLS, auth); the options above override it")


def zenoh_settings_from_args(args: argparse.Namespace) -> SimpleNamespace:
    """A settings object for `open_session`, with only what the user gave marked explicit."""
    zs = SimpleNamespace(
        connect=endpoints_arg(args.connect),
        listen=endpoints_arg(getattr(args, "listen", [])),
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


def check_machine(machine: str | None, prog: str) -> str | None:
    """A clear usage error for a machine id that cannot be a key chunk (no '/', '*', '$')."""
    if machine is not None and not MACHINE_RE.match(machine):
        print(f"{prog}: error: --machine {machine!r}: use letters, digits, '_' and '-' only", file=sys.stderr)
        return "bad"
    return None
