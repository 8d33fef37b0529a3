"""The daemon's queryables: bounded in Zenoh, served by one Python thread, cheap to flood.

Each queryable (`status`, `config`, `limits`, `cmd/*`) takes a Zenoh ring channel of a
few entries: when queries come faster than they are served, Zenoh drops the
oldest inside its own threads, before any Python runs or the GIL is taken
(a query flood starved the heartbeat thread through per-query Python
callbacks). Each ring has its own worker thread, blocked in Zenoh's `recv()`
with the GIL released, so an idle daemon spends nothing here and a flood on
one key never queues another key's query behind it. Together the workers stop
after `max_rate_hz` queries in a tenth of a second, which bounds the Python
time a flood can take.

Per query: the payload's length is checked before anything reads it
(`MAX_QUERY_BYTES`); `status` and `config` answers are kept as bytes for a
moment, so a burst of status queries costs one `Controls.status()`; a kept
status is served only while `status_version()` (the state, the interlock and
the faults) is what it was, so a trip shows at the next query, never a cached
`armed` after the DAQ took the hold. `limits`
reads only (no token): with no payload it answers `controls.limits()`, with
`{"key": "program/tool/operation"}` that key's detail. Refusals are
never logged one line each (finding 6): `cmd/*` refusals go to the audit log,
which writes them at most once per 10 s with a count, and other failed queries
are summed in one `zenoh.queries_refused` line per 10 s.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import zenoh

from millsense.daemon.publish.command_auth import Answer, CommandGate
from millsense.daemon.publish.payload import JSON_ENCODING, MAX_QUERY_BYTES, dumps, loads_object
from millsense.daemon.throttle import Throttle
from millsense.drivers.base import name_os_thread

RING_CAPACITY = 8
LOG_EVERY_S = 10.0
STATUS_CACHE_S = 0.2
CONFIG_CACHE_S = 2.0
LIMITS_CACHE_S = 1.0  # cleared when a command runs: the next read shows what it changed
TOO_LARGE = dumps({"ok": False, "error": f"payload over {MAX_QUERY_BYTES} bytes: refused unread"})


@dataclass
class _Entry:
    key: str
    serve: Callable[[Any, str | None], tuple[bool, bytes]]  # (query, command) -> (ok, body)
    command: str | None = None
    queryable: Any = None


class QueryServer:
    """Declares the queryables on `session` and serves each from its own thread until `close()`."""

    def __init__(self, session: zenoh.Session, prefix: str, *, status: Callable[[], dict],
                 config: Callable[[], dict], commands: dict[str, Callable[[dict, str], dict]],
                 gate: CommandGate | None, log: Any = None, capacity: int = RING_CAPACITY,
                 max_rate_hz: float = 1000.0, cache_status: bool = True,
                 limits: Callable[[str | None], dict] | None = None,
                 status_version: Callable[[], Any] | None = None):
        self._status, self._config, self._gate, self._log = status, config, gate, log
        self._status_version = status_version
        self._limits = limits
        self._commands = commands
        self._max_per_tick = max(1, int(max_rate_hz / 10))
        self._cache: dict[str, tuple[float, bytes, Any]] = {}   # name -> (until, body, version)
        self._cache_status = cache_status
        self._stop = threading.Event()
        self._lock = threading.Lock()  # counters and the refusal log line, shared by the workers
        self.queries = 0
        self.errors = 0
        self.too_large = 0
        self._busy_s = 0.0
        self._busy_max_s = 0.0
        self._refused = Throttle(LOG_EVERY_S)

        entries = [_Entry(f"{prefix}/status", self._serve_status), _Entry(f"{prefix}/config", self._serve_config)]
        if limits is not None:
            entries.append(_Entry(f"{prefix}/limits", self._serve_limits))
        for name in commands or {"reset": None}:
            entries.append(_Entry(f"{prefix}/cmd/{name}", self._serve_command, command=name))
        self._entries: list[_Entry] = []
        try:
            for e in entries:
                e.queryable = session.declare_queryable(e.key, zenoh.handlers.RingChannel(capacity))
                self._entries.append(e)
        except BaseException:
            self._undeclare()
            raise
        self._budget_lock = threading.Lock()
        self._tick_end, self._served = time.monotonic() + 0.1, 0
        self._threads = [threading.Thread(target=self._run, args=(e,), name=_thread_name(e), daemon=True)
                         for e in self._entries]
        for t in self._threads:
            t.start()

    # ---- workers ---------------------------------------------------------------------
    def _run(self, entry: _Entry) -> None:
        name_os_thread(_thread_name(entry, os_name=True))
        while not self._stop.is_set():
            try:
                query = entry.queryable.handler.recv()  # blocks in Zenoh, GIL released
            except Exception:  # noqa: BLE001 - the channel closed: we are stopping
                return
            self._wait_for_budget()
            t0 = time.perf_counter()
            self._answer(entry, query)
            dt = time.perf_counter() - t0
            with self._lock:
                self._busy_s += dt
                self._busy_max_s = max(self._busy_max_s, dt)

    def _wait_for_budget(self) -> None:
        """At most `max_rate_hz / 10` queries a tenth of a second, all workers together; over it, the
        worker waits for the next tenth while its ring holds (and drops) what comes meanwhile."""
        while not self._stop.is_set():
            with self._budget_lock:
                now = time.monotonic()
                if now >= self._tick_end:
                    self._tick_end, self._served = now + 0.1, 0
                if self._served < self._max_per_tick:
                    self._served += 1
                    return
                wait_s = self._tick_end - now
            self._stop.wait(wait_s)

    def _answer(self, entry: _Entry, query: Any) -> None:
        with self._lock:
            self.queries += 1
        try:
            with query:
                payload = query.payload
                if payload is not None and len(payload) > MAX_QUERY_BYTES:
                    self.too_large += 1
                    ok, body = False, TOO_LARGE
                    if entry.command is not None and self._gate is not None:
                        self._gate.refuse_unparsed(entry.command, f"payload over {MAX_QUERY_BYTES} bytes")
                    else:
                        self._note_refusal(entry.key, "payload too large")
                else:
                    ok, body = entry.serve(query, entry.command)
                if ok:
                    query.reply(entry.key, body, encoding=JSON_ENCODING)
                else:
                    query.reply_err(body, encoding=JSON_ENCODING)
        except Exception as exc:  # noqa: BLE001 - the querier went away, or the session closed
            self._note_refusal(entry.key, f"reply failed: {type(exc).__name__}: {exc}")

    # ---- the kinds of query --------------------------------------------------------------
    def _serve_status(self, _query: Any, _command: str | None) -> tuple[bool, bytes]:
        return self._cached("status", STATUS_CACHE_S if self._cache_status else 0.0, self._status,
                            self._status_version)

    def _serve_config(self, _query: Any, _command: str | None) -> tuple[bool, bytes]:
        return self._cached("config", CONFIG_CACHE_S, self._config)

    def _serve_limits(self, query: Any, _command: str | None) -> tuple[bool, bytes]:
        """No payload: every key's summary (cached); `{"key": K}`: that key's detail (not cached)."""
        from millsense.daemon.publish.limits_args import parse_key

        payload = query.payload
        data = payload.to_bytes() if payload is not None else b""
        if not data.strip():
            return self._cached("limits", LIMITS_CACHE_S, lambda: self._limits(None))
        try:
            request = loads_object(data)
            extra = sorted(set(request) - {"key"})
            if extra:
                raise ValueError(f"limits takes only \"key\" (got {', '.join(extra)})")
            key = parse_key(request.get("key"))
        except ValueError as exc:
            self._note_refusal("limits", str(exc))
            return False, dumps({"ok": False, "error": str(exc)})
        return self._cached(f"limits {key}", 0.0, lambda: self._limits(key))

    def _cached(self, name: str, keep_s: float, produce: Callable[[], dict],
                version: Callable[[], Any] | None = None) -> tuple[bool, bytes]:
        """`version`: what the kept answer must still match to be served (read before producing, so an
        answer produced across a change is kept under the older version and not served again)."""
        now = time.monotonic()
        hit = self._cache.get(name)
        try:
            current = version() if version is not None else None
        except Exception:  # noqa: BLE001 - no version, no cache: always fresh
            current, keep_s, hit = object(), 0.0, None
        if hit is not None and now < hit[0] and hit[2] == current:
            return True, hit[1]
        try:
            result = produce()
            if not isinstance(result, dict):
                raise TypeError(f"controls returned {type(result).__name__}, expected a dict")
            body = dumps(result)
        except Exception as exc:  # noqa: BLE001 - a query must never kill the daemon
            reason = str(exc) if isinstance(exc, (ValueError, LookupError)) else f"{type(exc).__name__}: {exc}"
            self._note_refusal(name, reason)
            return False, dumps({"ok": False, "error": reason})
        if keep_s > 0:
            self._cache[name] = (now + keep_s, body, current)
        return True, body

    def _serve_command(self, query: Any, command: str | None) -> tuple[bool, bytes]:
        command = command or "reset"
        if self._gate is None or command not in self._commands:
            self._note_refusal(f"cmd/{command}", "no controls")
            return False, dumps({"ok": False, "error": f"this daemon has no interlock to {command}"})
        payload = query.payload
        data = payload.to_bytes() if payload is not None else b""
        try:
            if not data.strip():
                raise ValueError('payload is empty: send {"step": "challenge", ...} (docs/zenoh.md)')
            request = loads_object(data)
        except ValueError as exc:
            return self._sent(self._gate.refuse_unparsed(command, str(exc)))
        return self._sent(self._gate.handle(command, request, self._commands[command]))

    def _sent(self, answer: Answer) -> tuple[bool, bytes]:
        if answer.ran:
            self._cache.clear()  # the next status shows what the command changed
        return answer.ok, answer.body

    # ---- counters, logging, teardown ---------------------------------------------------
    def stats(self) -> dict[str, Any]:
        served = max(1, self.queries)
        return {
            "queries": self.queries,
            "query_errors": self.errors,
            "queries_too_large": self.too_large,
            "query_python_ms_mean": round(1000 * self._busy_s / served, 3),
            "query_python_ms_max": round(1000 * self._busy_max_s, 3),
        }

    def _note_refusal(self, key: str, reason: str) -> None:
        """Counted always; logged at most once per LOG_EVERY_S, with the count since the last line."""
        with self._lock:
            self.errors += 1
            self._log_refused(self._refused.note({"key": key, "error": reason}))

    def _log_refused(self, due: tuple[int, Any] | None) -> None:
        if due is not None and self._log is not None:
            count, last = due
            try:
                self._log.warning("zenoh.queries_refused", count=count, last=last, every_s=LOG_EVERY_S)
            except Exception:  # noqa: BLE001 - logging must not break the queryables
                pass

    def close(self, timeout_s: float = 1.0) -> None:
        self._stop.set()
        self._undeclare()  # closes the rings: each worker's recv() returns with an error and the worker ends
        deadline = time.monotonic() + timeout_s
        for t in self._threads:
            t.join(max(0.0, deadline - time.monotonic()))
        with self._lock:
            self._log_refused(self._refused.pending())

    def _undeclare(self) -> None:
        for e in self._entries:
            try:
                e.queryable.undeclare()
            except Exception:  # noqa: BLE001 - already undeclared, or the session closed
                pass
        self._entries = []


def _thread_name(entry: _Entry, os_name: bool = False) -> str:
    """`zenoh-query-status` … and `zenoh-cmd-reset` …; in the OS (15 bytes: `top -H`) `ms-q-status`, `ms-c-reset`."""
    tail = entry.key.rsplit("/", 1)[-1]
    if entry.command is not None:
        return f"ms-c-{tail}" if os_name else f"zenoh-cmd-{tail}"
    return f"ms-q-{tail}" if os_name else f"zenoh-query-{tail}"
