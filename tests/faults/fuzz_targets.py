"""Fuzz targets: what must hold for any bytes from a DAQ. Used by bench/fuzz.py and test_corpus.py.

`decoder_target(data)` — the stream decoder (drivers/decoder.py):

- `feed` never raises, whatever the bytes;
- the frames it returns are exactly those of a spec-literal reference decoder
  written here from daq-protocol.md ("drop one byte and hunt for the next
  sync; never trust a length before the CRC checks out"), byte by byte, with
  no fast path: a differential check of the vectorised path;
- feeding the same bytes in chunks (sizes drawn from the input's first byte)
  gives the same frames as feeding them whole;
- the counters add up (consumed + buffered = fed; samples counted = samples
  returned) and at most one frame's worth (4102 bytes) is held back;
- every Samples is int16, (S, C) with C the channel count of the last
  descriptor.

`modbus_target(data)` — the Modbus reader's response handling
(drivers/modbus_driver.py): the driver runs its connect and a few polls
against a client whose every answer is decoded by pymodbus' own PDU decoder
from the fuzz bytes (a timeout, an exception response, a well-formed answer
with fuzzed values, or raw fuzzed PDU bytes). The only exception that may come
out of a poll is `LinkDown` (which the driver's base class turns into "link
down, reconnect"), and whatever it hands over is well-formed: a descriptor with
1..125 channels, samples as (n, C) int16 with 1 <= n <= ring depth and a
32-bit index, never more samples in a poll than the head moved.
"""

from __future__ import annotations

import logging
import struct

import numpy as np

from millsense.drivers.protocol import (
    _COMMAND_ARG_LEN,
    INDEX_MOD,
    MAX_PAYLOAD,
    TYPE_COMMAND,
    TYPE_DESCRIPTOR,
    TYPE_SAMPLES,
    TYPE_STATUS,
    Channel,
    ChannelKind,
    Command,
    Descriptor,
    Samples,
    Status,
    StreamDecoder,
    crc16_modbus,
)

MAX_HELD = 4096 + 7 - 1  # one incomplete frame at most


# --------------------------------------------------------------------------- stream decoder
def reference_decode(data: bytes) -> tuple[list, int]:
    """daq-protocol.md, literally: (frames, bytes left waiting at the end)."""
    out: list = []
    desc: Descriptor | None = None
    n = len(data)
    p = 0
    while p < n:
        if data[p] != 0xA5:
            p += 1
            continue
        if p + 1 >= n:
            break  # a trailing 0xA5 may be half a sync
        if data[p + 1] != 0x5A:
            p += 1
            continue
        if n - p < 5:
            break
        ftype, length = data[p + 2], data[p + 3] | (data[p + 4] << 8)
        if ftype not in (TYPE_SAMPLES, TYPE_DESCRIPTOR, TYPE_STATUS, TYPE_COMMAND) or length > MAX_PAYLOAD:
            p += 1
            continue
        need = {TYPE_SAMPLES: 11, TYPE_DESCRIPTOR: 9, TYPE_STATUS: 5, TYPE_COMMAND: 6}[ftype]
        if n - p < need:
            break
        if ftype == TYPE_SAMPLES:
            c, s = data[p + 9], data[p + 10]
            plausible = c >= 1 and 1 <= s <= 64 and length == 6 + 2 * c * s
        elif ftype == TYPE_DESCRIPTOR:
            plausible = data[p + 8] >= 1 and length == 4 + 9 * data[p + 8]
        elif ftype == TYPE_STATUS:
            plausible = length == 4
        else:
            arg = _COMMAND_ARG_LEN.get(data[p + 5])
            plausible = arg is not None and length == 1 + arg
        if not plausible:
            p += 1
            continue
        end = p + 5 + length + 2
        if end > n:
            break
        if crc16_modbus(data[p + 2 : end - 2]) != data[end - 2] | (data[end - 1] << 8):
            p += 1
            continue
        payload = data[p + 5 : end - 2]
        if ftype == TYPE_SAMPLES:
            first, c, s = struct.unpack_from("<IBB", payload)
            if desc is not None and c == desc.channel_count:
                counts = np.frombuffer(payload, dtype="<i2", offset=6).reshape(s, c)
                out.append(Samples(first, counts.astype(np.int16)))
        elif ftype == TYPE_DESCRIPTOR:
            version, rate, c = struct.unpack_from("<BHB", payload)
            if rate == 0:
                p += 1
                continue
            chans = []
            for i in range(c):
                kind, raw = struct.unpack_from("<B8s", payload, 4 + 9 * i)
                name = raw.rstrip(b"\0")
                try:
                    chans.append(Channel(ChannelKind(kind), name.decode("ascii")))
                except (ValueError, UnicodeDecodeError):
                    chans.append(Channel(ChannelKind.OTHER, name.decode("latin-1")))
            desc = Descriptor(rate, tuple(chans), version)
            out.append(desc)
        elif ftype == TYPE_STATUS:
            out.append(Status(*struct.unpack("<BBH", payload)))
        else:
            arg = None
            if length == 2:
                arg = payload[1]
            elif length == 3:
                arg = payload[1] | (payload[2] << 8)
            out.append(Command(payload[0], arg))
        p = end
    return out, n - p


def _normal(frames: list) -> list:
    """Frames with runs of contiguous Samples joined, so that how they were merged does not matter."""
    out: list = []
    for f in frames:
        if isinstance(f, Samples):
            last = out[-1] if out else None
            if isinstance(last, list) and last[1] == f.first_index:
                last[1] = (f.first_index + len(f.counts)) % INDEX_MOD
                last[2] += f.counts.tobytes()
                continue
            out.append(["S", (f.first_index + len(f.counts)) % INDEX_MOD, f.counts.tobytes(), f.first_index])
        else:
            out.append(f)
    return out


def _feed_checked(dec: StreamDecoder, chunk: bytes) -> list:
    desc = dec.descriptor
    frames = dec.feed(chunk)
    for f in frames:
        if isinstance(f, Samples):
            c = f.counts
            assert c.dtype == np.int16 and c.ndim == 2 and len(c) >= 1, c.shape
            assert desc is not None and c.shape[1] == desc.channel_count, "samples of the wrong width"
            assert 0 <= f.first_index < INDEX_MOD
        elif isinstance(f, Descriptor):
            desc = f
        else:
            assert isinstance(f, (Status, Command)), type(f)
    assert dec.buffered <= MAX_HELD, dec.buffered
    return frames


def _chunks(data: bytes, seed: int) -> list[bytes]:
    rng = np.random.default_rng(seed)
    out, p = [], 0
    while p < len(data):
        k = int(rng.integers(1, 64)) if seed % 3 else int(rng.integers(1, 5000))
        out.append(data[p : p + k])
        p += k
    return out


def decoder_target(data: bytes) -> None:
    if not data:
        return
    stream = data[1:]
    whole = StreamDecoder()
    got = _feed_checked(whole, stream)
    st = whole.stats
    assert st.consumed_bytes + whole.buffered == len(stream), (st, whole.buffered)
    assert st.samples == sum(len(f.counts) for f in got if isinstance(f, Samples))
    ref, left = reference_decode(stream)
    assert _normal(got) == _normal(ref), "the decoder and the spec disagree"
    assert whole.buffered == left, (whole.buffered, left)
    chunked = StreamDecoder()
    parts: list = []
    for chunk in _chunks(stream, data[0]):
        parts += _feed_checked(chunked, chunk)
    assert _normal(parts) == _normal(got), "chunking changed the result"
    assert chunked.buffered == whole.buffered and chunked.stats == whole.stats, (chunked.stats, whole.stats)


# --------------------------------------------------------------------------- Modbus reader
class _Bytes:
    def __init__(self, data: bytes) -> None:
        self.data = data
        self.pos = 0

    def take(self, n: int) -> bytes:
        out = self.data[self.pos : self.pos + n]
        self.pos += len(out)
        return out

    def byte(self) -> int | None:
        b = self.take(1)
        return b[0] if b else None


class FuzzClient:
    """In place of pymodbus' client: each answer comes from the fuzz bytes, through pymodbus' PDU decoder."""

    def __init__(self, data: bytes) -> None:
        from pymodbus.pdu import DecodePDU

        self.src = _Bytes(data)
        self.decoder = DecodePDU(False)

    def connect(self) -> bool:
        return self.src.byte() not in (None, 0)

    def close(self) -> None:
        pass

    def _answer(self, fc: int, count: int, bits: bool = False):
        from pymodbus.exceptions import ModbusIOException

        mode = self.src.byte()
        if mode is None or mode < 16:
            raise ModbusIOException("no answer (fuzz: timeout)")
        if mode < 40:
            pdu = bytes([fc | 0x80, mode % 12])  # exception response, any code
        elif mode < 200:
            if fc in (5, 6, 15, 16):
                pdu = bytes([fc]) + self.src.take(4)
            else:
                nbytes = (count + 7) // 8 if bits else 2 * count
                if mode >= 190:  # a byte count that does not match the request
                    nbytes = self.src.byte() or 0
                body = self.src.take(nbytes)
                pdu = bytes([fc, len(body) & 0xFF]) + body
        else:
            pdu = bytes([fc if mode & 1 else self.src.byte() or 0]) + self.src.take(mode - 200)
        try:
            rr = self.decoder.decode(pdu)
        except Exception as exc:  # noqa: BLE001 - pymodbus' framer would drop the frame: the client times out
            raise ModbusIOException(f"undecodable answer: {exc}") from None
        if rr is None:
            raise ModbusIOException("undecodable answer")
        return rr

    def read_input_registers(self, address, count, device_id=1):
        return self._answer(4, count)

    def read_holding_registers(self, address, count, device_id=1):
        return self._answer(3, count)

    def read_coils(self, address, count, device_id=1):
        return self._answer(1, count, bits=True)

    def read_discrete_inputs(self, address, count, device_id=1):
        return self._answer(2, count, bits=True)

    def write_coils(self, address, values, device_id=1):
        return self._answer(15, len(values))

    def write_register(self, address, value, device_id=1):
        return self._answer(6, 1)


_QUIET = False


def quiet_logs() -> None:
    """For bench/fuzz.py only (it changes structlog's global configuration): the driver logs
    every refused command at debug level, not what a fuzz run wants to print."""
    global _QUIET
    if not _QUIET:
        import structlog

        logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
        structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.CRITICAL))
        _QUIET = True


def modbus_target(data: bytes, polls: int = 6) -> None:
    from millsense.drivers.base import LinkDown
    from millsense.drivers.modbus_driver import ModbusTcpDriver

    client = FuzzClient(data)
    drv = ModbusTcpDriver("fuzz", 1, unit=1, poll_ms=1)
    drv.poll_s = 0.0
    drv._make_client = lambda: client
    if data[:1] and data[0] & 1:
        drv._watchdog_ms = 500  # written after connect: a write the DAQ may refuse
    try:
        drv._connect()
        drv.link_up = True  # as the base class sets it once connected: outputs go to the client
        drv._after_connect()
        for _ in range(polls):
            drv._next_status = 0.0  # poll the outputs every time, not every 100 ms
            drv._next_poll = 0.0
            head_before = drv._next
            items = drv._read()
            moved = 0
            for it in items:
                if isinstance(it, Descriptor):
                    assert 1 <= it.channel_count <= 125 and it.sample_rate_hz >= 1, it
                elif isinstance(it, Samples):
                    c = it.counts
                    assert c.dtype == np.int16 and c.ndim == 2 and c.shape[1] == drv._channels, c.shape
                    assert 1 <= len(c) <= drv._ring_depth, (len(c), drv._ring_depth)
                    assert 0 <= it.first_index < INDEX_MOD
                    moved += len(c)
                else:
                    assert isinstance(it, Status), type(it)
                    assert 0 <= it.outputs <= 3 and it.flags in (0, 1) and 0 <= it.last_heartbeat <= 0xFFFF
            if head_before is not None and drv._next is not None:
                assert moved <= (drv._next - head_before) % INDEX_MOD or moved == 0
            # the outputs go through the same client: they may be refused, never raise
            assert drv.set_outputs(bool(data[-1] & 1)) in (True, False)
    except LinkDown:
        pass  # the base class makes it "link down, reconnect"
    finally:
        drv._disconnect()


# --------------------------------------------------------------------------- input generators
# Plausible inputs, mutated: pure random bytes rarely get past a CRC or a register count.
def mutate(data: bytes, rng) -> bytes:
    b = bytearray(data)
    for _ in range(rng.randrange(0, 5)):
        if not b:
            break
        i = rng.randrange(len(b))
        op = rng.random()
        if op < 0.45:
            b[i] ^= 1 << rng.randrange(8)
        elif op < 0.6:
            del b[i : i + rng.randrange(1, 24)]
        elif op < 0.75:
            b[i:i] = rng.randbytes(rng.randrange(1, 12))
        elif op < 0.85:
            b[i:i] = b"\xa5\x5a"
        else:
            j = rng.randrange(len(b))
            b[i:i] = b[j : j + rng.randrange(1, 64)]  # a piece of itself elsewhere
    return bytes(b)


def stream_input(rng) -> bytes:
    """First byte: the chunking seed; then frames of a small DAQ, some of them damaged."""
    from millsense.drivers.protocol import encode_command, encode_descriptor, encode_samples, encode_status

    c = rng.choice([1, 3, 8, 8, 13])
    desc = Descriptor(rng.choice([1000, 1000, 1, 65535]), tuple(Channel(ChannelKind(rng.randrange(8)), f"c{i}") for i in range(c)))
    parts = [encode_descriptor(desc)] if rng.random() < 0.9 else []
    idx = rng.choice([0, INDEX_MOD - 25, rng.randrange(INDEX_MOD)])
    s_fixed = rng.choice([None, 1, 10, 10, 64 // c])
    for _ in range(rng.randrange(1, 24)):
        k = rng.random()
        if k < 0.75:
            s = s_fixed or rng.randrange(1, 65)
            counts = np.frombuffer(rng.randbytes(2 * c * s), dtype=np.int16).reshape(s, c)
            parts.append(encode_samples(idx, counts))
            idx = (idx + s + (rng.randrange(1, 5) if rng.random() < 0.05 else 0)) % INDEX_MOD
        elif k < 0.85:
            parts.append(encode_status(Status(rng.randrange(4), rng.randrange(4), rng.randrange(65536))))
        elif k < 0.93:
            parts.append(encode_command(Command(rng.choice([1, 2, 3]), rng.randrange(256))))
        else:
            c2 = rng.choice([c, c, c + 1, 1])
            parts.append(encode_descriptor(Descriptor(1000, tuple(Channel(ChannelKind.OTHER, f"x{i}") for i in range(c2)))))
    return bytes([rng.randrange(256)]) + mutate(b"".join(parts), rng)


def modbus_input(rng) -> bytes:
    """Answers of a plausible Modbus DAQ, in FuzzClient's format, then mutated."""
    out = bytearray([rng.choice([1, 2, 3])])  # connect; odd: a watchdog write follows

    def answer(regs: list[int] | int | None = None, nbits: int = 0, write: bool = False) -> None:
        if rng.random() < 0.03:
            out.append(rng.randrange(0, 40))  # a timeout or an exception response
            return
        out.append(rng.randrange(40, 190))
        if write:
            out.extend(rng.randbytes(4))
        elif isinstance(regs, int):
            out.extend(rng.randbytes(2 * regs))  # that many registers of anything
        elif regs is not None:
            out.extend(b"".join((r & 0xFFFF).to_bytes(2, "big") for r in regs))
        else:
            out.extend(rng.randbytes((nbits + 7) // 8))

    if out[0] & 1:
        answer(write=True)
    c = rng.choice([1, 3, 8, 8, 13, 125])
    depth = rng.choice([1, 10, 100, 4096, 65535])
    answer([1, c, 1000, depth])
    for a in range(0, 5 * c, 125):
        answer([rng.randrange(8) if i % 5 == 0 else rng.randrange(65536) for i in range(min(125, 5 * c - a))])
    head = rng.choice([0, INDEX_MOD - 50, rng.randrange(INDEX_MOD)])
    nxt = None
    for _ in range(6):
        answer(nbits=2)
        answer(nbits=1)
        answer([rng.randrange(65536)])
        answer([head >> 16, head & 0xFFFF])
        if nxt is not None:
            behind = (head - nxt) % INDEX_MOD
            if behind < INDEX_MOD // 2:
                if behind > depth:
                    nxt, behind = (head - depth) % INDEX_MOD, depth
                k, per = nxt, max(1, 125 // c)
                while behind and len(out) < 20000:  # past that, the reader meets a timeout: fine
                    n = min(per, behind, depth - k % depth)
                    answer(n * c)
                    k, behind = (k + n) % INDEX_MOD, behind - n
                answer([head >> 16, head & 0xFFFF])
        nxt = head
        head = (head + rng.choice([0, 1, 20, 20, 300, depth + 7, INDEX_MOD - 5])) % INDEX_MOD
        answer(write=True)  # set_outputs after the poll
    return mutate(bytes(out), rng) if rng.random() < 0.7 else bytes(out)
