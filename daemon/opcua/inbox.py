"""The Zenoh side of `millsense opcua`: subscribers in, one bounded inbox out.

Zenoh calls back on its own threads; the OPC UA server runs on an asyncio loop. The callbacks
only decode and put into `Inbox`, which the loop drains. Memory is bounded per machine whatever
the publishers do: the newest estimate and status of a machine replace the older ones (an OPC UA
variable shows one value; a client that samples it at 10 Hz needs no queue behind it), while
alarm changes, process summaries and presence changes, which are events, wait in one deque of
`MAX_EVENTS`, oldest dropped and counted when it is full.
"""

from __future__ import annotations

import json
import threading
from collections import deque
from collections.abc import Callable
from typing import Any

KINDS = ("estimate", "alarm", "status", "process")
COALESCED = ("estimate", "status")  # latest wins
MAX_EVENTS = 1024
MAX_PAYLOAD_BYTES = 65536  # an estimate is about 1 KB, a status a few KB: more is not a daemon's


class Inbox:
    """Thread-safe hand-over from Zenoh's threads to the asyncio loop (`wake` is called on each put)."""

    def __init__(self, wake: Callable[[], None] = lambda: None) -> None:
        self._lock = threading.Lock()
        self._latest: dict[tuple[str, str], dict[str, Any]] = {}
        self._events: deque[tuple[str, str, dict[str, Any]]] = deque(maxlen=MAX_EVENTS)
        self._wake = wake
        self.dropped = 0
        self.refused = 0

    def put(self, machine: str, kind: str, payload: dict[str, Any]) -> None:
        with self._lock:
            if kind in COALESCED:
                self._latest[(machine, kind)] = payload
            else:
                if len(self._events) == self._events.maxlen:
                    self.dropped += 1
                self._events.append((machine, kind, payload))
        self._wake()

    def take(self) -> list[tuple[str, str, dict[str, Any]]]:
        """Everything waiting: events first, in order, then the latest estimate and status of each machine.

        Events first so that an `alive` precedes the first values of a machine that just appeared.
        """
        with self._lock:
            out = list(self._events)
            self._events.clear()
            out += [(m, k, p) for (m, k), p in self._latest.items()]
            self._latest.clear()
        return out


def machine_of(key: str) -> str | None:
    parts = key.split("/")
    return parts[1] if len(parts) == 3 and parts[0] == "millsense" else None


def subscribe(session: Any, inbox: Inbox, machine: str = "*") -> list[Any]:
    """Declare the subscribers into `inbox`; the caller undeclares the returned entities."""
    import zenoh

    def on_sample(kind: str) -> Callable[[Any], None]:
        def callback(sample: Any) -> None:
            name = machine_of(str(sample.key_expr))
            data = sample.payload.to_bytes()
            if name is None or len(data) > MAX_PAYLOAD_BYTES:
                inbox.refused += 1
                return
            try:
                payload = json.loads(data)
            except (UnicodeDecodeError, ValueError):
                payload = None
            if not isinstance(payload, dict):
                inbox.refused += 1
                return
            inbox.put(name, kind, payload)

        return callback

    def on_alive(sample: Any) -> None:
        name = machine_of(str(sample.key_expr))
        if name is not None:
            inbox.put(name, "alive" if sample.kind == zenoh.SampleKind.PUT else "gone", {})

    entities = [session.declare_subscriber(f"millsense/{machine}/{kind}", on_sample(kind)) for kind in KINDS]
    entities.append(session.liveliness().declare_subscriber(f"millsense/{machine}/alive", on_alive, history=True))
    return entities
