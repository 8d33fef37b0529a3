"""`millsense historian --config FILE`: every machine's alarms, process summaries, status changes, limit changes
and per-second load into the plant's PostgreSQL (docs/historian.md), a separate process beside the daemons.

Its file has `[historian]` (the DSN, its passfile, the machines, retention, the spool), `[zenoh]` and `[log]`;
`millsense check-config FILE` checks it. `--connect/--mode/--no-scouting/--zenoh-config` override its `[zenoh]`.
Needs the `historian` extra (psycopg 3).

Exit codes: 0 stopped by SIGTERM/SIGINT after its last flush; 1 PostgreSQL's schema cannot be used (a newer
version), Zenoh cannot be reached, the spool cannot be written; 2 a bad option; 78 a config error (section.key).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from millsense.daemon.publish.cli_args import EXIT_CONFIG, EXIT_USAGE, CliUsageError, add_zenoh_arguments, strip_rust

PROG = "millsense historian"
EXTRA_MISSING = (f"{PROG}: error: the historian needs the 'historian' extra (psycopg 3), not installed here: "
                 "pip install 'millsense[historian]'")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", "-c", metavar="FILE", required=True,
                        help="the historian's configuration ([historian], [zenoh], [log]; docs/historian.md)")
    add_zenoh_arguments(parser, listen=False)
    parser.add_argument("--log-format", choices=("auto", "json", "console"), default=None,
                        help="log lines (default: the file's [log] format)")


def _fail(message: str, code: int) -> int:
    print(f"{PROG}: error: {message}", file=sys.stderr)
    return code


def run(args: argparse.Namespace) -> int:
    try:
        import psycopg  # noqa: F401 - only to say clearly that the extra is missing
    except ImportError:
        print(EXTRA_MISSING, file=sys.stderr)
        return 1
    from millsense.daemon.config.errors import ConfigError
    from millsense.daemon.config.historian import load_historian_config

    try:
        settings = load_historian_config(args.config)
    except ConfigError as exc:
        for problem in exc.problems:
            print(problem, file=sys.stderr)
        return EXIT_CONFIG
    zenoh_settings = settings.zenoh
    if args.connect or args.mode or args.no_scouting or args.zenoh_config:
        from millsense.daemon.publish.cli_args import zenoh_settings_from_args

        try:
            zenoh_settings = zenoh_settings_from_args(args)
        except CliUsageError as exc:
            return _fail(str(exc), EXIT_USAGE)

    import threading

    import structlog

    from millsense.daemon import sdnotify
    from millsense.daemon.historian.schema import SchemaError
    from millsense.daemon.historian.service import Rows, serve
    from millsense.daemon.historian.spool import Spool, SpoolError
    from millsense.daemon.historian.writer import Writer
    from millsense.daemon.logging_setup import configure_logging
    from millsense.daemon.publish.session import ZenohConfigError, ZenohUnavailable, open_session
    from millsense.daemon.stop_signals import stop_on_signals

    configure_logging(settings.log.level, args.log_format or settings.log.format, stream=sys.stderr)
    log = structlog.get_logger("millsense.historian")
    h = settings.historian
    stop = threading.Event()
    stop_on_signals(stop, hangup=True)
    try:
        spool = Spool(Path(h.spool_dir), int(h.spool_max_mb * 1e6))
    except (OSError, SpoolError) as exc:
        return _fail(f"historian.spool_dir: {h.spool_dir}: {getattr(exc, 'strerror', None) or exc}", EXIT_CONFIG)
    writer = Writer(h.dsn, h.passfile, spool, h.retention_days.model_dump(), log)
    try:
        writer.flush()   # connect (or start spooling) and check the schema before anything is taken
    except SchemaError as exc:
        return _fail(str(exc), 1)
    try:
        session = open_session(zenoh_settings, retry_for_s=None, stop=stop)
    except ZenohConfigError as exc:
        return _fail(strip_rust(str(exc)), 1)
    except ZenohUnavailable as exc:
        if stop.is_set():
            writer.close()
            return 0
        return _fail(strip_rust(str(exc)), 1)
    log.info("historian.started", machines=h.machines, spool_dir=h.spool_dir, db=writer.status()["db"],
             revolutions_for=h.revolutions_for)
    sdnotify.notify(ready=True, status="historian: starting")

    def on_status(state: dict) -> None:
        spooled = f", {state['spooled_rows']} rows spooled" if state["spooled_rows"] else ""
        sdnotify.notify(status=f"historian: PostgreSQL {state['db']}{spooled}, "
                               f"{sum(state['written'].values())} rows written")

    try:
        serve(session, h.machines, writer, Rows(writer, set(h.revolutions_for)), stop, log, on_status)
    except SchemaError as exc:   # a reconnection found a newer schema: stop writing
        return _fail(str(exc), 1)
    finally:
        sdnotify.notify(stopping=True)
        session.close()
    return 0
