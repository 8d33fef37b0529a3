"""Logging: JSON lines vs console, the auto choice, no waiting on a blocked sink, rate limiting."""

from __future__ import annotations

import datetime as dt
import io
import json
import logging
import os
import subprocess
import sys
import time

import pytest
import structlog

from millsense.daemon.logging_setup import (
    NonBlockingWriter,
    RateLimitedLogger,
    configure_logging,
    flush_logs,
    resolve_format,
)


class Tty(io.StringIO):
    def isatty(self) -> bool:
        return True


@pytest.fixture(autouse=True)
def _restore_logging():
    yield
    root = logging.getLogger()
    for h in [h for h in root.handlers if h.get_name() == "millsense"]:
        root.removeHandler(h)
    structlog.reset_defaults()


def test_json_lines_with_iso_utc_timestamps():
    out = io.StringIO()
    assert configure_logging("info", "json", stream=out, nonblocking=False) == "json"
    structlog.get_logger("millsense.test").info("daq.connected", port="/dev/ttyACM0", samples=3)
    structlog.get_logger("millsense.test").debug("hidden")
    # a library logger nobody else configures (the Modbus driver quiets "pymodbus" on purpose)
    logging.getLogger("thirdparty.lib").warning("from %s", "stdlib")
    lines = [json.loads(ln) for ln in out.getvalue().splitlines()]
    assert [ln["event"] for ln in lines] == ["daq.connected", "from stdlib"]
    first = lines[0]
    assert (first["level"], first["logger"], first["port"], first["samples"]) == ("info", "millsense.test", "/dev/ttyACM0", 3)
    ts = dt.datetime.fromisoformat(first["timestamp"].replace("Z", "+00:00"))
    assert ts.utcoffset() == dt.timedelta(0) and abs((dt.datetime.now(dt.UTC) - ts).total_seconds()) < 60
    assert lines[1]["logger"] == "thirdparty.lib" and lines[1]["level"] == "warning"


def test_console_format_is_not_json():
    out = io.StringIO()
    configure_logging("debug", "console", stream=out, nonblocking=False)
    structlog.get_logger("millsense.test").debug("revolution.split", rev=7)
    line = out.getvalue().strip()
    assert "revolution.split" in line and "rev=7" in line and "[debug" in line
    with pytest.raises(json.JSONDecodeError):
        json.loads(line)


def test_auto_picks_console_on_a_tty_and_json_under_systemd_or_a_pipe():
    assert resolve_format("auto", Tty(), env={}) == "console"
    assert resolve_format("auto", io.StringIO(), env={}) == "json"
    assert resolve_format("auto", Tty(), env={"JOURNAL_STREAM": "8:1234"}) == "json"
    assert resolve_format("auto", Tty(), env={"INVOCATION_ID": "abc"}) == "json"
    assert resolve_format("console", io.StringIO(), env={"INVOCATION_ID": "abc"}) == "console"


@pytest.mark.serial
def test_a_blocked_sink_does_not_block_the_logger():
    """A pipe nobody reads (a stalled journald): log calls return at once, excess lines are dropped."""
    r, w = os.pipe()
    os.set_blocking(w, True)
    sink = os.fdopen(w, "w", buffering=1)
    try:
        writer = NonBlockingWriter(sink, max_lines=100)
        configure_logging("info", "json", stream=writer, nonblocking=False)
        log = structlog.get_logger("millsense.test")
        started = time.monotonic()
        for i in range(3000):  # ~300 kB: far beyond the 64 kB pipe buffer
            log.info("blocked", i=i, pad="x" * 80)
        elapsed = time.monotonic() - started
        assert elapsed < 10.0  # generous: the point is that it returns at all (a blocking write never would)
        assert writer.dropped > 0
    finally:
        os.close(r)  # the writer thread's write fails (EPIPE) and it carries on
        writer.close()
        try:
            sink.close()
        except BrokenPipeError:
            pass


def test_queued_lines_are_written_before_exit(tmp_path):
    code = (
        "import sys, structlog\n"
        "from millsense.daemon.logging_setup import configure_logging\n"
        "configure_logging('info', 'json', stream=sys.stderr)\n"
        "for i in range(200): structlog.get_logger('t').info('line', i=i)\n"
    )
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert p.returncode == 0
    assert [json.loads(ln)["i"] for ln in p.stderr.splitlines()] == list(range(200))


def test_flush_logs_waits_for_the_writer():
    out = io.StringIO()
    configure_logging("info", "json", stream=out)
    structlog.get_logger("t").info("one")
    flush_logs(2.0)
    assert json.loads(out.getvalue())["event"] == "one"


def test_rate_limited_logger_counts_what_it_suppressed():
    now = [0.0]
    with structlog.testing.capture_logs() as logs:
        rl = RateLimitedLogger(structlog.get_logger("t"), interval_s=10.0, clock=lambda: now[0])
        assert rl.warning("decoder.bad_crc", port="p")
        assert not any(rl.warning("decoder.bad_crc", port="p") for _ in range(41))
        assert rl.warning("queue.overflow")  # another key is independent
        now[0] = 10.5
        assert rl.warning("decoder.bad_crc", port="p")
    assert [(e["event"], e.get("suppressed")) for e in logs] == [
        ("decoder.bad_crc", None), ("queue.overflow", None), ("decoder.bad_crc", 41)]


def test_the_journal_keeps_the_alarm_kind_and_the_docs_recipe_finds_overloads_alone(tmp_path):
    """Issue 10, finding 7: a real daemon, the crash scenario, an overload and then a crash.

    The daemon logs JSON lines to stdout (the journal under systemd). The docs' recipe
    `journalctl -u millsense@M -o cat | grep '"alarm_level": "overload"'` is run here on those
    lines with grep itself: it must find the overload and nothing else.
    """
    import shutil
    import signal as _signal

    from tests.conftest import free_tcp_port
    from tests.e2e.helpers import Procs, wait_for, write_config

    daq_port = free_tcp_port()
    cfg = write_config(
        tmp_path / "d.toml",
        machine="log-kinds",
        daq=f'transport = "tcp"\nhost = "127.0.0.1"\ntcp_port = {daq_port}',
        # the steady slot cut is about 4 N·m: over 3 N·m is an overload; the boss passes 15 kW: a crash.
        # The interlock is off so that the feed keeps going into the boss.
        alarms="torque_limit_nm = 3.0\nrevolutions = 2\ncrash_power_w = 15000.0",
        interlock="enabled = false",
    )
    with Procs(tmp_path) as procs:
        procs.start("sim", ["sim", "--scenario", "crash", "--tcp", f"127.0.0.1:{daq_port}", "--realtime"])
        wait_for(lambda: "serving" in procs.text("sim"), 30.0, "emulator serving")
        daemon = procs.start("daemon", ["run", "--config", str(cfg)])
        wait_for(lambda: '"alarm_level": "crash"' in procs.text("daemon", "out") or daemon.poll() is not None,
                 60.0, "the crash alarm in the log")
        daemon.send_signal(_signal.SIGTERM)
        assert daemon.wait(10) == 0, procs.text("daemon")
    journal = tmp_path / "daemon.out"
    alarms = [json.loads(x) for x in journal.read_text().splitlines() if x.startswith("{") and '"event": "alarm"' in x]
    kinds = [a["alarm_level"] for a in alarms]
    assert "overload" in kinds and "crash" in kinds, kinds
    assert all(a["level"] == "warning" for a in alarms)  # the log level, as before
    for a in alarms:  # every field of the payload is kept
        assert {"t", "rev", "quantity", "value", "limit", "interlock"} <= set(a), a
    grep = shutil.which("grep")
    found = subprocess.run([grep, '"alarm_level": "overload"', str(journal)], capture_output=True, text=True).stdout
    lines = [json.loads(x) for x in found.splitlines()]
    assert lines and all(x["event"] == "alarm" and x["alarm_level"] == "overload" for x in lines)
    assert len(lines) == kinds.count("overload")
