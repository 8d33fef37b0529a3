"""The frame codec: known CRC values, round trips, and the decoder against noise (hypothesis)."""

from __future__ import annotations

import struct

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from millsense.drivers.protocol import (
    CMD_HEARTBEAT,
    CMD_SEND_DESCRIPTOR,
    CMD_SET_OUTPUTS,
    Channel,
    ChannelKind,
    Command,
    Descriptor,
    Samples,
    Status,
    StreamDecoder,
    crc16_modbus,
    crc16_modbus_rows,
    encode_command,
    encode_descriptor,
    encode_sample_frames,
    encode_samples,
    encode_status,
)
from tests.firmware.frames import crc16  # CRC-16/MODBUS from its definition, written from the doc

pytestmark = pytest.mark.quick

DESC = Descriptor(1000, tuple(Channel(ChannelKind.CURRENT, f"ch{i}") for i in range(4)))


def test_crc_check_value_and_a_modbus_request():
    # the catalogue check value of CRC-16/MODBUS, and the classic "read 2 holding regs" ADU
    assert crc16_modbus(b"123456789") == 0x4B37
    assert crc16_modbus(bytes.fromhex("010300000002")) == 0x0BC4  # sent on the wire as C4 0B


@given(st.integers(0, 40).flatmap(lambda n: st.lists(st.binary(min_size=n, max_size=n), min_size=1, max_size=8)))
@settings(max_examples=60)
def test_crc_scalar_and_vectorised_agree_with_the_definition(rows):
    arr = np.frombuffer(b"".join(rows), dtype=np.uint8).reshape(len(rows), len(rows[0]))
    expected = [crc16(r) for r in rows]
    assert [crc16_modbus(r) for r in rows] == expected
    assert crc16_modbus_rows(arr).tolist() == expected


def test_samples_frame_layout_is_the_spec():
    counts = np.array([[1, -2], [3, -4]], dtype=np.int16)
    frame = encode_samples(0x01020304, counts)
    assert frame[:2] == b"\xa5\x5a" and frame[2] == 0x01
    (length,) = struct.unpack_from("<H", frame, 3)
    assert length == 6 + 2 * 2 * 2 == len(frame) - 7
    assert frame[5:9] == bytes([4, 3, 2, 1]) and frame[9] == 2 and frame[10] == 2
    assert struct.unpack_from("<4h", frame, 11) == (1, -2, 3, -4)
    assert struct.unpack_from("<H", frame, len(frame) - 2)[0] == crc16(frame[2:-2])


def test_round_trip_of_every_frame_type():
    dec = StreamDecoder()
    counts = np.arange(24, dtype=np.int16).reshape(6, 4) - 12
    status = Status(outputs=3, flags=1, last_heartbeat=65535)
    commands = [Command(CMD_SET_OUTPUTS, 1), Command(CMD_HEARTBEAT, 513), Command(CMD_SEND_DESCRIPTOR, None)]
    data = encode_descriptor(DESC) + encode_samples(7, counts) + encode_status(status)
    data += b"".join(encode_command(c) for c in commands)
    out = dec.feed(data)
    assert out[0] == DESC and out[2] == status and out[3:] == commands
    assert out[1].first_index == 7 and np.array_equal(out[1].counts, counts)


def test_many_frames_equal_single_frames_and_merge_across_the_wrap():
    counts = np.random.default_rng(1).integers(-32768, 32767, size=(95, 4)).astype(np.int16)
    first = (1 << 32) - 40  # the index wraps inside the block
    bulk = encode_sample_frames(first, counts, per_frame=10)
    single = b"".join(encode_samples((first + a) % (1 << 32), counts[a : a + 10]) for a in range(0, 95, 10))
    assert bulk == single
    out = StreamDecoder().feed(encode_descriptor(DESC) + bulk)
    assert len(out) == 2 and out[1].first_index == first  # one merged block
    assert np.array_equal(out[1].counts, counts)


def test_refuses_samples_with_another_channel_count_and_before_a_descriptor():
    dec = StreamDecoder()
    three = np.zeros((5, 3), dtype=np.int16)
    four = np.ones((5, 4), dtype=np.int16)
    assert dec.feed(encode_samples(0, four)) == []
    assert dec.stats.samples_before_descriptor == 5
    contiguous = encode_sample_frames(10, np.ones((15, 4), np.int16), 5)
    out = dec.feed(encode_descriptor(DESC) + encode_samples(5, three) + contiguous)
    assert dec.stats.descriptor_mismatch == 1
    assert [type(f) for f in out] == [Descriptor, Samples]
    assert dec.stats.samples == 15


@pytest.mark.parametrize(
    "patch",
    [
        (3, struct.pack("<H", 4097)),  # longer than any frame
        (10, bytes([65])),  # S outside 1..64
        (9, bytes([5])),  # C*S no longer matches L
    ],
)
def test_impossible_lengths_are_dropped_without_waiting(patch):
    dec = StreamDecoder()
    dec.feed(encode_descriptor(DESC))
    good = encode_samples(0, np.zeros((2, 4), dtype=np.int16))
    pos, repl = patch
    bad = bytearray(good)
    bad[pos : pos + len(repl)] = repl
    out = dec.feed(bytes(bad) + good)
    # the next frame arrives at once: the decoder did not wait for the bad length's bytes
    assert len(out) == 1 and dec.stats.bad_length == 1
    assert dec.stats.dropped_bytes == len(bad)


def test_garbage_does_not_grow_the_buffer():
    dec = StreamDecoder()
    dec.feed(encode_descriptor(DESC))
    rng = np.random.default_rng(3)
    biggest = 0
    for _ in range(200):  # 10 MB of noise, with plenty of syncs and plausible headers
        chunk = bytearray(rng.bytes(50_000))
        for pos in rng.integers(0, len(chunk) - 5, size=20):
            chunk[pos : pos + 5] = b"\xa5\x5a\x01" + struct.pack("<H", int(rng.integers(8, 4097)))
        dec.feed(bytes(chunk))
        biggest = max(biggest, dec.buffered)
    assert biggest <= 4096 + 7
    assert dec.stats.consumed_bytes + dec.buffered == len(encode_descriptor(DESC)) + 200 * 50_000


# ----------------------------------------------------------------- hypothesis


@st.composite
def streams(draw):
    """Frames as sent, then what the wire made of them: chunking, corruption, garbage."""
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    n_frames = draw(st.integers(1, 40))
    fixed_s = draw(st.one_of(st.none(), st.integers(1, 12)))  # equal frames: the vectorised path
    sent = [("descriptor", DESC)]
    wire = [encode_descriptor(DESC)]
    index = draw(st.integers(0, 2**32 - 1))
    for _ in range(n_frames):
        kinds = ["samples"] * (12 if fixed_s else 3) + ["status", "descriptor"]
        kind = draw(st.sampled_from(kinds))
        if kind == "samples":
            s = fixed_s or draw(st.integers(1, 12))
            counts = rng.integers(-32768, 32768, size=(s, 4)).astype(np.int16)
            sent.append(("samples", (index, counts)))
            wire.append(encode_samples(index, counts))
            index = (index + s) % (1 << 32)
        elif kind == "status":
            status = Status(draw(st.integers(0, 3)), draw(st.integers(0, 3)), draw(st.integers(0, 65535)))
            sent.append(("status", status))
            wire.append(encode_status(status))
        else:
            sent.append(("descriptor", DESC))
            wire.append(encode_descriptor(DESC))
    corrupt = draw(st.lists(st.booleans(), min_size=len(wire), max_size=len(wire)))
    garbage = draw(st.lists(st.binary(max_size=30), min_size=len(wire), max_size=len(wire)))
    out = b""
    for frame, bad, junk in zip(wire, corrupt, garbage):
        if bad:
            b = bytearray(frame)
            b[int(rng.integers(0, len(b)))] ^= int(rng.integers(1, 256))
            frame = bytes(b)
        out += junk + frame
    cuts = sorted(draw(st.lists(st.integers(0, len(out)), max_size=12)))
    chunks = [out[a:b] for a, b in zip([0, *cuts], [*cuts, len(out)])]
    return sent, chunks, corrupt


def _sent_samples(sent):
    out = {}
    for kind, value in sent:
        if kind == "samples":
            first, counts = value
            for k in range(len(counts)):
                out[(first + k) % (1 << 32)] = tuple(counts[k].tolist())
    return out


@given(streams())
@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
def test_decoded_frames_are_frames_that_were_sent(case):
    sent, chunks, corrupt = case
    dec = StreamDecoder()
    got = []
    for chunk in chunks:
        got += dec.feed(chunk)
    truth = _sent_samples(sent)
    sent_status = {v for k, v in sent if k == "status"}
    n_samples = 0
    for frame in got:
        if isinstance(frame, Samples):
            for k in range(len(frame.counts)):
                idx = (frame.first_index + k) % (1 << 32)
                assert truth[idx] == tuple(frame.counts[k].tolist())  # a sample that was sent, unchanged
                n_samples += 1
        elif isinstance(frame, Status):
            assert frame in sent_status
        else:
            assert frame == DESC
    total = sum(len(c) for c in chunks)
    st_ = dec.stats
    assert st_.samples == n_samples
    assert st_.consumed_bytes + dec.buffered == total
    assert dec.buffered <= 4096 + 7
    # counts add up: every intact frame is decoded, every corrupted one is not
    # (CRC-16 catches any single changed byte)
    intact = [f for f, bad in zip(sent, corrupt) if not bad]
    assert st_.frames == len(intact)
    intact_samples = sum(len(v[1]) for k, v in intact if k == "samples")
    assert n_samples + st_.samples_before_descriptor == intact_samples
    intact_bytes = sum(len(_encode(k, v)) for k, v in intact)
    assert st_.dropped_bytes + dec.buffered == total - intact_bytes


def _encode(kind, value) -> bytes:
    if kind == "descriptor":
        return encode_descriptor(value)
    if kind == "status":
        return encode_status(value)
    return encode_samples(*value)


@given(streams())
@settings(max_examples=60, deadline=None)
def test_clean_stream_in_any_chunking_loses_nothing(case):
    sent, chunks, _ = case
    # rebuild the same frames without corruption or garbage, cut at the same places
    wire = b"".join(_encode(k, v) for k, v in sent)
    cuts = sorted({min(len(wire), sum(len(c) for c in chunks[:i])) for i in range(1, len(chunks))})
    dec = StreamDecoder()
    got = []
    for a, b in zip([0, *cuts], [*cuts, len(wire)]):
        got += dec.feed(wire[a:b])
    got_samples = sum(len(f.counts) for f in got if isinstance(f, Samples))
    assert got_samples == sum(len(v[1]) for k, v in sent if k == "samples")
    assert dec.stats.dropped_bytes == 0 and dec.stats.bad_crc == 0
    assert dec.stats.frames == len(sent) and dec.buffered == 0


@pytest.mark.parametrize("sync_inside", [False, True])
def test_corrupted_frames_in_a_long_run_lose_exactly_themselves(sync_inside):
    """The vectorised path: a bad frame inside a run of equal frames costs only that frame."""
    rng = np.random.default_rng(5)
    counts = rng.integers(-32768, 32768, size=(2000, 4)).astype(np.int16)
    frames = [encode_samples(a, counts[a : a + 10]) for a in range(0, 2000, 10)]
    bad = sorted(rng.choice(len(frames), size=7, replace=False).tolist())
    for i in bad:
        f = bytearray(frames[i])
        if sync_inside:
            f[20:22] = b"\xa5\x5a"  # a sync pattern inside the damaged payload
        else:
            f[30] ^= 0x40
        frames[i] = bytes(f)
    dec = StreamDecoder()
    out = dec.feed(encode_descriptor(DESC) + b"".join(frames))
    got = {}
    for f in out:
        if isinstance(f, Samples):
            for k in range(len(f.counts)):
                got[f.first_index + k] = f.counts[k]
    missing = sorted(set(range(2000)) - set(got))
    assert missing == [10 * i + k for i in bad for k in range(10)]
    assert all(np.array_equal(got[i], counts[i]) for i in got)
    assert dec.stats.bad_crc >= len(bad)


@pytest.mark.parametrize("where", ["payload", "index", "crc"])
def test_a_read_shaped_like_the_last_frame_with_one_byte_changed_is_not_decoded(where):
    """The live reader's shortcut (`_one_like_last`) takes a read that starts like the last accepted SAMPLES frame:
    it still checks the CRC. The property test above finds a shortcut without its CRC check only when its random
    stream happens to put a damaged frame of the last one's shape at the start of a read (the planted-bug run
    of stop 31 drew no such stream), so this is the case by hand, one read a frame, as the reader thread reads."""
    dec = StreamDecoder()
    counts = np.arange(5 * 4, dtype=np.int16).reshape(5, 4)
    first = encode_samples(0, counts)
    dec.feed(encode_descriptor(DESC))
    assert [f.first_index for f in dec.feed(first)] == [0]                   # the shape the shortcut learns
    damaged = bytearray(encode_samples(5, counts + 1))
    damaged[{"payload": 11 + 7, "index": 5, "crc": len(damaged) - 1}[where]] ^= 0x40
    assert dec.feed(bytes(damaged)) == []                                    # not a frame: never samples
    assert dec.stats.frames == 2 and dec.stats.samples == 5
    good = encode_samples(10, counts + 2)
    got = dec.feed(good)                                                     # the next good read is decoded again
    assert [f.first_index for f in got if isinstance(f, Samples)] == [10]
    assert dec.stats.samples == 10
