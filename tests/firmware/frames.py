"""The wire, as docs/protocol.md writes it: written here from the doc alone, not from drivers/protocol.py,
so the firmware is checked against the document and not against the other implementation."""

from __future__ import annotations

import struct
from dataclasses import dataclass


def crc16(data: bytes) -> int:
    """CRC-16/MODBUS: reflected polynomial 0xA001, initial 0xFFFF."""
    crc = 0xFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc


def frame(ftype: int, payload: bytes) -> bytes:
    """A5 5A, type, uint16 length, payload, then the CRC over type, length and payload (all little-endian)."""
    body = bytes([ftype]) + struct.pack("<H", len(payload)) + payload
    return b"\xa5\x5a" + body + struct.pack("<H", crc16(body))


def set_outputs(bits: int) -> bytes:
    return frame(0x10, bytes([0x01, bits]))


def heartbeat(counter: int) -> bytes:
    return frame(0x10, struct.pack("<BH", 0x02, counter))


def send_descriptor() -> bytes:
    return frame(0x10, bytes([0x03]))


def set_override(tenths: int) -> bytes:
    return frame(0x10, struct.pack("<BH", 0x04, tenths))


@dataclass
class Frame:
    type: int
    payload: bytes

    def samples(self) -> tuple[int, int, int, list[tuple[int, ...]]]:
        """SAMPLES: (first index, C, S, S sample tuples of C int16)."""
        first, c, s = struct.unpack_from("<IBB", self.payload)
        counts = struct.unpack_from(f"<{c * s}h", self.payload, 6)
        return first, c, s, [counts[k * c:(k + 1) * c] for k in range(s)]

    def descriptor(self) -> dict:
        version, rate, c = struct.unpack_from("<BHB", self.payload)
        channels = []
        for k in range(c):
            kind = self.payload[4 + 9 * k]
            name = self.payload[5 + 9 * k:13 + 9 * k].rstrip(b"\0").decode("ascii")
            channels.append((kind, name))
        caps = self.payload[4 + 9 * c] if version >= 2 else 0
        return {"version": version, "rate": rate, "channels": channels, "capabilities": caps,
                "length": len(self.payload)}

    def status(self) -> dict:
        outputs, flags, heartbeat = struct.unpack_from("<BBH", self.payload)
        out = {"outputs": outputs, "flags": flags, "heartbeat": heartbeat, "length": len(self.payload)}
        if len(self.payload) >= 6:
            out["override"] = struct.unpack_from("<H", self.payload, 4)[0]
        return out

    def context(self) -> dict:
        index, program, tool, operation, flags = struct.unpack("<IIIHB", self.payload[:15])
        return {"index": index, "program": program, "tool": tool, "operation": operation, "flags": flags}


class Decoder:
    """Board-to-host frames out of a byte stream. A bad CRC or an impossible length drops one byte and the
    hunt for A5 5A goes on (the firmware's stream should never need it: `bad` counts it)."""

    def __init__(self) -> None:
        self.buf = bytearray()
        self.bad = 0

    def feed(self, data: bytes) -> list[Frame]:
        self.buf += data
        out = []
        while True:
            i = self.buf.find(b"\xa5\x5a")
            if i < 0:
                del self.buf[: max(0, len(self.buf) - 1)]
                return out
            del self.buf[:i]
            if len(self.buf) < 5:
                return out
            ftype, length = self.buf[2], struct.unpack_from("<H", self.buf, 3)[0]
            if length > 4096 or ftype not in (1, 2, 3, 4):
                self.bad += 1
                del self.buf[:1]
                continue
            if len(self.buf) < 7 + length:
                return out
            if crc16(bytes(self.buf[2:5 + length])) != struct.unpack_from("<H", self.buf, 5 + length)[0]:
                self.bad += 1
                del self.buf[:1]
                continue
            out.append(Frame(ftype, bytes(self.buf[5:5 + length])))
            del self.buf[:7 + length]
