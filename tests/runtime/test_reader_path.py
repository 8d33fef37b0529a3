"""The reader thread's per-frame path (issue 13): the decoder's one-frame shortcut, the TCP reader's
one call per frame, the OS names of the daemon's threads."""

from __future__ import annotations

import os
import socket
import threading

import numpy as np
import pytest

from millsense.drivers.base import name_os_thread
from millsense.drivers.protocol import (
    Channel,
    ChannelKind,
    Descriptor,
    Status,
    StreamDecoder,
    encode_descriptor,
    encode_samples,
    encode_status,
)
from millsense.drivers.tcp_driver import TcpDriver

pytestmark = pytest.mark.quick

DESC = Descriptor(1000, tuple(Channel(ChannelKind.OTHER, f"c{k}") for k in range(4)))


def _frames(n: int, per: int = 10, seed: int = 1) -> list[bytes]:
    rng = np.random.default_rng(seed)
    return [encode_samples(k * per, rng.integers(-3000, 3000, (per, 4)).astype(np.int16)) for k in range(n)]


def _same(a: list, b: list) -> None:
    assert len(a) == len(b)
    for x, y in zip(a, b):
        assert type(x) is type(y)
        if hasattr(x, "counts"):
            assert x.first_index == y.first_index
            assert x.counts.dtype == np.int16 and x.counts.flags.writeable
            np.testing.assert_array_equal(x.counts, y.counts)
        else:
            assert x == y


def test_one_frame_reads_decode_as_the_whole_stream_does() -> None:
    """Frame by frame (the shortcut) and in one piece (the general path): the same frames, the same
    counters, with a corrupt frame, a STATUS behind a frame, a frame of another shape between them."""
    frames = _frames(12)
    bad = bytearray(frames[3])
    bad[20] ^= 0xFF  # a corrupt frame: the shortcut must not take it
    odd = encode_samples(120, np.arange(20, dtype=np.int16).reshape(5, 4))  # another samples-per-frame
    status = encode_status(Status(0, 0, 7))
    reads = [encode_descriptor(DESC), frames[0], frames[1], frames[2], bytes(bad), frames[4],
             frames[5] + status, odd, frames[6], frames[7] + frames[8], frames[9][:50], frames[9][50:], frames[10]]
    piecewise, whole = StreamDecoder(), StreamDecoder()
    got = [f for r in reads for f in piecewise.feed(r)]
    want = whole.feed(b"".join(reads))
    # the general path merges contiguous frames of one read: compare sample by sample
    assert [type(f) for f in got if not hasattr(f, "counts")] == [type(f) for f in want if not hasattr(f, "counts")]
    cat = lambda fs: np.concatenate([f.counts for f in fs if hasattr(f, "counts")])  # noqa: E731
    np.testing.assert_array_equal(cat(got), cat(want))
    assert piecewise.stats.as_dict() == whole.stats.as_dict()
    assert piecewise.stats.bad_crc == 1


def test_the_shortcut_takes_the_live_reads() -> None:
    """A frame alone in a read, or with a STATUS behind it, goes the short way (no general path)."""
    dec = StreamDecoder()
    frames = _frames(4)
    dec.feed(encode_descriptor(DESC) + frames[0])
    calls = []
    general = dec._feed
    dec._feed = lambda data: calls.append(len(data)) or general(data)  # type: ignore[method-assign]
    _same(dec.feed(frames[1]), StreamDecoder().feed(encode_descriptor(DESC) + frames[1])[1:])
    assert calls == []
    out = dec.feed(frames[2] + encode_status(Status(0, 0, 3)))
    assert [type(f).__name__ for f in out] == ["Samples", "Status"]
    assert calls == [len(encode_status(Status(0, 0, 3)))]  # only the STATUS went the general way


def test_tcp_reader_reads_each_frame_as_it_lands_and_stops_promptly() -> None:
    """Blocking `recv` under the kernel's timeout: frames arrive, and close() returns though nothing comes."""
    server = socket.create_server(("127.0.0.1", 0))
    port = server.getsockname()[1]
    drv = TcpDriver("127.0.0.1", port, read_timeout_s=0.05)
    drv.start()
    conn, _ = server.accept()
    try:
        assert drv.wait_connected(10.0)
        conn.sendall(encode_descriptor(DESC))
        frames = _frames(5)
        for f in frames:
            conn.sendall(f)
        got = []
        while sum(len(b.counts) for b in got) < 50:
            ev = drv.get(timeout=10.0)
            assert ev is not None, "no frames from the reader"
            if hasattr(ev, "counts"):
                got.append(ev)
        assert got[0].seq == 0
        done = threading.Event()
        threading.Thread(target=lambda: (drv.close(), done.set()), daemon=True).start()
        assert done.wait(10.0), "close() hung on a reader blocked in recv"
    finally:
        drv.close()
        conn.close()
        server.close()


def test_threads_carry_their_names_into_the_os() -> None:
    seen = {}

    def run() -> None:
        name_os_thread("ms-test-name-too-long-for-linux")
        seen["comm"] = open(f"/proc/self/task/{threading.get_native_id()}/comm").read().strip()

    t = threading.Thread(target=run)
    t.start()
    t.join()
    if os.path.exists("/proc/self/task"):
        assert seen["comm"] == "ms-test-name-to"  # Linux keeps 15 bytes


def test_tcp_reader_keeps_the_last_frames_of_a_peer_that_closes() -> None:
    """Frames the DAQ sent right before it closed are decoded before the link goes down."""
    server = socket.create_server(("127.0.0.1", 0))
    drv = TcpDriver("127.0.0.1", server.getsockname()[1], read_timeout_s=0.05)
    drv.read_interval_s = 0.5  # what lands within 0.5 s of a read goes the batched way, for sure
    drv.start()
    conn, _ = server.accept()
    try:
        assert drv.wait_connected(10.0)
        conn.sendall(encode_descriptor(DESC) + _frames(1)[0])
        first = drv.get(timeout=10.0)
        while first is not None and not hasattr(first, "counts"):
            first = drv.get(timeout=10.0)
        assert first is not None
        conn.sendall(b"".join(_frames(6)[1:]))  # within the spacing of the last read: the batched read
        conn.close()  # with the driver's descriptor request unread: a reset, found by the batched read
        got, down = len(first.counts), None
        while down is None:
            ev = drv.get(timeout=10.0)
            assert ev is not None, "the link never went down"
            if hasattr(ev, "counts"):
                got += len(ev.counts)
            elif hasattr(ev, "up") and not ev.up:
                down = ev
        assert got == 60
    finally:
        drv.close()
        server.close()
