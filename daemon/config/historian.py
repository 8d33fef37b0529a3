"""`millsense historian`'s configuration file: `[historian]`, `[zenoh]`, `[log]` (docs/historian.md).

Its own TOML beside the daemons' (the historian serves many machines and runs no DAQ), checked by
`millsense check-config` the way a daemon's is: every problem at once, each as `section.key: what is wrong
(what is expected)`, exit 78. The database password is never in this file: `dsn` names the server, the user and
the database, and libpq reads the password from `passfile`, a file of the historian's user only (mode 0600 or
tighter: libpq itself ignores a passfile others can read). Only pydantic and the standard library are imported
here (check-config stays quick; psycopg is the historian extra's).
"""

from __future__ import annotations

import os
import re
import stat
from pathlib import Path
from typing import Annotated, Any
from urllib.parse import parse_qs, urlsplit

from pydantic import AfterValidator, BaseModel, ConfigDict, Field, ValidationError, field_validator

from millsense.daemon.config.checks import read_toml
from millsense.daemon.config.errors import ConfigError, problems_from
from millsense.daemon.config.models import LogSettings, MACHINE_PATTERN, ZenohSettings

CONFIG_WHAT = "a millsense historian TOML configuration"
TABLES = ("alarms", "processes", "status_changes", "limit_changes", "load_1s", "revolutions")
# One chunk of `millsense/<machine>/...`: a machine id, `*` (every machine), or Zenoh's in-chunk wildcard `$*`
# (`hall2-$*`: every machine whose id starts with hall2-).
MACHINES_RE = re.compile(r"^(\*|(?:[A-Za-z0-9_-]|\$\*)+)\Z")
_PASSWORD_KV = re.compile(r"(^|\s)password\s*=", re.IGNORECASE)


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False)


def dsn_problem(dsn: str) -> str | None:
    """Why `dsn` cannot be the historian's DSN, or None. A password in it would sit in a config file and show in
    `ps` of any tool it is handed to: it belongs in the passfile."""
    text = dsn.strip()
    if not text:
        return "empty (a libpq connection string: 'host=db.plant port=5432 dbname=millsense user=historian')"
    if text.startswith(("postgresql://", "postgres://")):
        try:
            parts = urlsplit(text)
            has_password = parts.password is not None or "password" in {k.lower() for k in parse_qs(parts.query)}
        except ValueError as exc:
            return f"not a connection URI ({exc})"
    else:
        has_password = bool(_PASSWORD_KV.search(text))
    if has_password:
        return ("holds a password: put it in the libpq passfile named by historian.passfile "
                "(host:port:dbname:user:password, mode 0600), never in the config")
    return None


def passfile_problem(path: Path) -> str | None:
    """Why libpq would not use `path` as the password file, or None (libpq ignores one that its group or others
    can read; a missing one means no password: the connection then fails later, so say it now)."""
    try:
        st = path.stat()
    except FileNotFoundError:
        return f"{path} does not exist (a libpq password file: host:port:dbname:user:password, mode 0600)"
    except OSError as exc:
        return f"{path} cannot be read: {exc.strerror or exc}"
    if not stat.S_ISREG(st.st_mode):
        return f"{path} is not a file"
    if st.st_mode & (stat.S_IRWXG | stat.S_IRWXO):
        return (f"{path} has mode {stat.S_IMODE(st.st_mode):04o}: libpq ignores a password file its group or others "
                f"can read (chmod 600 {path})")
    if not os.access(path, os.R_OK):
        return f"{path} cannot be read by this user"
    return None


def _machines(value: str) -> str:
    if not MACHINES_RE.match(value):
        raise ValueError("a machine id, '*' (every machine) or an id with Zenoh's '$*' wildcard ('hall2-$*')")
    return value


class RetentionDays(_Section):
    """Days each table keeps (whole day partitions are dropped past it)."""

    alarms: float = Field(3650.0, gt=0, le=36500)
    processes: float = Field(3650.0, gt=0, le=36500)
    status_changes: float = Field(3650.0, gt=0, le=36500)
    limit_changes: float = Field(3650.0, gt=0, le=36500)
    load_1s: float = Field(400.0, gt=0, le=36500)
    revolutions: float = Field(14.0, gt=0, le=36500)


class HistorianSettings(_Section):
    """`[historian]`."""

    dsn: str
    passfile: str = ""
    machines: Annotated[str, AfterValidator(_machines)] = "*"
    retention_days: RetentionDays = Field(default_factory=RetentionDays)
    spool_dir: str = ""
    spool_max_mb: float = Field(256.0, ge=1, le=1_000_000)
    revolutions_for: list[Annotated[str, Field(pattern=MACHINE_PATTERN, max_length=64)]] = Field(default_factory=list)

    @field_validator("dsn")
    @classmethod
    def _dsn(cls, value: str) -> str:
        problem = dsn_problem(value)
        if problem:
            raise ValueError(problem)
        return value


class HistorianFile(_Section):
    """The whole file. Required: `[historian] dsn`."""

    historian: HistorianSettings
    zenoh: ZenohSettings = Field(default_factory=ZenohSettings)
    log: LogSettings = Field(default_factory=LogSettings)


def is_historian_file(data: Any) -> bool:
    """A TOML that is the historian's (check-config tells the two kinds of file apart by this)."""
    return isinstance(data, dict) and "historian" in data and "daq" not in data


def load_historian_config(path: str | os.PathLike[str]) -> HistorianFile:
    """Read and check the file. Raises ConfigError listing every problem. Relative paths (`passfile`,
    `spool_dir`, `zenoh.config_file`) are taken from the file's folder; `spool_dir` empty is systemd's
    STATE_DIRECTORY."""
    p = Path(path)
    data, problems = read_toml(p, str(p), CONFIG_WHAT)
    if data is None:
        raise ConfigError(problems)
    return historian_from(data, p.resolve().parent)


def historian_from(data: dict[str, Any], base_dir: Path) -> HistorianFile:
    try:
        settings = HistorianFile.model_validate(data)
    except ValidationError as exc:
        problems = problems_from(HistorianFile, exc)
        raw = data.get("historian") if isinstance(data.get("historian"), dict) else {}
        if isinstance(raw.get("passfile"), str) and raw["passfile"]:   # said too: one pass fixes the file
            problem = passfile_problem(_resolve(base_dir, raw["passfile"]))
            if problem:
                problems.append(f"historian.passfile: {problem}")
        raise ConfigError(problems) from None
    problems = []
    h = settings.historian
    updates: dict[str, Any] = {}
    if h.passfile:
        path = _resolve(base_dir, h.passfile)
        problem = passfile_problem(path)
        if problem:
            problems.append(f"historian.passfile: {problem}")
        updates["passfile"] = str(path)
    spool = h.spool_dir or (os.environ.get("STATE_DIRECTORY") or "").split(":")[0]
    if not spool:
        problems.append("historian.spool_dir: missing (a directory of the historian's own, where it keeps what "
                        "PostgreSQL has not taken yet; under systemd the unit's StateDirectory)")
    else:
        updates["spool_dir"] = str(_resolve(base_dir, spool))
    zenoh = settings.zenoh
    if zenoh.config_file:
        zpath = _resolve(base_dir, zenoh.config_file)
        if not zpath.is_file():
            problems.append(f"zenoh.config_file: {zpath} does not exist (a Zenoh JSON5 file; a relative path is "
                            "taken from the config file's folder)")
        zenoh = zenoh.model_copy(update={"config_file": str(zpath)})
    if problems:
        raise ConfigError(problems)
    return settings.model_copy(update={"historian": h.model_copy(update=updates), "zenoh": zenoh})


def _resolve(base_dir: Path, value: str) -> Path:
    p = Path(value).expanduser()
    return p if p.is_absolute() else base_dir / p


def summary(settings: HistorianFile) -> str:
    h = settings.historian
    kept = ", ".join(f"{t} {getattr(h.retention_days, t):g} d" for t in TABLES)
    full = ", ".join(h.revolutions_for) or "none"
    return (f"historian of machines '{h.machines}', zenoh {settings.zenoh.mode}, retention {kept}, "
            f"full revolutions for {full}, spool {h.spool_dir} ≤ {h.spool_max_mb:g} MB")
