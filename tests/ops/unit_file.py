"""The daemon's systemd unit as data: its options, and the environment it gives the daemon (for the
tests and benchmarks that run the daemon as the service does)."""

from __future__ import annotations

from pathlib import Path

from tests.config.helpers import REPO

UNIT = REPO / "systemd" / "millsense@.service"


def unit_options(unit: Path = UNIT) -> dict[str, list[str]]:
    """Every `Key=value` of a unit (the daemon's by default), values in order (a key may repeat)."""
    opts: dict[str, list[str]] = {}
    for line in unit.read_text().splitlines():
        if "=" in line and not line.lstrip().startswith(("#", "[")):
            k, v = line.split("=", 1)
            opts.setdefault(k.strip(), []).append(v.strip())
    return opts


def unit_environment() -> dict[str, str]:
    """The variables the unit's `Environment=` lines set (one NAME=value each, as this unit writes them)."""
    return dict(line.split("=", 1) for line in unit_options().get("Environment", []))
