"""Structured logs: JSON lines under systemd or into a pipe, readable lines on a terminal.

`configure_logging(level, fmt, stream=...)` sets up structlog over the stdlib
`logging` module, so third-party loggers (pymodbus, zenoh's Python side) come
out in the same format. Every event carries `timestamp` (ISO 8601, UTC),
`level`, `logger` and `event` plus its own fields.

"auto" picks JSON when the process runs under systemd (`$JOURNAL_STREAM` or
`$INVOCATION_ID` set) or the stream is not a terminal, and the console renderer
on a terminal. The stream is a parameter: `run` logs to stdout under systemd
(interfaces.md) and stderr otherwise; `replay` keeps stdout for its JSON output.

**On a terminal** (`ConsoleLines`) a line is for a person: local time, no
`None` fields, numbers to 3 significant digits, epoch times as local times,
an alarm as a sentence with the interlock's action in words, a fault without
its diagnostic dump (the JSON line keeps everything, exactly). The writer
also owns the terminal's last line, the **live line** (`show_live`): a log
line first erases it and it is drawn again below, so the two never share a
line.

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
import datetime as dt
import logging
import math
import os
import re
import sys
import threading
import time
from typing import Any, TextIO

import structlog

LEVELS = ("debug", "info", "warning", "error", "critical")
_HANDLER_NAME = "millsense"
ERASE_LINE = "\r\x1b[K"  # column 0, then erase to the end of the line (ECMA-48 EL)


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

    With `terminal=True` the writer also keeps the live line (`show_live`,
    latest text wins) as the terminal's last line. Only the writer thread
    touches the terminal, so a log line and the live line cannot interleave:
    a batch of log lines first erases the live line, and the live line is
    drawn again after it, cut to the terminal's width (a wrapped line could
    not be erased with one carriage return).
    """

    def __init__(self, stream: TextIO, max_lines: int = 10000, *, terminal: bool = False):
        self.stream = stream
        self.max_lines = max_lines
        self.terminal = terminal
        self.dropped = 0
        self._q: collections.deque[str] = collections.deque()
        self._cv = threading.Condition()
        self._closed = False
        self._busy = False
        self._live: str | None = None  # the live line last asked for
        self._live_dirty = False  # asked for since the writer last drew it
        self._live_shown = False  # on screen now (writer thread only)
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

    def show_live(self, text: str) -> None:
        """Show `text` as the live line (a terminal writer only); returns at once."""
        if not self.terminal:
            return
        with self._cv:
            self._live = text.replace("\n", " ").replace("\r", " ")
            self._live_dirty = True
            self._cv.notify()

    def end_live(self) -> None:
        """The live line becomes an ordinary line (its last state stays on screen); no more redraws."""
        with self._cv:
            if self._live is not None:
                self._q.append(self._live + "\n")
                self._live = None
                self._cv.notify()

    def _drain(self) -> None:
        from millsense.drivers.base import name_os_thread  # here: every command imports this module; numpy stays out of it

        name_os_thread("ms-log")
        while True:
            with self._cv:
                while not self._q and not self._live_dirty and not self._closed:
                    self._cv.wait()
                if not self._q and not self._live_dirty and self._closed:
                    return
                batch = "".join(self._q)
                self._q.clear()
                live, redraw = self._live, self._live_dirty
                self._live_dirty = False
                self._busy = True
            try:
                if self.terminal:
                    batch = self._on_terminal(batch, live, redraw)
                self.stream.write(batch)
                self.stream.flush()
            except (OSError, ValueError):  # closed or broken sink: nothing sensible to do with a log line
                pass
            finally:
                with self._cv:
                    self._busy = False
                    self._cv.notify_all()

    def _on_terminal(self, batch: str, live: str | None, redraw: bool) -> str:
        """What to write: the live line erased before log lines, drawn again after them."""
        out = ""
        if batch:
            if self._live_shown:
                out = ERASE_LINE
                self._live_shown = False
            out += batch
        if live is not None and (redraw or batch):
            cols = _columns(self.stream)
            out += "\r" + (live[: cols - 1] if cols > 1 else live) + "\x1b[K"
            self._live_shown = True
        return out

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


def _columns(stream: Any) -> int:
    """The terminal's width, 0 when unknown (a pty nobody sized)."""
    try:
        return os.get_terminal_size(stream.fileno()).columns
    except (AttributeError, ValueError, OSError):
        return 0


def _isatty(stream: Any) -> bool:
    try:
        return bool(getattr(stream, "isatty", lambda: False)())
    except (ValueError, OSError):  # closed stream
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
        render = [structlog.processors.format_exc_info, ConsoleLines(colors=_isatty(stream))]
    formatter = structlog.stdlib.ProcessorFormatter(
        foreign_pre_chain=shared,
        processors=[structlog.stdlib.ProcessorFormatter.remove_processors_meta, *render],
    )
    # The live line lives on the log stream when that is a person's terminal, never under systemd.
    terminal = nonblocking and _isatty(stream) and not under_systemd(env)
    sink: Any = NonBlockingWriter(stream, terminal=terminal) if nonblocking else stream
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


def live_writer() -> NonBlockingWriter | None:
    """The log writer if it can carry the live line (the logs go to a terminal), else None."""
    for h in logging.getLogger().handlers:
        sink = getattr(h, "stream", None)
        if h.get_name() == _HANDLER_NAME and isinstance(sink, NonBlockingWriter) and sink.terminal:
            return sink
    return None


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


# ---------------------------------------------------------------------------------------------- the console
_LOCAL_TIME_KEYS = ("t", "since")  # Unix times (s): shown as the local clock time
# A decimal number standing on its own (not part of a version, an address or an ISO time).
_DECIMAL = re.compile(r"(?<![\w.:])-?\d+\.\d+(?:[eE][+-]?\d+)?(?![\w.:])")
_LEVEL_STYLES = {"debug": "\x1b[34m", "info": "\x1b[32m", "warning": "\x1b[33m", "error": "\x1b[1;31m", "critical": "\x1b[1;31m"}
_DIM, _BOLD, _RESET = "\x1b[2m", "\x1b[1m", "\x1b[0m"
_NESTED_MAX = 120  # characters of a dict or list on a console line


def readable_number(value: float) -> str:
    """3 significant digits; 100 to 9999 as a whole number (1665 W reads better than 1.66e+03 W)."""
    if not math.isfinite(value):
        return str(value)
    if 100 <= abs(value) < 10000:
        return f"{value:.0f}"
    return f"{value:.3g}"


def _significant_digits(text: str) -> int:
    mantissa = re.split(r"[eE]", text)[0]
    return len(mantissa.replace("-", "").replace(".", "").lstrip("0"))


def shorten_numbers(text: str) -> str:
    """Decimal numbers in free text (a fault's reason) cut to 3 significant digits when longer than 4."""
    return _DECIMAL.sub(
        lambda m: readable_number(float(m.group())) if _significant_digits(m.group()) > 4 else m.group(), text
    )


def local_time(unix_s: float, ms: bool = False) -> str:
    """Clock time in the local zone, with the date when it is not today."""
    when = dt.datetime.fromtimestamp(unix_s)
    text = when.strftime("%H:%M:%S.%f")[:-3] if ms else when.strftime("%H:%M:%S")
    return text if when.date() == dt.date.today() else f"{when:%Y-%m-%d} {text}"


def _console_value(key: str, value: Any) -> str:
    if isinstance(value, int):  # bool too
        return str(value)
    if isinstance(value, float):
        if key in _LOCAL_TIME_KEYS and value > 1e8:
            return local_time(value, ms=key == "t")
        return readable_number(value)
    if isinstance(value, str):
        text = shorten_numbers(value)
        return f'"{text}"' if (not text or any(c.isspace() for c in text)) else text
    if isinstance(value, dict):
        text = "{" + ", ".join(f"{k}: {_console_value(str(k), v)}" for k, v in value.items() if v is not None) + "}"
    elif isinstance(value, (list, tuple)):
        text = "[" + ", ".join(_console_value(key, v) for v in value) + "]"
    else:
        text = shorten_numbers(str(value))
    return text if len(text) <= _NESTED_MAX else text[: _NESTED_MAX - 1] + "…"


def _interlock_words(kind: str, action: Any) -> str:
    """The alarm payload's `interlock` in words: what the feed does because of this alarm."""
    if action == "feed_hold":
        return "feed still held" if kind == "clear" else "feed held"
    if action is None:
        return "no action"
    return str(action).replace("_", " ")


def _alarm_event(ed: dict[str, Any]) -> str:
    """`alarm overload: torque_nm 2.53, limit 2, rev 79; feed held` (the sample time is the line's)."""
    kind = str(ed.pop("alarm_level", None) or "?")
    value, limit, rev = ed.pop("value", None), ed.pop("limit", None), ed.pop("rev", None)
    ed.pop("t", None)
    parts = [str(ed.pop("quantity", None) or "")]
    if value is not None:
        parts[0] += " " + _console_value("value", float(value))
    if limit is not None:
        parts.append("limit " + _console_value("limit", float(limit)))
    if rev is not None:
        parts.append(f"rev {rev}")
    return f"alarm {kind}: {', '.join(p for p in parts if p)}; {_interlock_words(kind, ed.pop('interlock', None))}"


def _fault_event(ed: dict[str, Any]) -> str:
    """`fault daq_link: <reason>` and three numbers from the dump (the JSON line keeps all of it)."""
    text = f"fault {ed.pop('kind', '?')}: {shorten_numbers(str(ed.pop('reason', '')))}"
    dump = ed.pop("dump", None)
    if isinstance(dump, dict):
        interlock = dump.get("interlock")
        ed["samples"] = dump.get("samples")
        ed["revolutions"] = dump.get("revolutions")
        ed["interlock"] = interlock.get("interlock") if isinstance(interlock, dict) else None
    return text


class ConsoleLines:
    """structlog's last processor on a terminal: one line a person reads at a glance.

    `14:47:25 [warning] alarm overload: torque_nm 2.53, limit 2, rev 79; feed held`.
    A traceback or exception follows on its own lines.
    """

    def __init__(self, colors: bool = False):
        self.colors = colors

    def _style(self, style: str, text: str) -> str:
        return f"{style}{text}{_RESET}" if self.colors else text

    def __call__(self, _logger: Any, _name: str, event_dict: dict[str, Any]) -> str:
        ed = {k: v for k, v in event_dict.items() if v is not None}
        stamp = ed.pop("timestamp", None)
        level = str(ed.pop("level", "info"))
        logger = str(ed.pop("logger", "") or "")
        trailer = [str(ed.pop(k)) for k in ("exception", "stack", "traceback") if k in ed]
        event = str(ed.pop("event", ""))
        if event == "alarm":
            event = _alarm_event(ed)
        elif event == "fault":
            event = _fault_event(ed)
        else:
            event = shorten_numbers(event)
        fields = "".join(f" {k}={_console_value(k, v)}" for k, v in ed.items() if v is not None)
        source = "" if not logger or logger.startswith("millsense") else f" [{logger}]"
        line = (
            f"{self._style(_DIM, _clock(stamp))} [{self._style(_LEVEL_STYLES.get(level, ''), level)}]{' ' * (7 - len(level))} "
            f"{self._style(_BOLD, event)}{source}{fields}"
        )
        return "\n".join([line, *trailer])


def _clock(stamp: Any) -> str:
    """The log line's ISO UTC timestamp as local clock time."""
    if not isinstance(stamp, str):
        return time.strftime("%H:%M:%S")
    try:
        return dt.datetime.fromisoformat(stamp.replace("Z", "+00:00")).astimezone().strftime("%H:%M:%S")
    except ValueError:
        return stamp
