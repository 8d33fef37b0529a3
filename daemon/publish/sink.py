"""ZenohSink: the pipeline's `Sink` on Zenoh, plus the queryables and the presence token.

Publishing never blocks the estimator. `estimate()` and `status()` append to a
bounded deque (the oldest entry goes when it is full, and is counted) and wake
one publisher thread; `alarm()` goes to its own queue, which the thread always
empties first, and is never dropped (alarms are rare: one per state change).
Serialisation to JSON happens on the publisher thread too.

Keys (interfaces.md), prefix `millsense/<machine>`:

| key | QoS |
| --- | --- |
| `estimate` | publisher, CongestionControl.DROP, Priority.DATA, batched |
| `alarm` | publisher, CongestionControl.BLOCK, Priority.REAL_TIME, express |
| `status` | publisher (DROP) and queryable |
| `config` | queryable: `controls.config()` |
| `cmd/reset`, `cmd/test-trip` | queryables: the challenge–response of command_auth.py, then `controls.reset(requester=...)` / `controls.test_trip(requester=...)` |
| `alive` | liveliness token |

The queryables take bounded ring channels, each served by its own worker thread
(daemon/publish/queryables.py), so a query flood is dropped inside Zenoh and
never starves the heartbeat. Whatever a query carries and whatever `controls`
raises, the answer is a JSON reply, never an exception escaping into Zenoh.
The command policy and token come from `controls.settings.interlock` (the
Runner's), unless `command_policy` / `command_token` are given.
"""

from __future__ import annotations

import collections
import threading
import time
from typing import Any, Protocol

import zenoh

from millsense.daemon.audit import AuditLog
from millsense.daemon.publish.command_auth import CommandGate, policy_and_token
from millsense.daemon.publish.payload import dumps
from millsense.daemon.publish.queryables import QueryServer
from millsense.drivers.base import name_os_thread


class Controls(Protocol):
    """What the queryables ask of the running daemon (docs/architecture.md)."""

    def status(self) -> dict: ...
    def config(self) -> dict: ...
    def reset(self, requester: str = "") -> dict: ...
    # optional: test_trip(requester="") -> dict (then `cmd/test-trip` is declared);
    # `settings.interlock` (reset policy and token); `audit` (an AuditLog)


def _no_args(name: str, method: Any) -> Any:
    def run(args: dict, requester: str) -> dict:
        if args:
            raise ValueError(f"{name} takes no args (got {', '.join(sorted(args))})")
        return method(requester=requester)

    return run


def key_prefix(machine: str) -> str:
    return f"millsense/{machine}"


_ESTIMATE, _STATUS = 0, 1


class ZenohSink:
    """Publishes estimates, alarms and status; answers status/config/cmd queries.

    `session`: an open `zenoh.Session` (the caller owns it and closes it after
    `close()`). `controls`: a `Controls` or None (then `config` and `cmd/reset`
    reply with an error and `status` with the latest published status).
    `queue_size`: how many estimates/status may wait before the oldest is dropped.
    `expects_router`: the session is a client, so having no router is worth a warning.
    """

    def __init__(
        self,
        session: zenoh.Session,
        machine: str,
        controls: Controls | None = None,
        *,
        queue_size: int = 1024,
        close_timeout_s: float = 2.0,
        log: Any = None,
        expects_router: bool = False,
        command_policy: str | None = None,
        command_token: str | None = None,
    ) -> None:
        if queue_size < 1:
            raise ValueError("queue_size must be >= 1")
        self.machine = machine
        self.prefix = key_prefix(machine)
        self._session = session
        self._controls = controls
        self._close_timeout_s = close_timeout_s
        self._log = log

        self._queue: collections.deque[tuple[int, dict]] = collections.deque()
        self._queue_size = queue_size
        self._alarms: collections.deque[dict] = collections.deque()
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._closing = False
        self._closed = False
        self._latest_status: dict | None = None
        self._expects_router = expects_router
        self._had_router: bool | None = None

        self._published = 0
        self._alarms_published = 0
        self._dropped = 0
        self._errors = 0
        self._queries: QueryServer | None = None
        if controls is None:
            self.gate: CommandGate | None = None
        else:
            policy, token = (command_policy, command_token or "") if command_policy else policy_and_token(controls)
            audit = getattr(controls, "audit", None) or AuditLog(None, machine)
            self.gate = CommandGate(machine, policy, token, audit)

        encoding = zenoh.Encoding.APPLICATION_JSON
        self._declared: list[Any] = []
        try:
            self._pub_estimate = self._keep(
                session.declare_publisher(
                    f"{self.prefix}/estimate",
                    encoding=encoding,
                    congestion_control=zenoh.CongestionControl.DROP,
                    priority=zenoh.Priority.DATA,
                    express=False,
                )
            )
            self._pub_alarm = self._keep(
                session.declare_publisher(
                    f"{self.prefix}/alarm",
                    encoding=encoding,
                    congestion_control=zenoh.CongestionControl.BLOCK,
                    priority=zenoh.Priority.REAL_TIME,
                    express=True,
                )
            )
            self._pub_status = self._keep(
                session.declare_publisher(
                    f"{self.prefix}/status",
                    encoding=encoding,
                    congestion_control=zenoh.CongestionControl.DROP,
                    priority=zenoh.Priority.DATA,
                    express=False,
                )
            )
            self._queries = QueryServer(session, self.prefix, status=self._status_answer, config=self._config_answer,
                                        commands=self._commands(controls), gate=self.gate, log=log,
                                        cache_status=controls is not None)
            self._token = self._keep(session.liveliness().declare_token(f"{self.prefix}/alive"))
        except BaseException:
            if self._queries is not None:
                self._queries.close()
            self._undeclare_all()
            raise

        self._thread = threading.Thread(target=self._run, name=f"zenoh-sink-{machine}", daemon=True)
        self._thread.start()

    def _keep(self, entity: Any) -> Any:
        self._declared.append(entity)
        return entity

    # ---- Sink protocol: every method returns at once -------------------------------

    def estimate(self, payload: dict) -> None:
        self._enqueue(_ESTIMATE, payload)

    def status(self, payload: dict) -> None:
        """Published, and kept as the answer to status queries when there are no controls."""
        self._latest_status = dict(payload)
        self._enqueue(_STATUS, payload)

    def alarm(self, payload: dict) -> None:
        """Never dropped: its own queue, published before any waiting estimate."""
        if self._closed:
            with self._lock:
                self._dropped += 1
            return
        self._alarms.append(dict(payload))
        self._wake.set()

    def _enqueue(self, kind: int, payload: dict) -> None:
        item = (kind, dict(payload))  # a shallow copy: the caller may reuse its dict
        with self._lock:
            if self._closing:
                self._dropped += 1
                return
            if len(self._queue) >= self._queue_size:
                self._queue.popleft()
                self._dropped += 1
            self._queue.append(item)
        self._wake.set()

    def close(self) -> None:
        """Flush what is queued (bounded by `close_timeout_s`), then undeclare everything.

        Idempotent. The liveliness token goes last but one step: subscribers of
        `millsense/*/alive` see DELETE once this returns.
        """
        with self._lock:
            if self._closing:
                already = True
            else:
                already = False
                self._closing = True
        if already:
            self._thread.join(self._close_timeout_s)
            return
        self._wake.set()
        self._thread.join(self._close_timeout_s)
        self._closed = True
        if self._queries is not None:
            self._queries.close(self._close_timeout_s)
        self._undeclare_all()

    def __enter__(self) -> ZenohSink:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    def connections(self) -> tuple[int | None, int | None]:
        """(routers, peers) the session is connected to now; None where zenoh cannot tell.

        With `expects_router` (a client session) losing the last router and
        finding one again are logged once each (`zenoh.no_router`,
        `zenoh.router_connected`): without a router everything published goes
        nowhere. A peer's count of peers is its subscribers coming and going:
        reported in status, not logged.
        """
        try:
            info = self._session.info
            now = (len(info.routers_zid()), len(info.peers_zid()))
        except Exception:  # noqa: BLE001 - a closed session: unknown, not an error
            return (None, None)
        has_router = now[0] > 0
        if self._expects_router and has_router != self._had_router:
            first, self._had_router = self._had_router is None, has_router
            if not has_router:
                self._warn("zenoh.no_router", peers=now[1])
            elif not first:
                self._info("zenoh.router_connected", routers=now[0])
        return now

    def stats(self) -> dict[str, int | None]:
        """Counters for status payloads and the diagnostic dump."""
        routers, peers = self.connections()
        return {
            "zenoh_routers": routers,
            "zenoh_peers": peers,
            "published": self._published,
            "alarms_published": self._alarms_published,
            "dropped": self._dropped,
            "queue_depth": len(self._queue),
            "alarm_queue_depth": len(self._alarms),
            "publish_errors": self._errors,
            **(self._queries.stats() if self._queries is not None else {}),
        }

    # ---- publisher thread ----------------------------------------------------------

    def _run(self) -> None:
        name_os_thread("ms-zenoh-sink")
        queue, alarms = self._queue, self._alarms
        while True:
            if alarms:
                self._put(self._pub_alarm, alarms.popleft(), alarm=True)
                continue
            if queue:
                try:
                    kind, payload = queue.popleft()
                except IndexError:  # emptied by the producer's drop-oldest in between
                    continue
                self._put(self._pub_estimate if kind == _ESTIMATE else self._pub_status, payload)
                continue
            if self._closing:
                return
            self._wake.wait(0.5)
            self._wake.clear()
            # set() may have come between the emptiness checks and clear(): look again
            # before sleeping (the loop does, since it re-checks both queues first).

    def _put(self, publisher: Any, payload: dict, *, alarm: bool = False) -> None:
        try:
            publisher.put(dumps(payload))
        except Exception as exc:  # a payload that cannot be serialised, or a closed session
            self._errors += 1
            self._warn("zenoh.publish_failed", key=str(publisher.key_expr), error=f"{type(exc).__name__}: {exc}")
            return
        if alarm:
            self._alarms_published += 1
        else:
            self._published += 1

    # ---- what the queryables answer (called on the query worker, daemon/publish/queryables.py) ----

    def _status_answer(self) -> dict:
        if self._controls is not None:
            return self._controls.status()
        if self._latest_status is None:
            raise LookupError("no status published yet")
        return self._latest_status

    def _config_answer(self) -> dict:
        if self._controls is None:
            raise LookupError("this daemon exposes no configuration")
        return self._controls.config()

    @staticmethod
    def _commands(controls: Any) -> dict[str, Any]:
        """`cmd/<name>` -> run(args, requester), for what `controls` can do; args are refused (none is taken)."""
        if controls is None:
            return {}
        out = {}
        for name, attr in (("reset", "reset"), ("test-trip", "test_trip")):
            method = getattr(controls, attr, None)
            if callable(method):
                out[name] = _no_args(name, method)
        return out

    # ---- teardown and logging ------------------------------------------------------

    def _undeclare_all(self) -> None:
        deadline = time.monotonic() + self._close_timeout_s
        for entity in reversed(self._declared):
            if time.monotonic() > deadline:
                self._warn("zenoh.undeclare_timeout", left=len(self._declared))
                break
            try:
                entity.undeclare()
            except Exception as exc:  # noqa: BLE001 - already undeclared, or session closed
                self._warn("zenoh.undeclare_failed", error=f"{type(exc).__name__}: {exc}")
        self._declared.clear()

    def _warn(self, event: str, **fields: Any) -> None:
        if self._log is not None:
            try:
                self._log.warning(event, **fields)
            except Exception:  # noqa: BLE001 - logging must not break publication
                pass

    def _info(self, event: str, **fields: Any) -> None:
        if self._log is not None:
            try:
                self._log.info(event, **fields)
            except Exception:  # noqa: BLE001
                pass
