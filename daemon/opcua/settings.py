"""What `millsense opcua` takes from `--config FILE`: its `[opcua]` section (issue 42) and the machine's id.

Only that section and `machine` are validated here, as `check-config` validates them (the same model,
config/opcua_section.py, the same `opcua.key: what is wrong` lines): the server's user need not be able
to read the files the rest of the daemon's configuration names. The command line overrides it key by key.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from millsense.daemon.config.errors import problems_from
from millsense.daemon.config.models import Settings
from millsense.daemon.config.opcua_section import OpcuaSettings


class OpcuaConfigError(Exception):
    """The `[opcua]` section cannot be used: one line per problem, `opcua.key: ...` (exit 78)."""


@dataclass(frozen=True)
class Identification:
    """OPC 40001-1's mandatory Identification of one machine (OPC 40501 MachineToolIdentificationType)."""

    manufacturer: str
    serial_number: str
    product_instance_uri: str


@dataclass
class FileSettings:
    machine: str | None
    opcua: OpcuaSettings
    tools: list[int]  # the `[tools.N]` numbers: one ToolType each under Equipment/Tools


def read_opcua_section(path: Path) -> FileSettings:
    """The `[opcua]` section of the daemon's TOML, its paths resolved from the file's folder. Raises OpcuaConfigError."""
    try:
        raw: dict[str, Any] = tomllib.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise OpcuaConfigError(f"--config {path}: cannot be read: {exc.strerror or exc}") from None
    except (UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise OpcuaConfigError(f"--config {path}: not a TOML file: {exc}") from None
    section = raw.get("opcua", {})
    if not isinstance(section, dict):
        raise OpcuaConfigError(f"{path}: opcua: not a section ([opcua] with its keys; docs/config.md)")
    try:
        settings = OpcuaSettings.model_validate(section)
    except ValidationError as exc:
        raise OpcuaConfigError("\n".join(f"{path}: {line}" for line in problems_from(Settings, exc, ("opcua",)))) from None
    base = path.resolve().parent
    resolved = {key: str(base / value) for key in ("cert", "key", "trust_dir", "operators_dir", "nodesets_dir")
                if (value := getattr(settings, key)) and not Path(value).expanduser().is_absolute()}
    machine = raw.get("machine") if isinstance(raw.get("machine"), str) else None
    tools = raw.get("tools") if isinstance(raw.get("tools"), dict) else {}
    numbers = sorted(int(k) for k in tools if isinstance(k, str) and k.isdigit())
    return FileSettings(machine=machine, opcua=settings.model_copy(update=resolved), tools=numbers)


def identification_of(settings: OpcuaSettings) -> Identification | None:
    """The machine's Identification, or None when the section does not give all three."""
    values = [getattr(settings, k).strip() for k in ("manufacturer", "serial_number", "product_instance_uri")]
    return Identification(*values) if all(values) else None
