"""`millsense limits import-operations FILE --config CONFIG`: a CSV sheet of operations into the operations file.

The sheet's header is exactly `config.operations.CSV_COLUMNS` (units in the names). Each row is checked as
check-config checks `[operations."P/T/O"]` — its own fields, then against the tool and material of the
configuration — and a problem names the row and section.key. Nothing is written unless every row passes and the
configuration, with the merged operations, loads (exit 78 otherwise, as check-config).

It writes the configuration's `[learning] operations_file` (relative to the configuration's folder), a file of
`[operations.*]` tables only: the operations already there are kept, a row's key replaces its own. That file is
the tool's; hand edits live in the main configuration's `[operations]` (never touched here). `--print` prints the
merged file instead. The daemon reads it at start: restart it to arm the new operations.
"""

from __future__ import annotations

import argparse
import sys
import tomllib
from pathlib import Path
from typing import Any

from millsense.daemon.config.checks import read_toml
from millsense.daemon.config.errors import ConfigError
from millsense.daemon.config.operations import operations_toml, read_operations_csv, write_atomically
from millsense.daemon.publish.cli_args import EXIT_CONFIG, EXIT_USAGE

PROG = "millsense limits import-operations"


def _fail(message: str, code: int) -> int:
    print(f"{PROG}: {message}", file=sys.stderr)
    return code


def run(args: argparse.Namespace) -> int:
    if args.target is None:
        return _fail("error: import-operations needs the CSV FILE, e.g. `millsense limits import-operations "
                     "ops.csv --config /etc/millsense/millsense.toml`", EXIT_USAGE)
    if not args.config:
        return _fail("error: import-operations needs --config (the configuration whose [learning] operations_file "
                     "it writes)", EXIT_USAGE)
    sheet = Path(args.target)
    try:
        text = sheet.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        return _fail(f"{sheet}: cannot be read: {getattr(exc, 'strerror', None) or exc}", EXIT_CONFIG)
    row_of: dict[str, int] = {}
    rows, row_problems = read_operations_csv(text, str(sheet), row_of)
    if row_problems and not rows:
        return _problems(row_problems)   # the good rows are checked further: every problem said in one pass
    config = Path(args.config)
    data, problems = read_toml(config, str(config), "a millsense TOML configuration")
    if data is None:
        return _problems(problems)
    learning = data.get("learning") if isinstance(data.get("learning"), dict) else {}
    name = learning.get("operations_file")
    if not isinstance(name, str) or not name:
        return _problems([f'learning.operations_file: not set in {config} (set e.g. operations_file = '
                          '"operations.toml" under [learning]: the file this command writes and the daemon reads)'])
    target = Path(name).expanduser()
    target = target if target.is_absolute() else config.resolve().parent / target
    kept: dict[str, dict[str, Any]] = {}
    if target.exists():
        old, problems = read_toml(target, f"learning.operations_file: {target}", "the operations file")
        if old is None:
            return _problems(problems)
        kept = {str(k): dict(v) for k, v in (old.get("operations") or {}).items() if isinstance(v, dict)}
    merged = {**kept, **rows}
    new_text = operations_toml(merged)
    problems = row_problems + _check(data, config, target, new_text, row_of, str(sheet))
    if problems:
        return _problems(sorted(problems, key=_row_number))
    if args.print:
        print(new_text, end="")
        return 0
    try:
        write_atomically(target, new_text)
    except OSError as exc:
        return _fail(f"{target}: cannot be written: {exc.strerror or exc}", EXIT_CONFIG)
    replaced = sorted(set(rows) & set(kept))
    print(f"{target}: {len(rows)} operation(s) from {sheet} ({len(replaced)} replaced), {len(merged)} in all; "
          "restart the daemon to arm them")
    return 0


def _check(data: dict[str, Any], config: Path, target: Path, new_text: str, row_of: dict[str, int],
           sheet: str) -> list[str]:
    """The configuration as the daemon would load it with the merged operations; problems of a row named by row."""
    from millsense.daemon.config.load import _settings_from

    try:
        ops = tomllib.loads(new_text)
    except tomllib.TOMLDecodeError as exc:   # cannot happen for what operations_toml writes; never a traceback
        return [f"{target}: {exc}"]
    data = dict(data)
    data["learning"] = {k: v for k, v in data["learning"].items() if k != "operations_file"}
    mine = data.get("operations") if isinstance(data.get("operations"), dict) else {}
    both = sorted(set(mine) & set(ops.get("operations", {})))
    data["operations"] = {**mine, **ops.get("operations", {})}
    problems = [f'{sheet}: operations."{k}": also in {config} [operations] (one place: remove it from one of them)'
                for k in both]
    try:
        _settings_from(data, config.resolve().parent)
    except ConfigError as exc:
        for p in exc.problems:
            row = next((n for k, n in row_of.items() if p.startswith(f'operations."{k}"')), None)
            problems.append(f"{sheet}: row {row}: {p}" if row is not None else p)
    return problems


def _row_number(problem: str) -> int:
    """Problems in the sheet's order (those of no row first)."""
    head, sep, rest = problem.partition(": row ")
    number = rest.split(":", 1)[0]
    return int(number) if sep and number.isdigit() else 0


def _problems(problems: list[str]) -> int:
    for p in problems:
        print(f"{PROG}: {p}", file=sys.stderr)
    return EXIT_CONFIG
