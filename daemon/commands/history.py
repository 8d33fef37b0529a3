"""`millsense history`: export the daemon's history (a time range, a program, a tool, an operation)
as CSV or JSON lines.

The file is found the way the daemon finds it: `--db PATH`, else `[history] path`
of `--config` in the daemon's state directory (docs/history.md). It is opened
read-only, so an export runs while the daemon writes. Only `machine` and
`[history]` are read from the config: an operator exporting data need not be
able to read the daemon's token file.

Exit codes: 0 done; 1 no database, or one that cannot be read; 2 a bad option;
78 a config error (named section.key).
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from datetime import datetime
from pathlib import Path

PROG = "millsense history"
EXIT_FAILURE = 1
EXIT_USAGE = 2
EXIT_CONFIG = 78


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", "-c", metavar="FILE", default=None,
                        help="the daemon's configuration (its machine and [history]; nothing else is read)")
    parser.add_argument("--db", metavar="PATH", default=None, help="the history file itself (wins over --config)")
    parser.add_argument("--what", default="revolutions", choices=("revolutions", "processes", "alarms", "limits"),
                        help="which rows (default: revolutions)")
    parser.add_argument("--from", dest="t_from", metavar="T", default=None,
                        help="from this time on: ISO 8601 (2026-11-23T08:00:00Z; no zone = local time) or Unix seconds")
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
        if args.db is None and args.config is None:
            raise _Usage("give --config FILE (the daemon's) or --db PATH (the history file)")
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
        if args.out is None:
            n = export.write(sys.stdout, args.what, items, args.format)
            sys.stdout.flush()
        else:
            try:
                with open(args.out, "w", encoding="utf-8", newline="") as out:
                    n = export.write(out, args.what, items, args.format)
            except OSError as exc:
                print(f"{PROG}: error: cannot write {args.out}: {exc.strerror or exc}", file=sys.stderr)
                return EXIT_FAILURE
            print(f"{PROG}: wrote {n} {args.what} rows to {args.out}", file=sys.stderr)
    except export.sqlite3.Error as exc:
        print(f"{PROG}: error: {path}: {exc}", file=sys.stderr)
        return EXIT_FAILURE
    finally:
        conn.close()
    return 0


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
