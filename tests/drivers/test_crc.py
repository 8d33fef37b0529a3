"""CRC-16/MODBUS: every path (Python loop, position-table gather, column loop) against the
bit-by-bit definition of the spec, on both sides of each path's switch-over."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from millsense.drivers import protocol
from millsense.drivers.protocol import GATHER_BELOW_ROWS, GATHER_FROM_BYTES, crc16_modbus, crc16_modbus_rows


def crc_bitwise(data: bytes) -> int:
    """daq-protocol.md: reflected polynomial 0xA001, initial 0xFFFF, one bit at a time."""
    crc = 0xFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc


def test_check_value_of_the_catalogue():
    assert crc16_modbus(b"123456789") == 0x4B37
    assert crc16_modbus(b"") == 0xFFFF


@pytest.mark.parametrize("n", [1, 2, 3, GATHER_FROM_BYTES - 1, GATHER_FROM_BYTES, GATHER_FROM_BYTES + 1, 189, 4099])
def test_one_body_either_side_of_the_switch(n):
    data = np.random.default_rng(n).integers(0, 256, n, dtype=np.uint8).tobytes()
    assert crc16_modbus(data) == crc_bitwise(data)


@settings(max_examples=300, deadline=None)
@given(st.binary(min_size=0, max_size=700))
def test_any_body(data):
    assert crc16_modbus(data) == crc_bitwise(data)


@pytest.mark.parametrize("rows, n", [(1, 7), (1, 189), (9, 33), (GATHER_BELOW_ROWS - 1, 23), (GATHER_BELOW_ROWS, 23),
                                     (GATHER_BELOW_ROWS + 1, 24), (3, 4099)])
def test_many_bodies_either_side_of_the_switch(rows, n):
    block = np.random.default_rng(rows * 7 + n).integers(0, 256, (rows, n), dtype=np.uint8)
    got = crc16_modbus_rows(block)
    for i in np.unique(np.linspace(0, rows - 1, 40).astype(int)):
        assert int(got[i]) == crc_bitwise(block[i].tobytes()), i


def test_no_rows():
    assert crc16_modbus_rows(np.zeros((0, 12), np.uint8)).shape == (0,)


def test_table_grows_for_a_longer_body_after_a_short_one():
    """The gather table is built to the longest body seen; a longer one must extend it, not wrap."""
    short = bytes(range(200))
    long = bytes(range(256)) * 12
    assert crc16_modbus(short) == crc_bitwise(short)
    assert crc16_modbus(long) == crc_bitwise(long)
    assert len(protocol._position[0]) >= len(long)
