"""A stop asked for is not a failure (issue 13, item 4): on a normal stop the heartbeats' end and the
DAQ link's end log at info, saying the stop was asked for; a real loss stays a warning."""

from __future__ import annotations

import socket
import threading
import types

import pytest
from structlog.testing import capture_logs

from millsense.daemon.runtime.interlock import Interlock
from millsense.drivers.tcp_driver import TcpDriver

pytestmark = pytest.mark.quick


def _events(logs: list[dict], name: str) -> list[dict]:
    return [e for e in logs if e["event"] == name]


class _Daq:
    """A real TCP driver on a real loopback server that reads and discards what the driver sends."""

    def __init__(self) -> None:
        self.server = socket.create_server(("127.0.0.1", 0))
        self.driver = TcpDriver("127.0.0.1", self.server.getsockname()[1], read_timeout_s=0.05)
        self.driver.start()
        self.conn, _ = self.server.accept()
        threading.Thread(target=self._sink, daemon=True).start()
        assert self.driver.wait_connected(10.0)

    def _sink(self) -> None:
        try:
            while self.conn.recv(4096):
                pass
        except OSError:
            pass

    def close(self) -> None:
        self.driver.close()
        self.conn.close()
        self.server.close()


def test_heartbeats_stopped_is_info_on_a_stop_and_warning_on_a_fault() -> None:
    daq = _Daq()
    try:
        il = Interlock(daq.driver, types.SimpleNamespace(enabled=True, heartbeat_ms=100, watchdog_ms=500))
        with capture_logs() as logs:
            il.beat(True)
            il.beat(False, stopping=True)  # the daemon stopping, as asked
            il.beat(True)
            il.beat(False)  # the pipeline not healthy: a real loss
        stopped = _events(logs, "interlock.heartbeats_stopped")
        assert [e["log_level"] for e in stopped] == ["info", "warning"]
        assert stopped[0].get("asked") is True and "stopping" in stopped[0]["detail"]
        assert "watchdog takes over" in stopped[1]["detail"] and "asked" not in stopped[1]
    finally:
        daq.close()


def test_link_down_on_close_is_info_with_a_detail() -> None:
    daq = _Daq()
    with capture_logs() as logs:
        daq.close()
    down = _events(logs, "daq.link_down")
    assert len(down) == 1
    assert (down[0]["log_level"], down[0]["reason"]) == ("info", "closed")
    assert "closing, as asked" in down[0]["detail"]


def test_link_lost_stays_a_warning() -> None:
    daq = _Daq()
    try:
        with capture_logs() as logs:
            daq.conn.shutdown(socket.SHUT_RDWR)  # the DAQ goes away
            daq.conn.close()
            for _ in range(200):
                if _events(logs, "daq.link_down"):
                    break
                threading.Event().wait(0.05)
        down = _events(logs, "daq.link_down")
        assert down and down[0]["log_level"] == "warning"
        assert "detail" not in down[0] and "closed by peer" in down[0]["reason"]
    finally:
        daq.close()
