"""`millsense check-config FILE`: validate a configuration without starting anything.

Exit 0 with a one-line summary when the file is valid, after one `warning:`
line for each thing a valid file still does that its user should know
(`config/warnings.py`); otherwise `ConfigError`
propagates to the CLI front door, which prints every problem (one per line,
`section.key: what is wrong (what is expected)`) and exits 78. Only pydantic,
the config modules and command_auth (the standard library's hmac: the policy in
effect, who may command over which transport, ends the summary) are imported:
this must stay quick enough for an editor hook.
"""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", metavar="FILE", help="the TOML configuration to check")


def summary(settings) -> str:
    """One line saying what the file configures, so a user sees it was read as meant."""
    daq = settings.daq
    where = {
        "serial": daq.port, "modbus-rtu": daq.port, "tcp": f"{daq.host}:{daq.tcp_port}",
        "modbus-tcp": f"{daq.host}:{daq.tcp_port}", "sim": f"scenario {daq.scenario}",
    }[daq.transport]
    armed = [k for k, v in settings.alarms.model_dump().items()
             if k.endswith(("_nm", "_n", "_w", "_a", "_pct")) and v is not None
             and k not in ("breakage_min_torque_nm", "hysteresis_pct")]
    parts = [
        f"machine {settings.machine}",
        f"daq {daq.transport} {where}",
        f"{len(settings.channels)} channels",
        f"{len(settings.gears)} gear{'s' if len(settings.gears) != 1 else ''}",
        f"depth {settings.depth.method}",
        f"{len(armed)} alarm limit{'s' if len(armed) != 1 else ''} armed",
        f"interlock {'on' if settings.interlock.enabled else 'off'}",
        f"zenoh {_zenoh_mode(settings.zenoh)}",
    ]
    if settings.calibration:
        parts.append(f"calibration {settings.calibration}")
    if settings.operations:   # issue 41: the physics' expected band of each (docs/learning.md)
        n = len(settings.operations)
        parts.append(f"{n} operation{'s' if n != 1 else ''} with an expected band "
                     f"(±{settings.learning.physics_tolerance_pct:g} %)")
    parts.append(_command_policy(settings))
    return ", ".join(parts)


def _zenoh_mode(zs) -> str:
    """The mode the daemon's session will have: a `config_file` says it unless the TOML does (issue 39: a
    client file was summarised as `zenoh peer`, the TOML key's default). Zenoh is imported only then: the
    JSON5 file is read by its own loader, as `run` reads it; one it cannot read is refused, as `run` does."""
    if not zs.config_file:
        return zs.mode
    from millsense.daemon.config.errors import ConfigError
    from millsense.daemon.publish.session import ZenohConfigError, mode_in_effect

    try:
        return mode_in_effect(zs)
    except ZenohConfigError as exc:
        raise ConfigError([str(exc)]) from None


def _command_policy(settings) -> str:
    """Who may command over which transport (issue 36): the policy in effect, a default resolved or not."""
    from millsense.daemon.publish.command_auth import policy_summary

    il = settings.interlock
    return policy_summary(il.reset or "off", bool(il.token()))


def run(args: argparse.Namespace) -> int:
    from millsense.daemon.config.load import load_config

    from millsense.daemon.config.warnings import config_warnings

    if _historian_file(args.file):   # issue 43: `millsense historian`'s own file (docs/historian.md)
        from millsense.daemon.config import historian

        settings = historian.load_historian_config(args.file)   # ConfigError: the same exit 78
        print(f"{args.file}: OK ({historian.summary(settings)})")
        return 0
    settings = load_config(args.file)  # ConfigError -> the CLI prints the problems, exit 78
    for warning in config_warnings(settings, args.file):
        print(f"warning: {warning}")
    print(f"{args.file}: OK ({summary(settings)})")
    return 0


def _historian_file(path: str) -> bool:
    """The file is a historian's (a `[historian]` section and no `[daq]`); an unreadable one goes to the daemon's
    loader, which says what is wrong with it."""
    from pathlib import Path

    from millsense.daemon.config.checks import read_toml
    from millsense.daemon.config.historian import CONFIG_WHAT, is_historian_file

    data, _ = read_toml(Path(path), path, CONFIG_WHAT)
    return is_historian_file(data)
