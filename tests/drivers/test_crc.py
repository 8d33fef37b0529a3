"""CRC-16/MODBUS: every path (the compiled one-body CRC, the position-table gather and the column loop
over many rows) against the bit-by-bit definition of the spec, on both sides of each path's switch-over."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from millsense.drivers import protocol
from millsense.drivers.protocol import GATHER_BELOW_ROWS, crc16_modbus, crc16_modbus_rows
from tests.firmware.frames import crc16

pytestmark = pytest.mark.quick


def test_check_value_of_the_catalogue():
    assert crc16_modbus(b"123456789") == 0x4B37
    assert crc16_modbus(b"") == 0xFFFF


def test_the_one_body_crc_is_the_compiled_one():
    """The reader thread's per-frame CRC is crcmod-plus's C extension (README, "Dependencies"): where its
    wheel's code does not load, crcmod falls back to pure Python silently, correct and five times slower."""
    import crcmod.crcmod

    assert crcmod.crcmod._usingExtension


@pytest.mark.parametrize("n", [1, 2, 3, 159, 160, 161, 189, 4099])
def test_one_body(n):
    data = np.random.default_rng(n).integers(0, 256, n, dtype=np.uint8).tobytes()
    assert crc16_modbus(data) == crc16(data)
    # the decoder passes slices of its bytearray buffer, and views
    assert crc16_modbus(bytearray(data)) == crc16_modbus(memoryview(data)) == crc16(data)


@settings(max_examples=300, deadline=None)
@given(st.binary(min_size=0, max_size=700))
def test_any_body(data):
    assert crc16_modbus(data) == crc16(data)


@pytest.mark.parametrize("rows, n", [(1, 7), (1, 189), (9, 33), (GATHER_BELOW_ROWS - 1, 23), (GATHER_BELOW_ROWS, 23),
                                     (GATHER_BELOW_ROWS + 1, 24), (3, 4099)])
def test_many_bodies_either_side_of_the_switch(rows, n):
    block = np.random.default_rng(rows * 7 + n).integers(0, 256, (rows, n), dtype=np.uint8)
    got = crc16_modbus_rows(block)
    for i in np.unique(np.linspace(0, rows - 1, 40).astype(int)):
        assert int(got[i]) == crc16(block[i].tobytes()), i


def test_no_rows():
    assert crc16_modbus_rows(np.zeros((0, 12), np.uint8)).shape == (0,)


def test_table_grows_for_a_longer_body_after_a_short_one():
    """The gather table is built to the longest body seen; a longer one must extend it, not wrap."""
    short = np.frombuffer(bytes(range(200)), np.uint8)[None, :]
    long = np.frombuffer(bytes(range(256)) * 12, np.uint8)[None, :]
    assert int(crc16_modbus_rows(short)[0]) == crc16(short.tobytes())
    assert int(crc16_modbus_rows(long)[0]) == crc16(long.tobytes())
    assert len(protocol._position[0]) >= long.shape[1]
