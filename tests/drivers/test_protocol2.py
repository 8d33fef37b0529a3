"""Protocol version 2 codec: CONTEXT, DESCRIPTOR capabilities, STATUS feed override,
COMMAND 0x04, longer payloads; and a version-1 stream unchanged."""

from __future__ import annotations

import struct

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from millsense.drivers.protocol import (
    CMD_SET_FEED_OVERRIDE,
    MAX_EXTENSION,
    MAX_PAYLOAD,
    Channel,
    ChannelKind,
    Command,
    Context,
    Descriptor,
    Samples,
    Status,
    StreamDecoder,
    crc16_modbus,
    encode_command,
    encode_context,
    encode_descriptor,
    encode_samples,
    encode_status,
)

pytestmark = pytest.mark.quick

CHANNELS = tuple(Channel(ChannelKind.CURRENT, f"ch{i}") for i in range(4))
DESC1 = Descriptor(1000, CHANNELS)
DESC2 = Descriptor(1000, CHANNELS, protocol_version=2, capabilities=3)


def _frame(ftype: int, payload: bytes) -> bytes:
    """A frame built from the spec by hand (not by the encoders under test)."""
    body = struct.pack("<BH", ftype, len(payload)) + payload
    return b"\xa5\x5a" + body + struct.pack("<H", crc16_modbus(body))


def test_context_frame_layout_is_the_spec():
    ctx = Context(index=0x01020304, program=70000, tool=123456, operation=0xBEEF, flags=0b1011)
    frame = encode_context(ctx)
    assert frame[2] == 0x04 and struct.unpack_from("<H", frame, 3)[0] == 15
    assert frame[5:9] == bytes([4, 3, 2, 1])
    assert struct.unpack_from("<IIHB", frame, 9) == (70000, 123456, 0xBEEF, 0b1011)
    assert frame == _frame(0x04, struct.pack("<IIIHB", 0x01020304, 70000, 123456, 0xBEEF, 0b1011))
    assert ctx.cycle and ctx.monitor and not ctx.afc_allowed and ctx.feed_held
    assert Context(0, 0, 0, 0, 0b0100).afc_allowed and not Context(0, 0, 0, 0, 0b0111).feed_held


def test_v2_descriptor_status_and_command_layouts():
    d = encode_descriptor(DESC2)
    assert struct.unpack_from("<H", d, 3)[0] == 4 + 9 * 4 + 1 and d[5] == 2 and d[-3] == 3  # capabilities last
    s = encode_status(Status(1, 0, 7, feed_override=1234))
    assert s == _frame(0x03, struct.pack("<BBHH", 1, 0, 7, 1234))
    c = encode_command(Command(CMD_SET_FEED_OVERRIDE, 2000))
    assert c == _frame(0x10, struct.pack("<BH", 0x04, 2000))
    with pytest.raises(ValueError, match="0..2000"):
        encode_command(Command(CMD_SET_FEED_OVERRIDE, 2001))


def test_round_trip_of_every_v2_frame():
    dec = StreamDecoder()
    ctx = Context(5, 2**32 - 1, 99999, 65535, 15)
    status = Status(3, 1, 65535, feed_override=0)
    cmd = Command(CMD_SET_FEED_OVERRIDE, 850)
    counts = np.arange(8, dtype=np.int16).reshape(2, 4)
    out = dec.feed(
        encode_descriptor(DESC2) + encode_context(ctx) + encode_samples(5, counts) + encode_status(status)
        + encode_command(cmd)
    )
    assert out[0] == DESC2 and out[0].has_feed_override and out[0].has_context
    assert out[1] == ctx and out[3] == status and out[4] == cmd
    assert np.array_equal(out[2].counts, counts)
    assert dec.stats.frames == 5 and dec.stats.dropped_bytes == 0


def test_a_version_1_stream_is_byte_for_byte_unchanged():
    # a version-1 descriptor and status have exactly their version-1 lengths, whatever else is set
    d = encode_descriptor(Descriptor(1000, CHANNELS, capabilities=3))
    assert struct.unpack_from("<H", d, 3)[0] == 4 + 9 * 4 and d == encode_descriptor(DESC1)
    assert encode_status(Status(1, 2, 3)) == _frame(0x03, struct.pack("<BBH", 1, 2, 3))
    out = StreamDecoder().feed(encode_descriptor(DESC1) + encode_status(Status(1, 2, 3)))
    assert out == [DESC1, Status(1, 2, 3)]
    assert out[0].capabilities == 0 and not out[0].has_feed_override and out[1].feed_override is None


def test_longer_payloads_from_version_2_on_are_taken_and_their_tail_ignored():
    tail = bytes(range(1, 11))
    d_payload = struct.pack("<BHB", 3, 1000, 4)
    d_payload += b"".join(struct.pack("<B8s", int(c.kind), c.name.encode()) for c in CHANNELS)
    d_payload += bytes([3]) + tail  # a version-3 device: capabilities, then fields we do not know
    s_payload = struct.pack("<BBHH", 1, 0, 9, 950) + tail
    dec = StreamDecoder()
    out = dec.feed(_frame(0x02, d_payload) + _frame(0x03, s_payload))
    assert out == [Descriptor(1000, CHANNELS, 3, 3), Status(1, 0, 9, 950)]
    assert dec.stats.dropped_bytes == 0


def test_longer_payloads_are_refused_where_version_1_rules_hold():
    tail = bytes(4)
    v1_desc = encode_descriptor(DESC1)
    # a descriptor that says version 1 has its exact length
    bad_desc = _frame(0x02, v1_desc[5:-2] + tail)
    # a status longer than version 2's before any version-2 descriptor was seen
    long_status = _frame(0x03, struct.pack("<BBHH", 1, 0, 9, 950) + tail)
    dec = StreamDecoder()
    assert dec.feed(bad_desc + v1_desc + long_status) == [DESC1]
    assert dec.stats.bad_length == 2 and dec.stats.frames == 1
    # and the tail is bounded: beyond MAX_EXTENSION the length counts as impossible at once
    dec2 = StreamDecoder()
    dec2.feed(encode_descriptor(DESC2))
    too_long = _frame(0x03, struct.pack("<BBHH", 1, 0, 9, 950) + bytes(MAX_EXTENSION + 1))
    good = encode_status(Status(0, 0, 1, 1000))
    assert dec2.feed(too_long + good) == [Status(0, 0, 1, 1000)]
    assert dec2.stats.bad_length == 1


def test_wrong_context_length_and_short_v2_status_are_refused():
    dec = StreamDecoder()
    frames = _frame(0x04, bytes(14)) + _frame(0x04, bytes(16)) + _frame(0x03, bytes(5))
    assert dec.feed(encode_descriptor(DESC2) + frames) == [DESC2]
    assert dec.stats.bad_length == 3


# ----------------------------------------------------------------- hypothesis


contexts = st.builds(
    Context,
    st.integers(0, 2**32 - 1), st.integers(0, 2**32 - 1), st.integers(0, 2**32 - 1),
    st.integers(0, 65535), st.integers(0, 255),
)
statuses = st.builds(Status, st.integers(0, 3), st.integers(0, 3), st.integers(0, 65535),
                     st.one_of(st.none(), st.integers(0, 2000)))
commands = st.builds(Command, st.just(CMD_SET_FEED_OVERRIDE), st.integers(0, 2000))


@st.composite
def v2_streams(draw):
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    sent = [DESC2]
    index = draw(st.integers(0, 2**32 - 1))
    for _ in range(draw(st.integers(1, 30))):
        kind = draw(st.sampled_from(["samples", "samples", "context", "status", "command", "descriptor"]))
        if kind == "samples":
            s = draw(st.integers(1, 12))
            sent.append(Samples(index, rng.integers(-32768, 32768, size=(s, 4)).astype(np.int16)))
            index = (index + s) % (1 << 32)
        elif kind == "context":
            sent.append(draw(contexts))
        elif kind == "status":
            sent.append(draw(statuses))
        elif kind == "command":
            sent.append(draw(commands))
        else:
            sent.append(DESC2)
    corrupt = draw(st.lists(st.booleans(), min_size=len(sent), max_size=len(sent)))
    garbage = draw(st.lists(st.binary(max_size=20), min_size=len(sent), max_size=len(sent)))
    cuts = draw(st.lists(st.integers(0, 10_000), max_size=10))
    return sent, corrupt, garbage, cuts, rng


def _encode(frame) -> bytes:
    if isinstance(frame, Descriptor):
        return encode_descriptor(frame)
    if isinstance(frame, Context):
        return encode_context(frame)
    if isinstance(frame, Status):
        return encode_status(frame)
    if isinstance(frame, Command):
        return encode_command(frame)
    return encode_samples(frame.first_index, frame.counts)


@given(v2_streams())
@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
def test_v2_frames_through_noise_are_frames_that_were_sent(case):
    sent, corrupt, garbage, cuts, rng = case
    wire = b""
    intact_bytes = 0
    for frame, bad, junk in zip(sent, corrupt, garbage):
        data = _encode(frame)
        if bad:
            b = bytearray(data)
            b[int(rng.integers(0, len(b)))] ^= int(rng.integers(1, 256))
            data = bytes(b)
        else:
            intact_bytes += len(data)
        wire += junk + data
    cuts = sorted(c % (len(wire) + 1) for c in cuts)
    dec = StreamDecoder()
    got = []
    for a, b in zip([0, *cuts], [*cuts, len(wire)]):
        got += dec.feed(wire[a:b])
    # A corrupted length field makes the decoder wait for up to MAX_PAYLOAD bytes before its CRC can
    # fail; the frames behind it are held, not lost. A live stream goes on: so does this one, with
    # bytes that hold no sync.
    padding = MAX_PAYLOAD + 16
    got += dec.feed(bytes(padding))
    truth = {}
    for f in sent:
        if isinstance(f, Samples):
            for k in range(len(f.counts)):
                truth[(f.first_index + k) % (1 << 32)] = tuple(f.counts[k].tolist())
    others = [f for f in sent if not isinstance(f, Samples)]
    for f in got:
        if isinstance(f, Samples):
            for k in range(len(f.counts)):
                assert truth[(f.first_index + k) % (1 << 32)] == tuple(f.counts[k].tolist())
        else:
            assert f in others  # a v2 frame decoded is one that was sent, field for field
    intact = [f for f, bad in zip(sent, corrupt) if not bad]
    assert dec.stats.frames == len(intact)  # every intact v2 frame decoded, no corrupted one
    assert dec.stats.dropped_bytes + dec.buffered == len(wire) + padding - intact_bytes


@given(contexts, statuses, commands)
def test_v2_round_trips_any_value(ctx, status, cmd):
    out = StreamDecoder().feed(encode_descriptor(DESC2) + encode_context(ctx) + encode_status(status)
                               + encode_command(cmd))
    assert out == [DESC2, ctx, status, cmd]
