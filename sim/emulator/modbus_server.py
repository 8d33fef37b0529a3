"""The device as a Modbus server (register map of daq-protocol.md): TCP, or RTU on a pty.

Built on ``pymodbus.simulator.SimDevice`` (the old datastore classes are
deprecated in 3.16 and only a shim over it).  Its ``action`` hook runs before every
request, inside the server's event loop: reads of the head and the ring are
filled from the device model at that moment, and writes to coils and holding
registers are applied to the device, so the model is the only state and a read is
always consistent with the head it reports.  Pacing runs in the same loop.

As daq-protocol.md asks of a device: it answers only its own unit id (over RTU
another unit's request gets silence, over TCP exception 0x0B), a read or write
outside the map (gaps included) gets exception 0x02, and a quantity of 0 or over
125 registers / 2000 bits gets 0x03. pymodbus' own request decoder rejects such
a quantity as a garbled frame (exception 0x01 with function code 0), so lenient
read requests are registered in its place; the unit id is checked in a thin
layer over pymodbus' simulator store.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import struct
import time

from pymodbus import FramerType
from pymodbus.constants import ExcCodes
from pymodbus.exceptions import NoSuchIdException
from pymodbus.pdu import ExceptionResponse
from pymodbus.pdu.bit_message import ReadCoilsRequest, ReadDiscreteInputsRequest
from pymodbus.pdu.register_message import ReadHoldingRegistersRequest, ReadInputRegistersRequest
from pymodbus.server import ModbusSerialServer, ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice
from pymodbus.simulator.simcore import SimCore

from millsense.sim.emulator.pacing import CncTimer, first_of
from millsense.sim.emulator.pty import PtyBridge
from millsense.drivers.protocol import FLAG_WATCHDOG, OUT_ALARM_LAMP, OUT_FEED_HOLD

RING_BASE = 1000
CHANNEL_TABLE = 16
HR_HEARTBEAT = 100
HR_WATCHDOG = 101
HR_FEED_OVERRIDE = 102  # version 2
FC_COILS, FC_DISCRETE, FC_HOLDING, FC_INPUT = 1, 2, 3, 4
FC_WRITE_COIL, FC_WRITE_REG, FC_WRITE_COILS, FC_WRITE_REGS = 5, 6, 15, 16
MAX_READ_REGS = 125
MAX_READ_BITS = 2000


class _UnitStore(SimCore):
    """pymodbus' simulator store, answering one unit id and the register map only.

    Another id raises NoSuchIdException, which pymodbus' request handler turns into
    exception 0x0B (TCP) or, with ``ignore_missing_devices``, into silence (RTU).
    The map is checked here, where the quantity is still in bits for coils and
    discrete inputs (the simulator's action hook sees 16-bit words).
    """

    def __init__(self, device: SimDevice, unit: int, in_map) -> None:
        super().__init__(device)
        self.unit = unit
        self.in_map = in_map

    def check_unit(self, device_id: int) -> None:
        if device_id != self.unit:
            raise NoSuchIdException(f"unit {device_id} is not this device ({self.unit})")

    async def async_getValues(self, device_id, func_code, address, count=1):
        self.check_unit(device_id)
        if not self.in_map(func_code, address, count):
            return ExcCodes.ILLEGAL_ADDRESS
        return await super().async_getValues(device_id, func_code, address, count)

    async def async_setValues(self, device_id, func_code, address, values):
        self.check_unit(device_id)
        if not self.in_map(func_code, address, len(values) if isinstance(values, list) else 1):
            return ExcCodes.ILLEGAL_ADDRESS
        return await super().async_setValues(device_id, func_code, address, values)


def _lenient_read(base: type, max_count: int) -> type:
    """A read request that decodes any quantity and answers a bad one with exception 0x03."""

    class LenientRead(base):
        def decode(self, data: bytes) -> None:
            self.address, self.count = struct.unpack(">HH", data[:4])

        async def datastore_update(self, context, device_id: int):
            check = getattr(context, "check_unit", None)
            if check is not None:
                check(device_id)  # another unit: silence or 0x0B, never 0x03
            if not 1 <= self.count <= max_count:
                return ExceptionResponse(self.function_code, ExcCodes.ILLEGAL_VALUE)
            return await super().datastore_update(context, device_id)

    LenientRead.__name__ = f"Lenient{base.__name__}"
    return LenientRead


LENIENT_READS = [
    _lenient_read(ReadCoilsRequest, MAX_READ_BITS),
    _lenient_read(ReadDiscreteInputsRequest, MAX_READ_BITS),
    _lenient_read(ReadHoldingRegistersRequest, MAX_READ_REGS),
    _lenient_read(ReadInputRegistersRequest, MAX_READ_REGS),
]


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
                 unit: int = 1, duration_samples: int | None = None, on_first_client=None):
        if not 1 <= unit <= 247:
            raise ValueError(f"Modbus unit id {unit} outside 1..247")
        self.device = device
        self.pacer = pacer
        self.host = host
        self.port = port
        self.rtu_link = rtu_link
        self.unit = unit
        self._bridge: PtyBridge | None = None
        self.duration_samples = duration_samples
        c = device.channel_count
        self._table = channel_table(device.descriptor)
        v2 = device.protocol >= 2
        # the register map of daq-protocol.md, as [first, end) ranges per function
        self._fixed_end = 16 if v2 else 6  # input registers 0-5, and 6-15 from version 2 on
        self._input_ranges = (
            (0, self._fixed_end),
            (CHANNEL_TABLE, CHANNEL_TABLE + len(self._table)),
            (RING_BASE, RING_BASE + device.ring_depth * c),
        )
        self._holding_range = (HR_HEARTBEAT, (HR_FEED_OVERRIDE if v2 else HR_WATCHDOG) + 1)
        n_input = RING_BASE + device.ring_depth * c
        simdata = (
            [SimData(0, count=16, datatype=DataType.BITS)],  # coils (0, 1 in the map; checked in _action)
            [SimData(0, count=16, datatype=DataType.BITS)],  # discrete inputs (0, 1)
            [SimData(0, count=HR_FEED_OVERRIDE + 1, datatype=DataType.REGISTERS)],  # holding
            [SimData(0, count=n_input, datatype=DataType.REGISTERS)],  # input
        )
        self.simdevice = SimDevice(id=unit, simdata=simdata, action=self._action)
        self._server: ModbusTcpServer | ModbusSerialServer | None = None
        self._cnc = CncTimer(device)  # applies the CNC's changes when due, so the status log has their times
        self.stop = asyncio.Event()
        # --start-on-connect: the first sample waits for the first request (a TCP connect alone reads nothing;
        # an RTU link has no connect), then `on_first_client(now)`
        self._on_first_client = on_first_client
        self._first_request = asyncio.Event()

    def _in_map(self, fc: int, address: int, count: int) -> bool:
        end = address + count
        if fc in (FC_COILS, FC_DISCRETE, FC_WRITE_COIL, FC_WRITE_COILS):
            return 0 <= address and end <= 2
        if fc in (FC_HOLDING, FC_WRITE_REG, FC_WRITE_REGS):
            lo, hi = self._holding_range
            return lo <= address and end <= hi
        if fc == FC_INPUT:
            return any(lo <= address and end <= hi for lo, hi in self._input_ranges)
        return False

    async def _action(self, fc, start, address, count, registers, values):
        now = time.monotonic()
        dev = self.device
        if self._on_first_client is not None and not self._first_request.is_set():
            # sample 0 is due now: this request already reads the head at the run's first index
            self._first_request.set()
            self.pacer.restart(now)
            self._on_first_client(now)
        if fc == FC_INPUT and values is None:
            if address < self._fixed_end:
                dev.update_cnc(now)  # the CNC's flags as of this moment
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
            bits = commanded if fc == FC_COILS else [dev.feed_hold, bool(dev.flags & FLAG_WATCHDOG)]
            self._set_bits(start, address, count, registers, bits)
        elif fc in (FC_WRITE_COIL, FC_WRITE_COILS) and values is not None:
            current = [bool(dev.commanded & OUT_FEED_HOLD), bool(dev.commanded & OUT_ALARM_LAMP)]
            for i, v in enumerate(values):
                if 0 <= address + i < 2:
                    current[address + i] = bool(v)
            dev.set_outputs(int(current[0]) | (int(current[1]) << 1), now)
            self._cnc.arm()
            self._arm_watchdog()  # a clear re-arms it: the deadline counts from the last heartbeat, none may follow
        elif fc in (FC_WRITE_REG, FC_WRITE_REGS) and values is not None:
            if HR_FEED_OVERRIDE in range(address, address + len(values)):
                override = int(values[HR_FEED_OVERRIDE - address])
                if not dev.set_feed_override(override, now):
                    return ExcCodes.ILLEGAL_VALUE  # outside 0..2000: nothing of this write is applied
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
                elif a == HR_FEED_OVERRIDE:
                    # what the host commanded; the device resets it to 1000 on a watchdog trip
                    registers[a - start] = dev.feed_override_commanded
        return None

    def _fixed_input(self, a: int) -> int:
        dev = self.device
        if a == 0:
            return dev.protocol
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
        if a < 16:
            return self._v2_input(a)
        if CHANNEL_TABLE <= a < CHANNEL_TABLE + len(self._table):
            return self._table[a - CHANNEL_TABLE]
        return 0

    def _v2_input(self, a: int) -> int:
        """Input registers 6-15 (version 2): override applied, capabilities, the CNC's context."""
        dev = self.device
        if a == 6:
            return dev.feed_override  # applied: the CNC's override after its lag, not the commanded one
        if a == 7:
            return dev.capabilities
        words = {
            8: dev.program >> 16, 9: dev.program & 0xFFFF,
            10: dev.tool >> 16, 11: dev.tool & 0xFFFF,
            12: dev.operation,
            13: dev.cnc_flags,
            14: dev.context_index >> 16, 15: dev.context_index & 0xFFFF,
        }
        return words[a]

    @staticmethod
    def _set_bits(start, address, count, registers, bits) -> None:
        """Write ``bits`` (from address 0) where pymodbus' runtime will read them back.

        The runtime reads bit ``address % 16`` onwards of register ``address - start``.
        ``count`` is what the runtime passes to the action hook: 16-bit words, not bits,
        so every bit of those words is filled.
        """
        from pymodbus.simulator.simutils import SimUtils

        offset = address - start
        bit_offset = address % 16
        reg_count = (bit_offset + count + 15) // 16
        flat = SimUtils.registersToBits(registers[offset : offset + reg_count])
        for k in range(len(flat)):
            a = address - bit_offset + k
            flat[k] = bool(bits[a]) if 0 <= a < len(bits) else False
        registers[offset : offset + reg_count] = SimUtils.bitsToRegisters(flat)

    def _arm_watchdog(self) -> None:
        deadline = self.device.watchdog_deadline()
        if deadline is not None:
            asyncio.get_running_loop().call_at(deadline + 0.0005, self._watchdog_check)

    def _watchdog_check(self) -> None:
        if self.device.check_watchdog(time.monotonic()):
            self._cnc.arm()

    async def open(self) -> None:
        """Listen; returns once clients can connect."""
        logging.getLogger("pymodbus").setLevel(logging.ERROR)
        if self.rtu_link is not None:
            self._bridge = PtyBridge(self.rtu_link)
            self._bridge.start()
            # a pty has no line rate; the baud rate only sets pymodbus' inter-frame timing
            # another unit's request on the bus is not ours to answer: silence
            self._server = ModbusSerialServer(self.simdevice, framer=FramerType.RTU, port=self._bridge.inner_path,
                                              baudrate=921600, ignore_missing_devices=True,
                                              custom_pdu=LENIENT_READS)
            where = f"the pty {self._bridge.inner_path}"
        else:
            self._server = ModbusTcpServer(self.simdevice, address=(self.host, self.port), custom_pdu=LENIENT_READS)
            where = f"{self.host}:{self.port} (in use or not a local address)"
        self._server.context = _UnitStore(self.simdevice, self.unit, self._in_map)
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
            if self._on_first_client is not None:
                await first_of(self._first_request, self.stop)
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
