"""Faults on the wire, each against the real emulator subprocess and the real driver."""

from __future__ import annotations

import time

import numpy as np
import pytest

from tests.drivers.emulator_proc import Emulator, ramp, rss_kb
from tests.drivers.test_contract import Collector, check_every_sample_once, open_transport


def _values_right(blocks) -> None:
    for b in blocks:
        np.testing.assert_array_equal(b.counts, ramp(b.index, len(b.counts)))


@pytest.mark.parametrize("transport", ["pty", "tcp", "modbus-tcp"])
def test_unplug_restart_reconnect_counts_the_gap(transport, tmp_path, port):
    emu, make = open_transport(transport, tmp_path, port)
    emu2 = None
    driver = make()
    try:
        emu.start()
        driver.start()
        assert driver.wait_connected(10.0)
        col = Collector(driver)
        col.pump(2.0)
        emu.kill()  # unplugged: no goodbye
        assert col.pump(3.0, until=lambda: any(not e.up for e in col.links)), "link down not reported"
        before = [b for _, b in col.blocks]
        n_before = len(before)
        last_end = before[-1].index + len(before[-1].counts)
        # the device comes back having counted on by 10000 samples while unplugged
        # (more than a Modbus ring of 4096 holds)
        restart_index = last_end + 10000
        args = emu.args[emu.args.index("--status-log") + 2 :]
        emu2 = Emulator(tmp_path, *args, "--start-index", str(restart_index), name="sim2")
        emu2.start()
        assert col.pump(10.0, until=lambda: [e.up for e in col.links][-1:] == [True]), "no reconnect"
        col.pump(2.0)
        blocks = [b for _, b in col.blocks]
        after = blocks[n_before:]
        assert after, "no samples after reconnect"
        _values_right(blocks)
        check_every_sample_once(before)
        if len(after) > 1:
            check_every_sample_once(after[1:])
        first = after[0]
        # the gap is exactly what the device indices say: nothing invented, nothing hidden
        if transport == "modbus-tcp":  # the ring still held the last D samples: read back from H - D
            assert first.index >= restart_index - 4096
        else:  # a stream starts where it is
            assert first.index >= restart_index
        assert first.lost_before == first.index - last_end >= 10000 - 4096
        assert first.seq == before[-1].seq + len(before[-1].counts) + first.lost_before
        assert not first.discontinuity
        # the gap is the outage's, not a lossy stream's (loss_check.py): the driver marks the block, only that one
        assert first.after_link_up and not any(b.after_link_up for b in before[1:] + after[1:])
        assert [e.up for e in col.links] == [True, False, True]
    finally:
        driver.close()
        emu.stop()
        if emu2 is not None:
            emu2.stop()


def test_corrupted_frames_lose_exactly_those_samples(tmp_path, port):
    emu, make = open_transport("tcp", tmp_path, port, "--corrupt-fraction", "0.01", "--seed", "4")
    driver = make()
    try:
        emu.start()
        driver.start()
        assert driver.wait_connected(10.0)
        col = Collector(driver)
        col.pump(6.0)
        driver.close()
        emu.stop()
        blocks = [b for _, b in col.blocks]
        _values_right(blocks)  # none delivered wrong
        lo = blocks[0].index
        hi = blocks[-1].index + len(blocks[-1].counts)
        received = np.concatenate([b.index + np.arange(len(b.counts)) for b in blocks])
        assert len(np.unique(received)) == len(received)
        missing = set(range(lo, hi)) - set(received.tolist())
        corrupted = set()
        for e in emu.events("corrupt"):
            if e["frame_type"] == "samples":
                corrupted.update(range(e["first_index"], e["first_index"] + e["samples"]))
        expected = {k for k in corrupted if lo <= k < hi}
        assert len(expected) >= 30, "too few corrupted frames for a meaningful test"
        assert missing == expected
        assert sum(b.lost_before for b in blocks[1:]) == len(expected)
        stats = driver.stats()
        assert stats["decoder_bad_crc"] + stats["decoder_bad_length"] + stats["decoder_unknown_type"] > 0
    finally:
        driver.close()
        emu.stop()


def test_modbus_reader_behind_the_ring_counts_overrun_and_resumes_inside_the_ring(tmp_path, port):
    """Resumed not at H - D, the oldest sample, which the device overwrites while it is read (a slow
    reader would start there again and again), but half a second (at most D/2) later."""
    from millsense.drivers.modbus_driver import OVERRUN_MARGIN_S

    keep = 500 - min(500 // 2, int(1000 * OVERRUN_MARGIN_S))  # the ramp's 1 kHz
    depth = 500
    emu, make = open_transport("modbus-tcp", tmp_path, port, "--ring-depth", str(depth))
    driver = make()
    try:
        emu.start()
        driver.start()
        assert driver.wait_connected(10.0)
        col = Collector(driver)
        col.pump(1.0)
        n_before = len(col.blocks)
        with driver._io_lock:  # the reader thread stalls for 2 D worth of samples
            time.sleep(2 * depth / 1000)
        col.pump(1.0)
        driver.close()  # no more reads: the counters below and the blocks are final
        col.pump(0.3)  # what was still queued
        blocks = [b for _, b in col.blocks]
        _values_right(blocks)
        check_every_sample_once(blocks[:n_before])
        gaps = [i for i, b in enumerate(blocks) if b.lost_before]
        assert gaps and gaps[0] >= n_before
        resumed = blocks[gaps[0]]
        stats = driver.stats()
        assert stats["overruns"] == 1
        # It read from H - keep on (in slices of READ_SLICE_S on a slow box); what the device
        # overwrote meanwhile is cut, and counted. On a loaded machine the catch-up can leave the
        # reader behind again (later, small gaps).
        later = [b.lost_before for b in blocks[gaps[0] + 1 :] if b.lost_before]
        assert all(n < depth // 2 for n in later), later
        assert 0 < len(resumed.counts) <= keep
        prev = blocks[gaps[0] - 1]
        assert resumed.lost_before == resumed.index - (prev.index + len(prev.counts))
        assert resumed.lost_before >= depth // 2
        assert stats["lost_samples"] == sum(b.lost_before for b in blocks)  # every loss is in a block, once
    finally:
        driver.close()
        emu.stop()


def test_garbage_at_1_mb_s_no_crash_memory_bounded(tmp_path, port):
    emu, make = open_transport("tcp", tmp_path, port, "--garbage-bps", "1000000")
    driver = make()
    try:
        emu.start()
        driver.start()
        assert driver.wait_connected(10.0)
        col = Collector(driver)
        col.pump(1.0)
        rss0 = rss_kb()
        biggest = 0
        for _ in range(40):
            col.pump(0.1)
            biggest = max(biggest, driver.stats()["decoder_buffered"])
        rss1 = rss_kb()
        stats = driver.stats()
        assert driver.link_up
        assert stats["decoder_dropped_bytes"] >= 3_000_000  # the garbage really came through
        assert biggest <= 4096 + 7
        assert rss1 - rss0 < 20_000, f"RSS grew by {rss1 - rss0} kB"
        blocks = [b for _, b in col.blocks]
        assert sum(len(b.counts) for b in blocks) >= 4500
        check_every_sample_once(blocks)
    finally:
        driver.close()
        emu.stop()


def test_a_daq_restarting_under_the_stream_is_not_trusted_until_its_descriptor():
    """A DAQ that restarts while the stream goes on (behind a serial gateway, a power glitch of the DAQ alone) and
    comes back with its channels in another order: its greeting DESCRIPTOR lost, its SAMPLES have the same width,
    so nothing refuses them. The probe of stop 27 saw a second of revolutions published valid at −46 N·m, no fault.
    The real TCP driver against a real socket: the samples after the index went back are held back (counted lost),
    the DAQ is asked for its DESCRIPTOR, and samples flow again once it came, after a discontinuity."""
    import socket
    import threading

    from millsense.drivers import create_driver
    from millsense.drivers.protocol import (
        CMD_SEND_DESCRIPTOR, Channel, ChannelKind, Command, Descriptor, encode_command, encode_descriptor,
        encode_sample_frames,
    )

    chans = (Channel(ChannelKind.VOLTAGE, "v_uv"), Channel(ChannelKind.CURRENT, "i_u"))
    before = Descriptor(1000, chans)
    after = Descriptor(1000, chans[::-1])   # rewired: the same width, another order
    asked = threading.Event()
    srv = socket.create_server(("127.0.0.1", 0))
    port = srv.getsockname()[1]

    def daq() -> None:
        conn, _ = srv.accept()
        with conn:
            conn.sendall(encode_descriptor(before) + encode_sample_frames(5000, ramp(5000, 500)[:, :2]))
            time.sleep(0.3)
            conn.sendall(encode_sample_frames(0, 7 * np.ones((300, 2), dtype=np.int16)))   # restarted: index 0
            got, deadline = b"", time.monotonic() + 5.0
            want = encode_command(Command(CMD_SEND_DESCRIPTOR))
            conn.settimeout(0.1)
            while want not in got and time.monotonic() < deadline:
                try:
                    got += conn.recv(4096)
                except socket.timeout:
                    pass
            if want in got:
                asked.set()
            conn.sendall(encode_descriptor(after) + encode_sample_frames(300, 9 * np.ones((200, 2), dtype=np.int16)))
            time.sleep(1.0)

    server = threading.Thread(target=daq, daemon=True)
    server.start()
    driver = create_driver("tcp", host="127.0.0.1", tcp_port=port)
    try:
        driver.start()
        assert driver.wait_connected(5.0)
        col = Collector(driver)
        assert col.pump(5.0, until=lambda: sum(len(b.counts) for _, b in col.blocks) >= 700), \
            f"{sum(len(b.counts) for _, b in col.blocks)} samples"
    finally:
        driver.close()
        srv.close()
    blocks = [b for _, b in col.blocks]
    assert asked.is_set(), "the driver did not ask the DAQ for its descriptor"
    assert not any((b.counts == 7).all() for b in blocks), "samples of unconfirmed channels were handed on"
    first = next(b for b in blocks if (b.counts == 9).all())
    assert first.discontinuity and first.lost_before >= 300
    assert driver.descriptor == after
    assert driver.stats()["samples_unconfirmed"] == 300
