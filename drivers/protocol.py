"""The DAQ stream protocol: CRC-16/MODBUS, frame encoders and an incremental decoder.

Frames are ``A5 5A | type | len (u16 LE) | payload | crc (u16 LE)``, the CRC over
type, length and payload (see ``shared/spec/daq-protocol.md``).

The decoder must keep up with millions of samples a second on one core, so it
never touches single bytes or samples in Python on the clean path: a run of
equal-length SAMPLES frames laid end to end is recognised with one numpy
comparison over a 2-D view of the buffer, their CRCs are computed together (one
table look-up per 16-bit column over all frames at once) and their payloads become
one int16 array.  Anything unusual (a descriptor, a bad header, a corrupted frame
that contains a sync pattern) falls back to a frame-by-frame walk with exactly the
spec's semantics: check the CRC before trusting a length, else drop one byte and
hunt for the next sync.  The decoder itself lives in ``drivers/decoder.py`` and is
re-exported here.
"""

from __future__ import annotations

import struct
from array import array
from dataclasses import dataclass
from enum import IntEnum

import crcmod.predefined
import numpy as np

SYNC = b"\xa5\x5a"
MAX_PAYLOAD = 4096
HEADER_LEN = 5  # sync, type, length
OVERHEAD = HEADER_LEN + 2  # + crc

TYPE_SAMPLES = 0x01
TYPE_DESCRIPTOR = 0x02
TYPE_STATUS = 0x03
TYPE_CONTEXT = 0x04  # version 2
TYPE_COMMAND = 0x10

OUT_FEED_HOLD = 0x01
OUT_ALARM_LAMP = 0x02
FLAG_WATCHDOG = 0x01
FLAG_OVERRUN = 0x02
CMD_SET_OUTPUTS = 0x01
CMD_HEARTBEAT = 0x02
CMD_SEND_DESCRIPTOR = 0x03
CMD_SET_FEED_OVERRIDE = 0x04  # version 2: uint16 in 0.1 % steps
_COMMAND_ARG_LEN = {CMD_SET_OUTPUTS: 1, CMD_HEARTBEAT: 2, CMD_SEND_DESCRIPTOR: 0, CMD_SET_FEED_OVERRIDE: 2}

# version 2: DESCRIPTOR capabilities, CONTEXT flags, the feed override's range
CAP_FEED_OVERRIDE = 0x01
CAP_CONTEXT = 0x02
CTX_CYCLE = 0x01
CTX_MONITOR = 0x02
CTX_AFC_ALLOWED = 0x04
CTX_FEED_HELD = 0x08
FEED_OVERRIDE_MAX = 2000  # 200.0 %
FEED_OVERRIDE_NEUTRAL = 1000  # 100.0 %: the programmed feed
# Payload lengths of version 1 and 2; from version 2 on a receiver takes longer
# DESCRIPTOR and STATUS payloads and ignores the tail (a later version's fields).
# The tail is bounded here so that a corrupted length field makes the decoder wait
# for at most this many extra bytes before the CRC rejects it, not for 4 KB.
STATUS_LEN_V1 = 4
STATUS_LEN_V2 = 6
CONTEXT_LEN = 15
MAX_EXTENSION = 256

MAX_SAMPLES_PER_FRAME = 64
INDEX_MOD = 1 << 32
SCALAR_BELOW = 8  # fewer equal frames than this: per-frame CRC beats numpy's per-call cost


class ChannelKind(IntEnum):
    OTHER = 0
    VOLTAGE = 1
    CURRENT = 2
    SPEED = 3
    ENCODER = 4
    FEED_CURRENT = 5
    FEED_RATE = 6
    FORCE = 7


@dataclass(frozen=True)
class Channel:
    kind: ChannelKind
    name: str


@dataclass(frozen=True)
class Descriptor:
    sample_rate_hz: int
    channels: tuple[Channel, ...]
    protocol_version: int = 1
    capabilities: int = 0  # version 2: bit 0 feed-override output, bit 1 context inputs

    @property
    def has_feed_override(self) -> bool:
        return self.protocol_version >= 2 and bool(self.capabilities & CAP_FEED_OVERRIDE)

    @property
    def has_context(self) -> bool:
        return self.protocol_version >= 2 and bool(self.capabilities & CAP_CONTEXT)

    @property
    def channel_count(self) -> int:
        return len(self.channels)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.channels)


@dataclass(frozen=True, eq=False)
class Samples:
    """Consecutive samples: ``counts[k]`` has device index ``(first_index + k) mod 2**32``."""

    first_index: int
    counts: np.ndarray  # (S, C) int16


@dataclass(frozen=True)
class Status:
    outputs: int
    flags: int
    last_heartbeat: int
    feed_override: int | None = None  # version 2: the override applied now, 0.1 % steps

    @property
    def feed_hold(self) -> bool:
        return bool(self.outputs & OUT_FEED_HOLD)

    @property
    def alarm_lamp(self) -> bool:
        return bool(self.outputs & OUT_ALARM_LAMP)

    @property
    def watchdog_tripped(self) -> bool:
        return bool(self.flags & FLAG_WATCHDOG)

    @property
    def overrun(self) -> bool:
        return bool(self.flags & FLAG_OVERRUN)


@dataclass(frozen=True)
class Context:
    """What the CNC says it is doing (version 2), from sample ``index`` on."""

    index: int  # the first sample index at which this context holds
    program: int
    tool: int
    operation: int
    flags: int

    @property
    def cycle(self) -> bool:
        return bool(self.flags & CTX_CYCLE)

    @property
    def monitor(self) -> bool:
        return bool(self.flags & CTX_MONITOR)

    @property
    def afc_allowed(self) -> bool:
        return bool(self.flags & CTX_AFC_ALLOWED)

    @property
    def feed_held(self) -> bool:
        """The CNC reports that it holds the feed: the proof that the feed-hold path works."""
        return bool(self.flags & CTX_FEED_HELD)


@dataclass(frozen=True)
class Command:
    command: int
    argument: int | None = None


# --------------------------------------------------------------------------- CRC


def _make_tables() -> tuple[np.ndarray, np.ndarray]:
    table = np.zeros(256, dtype=np.uint16)
    for i in range(256):
        crc = i
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
        table[i] = crc
    # Two bytes at a time: once both input bytes are xored into the 16-bit
    # register, two table steps are a pure function of the register.
    v = np.arange(65536, dtype=np.uint32)
    for _ in range(2):
        v = (v >> 8) ^ table[v & 0xFF].astype(np.uint32)
    return table, v.astype(np.uint16)


CRC_TABLE, _table2 = _make_tables()
_T1 = CRC_TABLE.tolist()
# an array, not a list: 65536 Python ints held 2.4 MB of the daemon's memory (issue 13); indexing costs the same
_T2 = array("H", _table2.tobytes())
CRC_TABLE2 = np.frombuffer(_T2, dtype=np.uint16)  # the same 128 KB, seen by numpy: not a second copy
del _table2


# Many frames at once (a replay's read, a catch-up): the CRC is linear over GF(2): the register after a
# body of n bytes is the register after n zero bytes (from the initial 0xFFFF) xor, for every byte b at
# position j, the register that b alone would leave followed by n-1-j zero bytes. So with a table
# POS[m, b] (byte b, then m zero bytes, from register 0) the bodies' CRCs are one gather and one
# xor-reduction: no loop over bytes or frames. That wins over the column loop below up to a few thousand
# frames at once, and over a call of the compiled CRC per frame (measured: bench/decoder_throughput.py).
GATHER_BELOW_ROWS = 2048
_MAX_BODY = 3 + MAX_PAYLOAD
_position = (np.empty((0, 256), np.uint16), np.empty(0, np.uint16))  # (POS, register after m zero bytes)
_bases: dict[int, np.ndarray] = {}


def _position_table(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(POS flattened, gather offsets of a body of n bytes, zero-body register), grown on demand.

    Grown in doublings to the longest body seen (189 bytes: 97 KB; a 4 KB payload:
    2 MB), never built whole at import. Replaced as one tuple, so a reader thread
    never sees a table and a zero column of different lengths.
    """
    pos, zero = _position
    if len(pos) < n:
        m = min(max(n, 2 * len(pos), 256), _MAX_BODY)
        pos = np.empty((m, 256), dtype=np.uint16)
        v = CRC_TABLE.copy()
        for k in range(m):
            pos[k] = v
            v = (v >> 8) ^ CRC_TABLE[v & 0xFF]
        zero = np.empty(m + 1, dtype=np.uint16)
        reg = 0xFFFF
        for k in range(m + 1):
            zero[k] = reg
            reg = (reg >> 8) ^ _T1[reg & 0xFF]
        globals()["_position"] = (pos, zero)
    base = _bases.get(n)
    if base is None:
        # byte j of n is followed by n-1-j others: its row of POS, as flat offsets
        base = np.arange(n - 1, -1, -1, dtype=np.intp) * 256
        if len(_bases) < 64:
            _bases[n] = base
    return pos.ravel(), base, zero


# CRC-16/MODBUS compiled (crcmod-plus: README, "Dependencies"). The reader thread checks one frame a wake-up,
# its caches cold after 10 ms of other work: 9-12 µs a 189-byte body paced so, against 21-37 µs for the
# byte-by-byte loop in Python and 62-77 µs for the numpy gather (bench/decoder_throughput.py).
_crc16_modbus_c = crcmod.predefined.mkCrcFun("modbus")


def crc16_modbus(data: bytes) -> int:
    """CRC-16/MODBUS (reflected 0xA001, init 0xFFFF) of ``data`` (bytes, bytearray or a memoryview)."""
    return _crc16_modbus_c(data)


def crc16_modbus_rows(rows: np.ndarray) -> np.ndarray:
    """CRC-16/MODBUS of every row of a 2-D uint8 array, vectorised across rows.

    Up to GATHER_BELOW_ROWS rows: the position table (one gather over all bytes).
    More: one look-up per 16-bit column over all rows at once, whose cost grows
    with the frame length and barely with the number of frames.
    """
    k, n = rows.shape
    if k == 0:
        return np.full(0, 0xFFFF, dtype=np.uint16)
    if k < GATHER_BELOW_ROWS and 0 < n <= _MAX_BODY:
        flat, base, zero = _position_table(n)
        return np.bitwise_xor.reduce(flat.take(base + rows), axis=1) ^ zero[n]
    crc = np.full(k, 0xFFFF, dtype=np.uint16)
    even = n & ~1
    if even:
        words = np.ascontiguousarray(rows[:, :even]).view("<u2").T.copy()
        for w in words:
            np.bitwise_xor(crc, w, out=crc)
            crc = CRC_TABLE2.take(crc)
    if n & 1:
        last = rows[:, n - 1].astype(np.uint16)
        crc = (crc >> 8) ^ CRC_TABLE.take((crc ^ last) & 0xFF)
    return crc


# ---------------------------------------------------------------------- encoders


def _frame(frame_type: int, payload: bytes) -> bytes:
    if len(payload) > MAX_PAYLOAD:
        raise ValueError(f"payload of {len(payload)} bytes exceeds {MAX_PAYLOAD}")
    body = struct.pack("<BH", frame_type, len(payload)) + payload
    return SYNC + body + struct.pack("<H", crc16_modbus(body))


def _as_counts(counts: np.ndarray) -> np.ndarray:
    counts = np.asarray(counts)
    if counts.ndim != 2:
        raise ValueError(f"counts must be (S, C), got shape {counts.shape}")
    if counts.dtype != np.int16:
        if counts.size and (counts.min() < -32768 or counts.max() > 32767):
            raise ValueError("counts out of int16 range")
        counts = counts.astype(np.int16)
    if not 1 <= counts.shape[1] <= 255:
        raise ValueError(f"channel count {counts.shape[1]} outside 1..255")
    return counts


def encode_samples(first_index: int, counts: np.ndarray) -> bytes:
    """One SAMPLES frame; ``counts`` is (S, C) with 1 <= S <= 64."""
    counts = _as_counts(counts)
    s, c = counts.shape
    if not 1 <= s <= MAX_SAMPLES_PER_FRAME:
        raise ValueError(f"sample count {s} outside 1..{MAX_SAMPLES_PER_FRAME}")
    payload = struct.pack("<IBB", first_index % INDEX_MOD, c, s) + counts.astype("<i2").tobytes()
    return _frame(TYPE_SAMPLES, payload)


def encode_sample_frames(first_index: int, counts: np.ndarray, per_frame: int = 10) -> bytes:
    """Many SAMPLES frames of ``per_frame`` samples (the last may be shorter), built in bulk."""
    counts = _as_counts(counts)
    n, c = counts.shape
    if not 1 <= per_frame <= MAX_SAMPLES_PER_FRAME:
        raise ValueError(f"per_frame {per_frame} outside 1..{MAX_SAMPLES_PER_FRAME}")
    if 6 + 2 * c * per_frame > MAX_PAYLOAD:
        raise ValueError(f"{per_frame} samples of {c} channels exceed one frame")
    full = n // per_frame
    out = b""
    if 0 < full < SCALAR_BELOW:  # a few frames: the scalar CRC is cheaper than numpy's per-call cost
        out = b"".join(
            encode_samples(first_index + a, counts[a : a + per_frame]) for a in range(0, full * per_frame, per_frame)
        )
    elif full:
        payload_len = 6 + 2 * c * per_frame
        flen = OVERHEAD + payload_len
        rows = np.zeros((full, flen), dtype=np.uint8)
        rows[:, 0] = 0xA5
        rows[:, 1] = 0x5A
        rows[:, 2] = TYPE_SAMPLES
        rows[:, 3] = payload_len & 0xFF
        rows[:, 4] = payload_len >> 8
        idx = (first_index + per_frame * np.arange(full, dtype=np.int64)) % INDEX_MOD
        rows[:, 5:9] = idx.astype("<u4").view(np.uint8).reshape(full, 4)
        rows[:, 9] = c
        rows[:, 10] = per_frame
        body = counts[: full * per_frame].astype("<i2").reshape(full, per_frame * c)
        rows[:, 11 : flen - 2] = body.view(np.uint8)
        crc = crc16_modbus_rows(rows[:, 2 : flen - 2])
        rows[:, flen - 2 :] = crc.astype("<u2").view(np.uint8).reshape(full, 2)
        out = rows.tobytes()
    if n > full * per_frame:
        out += encode_samples(first_index + full * per_frame, counts[full * per_frame :])
    return out


def encode_descriptor(d: Descriptor) -> bytes:
    parts = [struct.pack("<BHB", d.protocol_version, d.sample_rate_hz, d.channel_count)]
    for ch in d.channels:
        name = ch.name.encode("ascii")
        if len(name) > 8:
            raise ValueError(f"channel name {ch.name!r} longer than 8 characters")
        parts.append(struct.pack("<B8s", int(ch.kind), name))
    if d.protocol_version >= 2:
        parts.append(struct.pack("<B", d.capabilities & 0xFF))
    return _frame(TYPE_DESCRIPTOR, b"".join(parts))


def encode_status(s: Status) -> bytes:
    payload = struct.pack("<BBH", s.outputs & 0xFF, s.flags & 0xFF, s.last_heartbeat & 0xFFFF)
    if s.feed_override is not None:
        payload += struct.pack("<H", s.feed_override & 0xFFFF)
    return _frame(TYPE_STATUS, payload)


def encode_context(c: Context) -> bytes:
    for name, value, bits in (("index", c.index, 32), ("program", c.program, 32), ("tool", c.tool, 32),
                              ("operation", c.operation, 16), ("flags", c.flags, 8)):
        if not 0 <= value < 1 << bits:
            raise ValueError(f"context {name} {value} outside 0..{(1 << bits) - 1}")
    return _frame(TYPE_CONTEXT, struct.pack("<IIIHB", c.index, c.program, c.tool, c.operation, c.flags))


def encode_command(c: Command) -> bytes:
    if c.command == CMD_SET_OUTPUTS:
        payload = struct.pack("<BB", c.command, (c.argument or 0) & 0xFF)
    elif c.command == CMD_HEARTBEAT:
        payload = struct.pack("<BH", c.command, (c.argument or 0) & 0xFFFF)
    elif c.command == CMD_SEND_DESCRIPTOR:
        payload = struct.pack("<B", c.command)
    elif c.command == CMD_SET_FEED_OVERRIDE:
        value = c.argument or 0
        if not 0 <= value <= FEED_OVERRIDE_MAX:
            raise ValueError(f"feed override {value} outside 0..{FEED_OVERRIDE_MAX} (0.1 % steps)")
        payload = struct.pack("<BH", c.command, value)
    else:
        raise ValueError(f"unknown command 0x{c.command:02x}")
    return _frame(TYPE_COMMAND, payload)


_DECODER_NAMES = ("DecoderStats", "Frame", "StreamDecoder")


def __getattr__(name: str):
    """``StreamDecoder`` and friends live in drivers/decoder.py (which imports this
    module); they are public here, resolved on first use so there is no import cycle."""
    if name in _DECODER_NAMES:
        from millsense.drivers import decoder

        return getattr(decoder, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

__all__ = [
    "CAP_CONTEXT", "CAP_FEED_OVERRIDE", "CMD_HEARTBEAT", "CMD_SEND_DESCRIPTOR", "CMD_SET_FEED_OVERRIDE",
    "CMD_SET_OUTPUTS", "CTX_AFC_ALLOWED", "CTX_CYCLE", "CTX_FEED_HELD", "CTX_MONITOR", "FEED_OVERRIDE_MAX",
    "FEED_OVERRIDE_NEUTRAL", "FLAG_OVERRUN", "FLAG_WATCHDOG",
    "OUT_ALARM_LAMP", "OUT_FEED_HOLD", "Channel", "ChannelKind", "Command", "Context", "DecoderStats", "Descriptor",
    "Frame", "Samples", "Status", "StreamDecoder", "crc16_modbus", "crc16_modbus_rows", "encode_command",
    "encode_context", "encode_descriptor", "encode_sample_frames", "encode_samples", "encode_status",
]
