"""What a valid configuration still does that a user should know: warnings, never errors.

`check-config` prints each as one `warning: section.key: …` line (exit 0) and
`run` logs each at start (`config.warning`). Each names the key to change.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path
from typing import Any

from millsense.daemon.config.models import loopback_only


def config_warnings(settings: Any, path: str | os.PathLike[str] | None = None) -> list[str]:
    """Every warning for `settings`, read from `path` (None: no file, e.g. the demo)."""
    out: list[str] = []
    out += _interlock_warnings(settings)
    out += _security_warnings(settings, Path(path) if path is not None else None)
    out += _learning_warnings(settings)
    out += _afc_warnings(settings)
    out += _context_authority_warnings(settings, Path(path) if path is not None else None)
    out += _operations_warnings(settings)
    return out


def _operations_warnings(settings: Any) -> list[str]:
    """[operations] declared where nothing can arm their expected band (issue 41): it needs processes."""
    if not getattr(settings, "operations", None):
        return []
    learning, context = getattr(settings, "learning", None), getattr(settings, "context", None)
    if learning is not None and not learning.enabled:
        return ["learning.enabled: false, so the [operations] entries arm no expected band (it is checked per "
                "process, like the learned limits); only the fixed [alarms] limits guard the first parts"]
    if context is not None and context.source == "off":
        return ['context.source: "off", so no process has a key and the [operations] entries arm no expected band; '
                'only the fixed [alarms] limits guard the first parts']
    return []


def _context_authority_warnings(settings: Any, path: Path | None) -> list[str]:
    """AFC on with its context from Zenoh that nobody vouches for (issue 36): it will stay idle there."""
    out: list[str] = []
    context = getattr(settings, "context", None)
    afc = getattr(settings, "afc", None)
    if context is None:
        return out
    if (afc is not None and afc.enabled and context.source in ("zenoh", "auto") and not context.key()
            and context.trust != "acl"):
        where = "the Zenoh context" if context.source == "zenoh" else "a Zenoh context (a DAQ that reports none)"
        out.append(
            f"context.adapter_key_file: not set and trust is \"none\", while afc.enabled is true and the context "
            f"comes from Zenoh (source = \"{context.source}\"): anyone may put {where}, so AFC never follows it "
            "(idle, \"context not authenticated\"); sign the adapter's puts with a key from `millsense token new` "
            "(docs/zenoh.md, \"Signed context\"), or trust = \"acl\" behind a router whose ACL lets only "
            "adapters put it"
        )
    out += _secret_warnings("context.adapter_key", bool(context.key()), context.adapter_key_file, path, "key")
    return out


def _secret_warnings(key: str, inline: bool, file: str | None, path: Path | None, what: str) -> list[str]:
    """A secret other users could read or set: inline in a config file they can read (`key`), or in its own
    file (`key`_file) that is not the owner's alone. `what`: "token" or "key", for the messages."""
    out: list[str] = []
    if path is not None and inline and not file and _others_read(path):
        out.append(f"{key}: {path} holds the {what} and other users can read it "
                   f"(chmod 640 {path}, owner root, group millsense; or use {key.rsplit('.', 1)[1]}_file)")
    if file:
        secret_path = Path(file)
        if not secret_path.is_absolute() and path is not None:
            secret_path = path.resolve().parent / secret_path
        if _others_read(secret_path):
            out.append(f"{key}_file: {secret_path} can be read by other users (chmod 600, owner millsense)")
        if _others_write(secret_path):
            out.append(f"{key}_file: {secret_path} can be written by users other than its owner "
                       f"(chmod 600, owner millsense): they could set the {what}")
    return out


AFC_SLEW_MAX_S = 1.0  # the rate limit should bring the override from 100 % to the lower bound within this


def _afc_warnings(settings: Any) -> list[str]:
    """An `[afc]` that is valid but will not do what its author expects (docs/afc.md)."""
    out: list[str] = []
    afc = getattr(settings, "afc", None)
    if afc is None:
        return out
    if afc.air_override_pct > 100.0:
        out.append(
            f"afc.air_override_pct: {afc.air_override_pct:g} % is above the programmed feed: the tool enters each "
            "cut faster than programmed, before any estimate can slow it (100 or below)"
        )
    wanted = afc.target_key()
    for key in ("torque_nm", "force_n", "power_w"):
        if key != wanted and getattr(afc, f"target_{key}") is not None:
            out.append(f"afc.target_{key}: set but quantity is \"{afc.quantity}\": never used (target_{wanted})")
    for name, entry in sorted(afc.targets.items()):
        for key in ("torque_nm", "force_n", "power_w"):
            if key != wanted and getattr(entry, key) is not None:
                out.append(
                    f'afc.targets."{name}".{key}: set but quantity is "{afc.quantity}": never used ({wanted})'
                )
    slew_s = (100.0 - afc.min_override_pct) / afc.rate_pct_s
    if slew_s > AFC_SLEW_MAX_S:
        out.append(
            f"afc.rate_pct_s: {afc.rate_pct_s:g} %/s takes {slew_s:.1f} s from 100 % down to min_override_pct = "
            f"{afc.min_override_pct:g} %: a step into a deeper cut overloads the tool that long "
            f"(at least {(100.0 - afc.min_override_pct) / AFC_SLEW_MAX_S:g} %/s)"
        )
    return out


def _learning_warnings(settings: Any) -> list[str]:
    """Context, tools by number and learned limits that a valid file leaves unused or racing."""
    out: list[str] = []
    source = settings.context.source
    if source == "off" and settings.tools:
        tables = ", ".join(f"[tools.{n}]" for n in sorted(settings.tools))
        out.append(
            f"context.source: \"off\", so the daemon never knows the tool in the spindle: {tables} "
            "are never used and every cut is computed with [tool] (source = \"auto\")"
        )
    if source == "off" and settings.learning.enabled:
        out.append(
            "learning.enabled: true but context.source is \"off\": without program, tool and operation there "
            "are no processes to learn; only the fixed [alarms] limits watch the cut"
        )
    learning = settings.learning
    if learning.enabled and learning.min_width_pct <= learning.wear_rise_pct:
        out.append(
            f"learning.min_width_pct: {learning.min_width_pct:g} % is not above wear_rise_pct = "
            f"{learning.wear_rise_pct:g} %: a wearing tool may leave its envelope (envelope_high) before "
            "the wear warning says it is wearing (docs/learning.md)"
        )
    return out


def _interlock_warnings(settings: Any) -> list[str]:
    out: list[str] = []
    if not settings.interlock.enabled:
        return out
    alarms = settings.alarms
    if alarms.crash_power_w is None and alarms.crash_current_a is None:
        out.append(
            "alarms.crash_power_w: no sample-level limit is armed (crash_power_w or crash_current_a): with the "
            "interlock on, a crash waits for whole revolutions to close, and a spindle that stalls closes none"
        )
    if alarms.stall_current_a is None:
        out.append(
            "alarms.stall_current_a: not set: a spindle that stops under load is caught only by a sample-level "
            "limit on power or current, not by the stall check"
        )
    for i, gear in enumerate(settings.gears):
        if gear.inertia_kgm2 is None:
            out.append(
                f"gears[{i}].inertia_kgm2: not set for gear {gear.name!r}: speeding up reads as load, so a fast "
                "spindle start or speed change may trip the interlock (fit it with `millsense calibrate` on an "
                "air-cut run-up, or set it)"
            )
    return out


def _security_warnings(settings: Any, path: Path | None) -> list[str]:
    out: list[str] = []
    il = settings.interlock
    if il.reset == "token" and not il.token():
        out.append(
            "interlock.reset_token_file: not set, and reset is \"token\" (the default for a Zenoh session other "
            "hosts can reach): no command over the network can clear a feed hold; make a token with "
            "`millsense token new` (the local reset at the machine still works)"
        )
    if il.reset == "open" and not loopback_only(settings.zenoh):
        out.append(
            'interlock.reset: "open" while the Zenoh session can be reached from other hosts: anyone on the network '
            'may clear a feed hold (reset = "token" with a token from `millsense token new`)'
        )
    out += _secret_warnings("interlock.reset_token", il.reset_token is not None, il.reset_token_file, path, "token")
    return out


def _mode(path: Path) -> int | None:
    try:
        return path.stat().st_mode
    except OSError:
        return None


def _others_read(path: Path) -> bool:
    mode = _mode(path)
    return mode is not None and bool(mode & stat.S_IROTH)


def _others_write(path: Path) -> bool:
    mode = _mode(path)
    return mode is not None and bool(mode & (stat.S_IWOTH | stat.S_IWGRP))
