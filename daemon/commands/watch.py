"""`millsense watch`: a Zenoh subscriber showing live estimates, alarms, process summaries, status and presence.

On a terminal: one refreshing line per machine, with the process in the
spindle (program, tool, operation, revolutions since entry, the learned band),
the last finished process (verdict, energy, the tool's wear) and the alarm
(envelope and wear alarms with their process; a clear with the level it ends), and while the
feed is held, "feed held: <reason>, since <time>" first, until the daemon's status says the DAQ
released it. Piped, or with `--json`: one
JSON object per line, `{"key", "kind", "payload"}`, kind being estimate, alarm,
process, status, alive or gone, so that scripts and tests can read it.

Zenoh callbacks only put samples on a queue; the main thread prints, so lines
never interleave and Ctrl-C / SIGTERM / `--seconds` end it cleanly.
"""

from __future__ import annotations

import argparse
import json
import math
import queue
import sys
import threading
import time
from typing import Any

from millsense.daemon.publish.cli_args import (
    EXIT_USAGE,
    add_config_argument,
    add_zenoh_arguments,
    check_machine,
    client_settings,
    hint,
    strip_rust,
)
from millsense.daemon.status_text import TRIP_LEVELS, held_text, hold_of
from millsense.daemon.stop_signals import stop_on_signals

KINDS = ("estimate", "alarm", "process", "status")
PROG = "millsense watch"
# With nothing seen this long (or by the end of --seconds, if sooner), say once on stderr what to try.
HINT_AFTER_S = 5.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--machine", "-m", metavar="ID", default=None, help="only this machine (default: all)")
    add_config_argument(parser, "where to connect")
    add_zenoh_arguments(parser)
    parser.add_argument("--json", action="store_true", help="JSON lines even on a terminal")
    parser.add_argument("--seconds", type=float, default=None, metavar="N", help="stop after N seconds")


def run(args: argparse.Namespace) -> int:
    from millsense.daemon.publish.session import ZenohConfigError, ZenohUnavailable, open_session

    if check_machine(args.machine, PROG):
        return EXIT_USAGE
    if args.seconds is not None and not (args.seconds > 0 and math.isfinite(args.seconds)):
        print(f"{PROG}: error: --seconds must be a positive number", file=sys.stderr)
        return EXIT_USAGE
    connection = client_settings(args, PROG)
    if isinstance(connection, int):
        return connection
    daemon, settings = connection

    stop = threading.Event()
    stop_on_signals(stop)
    try:
        session = open_session(
            settings,
            retry_for_s=None if args.seconds is None else args.seconds,
            stop=stop,
            on_waiting=lambda event, f: print(
                f"{PROG}: waiting for a Zenoh router at {', '.join(f['connect']) or '(scouting)'} ({f['error']})",
                file=sys.stderr,
            ),
        )
    except ZenohConfigError as exc:
        print(f"{PROG}: error: {strip_rust(str(exc))}", file=sys.stderr)
        return 1
    except ZenohUnavailable as exc:
        print(f"{PROG}: error: {strip_rust(str(exc))}\n{hint(settings, daemon)}", file=sys.stderr)
        return 1

    inbox: queue.SimpleQueue[tuple[str, str, Any]] = queue.SimpleQueue()
    machine = args.machine or "*"
    as_json = args.json or not sys.stdout.isatty()
    entities = []
    try:
        for kind in KINDS:
            entities.append(session.declare_subscriber(f"millsense/{machine}/{kind}", _on_sample(inbox, kind)))
        entities.append(
            session.liveliness().declare_subscriber(f"millsense/{machine}/alive", _on_alive(inbox), history=True)
        )
        view = _JsonView() if as_json else _TtyView()
        started = time.monotonic()
        deadline = None if args.seconds is None else started + args.seconds
        hint_at = started + (HINT_AFTER_S if args.seconds is None else min(HINT_AFTER_S, args.seconds))
        heard = hinted = False
        try:
            while not stop.is_set():
                now = time.monotonic()
                if not (heard or hinted) and now >= hint_at:
                    hinted = True
                    where = f"millsense/{machine}/**"
                    print(f"{PROG}: nothing seen on {where} within {hint_at - started:g} s\n{hint(settings, daemon)}",
                          file=sys.stderr)
                wait = 0.2 if deadline is None else min(0.2, deadline - now)
                if wait <= 0:
                    break
                try:
                    key, kind, payload = inbox.get(timeout=wait if heard or hinted else max(0.01, min(wait, hint_at - now)))
                except queue.Empty:
                    view.tick()
                    continue
                heard = True
                view.show(key, kind, payload)
        except KeyboardInterrupt:
            pass
        view.done()
    finally:
        for e in entities:
            try:
                e.undeclare()
            except Exception:  # noqa: BLE001 - closing anyway
                pass
        session.close()
    return 0


def _decode(sample: Any) -> Any:
    data = sample.payload.to_bytes()
    try:
        return json.loads(data)
    except (UnicodeDecodeError, ValueError):
        return {"undecodable": data[:200].decode("utf-8", "replace")}


def _on_sample(inbox: queue.SimpleQueue, kind: str):
    def callback(sample: Any) -> None:
        inbox.put((str(sample.key_expr), kind, _decode(sample)))

    return callback


def _on_alive(inbox: queue.SimpleQueue):
    import zenoh

    def callback(sample: Any) -> None:
        key = str(sample.key_expr)
        kind = "alive" if sample.kind == zenoh.SampleKind.PUT else "gone"
        inbox.put((key, kind, {"machine": _machine_of(key)}))

    return callback


def _machine_of(key: str) -> str:
    parts = key.split("/")
    return parts[1] if len(parts) > 2 else key


class _JsonView:
    def show(self, key: str, kind: str, payload: Any) -> None:
        sys.stdout.write(json.dumps({"key": key, "kind": kind, "payload": payload}) + "\n")
        sys.stdout.flush()

    def tick(self) -> None:
        pass

    def done(self) -> None:
        pass


def _num(value: Any, fmt: str) -> str:
    return format(value, fmt) if isinstance(value, (int, float)) and not isinstance(value, bool) else "–"


class _TtyView:
    """One line per machine, redrawn in place at most 5 times a second."""

    def __init__(self) -> None:
        self.machines: dict[str, dict[str, Any]] = {}
        self.drawn = 0
        self.last_draw = 0.0
        self.dirty = False

    def show(self, key: str, kind: str, payload: Any) -> None:
        m = self.machines.setdefault(_machine_of(key), {"alive": None, "hold": None})
        if kind in ("alive", "gone"):
            m["alive"] = kind == "alive"
            self.dirty = True
            self.tick()
            return
        payload = payload if isinstance(payload, dict) else {}
        if kind == "alarm":
            payload = _with_was(m.setdefault("raised", {}), payload)
            _hold_from_alarm(m, payload)
        elif kind == "status":
            _hold_from_status(m, payload)
        m[kind] = payload
        self.dirty = True
        self.tick()

    def tick(self) -> None:
        now = time.monotonic()
        if self.dirty and now - self.last_draw >= 0.2:
            self._draw()
            self.last_draw = now
            self.dirty = False

    def done(self) -> None:
        if self.dirty:
            self._draw()
        sys.stdout.write("\n" if self.drawn else "no millsense publications seen\n")
        sys.stdout.flush()

    def _draw(self) -> None:
        out = []
        if self.drawn:
            out.append(f"\x1b[{self.drawn}F")  # back to the first line drawn last time
        for name in sorted(self.machines):
            out.append("\x1b[2K" + self._line(name, self.machines[name]) + "\n")
        self.drawn = len(self.machines)
        sys.stdout.write("".join(out))
        sys.stdout.flush()

    @staticmethod
    def _line(name: str, m: dict[str, Any]) -> str:
        e = m.get("estimate", {})
        a = m.get("alarm", {})
        s = m.get("status", {})
        presence = {True: "alive", False: "GONE", None: "?"}[m["alive"]]
        level = a.get("level", "none")
        alarm = f"{level} {a.get('quantity', '')} {_num(a.get('value'), '.1f')}".strip() if level not in ("none", "clear") else level
        if level == "clear" and a.get("quantity"):  # a clear reads as one: what it ends, never "value > limit"
            alarm += f" {a['quantity']}" + (f" (was {a['was']})" if a.get("was") else "")
        if level in ("envelope_high", "envelope_low", "expected_high", "expected_low", "wear"):
            alarm += f" {_process_key(a)}" + (f" rev {a['process_rev']}" if a.get("process_rev") is not None else "")
        if a.get("interlock"):
            alarm += f" [{a['interlock']}]"
        hold = m.get("hold")
        return (
            f"{name:<12} {presence:<5} " + (held_text(hold[0], hold[1]) + "  " if hold else "")
            + f"{_num(e.get('spindle_rpm'), '6.0f')} rpm  "
            f"T {_num(e.get('torque_nm'), '6.2f')}±{_num(e.get('torque_sigma_nm'), '.2f')} N·m"
            + _band(e) + "  "
            f"F {_num(e.get('force_n'), '7.1f')} N  "
            f"ae {_num(e.get('radial_depth_mm'), '.2f')} ap {_num(e.get('axial_depth_mm'), '.2f')} mm "
            f"({e.get('depth_status', '–')})" + _override(e) + _context(e) + _last_process(m.get("process", {}))
            + f"  alarm: {alarm}  status: {s.get('state', '–')}"
            + ("  [spindle speeding up: torque holds the inertia]" if e.get("accelerating") else "")
        )


def _with_was(raised: dict[str, str], alarm: dict[str, Any]) -> dict[str, Any]:
    """A clear, with the level it ends (`was`: the last level raised on its quantity, kept in `raised`)."""
    quantity = str(alarm.get("quantity"))
    if alarm.get("level") == "clear":
        return {**alarm, "was": raised[quantity]} if quantity in raised else alarm
    if isinstance(alarm.get("level"), str):
        raised[quantity] = alarm["level"]
    return alarm


def _hold_from_alarm(m: dict[str, Any], alarm: dict[str, Any]) -> None:
    """An alarm sent while the daemon holds the feed says so at once, before the next status does."""
    if alarm.get("interlock") != "feed_hold" or m.get("hold"):
        return
    t = alarm.get("t") if isinstance(alarm.get("t"), (int, float)) else None
    if alarm.get("level") not in TRIP_LEVELS:
        reason = "latched"  # a warning or a clear sent while held: held, not why
    else:  # the runner's reason for a trip (runner._trip_reason)
        side = "<" if alarm.get("level") == "envelope_low" else ">"
        reason = f"{alarm.get('level')} {alarm.get('quantity')} {alarm.get('value')} {side} {alarm.get('limit')}"
    m["hold"] = (reason, t)
    m["hold_from_alarm_t"] = t


def _hold_from_status(m: dict[str, Any], status: dict[str, Any]) -> None:
    """The status decides while held and when released; one older than the alarm that showed a hold does not
    release it (statuses and alarms travel at different priorities)."""
    hold = hold_of(status)
    t, alarm_t = status.get("t"), m.get("hold_from_alarm_t")
    if hold is None and m.get("hold") and isinstance(alarm_t, (int, float)) \
            and isinstance(t, (int, float)) and t < alarm_t + 1.0:
        return  # an alarm's t is its sample's: a status built within 1 s of it may predate the trip's decision
    m["hold"], m["hold_from_alarm_t"] = hold, None


def _process_key(p: dict[str, Any]) -> str:
    """program/tool/operation of a payload, "–" where unknown."""
    if isinstance(p.get("key"), str):
        return p["key"]
    parts = [p.get("program"), p.get("tool"), p.get("operation")]
    return "–" if all(v is None for v in parts) else "/".join("–" if v is None else str(v) for v in parts)


def _override(e: dict[str, Any]) -> str:
    """The feed override the CNC applied over the revolution, and the AFC's state and command when it is on."""
    applied = e.get("feed_override_pct")
    afc = e.get("afc") if isinstance(e.get("afc"), dict) else {}
    state = afc.get("state")
    if applied is None and state is None:
        return ""  # a daemon before issue 15: nothing to say
    out = f"  ovr {_num(applied, '.0f')} %"
    if state not in (None, "off", "unavailable"):
        target = f" → {_num(afc.get('target'), '.4g')}" if afc.get("target") is not None else ""
        out += f" AFC {state} cmd {_num(afc.get('override_pct'), '.0f')} %{target}"
    return out


def _context(e: dict[str, Any]) -> str:
    """The process in the spindle: P<program> T<tool> op<operation>, and revolutions since entry."""
    if all(e.get(k) is None for k in ("program", "tool", "operation")):
        return ""
    rev = f" r{e['process_rev']}" if e.get("process_rev") is not None else ""
    return f"  P{e.get('program', '–')} T{e.get('tool', '–')} op{e.get('operation', '–')}{rev}"


def _band(e: dict[str, Any]) -> str:
    """The learned envelope around this revolution's torque, where one is active."""
    low, high = e.get("envelope_low_nm"), e.get("envelope_high_nm")
    if low is None and high is None:
        return ""
    return f" [{_num(low, '.2f')}..{_num(high, '.2f')}]"


def _last_process(p: dict[str, Any]) -> str:
    """The last finished process: its key, verdict, cutting energy and the tool's wear and life."""
    if not p:
        return ""
    out = f"  last {_process_key(p)}: {p.get('verdict', '–')} {_num(p.get('energy_j'), '.0f')} J"
    if p.get("envelope") == "learning" and p.get("learned") is not None:
        out += f" (learning {p['learned']}/{p.get('learn_target', '–')})"
    if p.get("tool_wear_pct") is not None:
        out += f" wear {_num(p['tool_wear_pct'], '+.1f')} %"
    if p.get("tool_processes") is not None:
        out += f" life {p['tool_processes']}"
    return out
