"""The firmware's Modbus register map (docs/protocol.md, "Modbus map" and version 2's registers), over Modbus
TCP from the host build: read with request bytes built here from the Modbus spec (not pymodbus, not the
emulator), and under the real daemon (`transport = "modbus-tcp"`)."""

from __future__ import annotations

import os
import socket
import struct
import tty

import pytest

from tests.conftest import free_tcp_port
from tests.e2e.helpers import Procs, Subscriber, tcp, wait_for, write_config
from tests.e2e.truth import Timebase, match_estimates, steady_torque_misses
from tests.firmware import frames
from tests.firmware.conftest import ramp_counts
from tests.firmware.device import Firmware

RING = 1024
C = 8


class ModbusTcp:
    """Requests as bytes: MBAP (transaction, protocol 0, length, unit) and a PDU; the answer's PDU back."""

    def __init__(self, port: int) -> None:
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=10)
        self.tid = 0

    def pdu(self, pdu: bytes, unit: int = 1) -> bytes:
        self.tid = (self.tid + 1) & 0xFFFF
        self.sock.sendall(struct.pack(">HHHB", self.tid, 0, len(pdu) + 1, unit) + pdu)
        head = self._exactly(7)
        tid, proto, length, unit_back = struct.unpack(">HHHB", head)
        assert (tid, proto, unit_back) == (self.tid, 0, unit), head
        return self._exactly(length - 1)

    def _exactly(self, n: int) -> bytes:
        out = b""
        while len(out) < n:
            chunk = self.sock.recv(n - len(out))
            assert chunk, "the firmware closed the connection"
            out += chunk
        return out

    def read(self, fc: int, address: int, count: int, unit: int = 1) -> list[int] | int:
        """Registers (fc 3, 4) or bits (fc 1, 2); an exception's code as an int."""
        r = self.pdu(struct.pack(">BHH", fc, address, count), unit)
        if r[0] == fc | 0x80:
            return r[1]
        assert r[0] == fc and r[1] == len(r) - 2, r
        if fc in (3, 4):
            return list(struct.unpack(f">{count}H", r[2:]))
        return [(r[2 + i // 8] >> (i % 8)) & 1 for i in range(count)]

    def write_register(self, address: int, value: int) -> int | None:
        r = self.pdu(struct.pack(">BHH", 6, address, value))
        return r[1] if r[0] == 0x86 else None

    def write_coils(self, bits: list[int]) -> int | None:
        packed = sum(b << i for i, b in enumerate(bits))
        r = self.pdu(struct.pack(">BHHBB", 15, 0, len(bits), 1, packed))
        return r[1] if r[0] == 0x8F else None

    def close(self) -> None:
        self.sock.close()


def _s32(regs: list[int], i: int) -> int:
    return (regs[i] << 16) | regs[i + 1]


def test_the_register_map_and_its_exceptions(any_build, ramp_capture, tmp_path, port):
    capture_descriptor = next(f for f in frames.Decoder().feed(ramp_capture.read_bytes()) if f.type == 0x02)
    with Firmware(any_build / "msfw-host", tmp_path, ramp_capture, port, "--ring", str(RING),
                  transport="--modbus-tcp") as fw:
        mb = ModbusTcp(port)
        regs = mb.read(4, 0, 16)
        assert regs[:4] == [2, C, 1000, RING] and regs[6] == 1000 and regs[7] == 0x01, regs
        # the channel table: kind, then the name's 8 bytes two a register, the first byte high
        table = mb.read(4, 16, 5 * C)
        names = [(table[5 * i], b"".join(w.to_bytes(2, "big") for w in table[5 * i + 1:5 * i + 5])
                  .rstrip(b"\0").decode()) for i in range(C)]
        assert names == capture_descriptor.descriptor()["channels"]
        # the ring: samples H-D < k < H at 1000 + (k mod D)*C + c, read whole, H read again after
        wait_for(lambda: _s32(mb.read(4, 0, 16), 4) > RING, 20.0, "a full ring")
        head = _s32(mb.read(4, 0, 16), 4)
        ks = list(range(head - RING + 400, head - RING + 400 + 90))
        counts = []
        for a in range(0, len(ks), 15):       # at most 125 registers a read: 15 samples of 8
            counts += mb.read(4, 1000 + (ks[a] % RING) * C, 15 * C)
        assert _s32(mb.read(4, 0, 16), 4) - ks[0] < RING, "not overwritten while read"
        got = [tuple((v ^ 0x8000) - 0x8000 for v in counts[i * C:(i + 1) * C]) for i in range(len(ks))]
        assert got == [ramp_counts(k % 3000) for k in ks]
        # exceptions: outside the map 0x02, a quantity of 0 or over 125 registers 0x03, another unit 0x0B
        assert mb.read(4, 16 + 5 * C, 1) == 0x02 and mb.read(4, 1000 + RING * C, 1) == 0x02
        assert mb.read(4, 999, 2) == 0x02 and mb.read(3, 99, 1) == 0x02 and mb.read(1, 2, 1) == 0x02
        assert mb.read(4, 0, 0) == 0x03 and mb.read(4, 1000, 126) == 0x03 and mb.read(2, 0, 2001) == 0x03
        assert mb.read(4, 0, 1, unit=2) == 0x0B and mb.pdu(b"\x2b\x0e\x01\x00")[:2] == b"\xab\x01"
        # the override: holding 102, over 2000 refused with 0x03; input 6 the one applied
        assert mb.write_register(102, 2001) == 0x03 and mb.read(4, 6, 1) == [1000]
        assert mb.write_register(102, 1500) is None and mb.read(4, 6, 1) == [1500] and mb.read(3, 102, 1) == [1500]
        # coils: what the host commands; discrete input 0 the feed hold active, 1 the watchdog tripped
        assert mb.write_coils([1, 1]) is None and mb.read(1, 0, 2) == [1, 1] and mb.read(2, 0, 2) == [1, 0]
        assert mb.write_coils([0, 0]) is None and mb.read(2, 0, 2) == [0, 0]
        # the watchdog: period in holding 101, heartbeat in holding 100
        assert mb.write_register(101, 200) is None and mb.write_register(100, 1) is None
        fw.wait_event("watchdog")
        assert mb.read(2, 0, 2) == [1, 1] and mb.read(1, 0, 1) == [0] and mb.read(4, 6, 1) == [1000]
        assert mb.write_register(102, 1200) == 0x03, "no speeding up while the watchdog holds"
        # a heartbeat, then coil 0 = 0 clears the hold and the watchdog flag together
        assert mb.write_register(100, 2) is None and mb.write_coils([0, 0]) is None
        assert mb.read(2, 0, 2) == [0, 0] and mb.read(3, 100, 2) == [2, 200]
        mb.close()
        assert fw.stop() == 0, fw.stderr()


WATCHDOG_MS = 1000  # the daemons of the other live tests keep 1000: a loaded box delays a heartbeat by 300 ms
SKIP = 4000        # the capture from 4 s on: the cut, steady from 5 s


@pytest.mark.serial
@pytest.mark.parametrize("transport", ["modbus-tcp", "modbus-rtu"])
def test_the_daemon_over_modbus_estimates_and_a_killed_one_is_held_within_its_watchdog_time(
        plain_build, step_capture, tmp_path, transport):
    cap, truth = step_capture
    daq_port, z_port = free_tcp_port(), free_tcp_port()
    link = tmp_path / "rtu-link"
    if transport == "modbus-tcp":
        daq = f'transport = "modbus-tcp"\nhost = "127.0.0.1"\ntcp_port = {daq_port}\nunit = 1\npoll_ms = 20'
        served = ("--modbus-tcp", f"127.0.0.1:{daq_port}")
    else:
        daq = f'transport = "modbus-rtu"\nport = "{link}"\nbaudrate = 921600\nunit = 1\npoll_ms = 20'
        served = ("--modbus-rtu", str(link))
    cfg = write_config(tmp_path / "d.toml", machine="fw-mb", daq=daq, zenoh_listen=[tcp(z_port)],
                       interlock=f"enabled = true\nheartbeat_ms = 50\nwatchdog_ms = {WATCHDOG_MS}")
    with Firmware(plain_build / "msfw-host", tmp_path, cap, daq_port, "--skip", str(SKIP), "--ring", "2048",
                  transport=served[0], address=served[1]) as fw, Procs(tmp_path) as procs:
        daemon = procs.start("daemon", ["run", "--config", str(cfg)])
        sub = Subscriber([tcp(z_port)], "fw-mb")
        try:
            wait_for(lambda: len(sub.get("estimate")) >= 40 or daemon.poll() is not None, 60.0, "40 estimates")
            assert daemon.poll() is None, procs.text("daemon")
            status = sub.query("millsense/fw-mb/status")
        finally:
            live = sub.get("estimate")
            sub.close()
        # the daemon wrote the period (the firmware started with none) and heartbeats
        assert fw.events("watchdog_period")[-1]["watchdog_ms"] == WATCHDOG_MS
        assert not fw.events("watchdog")
        daemon.kill()
        daemon.wait(5)
        trip = fw.wait_event("watchdog")
        late_s = trip["mono"] - trip["last_heartbeat_mono"]
        assert WATCHDOG_MS / 1000 - 0.001 <= late_s <= WATCHDOG_MS / 1000 + 0.05, f"{late_s * 1e3:.1f} ms"
        held = fw.wait_event("outputs", lambda e: e["cause"] == "watchdog")
        assert held["feed_hold"] and held["watchdog"]
        start = fw.events("start")[0]
        assert fw.stop() == 0, fw.stderr()

    assert status and status[0]["daq_link"] == "up" and status[0]["lost_samples"] == 0, status
    revs = [e["rev"] for e in live]
    assert revs == list(range(revs[0], revs[0] + len(revs)))
    tb = Timebase(float(start["mono"]), float(start["wall"]), int(start["capture_first"]))
    matched = match_estimates(live, truth, tb)
    steady, bad = steady_torque_misses(matched, truth)
    assert len(steady) >= 15, f"only {len(steady)} steady cutting revolutions"
    assert not bad, bad[:8]


def _rtu(frame: bytes) -> bytes:
    return frame + frames.crc16(frame).to_bytes(2, "little")


def test_modbus_rtu_answers_its_unit_and_is_silent_to_others_and_to_bad_crcs(any_build, ramp_capture, tmp_path):
    link = tmp_path / "rtu-link"
    with Firmware(any_build / "msfw-host", tmp_path, ramp_capture, 0, "--unit", "7", transport="--modbus-rtu",
                  address=str(link)) as fw:
        fd = os.open(link, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        tty.setraw(fd)
        read_inputs = struct.pack(">BHH", 4, 0, 4)
        bad = bytearray(_rtu(b"\x07" + read_inputs))
        bad[-1] ^= 0x55
        # another unit's request, a damaged one for ours, then a good one: one answer, to the good one
        os.write(fd, _rtu(b"\x08" + read_inputs) + bytes(bad) + _rtu(b"\x07" + read_inputs))
        expected = _rtu(b"\x07\x04\x08" + struct.pack(">4H", 2, 8, 1000, 1024))
        got = bytearray()

        def answered() -> bool:
            try:
                got.extend(os.read(fd, 4096))
            except BlockingIOError:
                pass
            return len(got) >= len(expected)

        wait_for(answered, 20.0, "the RTU answer")
        # then a write whose answer is its echo: the bytes so far are exactly one answer, nothing for the others
        os.write(fd, _rtu(b"\x07" + struct.pack(">BHH", 6, 102, 900)))
        wait_for(lambda: answered() and len(got) >= len(expected) + 8, 20.0, "the write's echo")
        assert bytes(got) == expected + _rtu(b"\x07" + struct.pack(">BHH", 6, 102, 900))
        assert fw.wait_event("feed_override", lambda e: e["cause"] == "command")["value"] == 900
        os.close(fd)
        assert fw.stop() == 0, fw.stderr()
