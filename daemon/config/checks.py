"""Checks that need more than one section, the calibration file, and the DAQ's descriptor.

Each check takes the sections it needs and skips when one of them is itself
invalid (that problem is already reported), so one run reports every problem
it can see. Channel *kinds* are only known from the DAQ's DESCRIPTOR at run
time: at load, channels are checked by the names the spec uses (`fx`, `fy` for
a dynamometer) and nothing more; `descriptor_problems` is the real check,
called by the pipeline when the first DESCRIPTOR arrives.
"""

from __future__ import annotations

import json
import re
import tomllib
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Annotated, Any

from pydantic import BeforeValidator, Field, ValidationError

from millsense.daemon.config.errors import problems_from
from millsense.daemon.config.models import (
    AFC_MIN_GAIN, CutSettings, DepthSettings, Settings, ToolSettings, _cf_value, _Section,
)

# Datasheet names (architecture.md "Simulated sensors", daq-protocol.md "typical name") → kind name.
CONVENTIONAL_KINDS = {
    "v_uv": "VOLTAGE", "v_vw": "VOLTAGE", "v_wu": "VOLTAGE",
    "i_u": "CURRENT", "i_v": "CURRENT", "i_w": "CURRENT",
    "sp_rpm": "SPEED", "mot_rpm": "SPEED", "sp_enc": "ENCODER",
    "ix_feed": "FEED_CURRENT", "iy_feed": "FEED_CURRENT", "fx_rate": "FEED_RATE",
    "fx": "FORCE", "fy": "FORCE", "fz": "FORCE",
}
_EXAMPLE_FEED_FORCE = "e.g. ix_feed = { newton_per_amp = 950.0, friction_n = 120.0 }"


# ----------------------------------------------------------------------------- files
def read_toml(path: Path, label: str, what: str) -> tuple[dict[str, Any] | None, list[str]]:
    """Read and parse a TOML file; every failure is one problem naming `label`."""
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        return None, [f"{label}: {_it(label, path)}does not exist ({what})"]
    except IsADirectoryError:
        return None, [f"{label}: {_it(label, path)}is a directory ({what})"]
    except OSError as exc:
        return None, [f"{label}: {_it(label, path)}cannot be read: {exc.strerror or exc} ({what})"]
    return parse_toml(raw, label, what)


def _it(label: str, path: Path) -> str:
    """Name the file in the message unless the label already is its path."""
    return "" if label == str(path) else f"{path} "


def parse_toml(raw: bytes | str, label: str, what: str) -> tuple[dict[str, Any] | None, list[str]]:
    if isinstance(raw, bytes):
        try:
            text = raw.decode("utf-8")
        except UnicodeDecodeError as exc:
            return None, [f"{label}: not UTF-8 text: byte 0x{raw[exc.start]:02x} at offset {exc.start} ({what}, UTF-8 encoded)"]
    else:
        text = raw
    try:
        return tomllib.loads(text), []
    except tomllib.TOMLDecodeError as exc:
        msg = str(exc)
        m = re.search(r"\s*\(at line (\d+), column (\d+)\)\s*$", msg)
        if m:
            detail = msg[: m.start()]
            where = f"line {m.group(1)}, column {m.group(2)}"
        else:
            detail, where = re.sub(r"\s*\(at end of document\)\s*$", "", msg), "end of file"
        return None, [f"{label}: TOML syntax error at {where}: {detail} ({what}: valid TOML)"]
    except (ValueError, RecursionError) as exc:  # e.g. absurd nesting
        return None, [f"{label}: cannot be parsed as TOML: {type(exc).__name__} ({what})"]


# ----------------------------------------------------------------------------- across sections
def cross_problems(parts: Mapping[str, Any]) -> list[str]:
    """Rules spanning sections. `parts[name]` is the validated section, or None if invalid."""
    problems: list[str] = []
    channels, feed_force, cut, depth, tool = (parts.get(k) for k in ("channels", "feed_force", "cut", "depth", "tool"))
    if channels is not None and feed_force is not None:
        for name in feed_force:
            if name not in channels:
                problems.append(f"feed_force.{name}: no [channels.{name}] table (a configured feed_current channel)")
    if isinstance(depth, DepthSettings):
        method = depth.method
        if method == "dynamometer" and channels is not None:
            missing = [n for n in ("fx", "fy") if n not in channels]
            if missing:
                problems.append(
                    f'depth.method: "dynamometer" needs the force channels fx and fy; missing: '
                    f"{', '.join(f'[channels.{n}]' for n in missing)} (two dynamometer channels, [D] eq. 10)"
                )
        if method == "feed-drive" and feed_force is not None and not feed_force:
            problems.append(
                f'depth.method: "feed-drive" needs a [feed_force] entry for a feed_current channel ({_EXAMPLE_FEED_FORCE})'
            )
        if method == "torque-only" and isinstance(cut, CutSettings):
            if cut.mode != "slot" and cut.axial_depth_mm is None and cut.radial_depth_mm is None:
                problems.append(
                    'depth.method: "torque-only" needs one known depth (cut.axial_depth_mm or cut.radial_depth_mm, or cut.mode = "slot")'
                )
    problems.extend(_modbus_timeout_problems(parts.get("daq"), parts.get("interlock")))
    if isinstance(cut, CutSettings) and isinstance(tool, ToolSettings) and cut.radial_depth_mm is not None:
        d = tool.diameter_mm
        if cut.radial_depth_mm > d:
            problems.append(f"cut.radial_depth_mm: {cut.radial_depth_mm:g} is more than the tool diameter {d:g} (at most tool.diameter_mm)")
        elif cut.mode == "slot" and cut.radial_depth_mm != d:
            problems.append(
                f'cut.radial_depth_mm: {cut.radial_depth_mm:g} contradicts mode = "slot" (a slot\'s radial depth is the '
                f"tool diameter, {d:g}; leave it out, or use mode down/up)"
            )
    if isinstance(cut, CutSettings):
        problems.extend(_listed_tool_problems(cut, parts.get("tools")))
    problems.extend(_afc_gain_problems(parts.get("afc"), parts.get("material")))
    afc, interlock = parts.get("afc"), parts.get("interlock")
    if getattr(afc, "enabled", False) and interlock is not None and not getattr(interlock, "enabled", True):
        # the heartbeat is what lets the DAQ's watchdog put the override back to 100 % if the daemon dies
        problems.append("afc.enabled: true with the interlock off: without its heartbeat the DAQ's watchdog could not "
                        "return the feed override to 100 % if the daemon stopped (set [interlock] enabled = true, "
                        "or afc.enabled = false)")
    return problems


def _afc_gain_problems(afc: Any, material: Any) -> list[str]:
    """The controller's process gain from [material] (1 + ks_exp) must be one it can use (docs/afc.md)."""
    if afc is None or material is None or getattr(afc, "process_gain", 0.0) > 0:
        return []
    gain = 1.0 + material.ks_exp
    if gain < AFC_MIN_GAIN:
        return [f"afc.process_gain: not set, and 1 + material.ks_exp = {gain:g} is below {AFC_MIN_GAIN:g}: the load would "
                f"barely follow the feed (set process_gain, d ln(load) / d ln(feed), e.g. 0.56)"]
    return []


def _listed_tool_problems(cut: CutSettings, tools: Any) -> list[str]:
    """`[cut]`'s rules against each `[tools.N]`, as against `[tool]`: any of them may be in the spindle.

    The `[cut]` depth is one number for every tool, so a tool it cannot fit is the odd one out:
    the problem names that tool's `tools.N.diameter_mm` (its depths would read `out_of_range`).
    """
    radial = cut.radial_depth_mm
    if radial is None or not isinstance(tools, Mapping):
        return []
    problems = []
    for number, t in sorted(tools.items()):
        d = t.diameter_mm
        if radial > d:
            problems.append(
                f"tools.{number}.diameter_mm: {d:g} is less than cut.radial_depth_mm {radial:g} (a known radial depth "
                f"must fit every tool that may be in the spindle: at least {radial:g}, or leave "
                f"cut.radial_depth_mm out and measure it)"
            )
        elif cut.mode == "slot" and radial != d:
            problems.append(
                f'tools.{number}.diameter_mm: {d:g} contradicts cut.radial_depth_mm {radial:g} with mode = "slot" (a '
                f"slot's radial depth is each tool's own diameter: leave cut.radial_depth_mm out)"
            )
    return problems


def _modbus_timeout_problems(daq: Any, interlock: Any) -> list[str]:
    """A Modbus request holds the link while it waits: heartbeats must still reach the watchdog in time."""
    if daq is None or interlock is None or not daq.transport.startswith("modbus") or not interlock.enabled:
        return []
    room_ms = interlock.watchdog_ms - interlock.heartbeat_ms
    if daq.timeout_ms < room_ms:
        return []
    return [
        f"daq.timeout_ms: {daq.timeout_ms} leaves no room for a heartbeat before the DAQ's watchdog "
        f"(interlock.watchdog_ms {interlock.watchdog_ms} − heartbeat_ms {interlock.heartbeat_ms}): one unanswered "
        f"request would stop the feed (less than {room_ms}, or a longer watchdog_ms)"
    ]


# ----------------------------------------------------------------------------- calibration file
class CalibrationGear(_Section):
    """One `[[gears]]` of a file written by `millsense calibrate`."""

    name: str = Field(min_length=1)
    friction_torque_nm: float = Field(ge=0)
    viscous_nms: float = Field(ge=0)
    inertia_kgm2: float | None = Field(None, ge=0)  # fitted from air-cut run-ups, when the captures had them
    samples: int | None = Field(None, ge=0)
    r2: float | None = Field(None, allow_inf_nan=True)  # informative; a flat fit may give nan


class CalibrationTool(_Section):
    cf: Annotated[float, BeforeValidator(_cf_value)]


class CalibrationFile(_Section):
    gears: list[CalibrationGear] = Field(default_factory=list)
    tool: CalibrationTool | None = None


CALIBRATION_WHAT = "a TOML file written by `millsense calibrate`; a relative path is taken from the config file's folder"


def apply_calibration(parts: dict[str, Any], path: Path) -> list[str]:
    """Override `parts['gears']` friction (matched by name) and `parts['tool'].cf` in place.

    The calibrated C_f was fitted on `[tool]`'s cutter, so it is `[tool]`'s alone: a
    `[tools.N]` without its own `cf` keeps the `cf` the file gives `[tool]` (pinned
    here in `parts['tools']`, before `[tool]` takes the calibrated one).
    """
    data, problems = read_toml(path, "calibration", CALIBRATION_WHAT)
    if data is None:
        return problems
    try:
        cal = CalibrationFile.model_validate(data)
    except ValidationError as exc:
        return [f"calibration: {path}: {p}" for p in problems_from(CalibrationFile, exc)]
    gears = parts.get("gears")
    if gears is not None:
        by_name = {g.name: i for i, g in enumerate(gears)}
        updated = list(gears)
        for k, cg in enumerate(cal.gears):
            if cg.name not in by_name:
                problems.append(
                    f"calibration: {path}: gears[{k}].name: {json.dumps(cg.name)} is not a gear of this config "
                    f"(one of: {', '.join(by_name)})"
                )
                continue
            i = by_name[cg.name]
            update = {"friction_torque_nm": cg.friction_torque_nm, "viscous_nms": cg.viscous_nms}
            if cg.inertia_kgm2 is not None:
                update["inertia_kgm2"] = cg.inertia_kgm2
            updated[i] = updated[i].model_copy(update=update)
        parts["gears"] = updated
    if cal.tool is not None and parts.get("tool") is not None:
        configured_cf = parts["tool"].cf
        tools = parts.get("tools")
        if tools:
            parts["tools"] = {n: t if t.cf is not None else t.model_copy(update={"cf": configured_cf})
                              for n, t in tools.items()}
        parts["tool"] = parts["tool"].model_copy(update={"cf": cal.tool.cf})
    return problems


# ----------------------------------------------------------------------------- DAQ descriptor
def _pairs(channels: Any) -> list[tuple[str, str]]:
    """(name, KIND) pairs from a Descriptor, a {name: kind} mapping or an iterable of pairs."""
    items = getattr(channels, "channels", channels)
    items = items.items() if isinstance(items, Mapping) else items
    out = []
    for item in items:
        name, kind = (item.name, item.kind) if hasattr(item, "name") and hasattr(item, "kind") else item
        out.append((str(name), _kind_name(kind)))
    return out


def _kind_name(kind: Any) -> str:
    if hasattr(kind, "name") and isinstance(getattr(kind, "name"), str):
        return kind.name.upper()
    if isinstance(kind, int):
        try:
            from millsense.drivers.protocol import ChannelKind

            return ChannelKind(kind).name
        except (ImportError, ValueError):
            return "OTHER"
    return str(kind).upper().replace("-", "_")


def descriptor_problems(settings: Settings, channels: Any) -> list[str]:
    """Does the configuration fit the channels the DAQ announced? Every misfit, named.

    `channels`: the DESCRIPTOR (`.channels` of `Channel(kind, name)`), a
    `{name: kind}` mapping, or `(name, kind)` pairs; kinds as `ChannelKind`,
    their int codes or names. A DESCRIPTOR's sample rate must be `[daq] sample_rate_hz`.
    """
    sent = dict(_pairs(channels))
    problems: list[str] = []
    rate = getattr(channels, "sample_rate_hz", None)
    want = getattr(getattr(settings, "daq", None), "sample_rate_hz", None)
    if rate is not None and want is not None and float(rate) != float(want):
        # every speed, electrical frequency and power integral scales with the rate: believing a wrong
        # one gave 39 321 rpm and 102 000 N·m (issue 10), so nothing is estimated until they agree
        problems.append(
            f"daq.sample_rate_hz: the DAQ's descriptor says {rate:g} Hz, the configuration {want:g} Hz "
            f"(speeds and torques would be off by {float(rate) / float(want):.3g}×: set the DAQ to the configured "
            f"rate, or daq.sample_rate_hz to the rate it really samples at)"
        )
    listing = ", ".join(f"{n} ({k.lower()})" for n, k in sent.items()) or "nothing"
    used: dict[str, str] = {}
    for name, ch in settings.channels.items():
        if name not in sent:
            problems.append(f"channels.{name}: the DAQ does not send this channel (it sends: {listing})")
            continue
        kind = sent[name]
        used[name] = kind
        conventional = CONVENTIONAL_KINDS.get(name)
        if conventional and kind != conventional:
            problems.append(
                f"channels.{name}: the DAQ says it is a {kind.lower()} channel "
                f"(by its name, a {conventional.lower()} channel: check the wiring or the name)"
            )
        if kind == "ENCODER" and not ch.counts_per_rev:
            problems.append(f"channels.{name}.counts_per_rev: missing (an encoder channel needs counts per spindle revolution, e.g. 4096)")
        if kind != "ENCODER" and ch.counts_per_rev is not None:
            problems.append(f"channels.{name}.counts_per_rev: set on a {kind.lower()} channel (only for encoder channels)")

    def of(kind: str) -> list[str]:
        return [n for n, k in used.items() if k == kind]

    for kind, need, why in (("VOLTAGE", 2, "line voltages (v_uv, v_vw, v_wu)"), ("CURRENT", 2, "line currents (i_u, i_v, i_w)")):
        if len(of(kind)) < need:
            problems.append(
                f"channels: the power ([P] eq. 11) needs at least {need} {why} configured and sent; "
                f"found {', '.join(of(kind)) or 'none'} (a [channels.NAME] table per {kind.lower()} channel of the DAQ)"
            )
    if not of("ENCODER") and not of("SPEED"):
        problems.append("channels: no spindle speed or encoder channel configured and sent (sp_rpm, or sp_enc with counts_per_rev)")
    if settings.depth.method == "dynamometer" and len(of("FORCE")) < 2:
        problems.append(
            f'depth.method: "dynamometer" needs two force channels configured and sent; found {", ".join(of("FORCE")) or "none"}'
        )
    for name in settings.feed_force:
        if name in used and used[name] != "FEED_CURRENT":
            problems.append(f"feed_force.{name}: the DAQ says {name} is a {used[name].lower()} channel (a feed_current channel)")
    if settings.depth.method == "feed-drive" and not any(used.get(n) == "FEED_CURRENT" for n in settings.feed_force):
        problems.append('depth.method: "feed-drive" needs a feed_current channel with a [feed_force] entry, configured and sent')
    return problems


def channel_pairs(items: Iterable[Any]) -> list[tuple[str, str]]:
    """Public form of the (name, KIND) normalisation, for callers that log what the DAQ sends."""
    return _pairs(items)
