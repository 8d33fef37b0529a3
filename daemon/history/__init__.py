"""The embedded history: learned limits, process summaries, alarms and per-revolution estimates
in one SQLite file per machine, in the daemon's state directory (docs/history.md).

`HistoryStore` (store.py) writes it from its own thread; `schema.py` holds the
versioned schema and its migrations; `export.py` reads it for `millsense history`.
"""

from __future__ import annotations

import os
from pathlib import Path

from millsense.daemon.history.schema import SCHEMA_VERSION, NewerSchemaError
from millsense.daemon.history.store import HistoryStore

DEFAULT_NAME = "history.sqlite3"

__all__ = ["DEFAULT_NAME", "SCHEMA_VERSION", "HistoryStore", "NewerSchemaError", "history_path"]


def history_path(state_dir: Path, path_setting: str = "", config_dir: Path | None = None) -> Path:
    """Where `[history] path` puts the file (docs/config.md): empty -> `<state dir>/history.sqlite3`;
    a relative path is taken from the config file's folder (`config_dir`); `~` is expanded."""
    text = (path_setting or "").strip()
    if not text:
        return Path(state_dir) / DEFAULT_NAME
    p = Path(os.path.expanduser(text))
    if p.is_absolute():
        return p
    return (Path(config_dir) if config_dir is not None else Path(state_dir)) / p
