"""Protocol version 2 end to end: the real driver against the real emulator subprocess
(`millsense sim --protocol 2`) on each transport; and the Modbus server's answers to
requests outside its unit id, its map and its quantities, read with the real pymodbus client."""

from __future__ import annotations

import socket
import struct
import time

import pytest
import structlog

from millsense.drivers import create_driver
from millsense.drivers.base import LinkEvent, SampleBlock
from millsense.drivers.protocol import Context, Descriptor, Status
from tests.drivers.emulator_proc import Emulator
from tests.drivers.test_contract import HEARTBEAT_S, check_every_sample_once, open_transport

# the CNC applies the override at once here (its lag and rate limit: test_cnc_override.py), so the
# 200 ms watchdog cannot take it back to 100 % before it is reported
CNC_ARGS = ("--protocol", "2", "--program", "70000", "--tool", "123456", "--operation", "7",
            "--cnc-hold-lag-ms", "30", "--cnc-override-lag-ms", "0", "--cnc-override-rate-pct-s", "0")


class Events:
    """Every event of a driver, in arrival order, drained in the test thread."""

    def __init__(self, driver) -> None:
        self.driver = driver
        self.items: list = []

    def pump(self, seconds: float, until, heartbeat_s: float | None = None) -> bool:
        """Drain events for up to `seconds` or until `until()`; with `heartbeat_s`, keep the heartbeat going
        meanwhile (a wait for a STATUS must not race the device's 200 ms watchdog on a loaded box)."""
        deadline = time.monotonic() + seconds
        next_hb = time.monotonic()
        while time.monotonic() < deadline:
            if heartbeat_s is not None and time.monotonic() >= next_hb:
                self.driver.heartbeat()
                next_hb = time.monotonic() + heartbeat_s
            ev = self.driver.get(timeout=0.02)
            if ev is not None:
                self.items.append(ev)
            if until():
                return True
        return False

    def of(self, kind) -> list:
        return [e for e in self.items if isinstance(e, kind)]

    def first(self, pred) -> int | None:
        return next((i for i, e in enumerate(self.items) if pred(e)), None)


@pytest.mark.parametrize("transport", ["pty", "tcp", "modbus-tcp"])
def test_version_2_context_override_and_cnc_feed_held(transport, tmp_path, port):
    emu, make = open_transport(transport, tmp_path, port, *CNC_ARGS)
    driver = None
    try:
        emu.start()
        driver = make()
        if transport.startswith("modbus"):
            driver.set_watchdog_ms(200)
        driver.start()
        assert driver.wait_connected(10.0)
        ev = Events(driver)
        assert ev.pump(5.0, lambda: ev.of(Context) and any(s.feed_override is not None for s in ev.of(Status)))
        d = ev.of(Descriptor)[-1]
        assert d.protocol_version == 2 and d.capabilities == 0b11
        ctx = ev.of(Context)[0]
        assert (ctx.program, ctx.tool, ctx.operation) == (70000, 123456, 7)
        assert ctx.cycle and ctx.monitor and not ctx.feed_held
        assert ev.of(Status)[-1].feed_override == 1000

        # feed override: COMMAND 0x04 / holding register 102, reported in STATUS / input register 6. The heartbeat
        # goes on until the watchdog's step: before, a poll later than the 200 ms watchdog found 100 % again
        driver.heartbeat()
        assert driver.set_feed_override(850)
        assert ev.pump(3.0, lambda: any(s.feed_override == 850 for s in ev.of(Status)), HEARTBEAT_S), \
            "override not reported"

        # feed hold: the DAQ confirms, then the CNC reports it holds the feed
        n_before = len(ev.items)
        assert driver.set_outputs(True)
        assert ev.pump(3.0, lambda: any(c.feed_held for c in ev.of(Context))
                       and any(s.feed_hold for s in ev.of(Status)), HEARTBEAT_S), \
            "the DAQ or the CNC never reported feed held"
        held = ev.first(lambda e: isinstance(e, Context) and e.feed_held)
        assert held >= n_before  # arrived after the command (Modbus polls outputs at 10 Hz, so no order vs STATUS)
        blocks = [e for e in ev.items[held:] if isinstance(e, SampleBlock)]
        held_ctx = ev.items[held]
        assert held_ctx.index >= ctx.index  # from the sample index at which it changed
        # the emulator's log: the CNC changed after the output did
        out_t = next(e["mono"] for e in emu.events("outputs") if e["feed_hold"])
        cnc = emu.events("cnc_feed_held")
        assert cnc and cnc[0]["feed_held"] and cnc[0]["mono"] > out_t
        assert [e["feed_override"] for e in emu.events("feed_override")] == [850]

        # released: the CNC follows
        assert driver.set_outputs(False)
        assert ev.pump(3.0, lambda: not driver.last_context.feed_held and ev.of(Context)[-1].feed_held is False,
                       HEARTBEAT_S)

        # the heartbeat stops: the watchdog holds the feed and returns the override to 100.0 %
        assert ev.pump(3.0, lambda: any(s.watchdog_tripped and s.feed_override == 1000 for s in ev.of(Status))), \
            "watchdog trip did not return the override to 100 %"
        assert ev.pump(3.0, lambda: ev.of(Context)[-1].feed_held)
        causes = [e["cause"] for e in emu.events("feed_override")]
        assert causes == ["command", "watchdog"]
        assert not any(isinstance(e, LinkEvent) and not e.up for e in ev.items)
        if blocks:
            check_every_sample_once([b for b in ev.items if isinstance(b, SampleBlock)][-5:])
    finally:
        if driver is not None:
            driver.close()
        emu.stop()


@pytest.mark.parametrize("transport", ["tcp", "modbus-tcp"])
def test_a_version_1_daq_has_no_feed_override_and_says_so_once(transport, tmp_path, port):
    emu, make = open_transport(transport, tmp_path, port)
    driver = make()
    try:
        emu.start()
        driver.start()
        assert driver.wait_connected(10.0)
        ev = Events(driver)
        assert ev.pump(5.0, lambda: driver.descriptor is not None and ev.of(SampleBlock))
        with structlog.testing.capture_logs() as logs:
            assert not driver.set_feed_override(900)
            assert not driver.set_feed_override(950)
        said = [e for e in logs if e["event"] == "daq.no_feed_override"]
        assert len(said) == 1 and said[0]["protocol_version"] == 1
        ev.pump(0.5, lambda: False)
        assert driver.descriptor.protocol_version == 1 and driver.last_context is None
        assert not ev.of(Context) and all(s.feed_override is None for s in ev.of(Status))
        assert driver.set_outputs(True)  # the rest works as before
        assert ev.pump(3.0, lambda: driver.last_status is not None and driver.last_status.feed_hold)
        assert emu.events("feed_override") == []
    finally:
        driver.close()
        emu.stop()


# ------------------------------------------------------------- Modbus server answers


def _raw_read(sock: socket.socket, unit: int, fc: int, address: int, count: int, tid: int) -> bytes | None:
    """One Modbus TCP request by hand (the pymodbus client refuses to send a quantity over the limit)."""
    pdu = struct.pack(">BHH", fc, address, count)
    sock.sendall(struct.pack(">HHHB", tid, 0, len(pdu) + 1, unit) + pdu)
    try:
        reply = sock.recv(512)
    except TimeoutError:
        return None
    assert struct.unpack_from(">H", reply)[0] == tid
    return reply[7:]


@pytest.mark.parametrize("protocol", ["1", "2"])
def test_modbus_tcp_answers_its_unit_its_map_and_its_quantities(protocol, tmp_path, port):
    from pymodbus.client import ModbusTcpClient

    emu = Emulator(tmp_path, "--modbus-tcp", f"127.0.0.1:{port}", "--ring-depth", "100", "--unit", "3",
                   "--protocol", protocol)
    client = ModbusTcpClient("127.0.0.1", port=port, timeout=2, retries=0)
    try:
        emu.start()
        assert client.connect()
        assert client.read_input_registers(0, count=6, device_id=3).registers[0] == int(protocol)
        other = client.read_input_registers(0, count=6, device_id=1)
        assert other.isError() and other.exception_code == 0x0B  # gateway target failed to respond
        # outside the map: gaps, past the ring, coils and inputs past 1, holding below 100
        for rr in (
            client.read_input_registers(6 if protocol == "1" else 999, count=1, device_id=3),  # 6-15: version 2
            client.read_input_registers(16 + 5 * 8, count=1, device_id=3),
            client.read_input_registers(1000 + 100 * 8 - 1, count=2, device_id=3),
            client.read_coils(0, count=3, device_id=3),
            client.read_discrete_inputs(1, count=2, device_id=3),
            client.read_holding_registers(99, count=2, device_id=3),
            client.write_register(103 if protocol == "2" else 102, 1, device_id=3),
        ):
            assert rr.isError() and rr.exception_code == 0x02, rr
        assert client.read_holding_registers(100, count=2, device_id=3).registers == [0, 0]
        # both coils and both discrete inputs are in the map
        assert not client.write_coils(0, [False, True], device_id=3).isError()
        assert client.read_coils(0, count=2, device_id=3).bits[:2] == [False, True]
        assert client.read_discrete_inputs(0, count=2, device_id=3).bits[:2] == [False, False]
        if protocol == "2":
            rr = client.write_register(102, 2001, device_id=3)  # over 200.0 %
            assert rr.isError() and rr.exception_code == 0x03
            assert not client.write_register(102, 1234, device_id=3).isError()
            regs = client.read_input_registers(0, count=16, device_id=3).registers
            assert regs[7] == 0b11 and regs[13] == 0b0011
            assert client.read_holding_registers(102, count=1, device_id=3).registers == [1234]
            # input register 6 is the override applied: the CNC gets there through its lag
            deadline = time.monotonic() + 5.0
            while client.read_input_registers(6, count=1, device_id=3).registers != [1234]:
                assert time.monotonic() < deadline, "input register 6 never reached the commanded override"
                time.sleep(0.01)
        # a quantity over 125 registers or 2000 bits: exception 0x03, by hand
        with socket.create_connection(("127.0.0.1", port), timeout=2) as sock:
            assert _raw_read(sock, 3, 4, 1000, 126, 1) == bytes([0x84, 0x03])
            assert _raw_read(sock, 3, 3, 100, 0, 2) == bytes([0x83, 0x03])
            assert _raw_read(sock, 3, 1, 0, 2001, 3) == bytes([0x81, 0x03])
            assert _raw_read(sock, 3, 2, 0, 2001, 4) == bytes([0x82, 0x03])
            assert _raw_read(sock, 9, 4, 1000, 126, 5) == bytes([0x84, 0x0B])  # the unit is checked first
            assert _raw_read(sock, 3, 4, 1000, 125, 6)[:2] == bytes([0x04, 250])
    finally:
        client.close()
        emu.stop()


def test_modbus_rtu_is_silent_to_other_units(tmp_path):
    from pymodbus import FramerType
    from pymodbus.client import ModbusSerialClient

    link = str(tmp_path / "rtu")
    emu = Emulator(tmp_path, "--modbus-rtu", link, "--unit", "5", "--protocol", "2")
    client = ModbusSerialClient(link, framer=FramerType.RTU, baudrate=921600, timeout=0.3, retries=0)
    try:
        emu.start()
        assert client.connect()
        assert client.read_input_registers(0, count=16, device_id=5).registers[0] == 2
        from pymodbus.exceptions import ModbusIOException

        try:  # another unit on the bus: no answer at all, neither data nor an exception
            rr = client.read_input_registers(0, count=6, device_id=6)
        except ModbusIOException:
            rr = None
        assert rr is None, f"unit 6 got an answer: {rr}"
        rr = client.read_input_registers(900, count=1, device_id=5)
        assert rr.isError() and rr.exception_code == 0x02
        # still answering its own unit after the silence
        assert client.read_input_registers(0, count=1, device_id=5).registers == [2]
    finally:
        client.close()
        emu.stop()
