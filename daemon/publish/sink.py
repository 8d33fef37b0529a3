"""ZenohSink: the pipeline's `Sink` on Zenoh, plus the queryables and the presence token.

Publishing never blocks the estimator. `estimate()` and `status()` append to a
bounded deque (the oldest entry goes when it is full, and is counted) and wake
one publisher thread; `alarm()` goes to its own queue, which the thread always
empties first, and is never dropped (alarms are rare: one per state change).
`process()` (one summary per finished process: rare too) has its own bounded
queue, served after the alarms and before the estimates; a summary is dropped
only when `PROCESS_QUEUE` of them wait, and counted (`process_dropped`).
Serialisation to JSON happens on the publisher thread too.

Keys (interfaces.md), prefix `millsense/<machine>`:

| key | QoS |
| --- | --- |
| `estimate` | publisher, CongestionControl.DROP, Priority.DATA, batched |
| `alarm` | publisher, CongestionControl.BLOCK, Priority.REAL_TIME, express |
| `status` | publisher (DROP) and queryable |
| `process` | publisher, CongestionControl.BLOCK, Priority.DATA_HIGH, reliable, batched |
| `limits/change` | publisher, as `process`: `limits_change()`, an operator's applied change of one key's limits (runtime/controls.py) |
| `config` | queryable: `controls.config()` |
| `limits` | queryable, reads only: `controls.limits()`, or with `{"key": K}` `controls.limits_command({"action": "show", ...})` |
| `cmd/reset`, `cmd/test-trip` | queryables: the challenge–response of command_auth.py, then `controls.reset(requester=...)` / `controls.test_trip(requester=...)` |
| `cmd/limits` | queryable, the same challenge–response, args checked (limits_args.py), then `controls.limits_command(args, requester)` |
| `cmd/afc` | queryable, the same challenge–response, args checked (`check_afc_args`), then `controls.afc_command(args, requester)` |
| `context` | subscriber (when `[context] source` is auto or zenoh): `controls.on_context_payload(obj, source)`; the runner judges who vouches for it (learning/context_auth.py: a signed put that fails its MAC, run or sequence is refused and counted here; an unsigned one labels, never lets AFC run) |
| `alive` | liveliness token |

The queryables take bounded ring channels, each served by its own worker thread
(daemon/publish/queryables.py), so a query flood is dropped inside Zenoh and
never starves the heartbeat. The `context` subscriber is bounded the same way
(a ring of `RING_CAPACITY`: under a flood the oldest contexts go, the newest is
what counts) and served by its own thread; a payload over `MAX_QUERY_BYTES` is
refused by its length, unread, and refusals are logged at most once per 10 s
with a count (`zenoh.context_refused`). Whatever a query carries and whatever
`controls` raises, the answer is a JSON reply, never an exception escaping into Zenoh.
The command policy and token come from `controls.settings.interlock` (the
OperatorControls'), unless `command_policy` / `command_token` are given.
"""

from __future__ import annotations

import collections
import threading
import time
from queue import Empty as _Empty
from queue import SimpleQueue as _SimpleQueue
from typing import Any

import zenoh

from millsense.daemon.afc.args import afc_reply, check_afc_args
from millsense.daemon.audit import AuditLog
from millsense.daemon.controls import Controls
from millsense.daemon.publish.command_auth import CommandGate, policy_and_token
from millsense.daemon.publish.limits_args import check_args
from millsense.daemon.publish.payload import MAX_QUERY_BYTES, dumps, loads_object
from millsense.daemon.publish.queryables import LOG_EVERY_S, RING_CAPACITY, QueryServer
from millsense.daemon.throttle import Throttle
from millsense.drivers.base import name_os_thread

PROCESS_QUEUE = 256  # process summaries waiting to be published; one per finished operation, so rarely > 1
CONTEXT_SOURCES = ("auto", "zenoh")  # `[context] source` values under which the daemon listens on `context`
# A CNC changes its context a few times a second at most; past this many in a tenth of a second the
# thread waits for the next tenth while its ring drops the oldest, so a flood cannot take the GIL.
CONTEXT_PER_TICK = 20


def _no_args(name: str, method: Any) -> Any:
    def run(args: dict, requester: str) -> dict:
        if args:
            raise ValueError(f"{name} takes no args (got {', '.join(sorted(args))})")
        return method(requester=requester)

    return run


def _limits_run(method: Any) -> Any:
    """`cmd/limits`: args checked before the daemon's controls see them; the result names what was asked (audited)."""

    def run(args: dict, requester: str) -> dict:
        checked = check_args(args)  # ValueError: a signed refusal, audited with its reason
        result = method(checked, requester)
        if not isinstance(result, dict):
            return result  # the gate says what is wrong with it
        return {**checked, **result}

    return run


def _afc_run(method: Any) -> Any:
    """`cmd/afc`: args checked before the daemon's controls see them (a bad one is a signed, audited refusal)."""

    def run(args: dict, requester: str) -> dict:
        checked = check_afc_args(args)
        return afc_reply(checked, method(checked, requester))

    return run


def key_prefix(machine: str) -> str:
    return f"millsense/{machine}"


class _Wake:
    """The publisher thread's wake-up, as `threading.Event` is used here (`set`, `wait`, `clear`). `set()` is one
    C call (`SimpleQueue.put`) where `Event.set` runs a lock and a Condition's notify in Python: on the estimator
    thread, cold after its sleep, 58 µs against 18, paid by every revolution before its latency is taken."""

    def __init__(self) -> None:
        self._tokens: _SimpleQueue[None] = _SimpleQueue()

    def set(self) -> None:
        self._tokens.put(None)

    def wait(self, timeout_s: float) -> None:
        try:
            self._tokens.get(timeout=timeout_s)
        except _Empty:
            pass

    def clear(self) -> None:
        while True:
            try:
                self._tokens.get_nowait()
            except _Empty:
                return


def machine_alive(session: Any, machine: str, window_s: float = 0.3) -> bool:
    """Is a daemon already alive as `machine` on this Zenoh network (its `alive` token)? Asked before this
    daemon declares its own: two daemons under one name (a copied configuration) interleave their estimates on
    one key, answer each other's challenges (a network reset fails) and merge their status. A session that has
    just opened may still be learning its peers' tokens: asked again for `window_s`."""
    deadline = time.monotonic() + window_s
    while True:
        for reply in session.liveliness().get(f"{key_prefix(machine)}/alive", timeout=0.1):
            if reply.ok is not None:
                return True
        if time.monotonic() >= deadline:
            return False
        time.sleep(0.05)


def other_daemons(session: Any, machine: str, timeout_s: float = 0.5) -> list[str]:
    """The Zenoh ids of the other daemons answering as `machine` now, this one left out: asked of every `status`
    queryable of the name, unconsolidated (two daemons' answers on one key would otherwise be merged into one).
    `machine_alive` asks once, before this daemon declares itself; this is asked while it runs, for networks joined
    later (a router connecting two segments, a laptop bridging them). A reply without a replier id (an older
    Zenoh) is counted as another only beyond this daemon's own one answer."""
    import zenoh

    own = str(session.info.zid())
    others, anonymous = set(), 0
    for reply in session.get(f"{key_prefix(machine)}/status", target=zenoh.QueryTarget.ALL,
                             consolidation=zenoh.ConsolidationMode.NONE, timeout=timeout_s):
        replier = getattr(getattr(reply, "replier_id", None), "zid", None)
        if replier is None:
            anonymous += 1
        elif str(replier) != own:
            others.add(str(replier))
    return sorted(others) + ["(unknown)"] * max(0, anonymous - 1)


def _context_source(sample: Any) -> str:
    """Who put a context, as far as Zenoh says: the publisher's Zenoh id when it sent one (unverified)."""
    info = getattr(sample, "source_info", None)
    source_id = getattr(info, "source_id", None) if info is not None else None
    zid = getattr(source_id, "zid", None)
    return f"zenoh zid:{zid} (self-declared)" if zid is not None else "zenoh"


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
        self._processes: collections.deque[dict] = collections.deque()
        self._limit_changes: collections.deque[dict] = collections.deque()   # an operator's: rare, never many
        self._lock = threading.Lock()
        self._wake = _Wake()
        self._closing = False
        self._closed = False
        self._latest_status: dict | None = None
        self._expects_router = expects_router
        self._had_router: bool | None = None

        self._published = 0
        self._alarms_published = 0
        self._dropped = 0
        self._errors = 0
        self._process_published = 0
        self._process_dropped = 0
        self._limit_changes_published = 0
        self._limit_changes_dropped = 0
        self._context_taken = 0
        self._context_refused = 0
        self._context_refusals = Throttle(LOG_EVERY_S)
        self._context_sub: Any = None
        self._context_thread: threading.Thread | None = None
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
            self._pub_process = self._keep(
                session.declare_publisher(
                    f"{self.prefix}/process",
                    encoding=encoding,
                    # Rare and wanted by historians: wait for the network rather than lose one.
                    congestion_control=zenoh.CongestionControl.BLOCK,
                    priority=zenoh.Priority.DATA_HIGH,
                    reliability=zenoh.Reliability.RELIABLE,
                    express=False,
                )
            )
            self._pub_limit_change = self._keep(
                session.declare_publisher(
                    f"{self.prefix}/limits/change",
                    encoding=encoding,
                    congestion_control=zenoh.CongestionControl.BLOCK,   # rare, and the plant's record of who
                    priority=zenoh.Priority.DATA_HIGH,
                    reliability=zenoh.Reliability.RELIABLE,
                    express=False,
                )
            )
            has_limits = callable(getattr(controls, "limits", None)) and callable(
                getattr(controls, "limits_command", None))
            self._queries = QueryServer(session, self.prefix, status=self._status_answer, config=self._config_answer,
                                        commands=self._commands(controls), gate=self.gate, log=log,
                                        cache_status=controls is not None,
                                        limits=self._limits_answer if has_limits else None,
                                        status_version=getattr(controls, "status_version", None))
            self._declare_context(controls)
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

    def process(self, payload: dict) -> None:
        """One finished process's summary: its own queue, after alarms, before estimates; drops counted."""
        with self._lock:
            if self._closing:
                self._process_dropped += 1
                return
            if len(self._processes) >= PROCESS_QUEUE:
                self._processes.popleft()
                self._process_dropped += 1
            self._processes.append(dict(payload))
        self._wake.set()

    def limits_change(self, payload: dict) -> None:
        """An operator's applied change of one key's limits (`limits/change`): queued like a process summary."""
        with self._lock:
            if self._closing:
                self._limit_changes_dropped += 1
                return
            if len(self._limit_changes) >= PROCESS_QUEUE:
                self._limit_changes.popleft()
                self._limit_changes_dropped += 1
            self._limit_changes.append(dict(payload))
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
        self._undeclare_all()  # the context subscriber's ring closes: its thread ends
        if self._context_thread is not None:
            self._context_thread.join(self._close_timeout_s)
        with self._lock:
            self._log_context_refused(self._context_refusals.pending())

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
            "process_published": self._process_published,
            "process_dropped": self._process_dropped,
            "limit_changes_published": self._limit_changes_published,
            "limit_changes_dropped": self._limit_changes_dropped,
            "context_taken": self._context_taken,
            "context_refused": self._context_refused,
            **(self._queries.stats() if self._queries is not None else {}),
        }

    # ---- publisher thread ----------------------------------------------------------

    def _run(self) -> None:
        name_os_thread("ms-zenoh-sink")
        queue, alarms, processes, changes = self._queue, self._alarms, self._processes, self._limit_changes
        while True:
            if alarms:
                self._put(self._pub_alarm, alarms.popleft(), alarm=True)
                continue
            if changes:
                with self._lock:
                    payload = changes.popleft() if changes else None
                if payload is not None and self._put(self._pub_limit_change, payload):
                    self._limit_changes_published += 1
                continue
            if processes:
                with self._lock:
                    payload = processes.popleft() if processes else None
                if payload is not None and self._put(self._pub_process, payload):
                    self._process_published += 1
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

    def _put(self, publisher: Any, payload: dict, *, alarm: bool = False) -> bool:
        try:
            publisher.put(dumps(payload))
        except Exception as exc:  # a payload that cannot be serialised, or a closed session
            self._errors += 1
            self._warn("zenoh.publish_failed", key=str(publisher.key_expr), error=f"{type(exc).__name__}: {exc}")
            return False
        if alarm:
            self._alarms_published += 1
        else:
            self._published += 1
        return True

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

    def _limits_answer(self, key: str | None) -> dict:
        """Every key's summary, or one key's detail: reads, so no token and no audit line."""
        if key is None:
            return self._controls.limits()
        result = self._controls.limits_command({"action": "show", "key": key}, "limits query (read)")
        if isinstance(result, dict) and result.get("ok") is False:
            raise LookupError(str(result.get("error") or f"no limits for {key}"))
        return result

    # ---- the context subscriber (its own thread, daemon/publish/queryables.py's pattern) ----------

    def _declare_context(self, controls: Any) -> None:
        handler = getattr(controls, "on_context_payload", None)
        source = getattr(getattr(getattr(controls, "settings", None), "context", None), "source", "auto")
        if not callable(handler) or source not in CONTEXT_SOURCES:
            return  # "daq" or "off": nobody may tell this daemon its context over the network
        self._context_sub = self._keep(
            self._session.declare_subscriber(f"{self.prefix}/context", zenoh.handlers.RingChannel(RING_CAPACITY)))
        self._context_thread = threading.Thread(target=self._context_loop, args=(self._context_sub, handler),
                                                name=f"zenoh-context-{self.machine}", daemon=True)
        self._context_thread.start()

    def _context_loop(self, subscriber: Any, handler: Any) -> None:
        name_os_thread("ms-zenoh-ctx")
        tick_end, served = time.monotonic() + 0.1, 0
        while True:
            try:
                sample = subscriber.handler.recv()  # blocks in Zenoh, GIL released
            except Exception:  # noqa: BLE001 - the ring closed: the sink is closing
                return
            now = time.monotonic()
            if now >= tick_end:
                tick_end, served = now + 0.1, 0
            elif served >= CONTEXT_PER_TICK:
                time.sleep(tick_end - now)
                tick_end, served = time.monotonic() + 0.1, 0
            served += 1
            self._take_context(sample, handler)

    def _take_context(self, sample: Any, handler: Any) -> None:
        payload = sample.payload
        if payload is not None and len(payload) > MAX_QUERY_BYTES:
            self._refuse_context(f"payload over {MAX_QUERY_BYTES} bytes: refused unread")
            return
        try:
            obj = loads_object(payload.to_bytes() if payload is not None else b"")
        except ValueError as exc:
            self._refuse_context(str(exc))
            return
        try:
            handler(obj, _context_source(sample))
        except ValueError as exc:   # the daemon's refusal of its content (or of Zenoh as the context's source)
            self._refuse_context(str(exc))
            return
        except Exception as exc:  # noqa: BLE001 - a context must never kill the sink
            self._refuse_context(f"{type(exc).__name__}: {exc}")
            return
        with self._lock:
            self._context_taken += 1

    def _refuse_context(self, reason: str) -> None:
        with self._lock:
            self._context_refused += 1
            self._log_context_refused(self._context_refusals.note(reason))

    def _log_context_refused(self, due: tuple[int, Any] | None) -> None:
        if due is not None:
            count, last = due
            self._warn("zenoh.context_refused", key=f"{self.prefix}/context", count=count, last=last,
                       every_s=LOG_EVERY_S)

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
        method = getattr(controls, "limits_command", None)
        if callable(method):
            out["limits"] = _limits_run(method)
        method = getattr(controls, "afc_command", None)
        if callable(method):
            out["afc"] = _afc_run(method)
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
