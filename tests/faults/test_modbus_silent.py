"""A Modbus DAQ that never answers: the port opens, the device behind it stays silent.

Wrong unit id, wrong baud rate, an unplugged RS-485 pair, a gateway whose serial side is dead:
the serial port (or the gateway's TCP port) opens fine, and opening it is not the DAQ answering.
The link counts as up only once the device has answered (its descriptor read after connect).
While it stays silent: one `daq.link_down` saying what to check, then reconnects with back-off
and no `daq.link_up` / `daq.link_down` pair a second (which also misled every LinkEvent consumer:
status `link_up`, the link counters, the loss check counting short outages). Once it answers: one
`daq.link_up`. Real parts: `millsense sim` serving the register map (RTU on a pty, TCP behind the
fault proxy of tests/faults/netfault.py), the real driver here.
"""

from __future__ import annotations

import pytest
import structlog

from millsense.drivers import create_driver
from tests.drivers.emulator_proc import Emulator
from tests.drivers.test_contract import Collector
from tests.faults.netfault import ModbusProxy

FC_READ_INPUT = 4
SILENT_S = 4.0  # how long the silent device is watched (a window to count events in, not a budget)
SLOW_S = 60.0  # detects a failure; no budget (CI is a loaded 2-core box)


def _connect_failures(driver) -> int:
    return driver.stats().get("connect_failures", 0)


def _watch_silence(driver, col: Collector) -> None:
    """The device is silent: no link event at all (the link was never up, so none is lost either),
    while the driver keeps trying."""
    col.pump(SILENT_S)
    assert not col.links, f"a silent DAQ came and went as a link: {[(e.up, e.reason) for e in col.links][:6]}"
    assert col.pump(SLOW_S, until=lambda: _connect_failures(driver) >= 2), "the driver stopped trying"
    assert not col.links and not driver.link_up


def _link_lines(logs: list[dict]) -> tuple[list[dict], list[dict]]:
    return ([e for e in logs if e["event"] == "daq.link_up"], [e for e in logs if e["event"] == "daq.link_down"])


def _answers_once(driver, col: Collector) -> None:
    """The device answers now: one link up, samples flow, and it stays up."""
    assert col.pump(SLOW_S, until=lambda: any(e.up for e in col.links)), "never came up once the DAQ answered"
    n = len(col.blocks)
    assert col.pump(SLOW_S, until=lambda: len(col.blocks) > n + 5), "no samples after the link came up"
    assert [e.up for e in col.links] == [True], [(e.up, e.reason) for e in col.links]
    assert driver.descriptor is not None


@pytest.mark.slow
def test_rtu_a_unit_that_never_answers_is_no_link_up_and_one_that_starts_answering_is_one(tmp_path):
    link = str(tmp_path / "rtu-link")
    silent = Emulator(tmp_path, "--modbus-rtu", link, "--unit", "5", name="unit5")  # silent to unit 1 on the bus
    answering = Emulator(tmp_path, "--modbus-rtu", link, name="unit1")
    driver = create_driver("modbus-rtu", port=link, baudrate=921600, unit=1, poll_ms=20)
    try:
        with structlog.testing.capture_logs() as logs:
            silent.start()
            driver.start()
            col = Collector(driver)
            _watch_silence(driver, col)
            ups, downs = _link_lines(logs)
            assert not ups, ups[:3]
            assert len(downs) == 1, [d["reason"] for d in downs][:6]
            reason = downs[0]["reason"]
            assert f"the port opened but the DAQ at {link} unit 1 did not answer within 200 ms" in reason, reason
            assert "check unit id, baud rate, wiring" in reason, reason
            assert downs[0]["log_level"] == "warning"

            silent.stop()  # the device on the bus is now unit 1
            answering.start()
            _answers_once(driver, col)
        ups, downs = _link_lines(logs)
        assert len(ups) == 1 and len(downs) == 1, ([u["reason"] for u in ups], [d["reason"] for d in downs])
    finally:
        driver.close()
        silent.stop()
        answering.stop()


def test_tcp_a_gateway_whose_daq_never_answers_is_no_link_up_until_it_does(tmp_path, port):
    """TCP connects to the gateway at once; the DAQ behind it (here: the proxy swallowing every
    answer to a register read) says nothing."""
    emu = Emulator(tmp_path, "--modbus-tcp", f"127.0.0.1:{port}")
    proxy = driver = None
    try:
        emu.start()
        proxy = ModbusProxy(port)
        proxy.swallow(FC_READ_INPUT, 10**9)
        driver = create_driver("modbus-tcp", host="127.0.0.1", tcp_port=proxy.port, unit=1, poll_ms=20)
        with structlog.testing.capture_logs() as logs:
            driver.start()
            col = Collector(driver)
            _watch_silence(driver, col)
            assert proxy.connections >= 2, "the gateway's TCP port was not opened again"
            ups, downs = _link_lines(logs)
            assert not ups and len(downs) == 1, ([u["reason"] for u in ups][:3], [d["reason"] for d in downs][:6])
            reason = downs[0]["reason"]
            assert f"connected to 127.0.0.1:{proxy.port} but the DAQ unit 1 did not answer within 200 ms" in reason, \
                reason
            assert "check unit id" in reason and "baud rate, wiring" in reason, reason

            proxy.swallow(FC_READ_INPUT, 0)  # the serial side is back
            _answers_once(driver, col)
        ups, downs = _link_lines(logs)
        assert len(ups) == 1 and len(downs) == 1, ([u["reason"] for u in ups], [d["reason"] for d in downs])
    finally:
        if driver is not None:
            driver.close()
        if proxy is not None:
            proxy.close()
        emu.stop()


def test_tcp_a_unit_the_gateway_cannot_reach_is_no_link_up(tmp_path, port):
    """A Modbus TCP device or gateway answers another unit id with exception 0x0B (the target
    device failed to respond): an answer from the gateway, none from the DAQ."""
    emu = Emulator(tmp_path, "--modbus-tcp", f"127.0.0.1:{port}", "--unit", "5")
    driver = create_driver("modbus-tcp", host="127.0.0.1", tcp_port=port, unit=1, poll_ms=20)
    try:
        emu.start()
        with structlog.testing.capture_logs() as logs:
            driver.start()
            col = Collector(driver)
            _watch_silence(driver, col)
        ups, downs = _link_lines(logs)
        assert not ups and len(downs) == 1, ([u["reason"] for u in ups][:3], [d["reason"] for d in downs][:6])
        reason = downs[0]["reason"]
        assert f"connected to 127.0.0.1:{port} but the DAQ unit 1 did not answer" in reason, reason
        assert "exception 11" in reason and "check unit id" in reason, reason
    finally:
        driver.close()
        emu.stop()


def test_run_with_a_silent_daq_says_what_to_check(tmp_path, port):
    """`millsense run` gives up after `--connect-timeout` (exit 69) with the driver's last reason in its one line,
    not only "no connection": here, what to check on a DAQ that does not answer its unit id."""
    import subprocess

    from tests.e2e.helpers import CMD, write_config

    emu = Emulator(tmp_path, "--modbus-tcp", f"127.0.0.1:{port}", "--unit", "5")
    cfg = write_config(tmp_path / "m.toml", machine="silent-01",
                       daq=f'transport = "modbus-tcp"\nhost = "127.0.0.1"\ntcp_port = {port}\nunit = 1')
    try:
        emu.start()
        res = subprocess.run([*CMD, "run", "--config", str(cfg), "--connect-timeout", "3"], capture_output=True,
                             text=True, timeout=120, env={**__import__("os").environ,
                                                          "XDG_STATE_HOME": str(tmp_path / "state")})
    finally:
        emu.stop()
    assert res.returncode == 69, res.stdout[-2000:] + res.stderr
    lines = [line for line in res.stderr.splitlines() if "DAQ unreachable" in line]
    assert len(lines) == 1 and "within 3 s" in lines[0] and "did not answer" in lines[0] \
        and "check unit id" in lines[0], res.stderr
    assert "Traceback" not in res.stdout + res.stderr
