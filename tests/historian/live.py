"""Configs for the historian's live tests with real daemons: the part program's machine (config/part-program.toml)
on the in-process emulator (`transport = "sim"`, scenario `part-program`: the CNC's context, so processes), and
the historian's own file."""

from __future__ import annotations

import tomllib
from pathlib import Path

from tests.config.helpers import dumps
from tests.e2e.learning_run import CONFIG
from tests.e2e.test_expected_live import _operations


def p1001_daemon(path: Path, machine: str, *, zenoh: dict, interlock: dict | None = None,
                 operations: bool = False, alarms: dict | None = None) -> Path:
    """A daemon of program 1001 on the in-process emulator; `zenoh` its [zenoh] (scouting off always);
    `operations`: every operation's [operations] entry as the program really cuts (the expected band);
    `alarms`: keys that replace the file's [alarms] ones."""
    from millsense.sim.program import PROGRAMS

    doc = tomllib.loads(CONFIG.read_text())
    doc["machine"] = machine
    doc["daq"] = {"transport": "sim", "scenario": "part-program", "filter_cutoff_hz": 200, "filter_order": 2}
    if operations:
        ops = PROGRAMS["part-program"].operations
        t11 = next(op for op in ops if op.tool_number == 11)
        doc["operations"] = _operations(max(t11.depths_mm))
    doc["alarms"].update(alarms or {})
    doc["interlock"] = interlock or {"enabled": True, "heartbeat_ms": 50, "watchdog_ms": 1000, "reset": "open"}
    doc["zenoh"] = {"mode": "peer", "listen": [], "connect": [], **zenoh, "multicast_scouting": False}
    doc["log"] = {"level": "info", "format": "json"}
    path.write_text(dumps(doc))
    return path


def historian_config(path: Path, server, db: str, passfile: Path, *, connect: list[str], mode: str = "peer",
                     revolutions_for: tuple[str, ...] = ()) -> Path:
    path.write_text(f'[historian]\ndsn = "{server.dsn(db)}"\npassfile = "{passfile}"\nspool_dir = "spool"\n'
                    f'revolutions_for = {list(revolutions_for)!r}\n'.replace("'", '"') +
                    f'[zenoh]\nmode = "{mode}"\nconnect = {connect!r}\n'.replace("'", '"') +
                    'multicast_scouting = false\n[log]\nformat = "json"\n')
    return path
