"""A status payload in words, as every display says it: the hold and since when, the live line, sd_notify's
STATUS= line. Pure; shared by the live daemon (runtime/), `millsense watch` and the OPC UA server.
"""

from __future__ import annotations

import time
from typing import Any


def _fmt(value: Any, spec: str) -> str:
    if value is None:
        return "–"
    try:
        return format(float(value), spec)
    except (TypeError, ValueError):
        return "–"


# The alarm levels whose alarm, sent with `"interlock": "feed_hold"`, is the trip itself (pipeline/alarms.py,
# TRIP_LEVELS; envelope alarms hold as `[learning]` says): a display may show the hold from it at once.
TRIP_LEVELS = ("overload", "crash", "tool_breakage", "envelope_high", "envelope_low", "expected_high", "expected_low")


def hold_of(status: dict[str, Any]) -> tuple[str, float | None] | None:
    """(reason, since) while a status says the feed is held, else None.

    Held: the interlock latched (`feed_hold`: its reason and the trip's Unix time), the DAQ holds a
    feed this run did not set (`held_by_device`), or the DAQ's last STATUS still shows the hold (a
    release written but not yet confirmed)."""
    if not isinstance(status, dict):
        return None
    detail = status.get("interlock_detail") if isinstance(status.get("interlock_detail"), dict) else {}
    state = status.get("interlock")
    since = detail.get("since")
    since = float(since) if isinstance(since, (int, float)) and not isinstance(since, bool) else None
    if state == "feed_hold":
        reason = detail.get("reason")
        return (reason if isinstance(reason, str) and reason else "latched"), since
    if state == "held_by_device":
        return ("by the DAQ, not set by this run" + (" (its watchdog tripped)" if detail.get("watchdog_tripped")
                                                      else "")), since
    if detail.get("daq_feed_hold") is True:
        return "release not yet confirmed by the DAQ", since
    return None


def held_text(reason: str, since: float | None) -> str:
    """"feed held: <reason>, since HH:MM:SS" (local time), as every display says it."""
    when = f", since {time.strftime('%H:%M:%S', time.localtime(since))}" if since is not None else ""
    return f"feed held: {reason}{when}"


def summary_line(estimate: dict[str, Any] | None, alarm_state: str, status: dict[str, Any]) -> str:
    """The live line: state, interlock and alarm first (and while held, why and since when), then rpm,
    torque, force, depths.

    Fixed widths, so that a line refreshed in place does not jitter; what matters for
    safety comes first, because a terminal narrower than the line cuts its end.
    """
    e = estimate or {}
    hold = hold_of(status)
    return (
        f"{status.get('state', '?'):<8} interlock {status.get('interlock', '?'):<9}  alarm {alarm_state:<8}  "
        + (held_text(*hold) + "  " if hold is not None else "")
        + f"rev {e.get('rev', '–')!s:>6}  "
        f"{_fmt(e.get('spindle_rpm'), '5.0f')} rpm  "
        f"T {_fmt(e.get('torque_nm'), '6.2f')} N·m  "
        f"F {_fmt(e.get('force_n'), '6.0f')} N  "
        f"ae {_fmt(e.get('radial_depth_mm'), '5.2f')} ap {_fmt(e.get('axial_depth_mm'), '5.2f')} mm"
        + ("  (speeding up)" if e.get("accelerating") else "")
    )


def status_line(status: dict[str, Any]) -> str:
    """One-line health for sd_notify STATUS= and the debug stats line."""
    lat = status.get("latency_ms") or {}
    return (
        f"{status.get('state')}; DAQ {status.get('daq_link')}; {status.get('samples_received')} samples, "
        f"{status.get('lost_samples')} lost, {status.get('bad_frames')} bad frames; "
        f"{status.get('revolutions')} revs, p99 {_fmt(lat.get('p99'), '.2f')} ms; "
        f"alarm {status.get('alarm')}; interlock {status.get('interlock')}"
        + _afc_part(status.get("afc"))
        + _zenoh_part(status.get("sink"))
    )


def _afc_part(afc: dict[str, Any] | None) -> str:
    """Only while adaptive feed control is on: its state and the override it commands (issue 15)."""
    if not isinstance(afc, dict) or not afc.get("enabled"):
        return ""
    return f"; AFC {afc.get('state')} override {_fmt(afc.get('override_pct'), '.0f')} %"


def _zenoh_part(sink: dict[str, Any] | None) -> str:
    if not sink or sink.get("zenoh_routers") is None:
        return ""
    return f"; Zenoh {sink['zenoh_routers']} routers, {sink.get('zenoh_peers')} peers"
