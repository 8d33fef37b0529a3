"""What a person sees on a terminal (issue 12, item 3).

One real `millsense run --config` on a real pty, started before the emulator
(a late DAQ connect), then a real `millsense sim --tcp` playing the step
scenario into a warning and an overload. The module fixture keeps every byte
the terminal received; the tests replay them through a small terminal model
(carriage return, erase to end of line, newline) and read the screen a person
would have read.
"""

from __future__ import annotations

import fcntl
import io
import json
import logging
import os
import re
import select
import signal
import struct
import subprocess
import termios
import threading
import time
from pathlib import Path

import pytest
import structlog

from millsense.daemon.logging_setup import ConsoleLines, NonBlockingWriter, configure_logging, flush_logs, live_writer
from tests.conftest import free_tcp_port
from tests.e2e.helpers import CMD, Procs, tcp, wait_for, write_config

# The step scenario cuts at about 2 N·m, then at about 2.7 N·m (the e2e interlock test measures its plateaus).
WARN_NM, LIMIT_NM = 1.0, 2.3
TZ = "MST-05:45"  # POSIX: local time is UTC + 5 h 45 min, so a UTC time cannot pass for local
TZ_OFFSET_MIN = 5 * 60 + 45
SGR = re.compile(r"\x1b\[[0-9;]*m")
LOG_LINE = re.compile(r"^\d\d:\d\d:\d\d \[(debug|info|warning|error|critical)\]")
LIVE_MARK = " rpm  T "  # in every live line, in no log line
LIVE_LINE = re.compile(
    r"^(starting|running|degraded|stopping) +interlock \S+ +alarm \S+ +(feed held: .+, since \d\d:\d\d:\d\d  )?"
    r"rev +\S+ +\S+ rpm  T .* mm(  \(speeding up\))?$"
)
NUMBER = re.compile(r"(?<![\w.])-?\d+(?:\.\d+)?(?:[eE][+-]?\d+)?")


class Pty:
    """The master side of a pty, read by a thread so the child never blocks on a full terminal."""

    def __init__(self, columns: int = 250):
        self.master, self.slave = os.openpty()
        fcntl.ioctl(self.slave, termios.TIOCSWINSZ, struct.pack("HHHH", 50, columns, 0, 0))
        self.data = bytearray()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    def _read(self) -> None:
        while not self._stop.is_set():
            r, _, _ = select.select([self.master], [], [], 0.1)
            if not r:
                continue
            try:
                chunk = os.read(self.master, 65536)
            except OSError:  # every writer closed the slave
                return
            if not chunk:
                return
            with self._lock:
                self.data += chunk

    def text(self) -> str:
        with self._lock:
            return bytes(self.data).decode("utf-8", "replace")

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        for fd in (self.master, self.slave):
            try:
                os.close(fd)
            except OSError:
                pass


def screen(raw: str) -> list[str]:
    """The lines a terminal shows for `raw`: CR, erase-to-end-of-line, newline; colours dropped.

    Any other control sequence fails the test: the model would not know what it draws."""
    lines: list[str] = []
    cur: list[str] = []
    col = 0
    text = SGR.sub("", raw)
    i = 0
    while i < len(text):
        c = text[i]
        if text.startswith("\x1b[K", i):
            del cur[col:]
            i += 3
            continue
        assert c != "\x1b", f"unexpected control sequence {text[i:i + 8]!r}"
        if c == "\r":
            col = 0
        elif c == "\n":
            lines.append("".join(cur))
            cur, col = [], 0
        else:
            if col < len(cur):
                cur[col] = c
            else:
                cur.append(c)
            col += 1
        i += 1
    if cur:
        lines.append("".join(cur))
    return lines


def _significant(number: str) -> int:
    mantissa = re.split(r"[eE]", number)[0]
    return len(mantissa.replace("-", "").replace(".", "").lstrip("0"))


@pytest.fixture(scope="module")
def terminal(tmp_path_factory):
    """The daemon on a pty, started before its DAQ; the transcript once the overload has been shown."""
    tmp: Path = tmp_path_factory.mktemp("console")
    daq_port, z_port = free_tcp_port(), free_tcp_port()
    cfg = write_config(
        tmp / "d.toml",
        machine="console-01",
        daq=f'transport = "tcp"\nhost = "127.0.0.1"\ntcp_port = {daq_port}',
        zenoh_listen=[tcp(z_port)],
        alarms=f"torque_warn_nm = {WARN_NM}\ntorque_limit_nm = {LIMIT_NM}\nrevolutions = 2\nbreakage_drop_pct = 0",
        interlock='enabled = true\nheartbeat_ms = 50\nwatchdog_ms = 1000\nreset = "open"',
    )
    cfg.write_text(cfg.read_text().replace('format = "json"', 'format = "auto"'))
    env = {k: v for k, v in os.environ.items() if k not in ("JOURNAL_STREAM", "INVOCATION_ID", "NOTIFY_SOCKET")}
    env.update(PYTHONUNBUFFERED="1", TZ=TZ, XDG_STATE_HOME=str(tmp / "state"))
    pty = Pty()
    procs = Procs(tmp)
    daemon = subprocess.Popen(
        [*CMD, "run", "--config", str(cfg), "--connect-timeout", "120"],
        stdin=pty.slave, stdout=pty.slave, stderr=pty.slave, env=env,
    )
    try:
        wait_for(lambda: "daq.link_down" in pty.text() or daemon.poll() is not None, 60.0, "the daemon waiting for its DAQ")
        assert daemon.poll() is None, pty.text()
        procs.start("sim", ["sim", "--scenario", "step", "--tcp", f"127.0.0.1:{daq_port}", "--realtime"])
        wait_for(lambda: "alarm overload" in pty.text() or daemon.poll() is not None, 120.0, "an overload alarm line")
        assert daemon.poll() is None, pty.text()
        try:  # the live line drawn again after it, showing the held feed (the first test says if it never came)
            wait_for(lambda: re.search(r"alarm overload(.|\n)*interlock feed_hold +alarm", SGR.sub("", pty.text())),
                     30.0, "the live line showing the held feed")
        except AssertionError:
            pass
        daemon.send_signal(signal.SIGTERM)
        daemon.wait(30)
        wait_for(lambda: "daemon.stopped" in pty.text(), 10.0, "the daemon's last line")
        yield pty.text()
    finally:
        if daemon.poll() is None:
            daemon.kill()
            daemon.wait(10)
        procs.kill_all()
        pty.close()


def test_a_daemon_with_a_config_shows_the_live_line_on_a_terminal(terminal):
    live = [ln for ln in screen(terminal) if LIVE_MARK in ln]
    assert live, terminal
    assert "\r" in terminal  # refreshed in place
    held = [ln for ln in live if LIVE_LINE.match(ln) and "interlock feed_hold" in ln]
    assert held, live
    # why and since when, after the overload's alarm cleared too (issue 36, finding 7)
    why = re.compile(r"feed held: overload torque_nm [\d.]+ > 2\.3, since \d\d:\d\d:\d\d  rev")
    assert all(why.search(ln) for ln in held), held


def test_log_lines_never_share_a_line_with_the_live_line(terminal):
    lines = screen(terminal)
    for ln in lines:
        if LIVE_MARK in ln:
            assert LIVE_LINE.match(ln), f"a live line with something glued to it: {ln!r}"
        if LOG_LINE.search(ln):
            assert LIVE_MARK not in ln, ln
    # not vacuous: the alarm was logged while a live line was on screen
    plain = SGR.sub("", terminal)
    assert re.search(re.escape(LIVE_MARK) + r"(.|\n)*alarm overload", plain), plain


def test_an_alarm_line_reads_as_a_person_would(terminal):
    lines = [ln for ln in screen(terminal) if LOG_LINE.search(ln)]
    overload = [ln for ln in lines if "alarm overload" in ln]
    warning = [ln for ln in lines if "alarm warning" in ln]
    assert overload and warning, "\n".join(lines)
    for ln in overload + warning:
        m = re.match(r"^(\d\d):(\d\d):\d\d \[warning\] ", ln)
        assert m, ln
        now = time.gmtime()
        local_now_min = (now.tm_hour * 60 + now.tm_min + TZ_OFFSET_MIN) % 1440
        shown_min = int(m.group(1)) * 60 + int(m.group(2))
        assert min((shown_min - local_now_min) % 1440, (local_now_min - shown_min) % 1440) < 15, ln  # local, not UTC
        assert "torque_nm" in ln and "None" not in ln, ln
        assert not [n for n in NUMBER.findall(ln) if _significant(n) > 4], ln
    assert all("feed held" in ln for ln in overload), overload
    assert all("no action" in ln for ln in warning), warning
    hold = [ln for ln in lines if "interlock.feed_hold" in ln]
    assert hold and not [n for n in NUMBER.findall(hold[0]) if _significant(n) > 4], hold


def test_a_late_daq_connect_is_one_short_line_per_event(terminal):
    lines = screen(terminal)
    start = next(i for i, ln in enumerate(lines) if "daq.link_down" in ln)
    after = [ln for ln in lines[start:] if LOG_LINE.search(ln)]
    assert len([ln for ln in after if "daq.link_up" in ln]) == 1, after
    assert not [ln for ln in after if len(ln) > 200], "a multi-hundred-byte line"
    assert not [ln for ln in after if "fault" in ln or "daq_lost" in ln], "the DAQ was never lost: " + "\n".join(after)


# ------------------------------------------------------------------ the pieces, without processes


@pytest.fixture
def _restore_logging():
    yield
    root = logging.getLogger()
    for h in [h for h in root.handlers if h.get_name() == "millsense"]:
        root.removeHandler(h)
    structlog.reset_defaults()


class _Tty(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_json_off_a_terminal_keeps_exact_values_and_has_no_live_line(_restore_logging):
    out = io.StringIO()
    assert configure_logging("info", "auto", stream=out, env={}) == "json"
    assert live_writer() is None
    structlog.get_logger("millsense.runner").warning(
        "alarm", alarm_level="overload", quantity="torque_nm", value=2.533921430379955, limit=2.0, rev=79,
        t=1795445245.0261767, interlock=None,
    )
    flush_logs(5.0)
    (line,) = [json.loads(ln) for ln in out.getvalue().splitlines()]
    assert line["value"] == 2.533921430379955 and line["t"] == 1795445245.0261767 and line["interlock"] is None


def test_under_systemd_a_terminal_gets_no_live_line(_restore_logging):
    configure_logging("info", "auto", stream=_Tty(), env={"INVOCATION_ID": "x"})
    assert live_writer() is None
    configure_logging("info", "auto", stream=_Tty(), env={})
    assert live_writer() is not None


def test_the_writer_erases_the_live_line_before_a_log_line_and_draws_it_again():
    tty = _Tty()
    w = NonBlockingWriter(tty, terminal=True)
    try:
        w.show_live("running rev 1")
        wait_for(lambda: "running rev 1" in tty.getvalue(), 5.0, "the live line")
        w.write("12:00:00 [warning] alarm overload\n")
        wait_for(lambda: tty.getvalue().count("running rev 1") == 2, 5.0, "the live line drawn again")
        assert screen(tty.getvalue()) == ["12:00:00 [warning] alarm overload", "running rev 1"]
        w.end_live()
        w.write("12:00:01 [info] daemon.stopped\n")
        w.drain(5.0)
        assert screen(tty.getvalue()) == ["12:00:00 [warning] alarm overload", "running rev 1", "12:00:01 [info] daemon.stopped"]
    finally:
        w.close()


def test_console_alarm_and_fault_lines():
    render = ConsoleLines(colors=False)
    base = {"timestamp": "2026-11-23T10:33:57.5Z", "logger": "millsense.runner", "level": "warning"}
    line = render(None, "warning", {**base, "event": "alarm", "alarm_level": "daq_lost", "quantity": "daq", "value": None,
                                    "limit": None, "rev": None, "t": 1795445237.0486703, "interlock": None})
    assert "alarm daq_lost: daq; no action" in line and "None" not in line and "1795" not in line, line
    line = render(None, "warning", {**base, "event": "alarm", "alarm_level": "clear", "quantity": "torque_nm",
                                    "value": -0.4096584276166779, "limit": 2.0, "rev": 81, "interlock": "feed_hold"})
    assert "torque_nm -0.41, limit 2, rev 81; feed still held" in line, line
    dump = {"samples": 0, "revolutions": 0, "driver": {f"counter_{i}": i for i in range(40)}, "interlock": {"interlock": "armed"}}
    line = render(None, "error", {**base, "level": "error", "event": "fault", "kind": "daq_link", "reason": "lost it",
                                  "dump": dump, "traceback": None})
    assert line.endswith("fault daq_link: lost it samples=0 revolutions=0 interlock=armed"), line
