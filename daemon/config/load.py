"""Loading and validating the millsense configuration file (interfaces.md, "Configuration file").

The whole file is validated at start and *every* problem is reported at once,
each as `section.key: what is wrong (what is expected)`, so a user fixes a file
in one pass and systemd does not restart-loop on it (exit 78). Nothing here
prints or raises anything but `ConfigError`.

Public API::

    load_config(path) -> Settings
    load_config_text(text, source="<text>", base_dir=None) -> Settings
    demo_config() -> Settings                   # the embedded daemon/demo.toml
    effective_config_dict(settings) -> dict     # for the `config` queryable, secrets masked
    check_against_descriptor(settings, channels, *, raise_on_problems=True) -> list[str]

The models live in `models` (`Settings`), message shaping in `errors` (`ConfigError`), rules
across sections / the calibration file / the DAQ descriptor in `checks` (`descriptor_problems`).
"""

from __future__ import annotations

import functools
import os
import shlex
from importlib import resources
from pathlib import Path
from typing import Annotated, Any

from pydantic import SecretStr, TypeAdapter, ValidationError

from millsense.daemon.config.checks import (
    apply_calibration,
    cross_problems,
    descriptor_problems,
    parse_toml,
    read_toml,
)
from millsense.daemon.config.errors import ConfigError, problems_from
from millsense.daemon.config.operations import include_operations_file, operation_problems
from millsense.daemon.config.models import (
    AlarmSettings,
    ChannelSettings,
    CutSettings,
    DaqSettings,
    DepthSettings,
    FeedForceSettings,
    MIN_TOKEN_CHARS,
    GearSettings,
    InterlockSettings,
    LogSettings,
    MaterialSettings,
    MotorSettings,
    Settings,
    ToolSettings,
    SignalSettings,
    ZenohSettings,
    endpoint_problem,
    loopback_only,
)

__all__ = [
    "AlarmSettings", "ChannelSettings", "ConfigError", "CutSettings", "DaqSettings", "DepthSettings",
    "FeedForceSettings", "GearSettings", "InterlockSettings", "LogSettings", "MaterialSettings",
    "MotorSettings", "Settings", "SignalSettings", "ToolSettings", "ZenohSettings", "check_against_descriptor",
    "demo_config", "descriptor_problems", "effective_config_dict", "endpoint_problem", "load_config",
    "load_config_text",
]

CONFIG_WHAT = "a millsense TOML configuration"
SECRET_MASK = "***"


def load_config(path: str | os.PathLike[str]) -> Settings:
    """Read, parse and validate a configuration file. Raises `ConfigError` listing every problem.

    Relative paths inside it (`calibration`, `zenoh.config_file`,
    `interlock.reset_token_file`, `context.adapter_key_file`) are taken from the file's folder.
    """
    p = Path(path)
    data, problems = read_toml(p, str(p), CONFIG_WHAT)
    if data is None:
        raise ConfigError(problems)
    return _settings_from(data, p.resolve().parent if p.parent else Path.cwd())


def load_config_text(text: str | bytes, source: str = "<text>", base_dir: str | os.PathLike[str] | None = None) -> Settings:
    """Validate a configuration given as text; relative paths are taken from `base_dir` (default: cwd)."""
    data, problems = parse_toml(text, source, CONFIG_WHAT)
    if data is None:
        raise ConfigError(problems)
    return _settings_from(data, Path(base_dir) if base_dir is not None else Path.cwd())


def demo_config() -> Settings:
    """The built-in demo (`millsense run` with no `--config`): simulated DAQ, step cut, Zenoh on loopback."""
    text = resources.files("millsense.daemon").joinpath("demo.toml").read_text(encoding="utf-8")
    return load_config_text(text, source="<built-in demo.toml>")


def effective_config_dict(settings: Settings) -> dict[str, Any]:
    """The configuration as JSON-able data for the `config` queryable; secrets masked.

    `interlock.reset_token` becomes "***" when one is set (null otherwise): a
    subscriber can see *that* a token protects the reset, never the token.
    """
    data = settings.model_dump(mode="json")
    token = settings.interlock.reset_token
    data["interlock"]["reset_token"] = SECRET_MASK if token is not None and token.get_secret_value() else None
    data["context"]["adapter_key"] = SECRET_MASK if settings.context.key() else None
    return data


def check_against_descriptor(settings: Settings, channels: Any, *, raise_on_problems: bool = True) -> list[str]:
    """Check the configuration against the DAQ's DESCRIPTOR (or `{name: kind}` / pairs).

    Returns the problems (each names the channel and what was expected). By
    default a non-empty list is raised as `ConfigError` instead, which is what
    `run` (exit 78) and the pipeline want; `raise_on_problems=False` just returns it.
    """
    problems = descriptor_problems(settings, channels)
    if problems and raise_on_problems:
        raise ConfigError(problems)
    return problems


# ----------------------------------------------------------------------------- internals
@functools.cache
def _adapters() -> dict[str, TypeAdapter]:
    """One validator per top-level key, so a broken section does not hide the others' cross checks."""
    return {name: TypeAdapter(Annotated[f.annotation, f]) for name, f in Settings.model_fields.items()}


def _parts(data: dict[str, Any]) -> dict[str, Any]:
    """Each top-level section validated on its own: the value, its default, or None if invalid/missing."""
    parts: dict[str, Any] = {}
    for name, adapter in _adapters().items():
        field = Settings.model_fields[name]
        if name not in data:
            parts[name] = None if field.is_required() else field.get_default(call_default_factory=True)
            continue
        try:
            parts[name] = adapter.validate_python(data[name])
        except (ValidationError, ValueError, TypeError, RecursionError):
            parts[name] = None
    return parts


def _resolve(base_dir: Path, value: str) -> Path:
    p = Path(value).expanduser()
    return p if p.is_absolute() else base_dir / p


def _settings_from(data: dict[str, Any], base_dir: Path) -> Settings:
    problems: list[str] = include_operations_file(data, base_dir)   # [learning] operations_file (issue 41)
    settings: Settings | None = None
    try:
        settings = Settings.model_validate(data)
    except ValidationError as exc:
        problems.extend(problems_from(Settings, exc))
    except (ValueError, TypeError, RecursionError) as exc:  # defensive: never a traceback
        problems.append(f"configuration: cannot be validated: {type(exc).__name__}: {exc} (a millsense TOML configuration)")
    parts = {name: getattr(settings, name) for name in Settings.model_fields} if settings else _parts(data)
    if parts.get("daq") is None and isinstance(data.get("daq"), dict):
        problems.extend(_transport_problems(data["daq"]))

    updates: dict[str, Any] = {}
    if parts.get("calibration"):
        path = _resolve(base_dir, parts["calibration"])
        problems.extend(apply_calibration(parts, path))
        updates.update(calibration=str(path), gears=parts["gears"], tool=parts["tool"], tools=parts["tools"])
    zenoh = parts.get("zenoh")
    if zenoh is not None and zenoh.config_file:
        path = _resolve(base_dir, zenoh.config_file)
        if not path.is_file():
            problems.append(f"zenoh.config_file: {path} does not exist (a Zenoh JSON5 file; a relative path is taken from the config file's folder)")
        updates["zenoh"] = zenoh.model_copy(update={"config_file": str(path)})
    history = parts.get("history")
    if history is not None and history.path:  # relative to the config file's folder, like the others
        updates["history"] = history.model_copy(update={"path": str(_resolve(base_dir, history.path))})
    interlock = parts.get("interlock")
    if interlock is not None and interlock.reset_token_file:
        token, problem = _read_token(_resolve(base_dir, interlock.reset_token_file))
        if problem:
            problems.append(problem)
        else:
            updates["interlock"] = interlock.model_copy(update={"reset_token": SecretStr(token)})
    problems.extend(_adapter_key(parts, updates, base_dir))
    interlock = updates.get("interlock", parts.get("interlock"))
    if interlock is not None and interlock.reset is None and parts.get("zenoh") is not None:
        # Secure by default (docs/security.md): a session other hosts can reach takes commands only from
        # whoever proves the token. Without a token nobody can, over the network; `config.warnings` says so.
        # A loopback-only session is "open", which lets any local user clear or test a hold and nothing more:
        # whatever loosens protection needs the token or the uid-checked local socket (command_auth.OPEN_COMMANDS).
        reset = "open" if loopback_only(parts["zenoh"]) and not interlock.token() else "token"
        updates["interlock"] = interlock.model_copy(update={"reset": reset})
    problems.extend(cross_problems(parts))
    problems.extend(operation_problems(parts))
    if problems or settings is None:
        raise ConfigError(list(dict.fromkeys(problems)))
    return settings.model_copy(update=updates) if updates else settings


def _transport_problems(raw_daq: dict[str, Any]) -> list[str]:
    """The transport's address rules even when another `[daq]` key is broken (a typo must not hide them)."""
    subset = {k: raw_daq[k] for k in ("transport", "port", "host", "tcp_port") if k in raw_daq}
    try:
        DaqSettings.model_validate(subset)
    except ValidationError as exc:
        return problems_from(Settings, exc, prefix=("daq",))
    return []


def _adapter_key(parts: dict[str, Any], updates: dict[str, Any], base_dir: Path) -> list[str]:
    """`[context] adapter_key_file` read like the reset token's file; the key must not be the reset token
    (issue 36: an adapter that can sign context must not thereby be able to reset, nor the reverse)."""
    context = parts.get("context")
    if context is None:
        return []
    if context.adapter_key_file:
        path = _resolve(base_dir, context.adapter_key_file)
        key, problem = _read_token(path, "context.adapter_key_file", "the CNC adapter's key")
        if problem:
            return [problem]
        context = updates["context"] = context.model_copy(update={"adapter_key": SecretStr(key),
                                                                  "adapter_key_file": str(path)})
    interlock = updates.get("interlock", parts.get("interlock"))
    if context.key() and interlock is not None and context.key() == interlock.token():
        where = "adapter_key_file" if context.adapter_key_file else "adapter_key"
        return [f"context.{where}: holds the reset token; the adapter key must be a secret of its own "
                "(`millsense token new` makes another)"]
    return []


def _read_token(path: Path, key: str = "interlock.reset_token_file",
                secret: str = "the reset secret") -> tuple[str, str | None]:
    what = f"a file holding {secret} on one line, readable by the millsense user only"
    try:
        token = path.read_text(encoding="utf-8").strip()
    except FileNotFoundError:  # say how to make it (issue 39): quoted, so that the line can be pasted into a shell
        make = f"millsense token new --out {shlex.quote(str(path))}"
        return "", f"{key}: {path} does not exist ({what}: make one with `{make}`)"
    except (OSError, UnicodeDecodeError) as exc:
        return "", f"{key}: {path} cannot be read: {getattr(exc, 'strerror', None) or exc} ({what})"
    if not token:
        return "", f"{key}: {path} is empty ({what})"
    if len(token) < MIN_TOKEN_CHARS:
        return "", (f"{key}: {path} holds {len(token)} characters, too short to resist guessing "
                    f"(at least {MIN_TOKEN_CHARS}: `millsense token new` makes one)")
    return token, None
