"""`millsense sim --start-on-connect`: the run's first sample waits for the first client.

A live test starts the emulator, then the daemon; the emulator (as a machine does) plays from its start,
and a daemon whose start-up outlasts the lead-in misses the run's beginning (the first cut seen from its
middle). With the flag the first sample is made when the first client connects (Modbus: its first request),
so the client sees the run from its first sample however late it comes. The client here is late on
purpose: LATE_S after the emulator says it is serving, more than the frames the emulator would otherwise
have made and thrown away (10 samples a frame at 1 kHz).
"""

from __future__ import annotations

import socket
import subprocess
import time

import numpy as np
import pytest

from millsense.drivers.protocol import Samples, StreamDecoder
from tests.drivers.emulator_proc import SIM_CMD, Emulator, ramp
from tests.e2e.helpers import wait_for

LATE_S = 0.5  # the late client: what is tested, not a wait for anything to settle
START = 70000
RATE_HZ, PER_FRAME = 1000, 10  # the ramp's


def _samples(sock: socket.socket, n: int, timeout_s: float = 10.0) -> list[tuple[float, Samples]]:
    """The SAMPLES frames up to `n` samples, each with the monotonic time it was read."""
    dec = StreamDecoder()
    out: list[tuple[float, Samples]] = []
    deadline = time.monotonic() + timeout_s
    sock.settimeout(1.0)
    while sum(len(f.counts) for _, f in out) < n:
        assert time.monotonic() < deadline, f"not {n} samples within {timeout_s} s"
        try:
            data = sock.recv(4096)
        except TimeoutError:
            continue
        assert data, "the emulator closed the connection"
        now = time.monotonic()
        out += [(now, f) for f in dec.feed(data) if isinstance(f, Samples)]
    return out


@pytest.mark.quick
def test_the_first_tcp_client_sees_the_first_sample_however_late_it_connects(tmp_path, port):
    with Emulator(tmp_path, "--tcp", f"127.0.0.1:{port}", "--start-index", str(START), "--start-on-connect") as emu:
        assert emu.events("start") == []  # serving, and nothing played yet
        time.sleep(LATE_S)
        connected = time.monotonic()
        with socket.create_connection(("127.0.0.1", port), timeout=5) as sock:
            frames = _samples(sock, 100)
            assert frames[0][1].first_index == START
            k = START
            for read_at, f in frames:
                assert f.first_index == k
                np.testing.assert_array_equal(f.counts, ramp(k, len(f.counts)))
                k += len(f.counts)
                # played from the connect at 1 kHz, not the samples of LATE_S caught up in a burst (a bound
                # load can only keep: a sample is never read before it is made)
                assert k - START <= (read_at - connected) * RATE_HZ + PER_FRAME, (k - START, read_at - connected)
            (start,) = wait_for(lambda: emu.events("start"), 10.0, "the status log's start event")
            assert start["first_index"] == START and start["mono"] >= connected


@pytest.mark.quick
@pytest.mark.parametrize("transport", ["modbus-tcp", "modbus-rtu"])
def test_the_first_modbus_request_reads_the_first_index_however_late_it_comes(tmp_path, port, transport):
    from pymodbus import FramerType
    from pymodbus.client import ModbusSerialClient, ModbusTcpClient

    if transport == "modbus-tcp":
        where = f"127.0.0.1:{port}"
        client = ModbusTcpClient("127.0.0.1", port=port, timeout=2)
    else:
        where = str(tmp_path / "rtu")
        client = ModbusSerialClient(where, framer=FramerType.RTU, baudrate=921600, timeout=2, retries=0)
    emu = Emulator(tmp_path, f"--{transport}", where, "--start-index", str(START), "--start-on-connect")
    try:
        emu.start()
        assert emu.events("start") == []
        time.sleep(LATE_S)
        asked = time.monotonic()
        assert client.connect()
        hi, lo = client.read_input_registers(4, count=2, device_id=1).registers
        assert hi << 16 | lo == START  # the head: the index the next sample will get
        hi, lo = client.read_input_registers(4, count=2, device_id=1).registers
        # played from the request at 1 kHz, not the samples of LATE_S caught up in a burst
        assert (hi << 16 | lo) - START <= (time.monotonic() - asked) * RATE_HZ + 1
        (start,) = wait_for(lambda: emu.events("start"), 10.0, "the status log's start event")
        assert start["first_index"] == START and start["mono"] >= asked

        def head():
            hi, lo = client.read_input_registers(4, count=2, device_id=1).registers
            return (hi << 16 | lo) > START

        wait_for(head, 10.0, "the run playing after the first request")
    finally:
        client.close()
        emu.stop()


@pytest.mark.parametrize("where", [["--capture", "x.cap"], ["--pty", "x.pty"]])
def test_start_on_connect_without_a_client_to_wait_for_is_refused(tmp_path, where):
    res = subprocess.run([*SIM_CMD, "--scenario", "ramp", *where, "--start-on-connect"], capture_output=True,
                         text=True, timeout=60, cwd=tmp_path)
    assert res.returncode == 2, res.stderr
    assert "--start-on-connect" in res.stderr and "Traceback" not in res.stderr
