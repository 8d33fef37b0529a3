"""What the dashboard has seen, bounded, and the queues of the pages that watch it.

Memory is bounded twice: per machine (`ESTIMATES_PER_MACHINE` estimates, about
a minute at 10 revolutions a second, and `ALARMS_PER_MACHINE` alarms) and in
the number of machines (`MAX_MACHINES`; a further name is counted and
ignored, so a flood of invented machine names cannot grow the process). Each
open page has a queue of `CLIENT_QUEUE` updates; a page that does not keep up
loses its oldest updates (counted), never blocks a Zenoh callback. Pages are
bounded in all (`MAX_CLIENTS`) and per peer address (`MAX_CLIENTS_PER_PEER`), so
one screen that reconnects without closing its old streams cannot shut out the rest.

Estimates are cut down to the fields the page draws before they are kept, so a
kept revolution is a few hundred bytes whatever the daemon publishes.
"""

from __future__ import annotations

import collections
import threading
import time
from typing import Any

from millsense.daemon.publish.alarm_state import ShownAlarms, catch_up, caught_up

ESTIMATES_PER_MACHINE = 600
ALARMS_PER_MACHINE = 50
RECENT_ALARMS = 100
MAX_MACHINES = 256
CLIENT_QUEUE = 2000
MAX_CLIENTS = 32
MAX_CLIENTS_PER_PEER = 8

# The estimate fields the page shows; anything else a daemon adds is not kept.
ESTIMATE_FIELDS = (
    "rev", "t", "valid", "invalid", "spindle_rpm", "torque_nm", "force_n", "radial_depth_mm", "axial_depth_mm",
    "depth_status", "cutting", "program", "tool", "operation", "process_rev", "envelope_low_nm",
    "envelope_high_nm", "feed_override_pct", "afc",
)
STATUS_FIELDS = ("t", "state", "daq_link", "interlock", "interlock_detail", "alarm", "faults", "uptime_s", "version",
                 "afc", "revolutions", "learned_limits")
PROCESS_FIELDS = ("t", "process", "key", "program", "tool", "operation", "verdict", "envelope", "energy_ratio",
                  "tool_processes", "tool_wear_pct", "torque_peak_nm")


def _pick(payload: dict, fields: tuple[str, ...]) -> dict:
    return {k: payload[k] for k in fields if k in payload}


class Machine:
    """One machine's rings and latest words."""

    def __init__(self, name: str):
        self.name = name
        self.alive = False
        self.alive_since: float | None = None
        self.gone_since: float | None = None
        self.estimates: collections.deque[dict] = collections.deque(maxlen=ESTIMATES_PER_MACHINE)
        self.alarms: collections.deque[dict] = collections.deque(maxlen=ALARMS_PER_MACHINE)
        self.status: dict | None = None
        self.process: dict | None = None
        self.shown = ShownAlarms()   # the alarm changes listed, to catch up from `status` (alarm_state.py)

    def snapshot(self) -> dict[str, Any]:
        return {"machine": self.name, "alive": self.alive, "gone_since": self.gone_since,
                "estimates": list(self.estimates), "alarms": list(self.alarms), "status": self.status,
                "process": self.process}


class TooManyPages(Exception):
    """A page refused: the reason names the bound reached."""


class Client:
    """One open page: a bounded queue of updates and a count of those it lost."""

    def __init__(self, peer: str = "") -> None:
        self.peer = peer
        self.queue: collections.deque[dict] = collections.deque(maxlen=CLIENT_QUEUE)
        self.ready = threading.Condition()
        self.dropped = 0
        self.closed = False

    def put(self, update: dict) -> None:
        with self.ready:
            if len(self.queue) == self.queue.maxlen:
                self.dropped += 1  # the deque drops the oldest
            self.queue.append(update)
            self.ready.notify()

    def take(self, timeout_s: float) -> list[dict]:
        """Every waiting update, after waiting up to `timeout_s` for the first."""
        with self.ready:
            if not self.queue and not self.closed:
                self.ready.wait(timeout_s)
            out = list(self.queue)
            self.queue.clear()
            return out

    def close(self) -> None:
        with self.ready:
            self.closed = True
            self.ready.notify()


class Book:
    """Every machine seen, and the pages to tell. Thread-safe: Zenoh callbacks write, HTTP threads read."""

    def __init__(self, clock=time.time):
        self._clock = clock
        self._lock = threading.Lock()
        self.machines: dict[str, Machine] = {}
        self.recent_alarms: collections.deque[dict] = collections.deque(maxlen=RECENT_ALARMS)
        self.clients: list[Client] = []
        self.ignored_machines = 0

    # -- writers (Zenoh callbacks) -----------------------------------------------------
    def _machine(self, name: str) -> Machine | None:
        m = self.machines.get(name)
        if m is None:
            if len(self.machines) >= MAX_MACHINES:
                self.ignored_machines += 1
                return None
            m = self.machines[name] = Machine(name)
        return m

    def alive(self, name: str, present: bool) -> None:
        with self._lock:
            m = self._machine(name)
            if m is None:
                return
            m.alive = present
            now = self._clock()
            if present:
                m.alive_since, m.gone_since = now, None
            else:
                m.gone_since = now
            update = {"kind": "alive" if present else "gone", "machine": name, "t": now}
        self._tell(update)

    def publication(self, name: str, kind: str, payload: dict) -> None:
        updates: list[dict] = []
        with self._lock:
            m = self._machine(name)
            if m is None:
                return
            if kind == "estimate":
                payload = _pick(payload, ESTIMATE_FIELDS)
                m.estimates.append(payload)
            elif kind == "alarm":
                if not m.shown.is_new(payload):
                    return  # a status already brought it
                payload = self._list_alarm(m, payload)
            elif kind == "status":
                # alarms raised or cleared while this dashboard was not connected to the daemon
                updates = [{"kind": "alarm", "machine": name, "payload": self._list_alarm(m, a)}
                           for a in catch_up(m.shown, payload)]
                caught_up(m.shown, payload)
                payload = m.status = _pick(payload, STATUS_FIELDS)
            elif kind == "process":
                payload = m.process = _pick(payload, PROCESS_FIELDS)
            else:
                return
        for update in [*updates, {"kind": kind, "machine": name, "payload": payload}]:
            self._tell(update)

    def _list_alarm(self, m: Machine, payload: dict) -> dict:
        """Keep an alarm change in the machine's list and the recent ones (the lock held).

        A clear gets `was`, the level it ends (the one shown active for its quantity), so the page
        can say "clear force_n (was overload, limit 550.00)" rather than show its value against the limit."""
        had = m.shown.active.get(str(payload.get("quantity")))
        m.shown.shown(payload)
        payload = dict(payload, machine=m.name)
        if payload.get("level") == "clear" and had is not None and isinstance(had.get("level"), str):
            payload["was"] = had["level"]
        m.alarms.append(payload)
        self.recent_alarms.append(payload)
        return payload

    def _tell(self, update: dict) -> None:
        for c in list(self.clients):
            c.put(update)

    # -- readers (HTTP threads) --------------------------------------------------------
    def snapshot(self) -> dict[str, Any]:
        with self._lock:
            return {"machines": [m.snapshot() for m in self.machines.values()],
                    "recent_alarms": list(self.recent_alarms)}

    def subscribe(self, peer: str = "") -> Client:
        """A queue for a new page from `peer` (its address); TooManyPages past either bound."""
        with self._lock:
            if len(self.clients) >= MAX_CLIENTS:
                raise TooManyPages(f"too many pages open ({MAX_CLIENTS} open on this dashboard)")
            if sum(c.peer == peer for c in self.clients) >= MAX_CLIENTS_PER_PEER:
                raise TooManyPages(f"too many pages open from {peer} ({MAX_CLIENTS_PER_PEER} per address)")
            client = Client(peer)
            self.clients.append(client)
            return client

    def unsubscribe(self, client: Client) -> None:
        client.close()
        with self._lock:
            if client in self.clients:
                self.clients.remove(client)
