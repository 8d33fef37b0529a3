"""The device as a Modbus server (register map of daq-protocol.md): TCP, or RTU on a pty.

Built on ``pymodbus.simulator.SimDevice`` (the old datastore classes are
deprecated in 3.16 and only a shim over it).  Its ``action`` hook runs before every
request, inside the server's event loop: reads of the head and the ring are
filled from the device model at that moment, and writes to coils and holding
registers are applied to the device, so the model is the only state and a read is
always consistent with the head it reports.  Pacing runs in the same loop.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time

from pymodbus import FramerType
from pymodbus.server import ModbusSerialServer, ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from millsense.drivers.emulator.pty import PtyBridge
from millsense.drivers.protocol import OUT_ALARM_LAMP, OUT_FEED_HOLD

RING_BASE = 1000
CHANNEL_TABLE = 16
HR_HEARTBEAT = 100
HR_WATCHDOG = 101
FC_COILS, FC_DISCRETE, FC_HOLDING, FC_INPUT = 1, 2, 3, 4
FC_WRITE_COIL, FC_WRITE_REG, FC_WRITE_COILS, FC_WRITE_REGS = 5, 6, 15, 16


def channel_table(descriptor) -> list[int]:
    """Registers 16 .. 16+5C-1: kind, then the 8 name bytes two per register, first byte high."""
    regs: list[int] = []
    for ch in descriptor.channels:
        name = ch.name.encode("ascii").ljust(8, b"\0")
        regs.append(int(ch.kind))
        regs.extend((name[i] << 8) | name[i + 1] for i in range(0, 8, 2))
    return regs


class ModbusDeviceServer:
    """Modbus TCP on ``host:port``, or with ``rtu_link`` Modbus RTU on a pty reachable at that path."""

    def __init__(self, device, pacer, host: str = "", port: int = 0, *, rtu_link: str | None = None,
                 unit: int = 1, duration_samples: int | None = None):
        self.device = device
        self.pacer = pacer
        self.host = host
        self.port = port
        self.rtu_link = rtu_link
        self._bridge: PtyBridge | None = None
        self.duration_samples = duration_samples
        c = device.channel_count
        self._table = channel_table(device.descriptor)
        n_input = RING_BASE + device.ring_depth * c
        simdata = (
            [SimData(0, count=2, datatype=DataType.BITS)],  # coils
            [SimData(0, count=1, datatype=DataType.BITS)],  # discrete inputs
            [SimData(0, count=HR_WATCHDOG + 1, datatype=DataType.REGISTERS)],  # holding
            [SimData(0, count=n_input, datatype=DataType.REGISTERS)],  # input
        )
        # unit id 0 = answer every id, as a single device on its own TCP port does
        self.simdevice = SimDevice(id=0, simdata=simdata, action=self._action)
        self._server: ModbusTcpServer | ModbusSerialServer | None = None
        self.stop = asyncio.Event()

    async def _action(self, fc, start, address, count, registers, values):
        now = time.monotonic()
        dev = self.device
        if fc == FC_INPUT and values is None:
            for a in range(address, address + count):
                if a >= RING_BASE:
                    break
                registers[a - start] = self._fixed_input(a)
            if address + count > RING_BASE:
                lo = max(address, RING_BASE)
                registers[lo - start : address + count - start] = dev.ring_registers(
                    lo - RING_BASE, address + count - lo
                )
        elif fc in (FC_COILS, FC_DISCRETE) and values is None:
            commanded = [bool(dev.commanded & OUT_FEED_HOLD), bool(dev.commanded & OUT_ALARM_LAMP)]
            bits = commanded if fc == FC_COILS else [dev.feed_hold]
            self._set_bits(start, address, count, registers, bits)
        elif fc in (FC_WRITE_COIL, FC_WRITE_COILS) and values is not None:
            current = [bool(dev.commanded & OUT_FEED_HOLD), bool(dev.commanded & OUT_ALARM_LAMP)]
            for i, v in enumerate(values):
                if 0 <= address + i < 2:
                    current[address + i] = bool(v)
            dev.set_outputs(int(current[0]) | (int(current[1]) << 1), now)
        elif fc in (FC_WRITE_REG, FC_WRITE_REGS) and values is not None:
            for i, v in enumerate(values):
                if address + i == HR_HEARTBEAT:
                    dev.heartbeat(int(v), now)
                elif address + i == HR_WATCHDOG:
                    dev.set_watchdog_ms(int(v), now)
            self._arm_watchdog()
        elif fc == FC_HOLDING and values is None:
            for a in range(address, address + count):
                if a == HR_HEARTBEAT:
                    registers[a - start] = dev.last_heartbeat
                elif a == HR_WATCHDOG:
                    registers[a - start] = dev.watchdog_ms
        return None

    def _fixed_input(self, a: int) -> int:
        dev = self.device
        if a == 0:
            return 1
        if a == 1:
            return dev.channel_count
        if a == 2:
            return dev.sample_rate_hz
        if a == 3:
            return dev.ring_depth
        if a == 4:
            return dev.head >> 16
        if a == 5:
            return dev.head & 0xFFFF
        if CHANNEL_TABLE <= a < CHANNEL_TABLE + len(self._table):
            return self._table[a - CHANNEL_TABLE]
        return 0

    @staticmethod
    def _set_bits(start, address, count, registers, bits) -> None:
        """Write ``bits`` (from address 0) where pymodbus' runtime will read them back.

        The runtime reads bit ``address % 16`` onwards of register ``address - start``.
        """
        from pymodbus.simulator.simutils import SimUtils

        offset = address - start
        bit_offset = address % 16
        reg_count = (bit_offset + count + 15) // 16
        flat = SimUtils.registersToBits(registers[offset : offset + reg_count])
        for i in range(count):
            a = address + i
            flat[bit_offset + i] = bool(bits[a]) if 0 <= a < len(bits) else False
        registers[offset : offset + reg_count] = SimUtils.bitsToRegisters(flat)

    def _arm_watchdog(self) -> None:
        deadline = self.device.watchdog_deadline()
        if deadline is not None:
            asyncio.get_running_loop().call_at(deadline + 0.0005, self._watchdog_check)

    def _watchdog_check(self) -> None:
        self.device.check_watchdog(time.monotonic())

    async def open(self) -> None:
        """Listen; returns once clients can connect."""
        logging.getLogger("pymodbus").setLevel(logging.ERROR)
        if self.rtu_link is not None:
            self._bridge = PtyBridge(self.rtu_link)
            self._bridge.start()
            # a pty has no line rate; the baud rate only sets pymodbus' inter-frame timing
            self._server = ModbusSerialServer(self.simdevice, framer=FramerType.RTU, port=self._bridge.inner_path,
                                              baudrate=921600)
            where = f"the pty {self._bridge.inner_path}"
        else:
            self._server = ModbusTcpServer(self.simdevice, address=(self.host, self.port))
            where = f"{self.host}:{self.port} (in use or not a local address)"
        try:
            await self._server.serve_forever(background=True)
        except RuntimeError as exc:  # pymodbus' way of saying the bind or open failed
            self._close_bridge()
            raise OSError(f"cannot serve Modbus on {where}") from exc

    def _close_bridge(self) -> None:
        if self._bridge is not None:
            self._bridge.close()
            self._bridge = None

    async def run(self) -> None:
        if self._server is None:
            await self.open()
        try:
            while not self.stop.is_set():
                n = self.pacer.due(time.monotonic(), self.duration_samples)
                if n:
                    self.device.produce(n)
                if self.duration_samples is not None and self.pacer.produced >= self.duration_samples:
                    break
                delay = max(0.0, self.pacer.next_time() - time.monotonic()) if self.pacer.realtime else 0.0
                await asyncio.sleep(delay)  # the stop flag is seen within one batch
        finally:
            with contextlib.suppress(Exception):
                await self._server.shutdown()
            self._close_bridge()
