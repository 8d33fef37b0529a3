"""Which payload field becomes which OPC UA variable: one table, no asyncua, no Zenoh.

Each machine object holds folders (`Spindle`, `Safety`, `Process`, `Afc`); each variable is named
after the payload field it shows (docs/zenoh.md), so the unit is in its name (`torque_nm`) and a
reader of the Zenoh contract recognises it. A payload field that is `null` ("could not be
estimated") keeps the variable's last value with the status BadNoData, so a client never reads a
stale number as fresh.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

# OPC UA built-in types by name (asyncua's VariantType members), so this module needs no asyncua.
DOUBLE, INT64, BOOL, STRING = "Double", "Int64", "Boolean", "String"


@dataclass(frozen=True)
class Field:
    folder: str       # the folder under the machine object
    name: str         # the browse name: the payload's own field name
    kind: str         # which publication carries it: estimate, alarm, status, process
    path: tuple[str, ...]  # where in the payload (nested objects for `afc`)
    ua_type: str
    description: str


def _f(folder: str, name: str, kind: str, ua_type: str, description: str, path: tuple[str, ...] | None = None) -> Field:
    return Field(folder, name, kind, path or (name,), ua_type, description)


FIELDS: tuple[Field, ...] = (
    # One spindle revolution's estimate (docs/zenoh.md, `estimate`).
    _f("Spindle", "spindle_rpm", "estimate", DOUBLE, "spindle speed, rev/min"),
    _f("Spindle", "p_in_w", "estimate", DOUBLE, "electrical input power, W"),
    _f("Spindle", "p_gap_w", "estimate", DOUBLE, "air-gap power, W"),
    _f("Spindle", "torque_nm", "estimate", DOUBLE, "cutting torque at the spindle, N·m"),
    _f("Spindle", "torque_sigma_nm", "estimate", DOUBLE, "one standard uncertainty of the torque, N·m"),
    _f("Spindle", "force_n", "estimate", DOUBLE, "resultant cutting force, N"),
    _f("Spindle", "radial_depth_mm", "estimate", DOUBLE, "radial depth of cut, mm"),
    _f("Spindle", "axial_depth_mm", "estimate", DOUBLE, "axial depth of cut, mm"),
    _f("Spindle", "depth_status", "estimate", STRING,
       "ok, air_cut, no_second_force, out_of_range, unresolvable, speed_changing, speed_out_of_range, not_feeding, "
       "feed_out_of_range, outside_tool (docs/physics.md)"),
    _f("Spindle", "cutting", "estimate", BOOL, "the revolution cut (torque over [depth] min_torque_nm)"),
    _f("Spindle", "valid", "estimate", BOOL, "false for a damaged or implausible revolution"),
    _f("Spindle", "rev", "estimate", INT64, "the daemon's revolution number"),
    # Safety: the latest alarm change, and the daemon's own state once a second.
    _f("Safety", "alarm", "status", STRING, "the worst active alarm in one word (ok when none)"),
    _f("Safety", "interlock", "status", STRING, "armed, feed_hold, held_by_device or disabled"),
    _f("Safety", "state", "status", STRING, "daemon state: starting, running, degraded, stopping"),
    _f("Safety", "daq_link", "status", STRING, "the DAQ link: up or down"),
    _f("Safety", "last_alarm_level", "alarm", STRING, "level of the latest alarm change (clear when it ended)",
       ("level",)),
    _f("Safety", "last_alarm_quantity", "alarm", STRING, "the quantity the latest alarm judged", ("quantity",)),
    _f("Safety", "last_alarm_value", "alarm", DOUBLE, "its value", ("value",)),
    _f("Safety", "last_alarm_limit", "alarm", DOUBLE, "the limit it crossed", ("limit",)),
    # The process in the spindle (issue 14), and the last finished one.
    _f("Process", "program", "estimate", INT64, "program number (the CNC's context)"),
    _f("Process", "tool", "estimate", INT64, "tool number in the spindle"),
    _f("Process", "operation", "estimate", INT64, "operation number"),
    _f("Process", "process_rev", "estimate", INT64, "revolutions since the process's entry"),
    _f("Process", "envelope_low_nm", "estimate", DOUBLE, "learned band at this revolution, low side, N·m"),
    _f("Process", "envelope_high_nm", "estimate", DOUBLE, "learned band at this revolution, high side, N·m"),
    _f("Process", "processes", "status", INT64, "processes finished since the daemon started"),
    _f("Process", "last_process_key", "process", STRING, "program/tool/operation of the last finished process",
       ("key",)),
    _f("Process", "last_verdict", "process", STRING, "its verdict", ("verdict",)),
    _f("Process", "last_energy_j", "process", DOUBLE, "its cutting energy, J", ("energy_j",)),
    _f("Process", "tool_processes", "process", INT64, "processes the last tool has cut since it was new"),
    _f("Process", "tool_wear_pct", "process", DOUBLE, "that tool's wear: energy rise over its new state, %"),
    # Adaptive feed control (issue 15), where the daemon has it.
    _f("Afc", "feed_override_pct", "estimate", DOUBLE, "feed override the daemon asks for, %"),
    _f("Afc", "state", "estimate", STRING, "AFC state", ("afc", "state")),
    _f("Afc", "override_pct", "estimate", DOUBLE, "AFC override, %", ("afc", "override_pct")),
    _f("Afc", "target", "estimate", DOUBLE, "AFC target", ("afc", "target")),
)

OPTIONAL_FOLDERS = frozenset({"Afc"})  # made only when a payload first carries one of its fields
COALESCED_KINDS = ("estimate", "status")  # the newest replaces the older: unchanged values are not rewritten
ABSENT = object()  # the payload does not carry the field at all (an older daemon): leave the variable alone


def fields_of(kind: str) -> tuple[Field, ...]:
    return tuple(f for f in FIELDS if f.kind == kind)


def value_at(payload: dict[str, Any], field: Field) -> Any:
    """The field's value in `payload`: a converted value, None for JSON null, or ABSENT."""
    node: Any = payload
    for part in field.path:
        if not isinstance(node, dict) or part not in node:
            return ABSENT
        node = node[part]
    return convert(node, field.ua_type)


def convert(value: Any, ua_type: str) -> Any:
    """`value` as the variable's type, None when it is null or does not fit (never a wrong type)."""
    if value is None:
        return None
    if ua_type == STRING:
        return value if isinstance(value, str) else None
    if ua_type == BOOL:
        return value if isinstance(value, bool) else None
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    if ua_type == DOUBLE:
        return float(value)
    if ua_type == INT64:
        return int(value) if float(value).is_integer() and abs(value) < 2**63 else None
    return None
