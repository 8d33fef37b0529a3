"""The `millsense` command: one table of subcommands, exit codes, no tracebacks.

Each subcommand lives in its own module with ``add_arguments(parser)`` and
``run(args) -> int``; heavy imports happen inside ``run`` so that ``--help`` and
``check-config`` stay fast.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys

from millsense.daemon import __version__

EXIT_OK = 0
EXIT_FAILURE = 1
EXIT_USAGE = 2
EXIT_UNAVAILABLE = 69
EXIT_CONFIG = 78

# name -> (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "run": ("millsense.daemon.commands.run", "run the daemon (no --config: the built-in demo)"),
    "sim": ("millsense.sim.emulator.cli", "the DAQ emulator driven by the plant simulator"),
    "replay": ("millsense.daemon.commands.replay", "run the pipeline on a capture, JSON lines out"),
    "record": ("millsense.daemon.commands.record", "save what the configured DAQ sends"),
    "watch": ("millsense.daemon.commands.watch", "show live estimates, alarms and status"),
    "calibrate": ("millsense.daemon.commands.calibrate", "fit friction per gear (and C_f) from captures"),
    "check-config": ("millsense.daemon.commands.check_config", "validate a configuration file"),
    "reset": ("millsense.daemon.commands.reset", "clear a latched interlock (over Zenoh, or --local at the machine)"),
    "token": ("millsense.daemon.commands.token", "make a reset token (`token new`)"),
    "history": ("millsense.daemon.commands.history", "export the history (time range, program, tool, operation) as CSV or JSON lines"),
    "commission": ("millsense.daemon.commands.commission", "guided check of a machine's DAQ, wiring, feed hold and watchdog; a report"),
    "test-trip": ("millsense.daemon.commands.test_trip", "proof test: assert feed hold, time its confirmation, reset"),
    "limits": ("millsense.daemon.commands.limits", "see, accept, relearn, widen or narrow learned limits; false alarms, new tools"),
    "afc": ("millsense.daemon.commands.afc", "adaptive feed control: on, off, or its state (authorised like reset)"),
    "opcua": ("millsense.daemon.commands.opcua", "an OPC UA server for every machine seen on Zenoh (the opcua extra)"),
    "dashboard": ("millsense.daemon.commands.dashboard", "a web page of every machine on Zenoh: tiles, live plots, alarms, reset"),
    "historian": ("millsense.daemon.commands.historian", "the plant's history: every machine's alarms, processes, status and load into PostgreSQL (the historian extra)"),
    "router": ("millsense.daemon.commands.router", "Zenoh's router for the plant (TLS, access control), from pip"),
}


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The whole parser; with `only`, just that subcommand's module is imported and given its
    arguments (the others keep their one-line help): a run of `replay` does not pay for
    importing `run`, `watch` and the rest (start-up counts in replay's × real time)."""
    parser = argparse.ArgumentParser(
        prog="millsense",
        description="Cutting torque, force and depth of cut from a CNC spindle motor's own power.",
    )
    parser.add_argument("--version", action=_VersionAction)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, (module_name, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        if only is None or name == only:
            module = importlib.import_module(module_name)
            module.add_arguments(p)
            p.set_defaults(_module=module)
    return parser


def _command_in(argv: list[str]) -> str | None:
    """The subcommand argv names (the first word that is not an option), if it is one of ours."""
    for word in argv:
        if not word.startswith("-"):
            return word if word in COMMANDS else None
    return None


class _VersionAction(argparse.Action):
    """`--version`: millsense.daemon.__version__, which the package's metadata is built from."""

    def __init__(self, option_strings, dest, **kwargs):
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS,
                         help="show program's version number and exit")

    def __call__(self, parser, namespace, values, option_string=None):
        print(f"millsense {__version__}")  # on stdout, as argparse's own version action does
        parser.exit()


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    parser = build_parser(only=_command_in(argv))
    args = parser.parse_args(argv)
    from millsense.daemon.config.errors import ConfigError

    try:
        return int(args._module.run(args) or 0)
    except ConfigError as exc:
        for problem in exc.problems:
            print(problem, file=sys.stderr)
        return EXIT_CONFIG
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:
        # stdout closed by the reader (e.g. `| head`): not an error of ours.
        try:
            sys.stdout = open(os.devnull, "w")  # noqa: SIM115 - silence the flush at exit
        except OSError:
            pass
        return EXIT_OK
    except Exception as exc:  # noqa: BLE001 - the one place that turns a bug into an exit code
        if os.environ.get("MILLSENSE_DEBUG"):
            raise
        from millsense.daemon.publish.cli_args import strip_rust  # Zenoh's errors carry Rust source paths

        print(f"millsense {args.command}: error: {type(exc).__name__}: {strip_rust(str(exc))}", file=sys.stderr)
        print("(set MILLSENSE_DEBUG=1 to see the traceback)", file=sys.stderr)
        return EXIT_FAILURE


if __name__ == "__main__":
    sys.exit(main())
