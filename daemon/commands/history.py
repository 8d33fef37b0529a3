"""`millsense history`: export the daemon's history (a time range, a program, a tool, an operation)
as CSV or JSON lines.

The file is found the way the daemon finds it: `--db PATH`, else `[history] path`
of `--config` in the daemon's state directory (docs/history.md). It is opened
read-only, so an export runs while the daemon writes. Only `machine` and
`[history]` are read from the config: an operator exporting data need not be
able to read the daemon's token file.

With `--dsn` it reads the plant's PostgreSQL that `millsense historian` writes (docs/historian.md) instead:
every machine or those named by `--machine`, times printed in UTC with their offset.

Exit codes: 0 done; 1 no database, or one that cannot be read; 2 a bad option;
78 a config error (named section.key).
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from collections.abc import Callable
from datetime import datetime
from pathlib import Path
from typing import TextIO

PROG = "millsense history"
EXIT_FAILURE = 1
EXIT_USAGE = 2
EXIT_CONFIG = 78


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", "-c", metavar="FILE", default=None,
                        help="the daemon's configuration (its machine and [history]; nothing else is read)")
    parser.add_argument("--db", metavar="PATH", default=None, help="the history file itself (wins over --config)")
    parser.add_argument("--dsn", metavar="DSN", default=None,
                        help="read the plant's PostgreSQL (`millsense historian`, docs/historian.md) instead: a libpq "
                             "connection string without password (the password from --passfile or PGPASSFILE)")
    parser.add_argument("--passfile", metavar="FILE", default=None, help="with --dsn: the libpq password file")
    parser.add_argument("--machine", "-m", action="append", metavar="ID", default=None,
                        help="with --dsn: only this machine (repeatable; 'all' or none: every machine)")
    parser.add_argument("--what", default="revolutions",
                        choices=("revolutions", "processes", "alarms", "limits", "load", "status"),
                        help="which rows (default: revolutions; with --dsn also load (per second), status (its "
                             "changes); limits: with --dsn the learned limits' changes)")
    parser.add_argument("--from", dest="t_from", metavar="T", default=None,
                        help="from this time on: ISO 8601 with its offset (2026-11-23T08:00:00+01:00, or Z for "
                             "UTC; no offset = this computer's local time zone) or Unix seconds")
    parser.add_argument("--to", dest="t_to", metavar="T", default=None, help="before this time (as --from)")
    parser.add_argument("--program", type=str, default=None, metavar="N", help="only this CNC program number")
    parser.add_argument("--tool", type=str, default=None, metavar="N", help="only this tool number (T12: 12)")
    parser.add_argument("--operation", type=str, default=None, metavar="N", help="only this operation number")
    parser.add_argument("--format", "-f", default="csv", choices=("csv", "jsonl"), help="default: csv")
    parser.add_argument("--out", "-o", metavar="FILE", default=None, help="write here instead of stdout")


class _Usage(ValueError):
    pass


def parse_time(text: str, option: str) -> float:
    """ISO 8601 or Unix seconds -> Unix seconds."""
    try:
        value = float(text)
    except ValueError:
        try:
            value = datetime.fromisoformat(text.strip()).timestamp()
        except ValueError:
            raise _Usage(f"{option} {text!r}: not a time (ISO 8601 such as 2026-11-23T08:00:00Z, "
                         "or Unix seconds)") from None
    if not math.isfinite(value):
        raise _Usage(f"{option} {text!r}: not a time")
    return value


def _number(text: str | None, option: str) -> int | None:
    from millsense.daemon.learning.keys import UINT16_MAX, UINT32_MAX   # loads numpy: in `run`, not at --help

    if text is None:
        return None
    digits = text.strip()
    if not (digits.isascii() and digits.isdigit()):
        raise _Usage(f"{option} {text!r}: a whole number 0 or more (tool T12 is --tool 12)")
    widest = UINT16_MAX if option == "--operation" else UINT32_MAX   # a process key's fields
    if int(digits) > widest:
        raise _Usage(f"{option} {text!r}: at most {widest} (the DAQ's and the CNC adapter's field)")
    return int(digits)


def run(args: argparse.Namespace) -> int:
    from millsense.daemon.history import export

    try:
        t_from = parse_time(args.t_from, "--from") if args.t_from is not None else None
        t_to = parse_time(args.t_to, "--to") if args.t_to is not None else None
        if t_from is not None and t_to is not None and t_to <= t_from:
            raise _Usage("--to must be after --from")
        numbers = {name: _number(getattr(args, name), f"--{name}") for name in ("program", "tool", "operation")}
        if args.dsn is None and (args.machine or args.passfile):
            raise _Usage("--machine and --passfile read the plant's database: give --dsn")
        if args.dsn is None and args.what in ("load", "status"):
            raise _Usage(f"--what {args.what}: only the plant's database (--dsn) keeps it")
        if args.dsn is None and args.db is None and args.config is None:
            raise _Usage("give --config FILE (the daemon's), --db PATH (the history file) or --dsn (the plant's "
                         "PostgreSQL)")
        if args.dsn is not None:
            return _run_dsn(args, t_from, t_to, numbers)
    except _Usage as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    if args.db is not None:
        path = Path(args.db)
    else:
        problems, path = find_database(Path(args.config))
        if problems:
            for problem in problems:
                print(problem, file=sys.stderr)
            return EXIT_CONFIG
    try:
        conn = export.open_read_only(path)
    except export.ExportError as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return EXIT_FAILURE
    try:
        items = export.rows(conn, args.what, t_from=t_from, t_to=t_to, **numbers)
        if _emit(args, lambda out: export.write(out, args.what, items, args.format)):
            return EXIT_FAILURE
    except export.sqlite3.Error as exc:
        print(f"{PROG}: error: {path}: {exc}", file=sys.stderr)
        return EXIT_FAILURE
    finally:
        conn.close()
    return 0


def _emit(args: argparse.Namespace, write: Callable[[TextIO], int]) -> bool:
    """The rows to stdout, or to `--out` with a line on stderr saying how many; True if the file cannot be written
    (said). `write(out)` writes them and gives the count: the machine's history or the plant's."""
    if args.out is None:
        write(sys.stdout)
        sys.stdout.flush()
        return False
    try:
        with open(args.out, "w", encoding="utf-8", newline="") as out:
            n = write(out)
    except OSError as exc:
        print(f"{PROG}: error: cannot write {args.out}: {exc.strerror or exc}", file=sys.stderr)
        return True
    print(f"{PROG}: wrote {n} {args.what} rows to {args.out}", file=sys.stderr)
    return False


def find_database(config: Path) -> tuple[list[str], Path]:
    """(problems, path) from the daemon's TOML: its machine and `[history] path` in its state directory."""
    import tomllib

    from pydantic import ValidationError

    from millsense.daemon.config.errors import problems_from
    from millsense.daemon.config.models import HistorySettings, Settings
    from millsense.daemon.history import history_path
    from millsense.daemon.state_dir import SYSTEMD_STATE_ROOT, state_dir

    try:
        raw = tomllib.loads(config.read_text(encoding="utf-8"))
    except OSError as exc:
        return [f"--config {config}: cannot be read: {exc.strerror or exc}"], Path()
    except (UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        return [f"--config {config}: not a TOML file: {exc}"], Path()
    machine = raw.get("machine")
    problems = []
    if not isinstance(machine, str) or not machine:
        problems.append("machine: missing (the machine id names the daemon's state directory)")
    try:
        history = HistorySettings.model_validate(raw.get("history", {}))
    except ValidationError as exc:
        problems.extend(problems_from(Settings, exc, prefix=("history",)))
        history = None
    if problems:
        return problems, Path()
    config_dir = config.resolve().parent
    path = history_path(state_dir(machine), history.path, config_dir)
    unit_path = history_path(SYSTEMD_STATE_ROOT / machine, history.path, config_dir)  # a daemon under systemd
    if not (os.environ.get("STATE_DIRECTORY") or "").strip() and not path.exists() and unit_path.exists():
        path = unit_path
    return [], path


def _run_dsn(args: argparse.Namespace, t_from: float | None, t_to: float | None, numbers: dict) -> int:
    """The plant's database (issue 43). Raises _Usage for a bad option."""
    from millsense.daemon.config.historian import dsn_problem
    from millsense.daemon.publish.cli_args import MACHINE_RE

    problem = dsn_problem(args.dsn)
    if problem:
        raise _Usage(f"--dsn: {problem}".replace("named by historian.passfile", "given by --passfile"))
    machines = [m for m in (args.machine or []) if m != "all"]
    for m in machines:
        if not MACHINE_RE.match(m):
            raise _Usage(f"--machine {m!r}: a machine id (letters, digits, '_' and '-') or 'all'")
    with_numbers = {"revolutions", "processes", "alarms"}
    if args.what not in with_numbers and any(v is not None for v in numbers.values()):
        raise _Usage(f"--what {args.what}: no program, tool or operation to filter on")
    try:
        from millsense.daemon.historian import read
    except ImportError:
        print(f"{PROG}: error: --dsn needs the 'historian' extra (psycopg 3): pip install 'millsense[historian]'",
              file=sys.stderr)
        return EXIT_FAILURE
    import psycopg

    try:
        with read.connect(args.dsn, args.passfile) as conn:
            items = read.rows(conn, args.what, machines=machines, t_from=t_from, t_to=t_to, **numbers)
            if _emit(args, lambda out: read.write(out, args.what, items, args.format)):
                return EXIT_FAILURE
    except psycopg.Error as exc:
        message = " ".join(str(exc).split()) or type(exc).__name__
        print(f"{PROG}: error: the plant's database: {message}", file=sys.stderr)
        return EXIT_FAILURE
    return 0
