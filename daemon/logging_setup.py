"""Structured logs: JSON lines under systemd or into a pipe, readable lines on a terminal.

`configure_logging(level, fmt, stream=...)` sets up structlog over the stdlib
`logging` module, so third-party loggers (pymodbus, zenoh's Python side) come
out in the same format. Every event carries `timestamp` (ISO 8601, UTC),
`level`, `logger` and `event` plus its own fields.

"auto" picks JSON when the process runs under systemd (`$JOURNAL_STREAM` or
`$INVOCATION_ID` set) or the stream is not a terminal, and the console renderer
on a terminal. The stream is a parameter: `run` logs to stdout under systemd
(interfaces.md) and stderr otherwise; `replay` keeps stdout for its JSON output.

**The sample path never waits on a log write.** structlog itself is
synchronous, so three things keep a slow or blocked log sink (a full journald
pipe, a stopped terminal) away from the samples:

1. no log call on a per-sample or per-block path — estimator and alarms return
   values; the runner logs *state changes*;
2. lines go through `NonBlockingWriter`: `write()` appends to a bounded
   in-memory queue and returns; one writer thread does the blocking I/O; when
   the queue is full, lines are dropped and counted (`dropped`), never waited on;
3. `RateLimitedLogger` turns a repeated event (bad CRC, queue overflow) into at
   most one line per interval with a `suppressed` count.
"""

from __future__ import annotations

import atexit
import collections
import logging
import os
import sys
import threading
import time
from typing import Any, TextIO

import structlog

LEVELS = ("debug", "info", "warning", "error", "critical")
_HANDLER_NAME = "millsense"


def under_systemd(env: dict[str, str] | None = None) -> bool:
    """True when started by systemd (its journal or its invocation id is in the environment)."""
    e = os.environ if env is None else env
    return bool(e.get("JOURNAL_STREAM") or e.get("INVOCATION_ID"))


def resolve_format(fmt: str, stream: Any, env: dict[str, str] | None = None) -> str:
    """"auto" → "json" under systemd or off a TTY, "console" on a TTY."""
    if fmt in ("json", "console"):
        return fmt
    if under_systemd(env):
        return "json"
    isatty = getattr(stream, "isatty", None)
    try:
        return "console" if isatty is not None and isatty() else "json"
    except (ValueError, OSError):  # closed stream
        return "json"


class NonBlockingWriter:
    """A file-like whose `write` never blocks: a bounded queue drained by one thread.

    `max_lines` bounds memory; beyond it lines are dropped and counted in
    `dropped` (a log is worth less than a sample). `flush(timeout_s)` waits
    for the queue to drain, at most that long; it runs at interpreter exit.
    """

    def __init__(self, stream: TextIO, max_lines: int = 10000):
        self.stream = stream
        self.max_lines = max_lines
        self.dropped = 0
        self._q: collections.deque[str] = collections.deque()
        self._cv = threading.Condition()
        self._closed = False
        self._busy = False
        self._thread = threading.Thread(target=self._drain, name="millsense-log-writer", daemon=True)
        self._thread.start()
        atexit.register(self.drain, 2.0)

    def write(self, text: str) -> int:
        with self._cv:
            if len(self._q) >= self.max_lines:
                self.dropped += 1
                return 0
            self._q.append(text)
            self._cv.notify()
        return len(text)

    def _drain(self) -> None:
        while True:
            with self._cv:
                while not self._q and not self._closed:
                    self._cv.wait()
                if not self._q and self._closed:
                    return
                batch = "".join(self._q)
                self._q.clear()
                self._busy = True
            try:
                self.stream.write(batch)
                self.stream.flush()
            except (OSError, ValueError):  # closed or broken sink: nothing sensible to do with a log line
                pass
            finally:
                with self._cv:
                    self._busy = False
                    self._cv.notify_all()

    def flush(self) -> None:
        """Never waits: the writer thread flushes the real stream after each batch."""

    def drain(self, timeout_s: float = 1.0) -> None:
        deadline = time.monotonic() + timeout_s
        with self._cv:
            while (self._q or self._busy) and self._thread.is_alive():
                left = deadline - time.monotonic()
                if left <= 0:
                    return
                self._cv.wait(left)

    def close(self) -> None:
        self.drain()
        with self._cv:
            self._closed = True
            self._cv.notify_all()
        self._thread.join(timeout=1.0)

    def isatty(self) -> bool:
        return False


def configure_logging(
    level: str = "info",
    fmt: str = "auto",
    stream: TextIO | None = None,
    *,
    nonblocking: bool = True,
    env: dict[str, str] | None = None,
) -> str:
    """Configure structlog and stdlib logging; returns the format used ("json" or "console").

    Idempotent: calling it again replaces the previous handler (tests, `run` after
    the config is read).
    """
    stream = sys.stderr if stream is None else stream
    level_name = level.lower() if level.lower() in LEVELS else "info"
    resolved = resolve_format(fmt, stream, env)
    timestamper = structlog.processors.TimeStamper(fmt="iso", utc=True)
    shared = [
        structlog.contextvars.merge_contextvars,
        structlog.stdlib.add_logger_name,
        structlog.stdlib.add_log_level,
        timestamper,
    ]
    if resolved == "json":
        render: list[Any] = [structlog.processors.format_exc_info, structlog.processors.JSONRenderer(default=str)]
    else:
        colors = bool(getattr(stream, "isatty", lambda: False)())
        render = [structlog.dev.ConsoleRenderer(colors=colors)]
    formatter = structlog.stdlib.ProcessorFormatter(
        foreign_pre_chain=shared,
        processors=[structlog.stdlib.ProcessorFormatter.remove_processors_meta, *render],
    )
    sink: Any = NonBlockingWriter(stream) if nonblocking else stream
    handler = logging.StreamHandler(sink)
    handler.set_name(_HANDLER_NAME)
    handler.setFormatter(formatter)
    root = logging.getLogger()
    for old in [h for h in root.handlers if h.get_name() == _HANDLER_NAME]:
        root.removeHandler(old)
        old_sink = getattr(old, "stream", None)
        if isinstance(old_sink, NonBlockingWriter):
            old_sink.close()
    root.addHandler(handler)
    root.setLevel(getattr(logging, level_name.upper()))
    structlog.configure(
        processors=[structlog.stdlib.filter_by_level, *shared, structlog.processors.StackInfoRenderer(),
                    structlog.stdlib.ProcessorFormatter.wrap_for_formatter],
        logger_factory=structlog.stdlib.LoggerFactory(),
        wrapper_class=structlog.stdlib.BoundLogger,
        cache_logger_on_first_use=False,  # modules bind loggers at import, before this runs
    )
    return resolved


def flush_logs(timeout_s: float = 1.0) -> None:
    """Wait (bounded) until queued log lines are written: call before exiting."""
    for h in logging.getLogger().handlers:
        sink = getattr(h, "stream", None)
        if isinstance(sink, NonBlockingWriter):
            sink.drain(timeout_s)


class RateLimitedLogger:
    """At most one line per `key` per `interval_s`; the next line says how many were suppressed.

    For events that can repeat at frame rate (bad CRC, dropped blocks): the
    first occurrence is logged at once, repeats within the interval only
    counted. Thread-safe; `clock` is injectable for tests.
    """

    def __init__(self, logger: Any, interval_s: float = 10.0, clock: Any = time.monotonic):
        self._log = logger
        self.interval_s = interval_s
        self._clock = clock
        self._lock = threading.Lock()
        self._last: dict[str, float] = {}
        self._suppressed: dict[str, int] = {}

    def log(self, level: str, event: str, *, key: str | None = None, **fields: Any) -> bool:
        """Log `event` unless `key` (default: the event) was logged less than `interval_s` ago."""
        k = key or event
        now = self._clock()
        with self._lock:
            last = self._last.get(k)
            if last is not None and now - last < self.interval_s:
                self._suppressed[k] = self._suppressed.get(k, 0) + 1
                return False
            self._last[k] = now
            suppressed = self._suppressed.pop(k, 0)
        if suppressed:
            fields["suppressed"] = suppressed
        getattr(self._log, level)(event, **fields)
        return True

    def debug(self, event: str, **fields: Any) -> bool:
        return self.log("debug", event, **fields)

    def info(self, event: str, **fields: Any) -> bool:
        return self.log("info", event, **fields)

    def warning(self, event: str, **fields: Any) -> bool:
        return self.log("warning", event, **fields)

    def error(self, event: str, **fields: Any) -> bool:
        return self.log("error", event, **fields)
