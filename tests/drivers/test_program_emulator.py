"""The part program behind the real emulator: CONTEXT frames over TCP and in a capture, Modbus registers 8-15.

The expected context comes from the plant itself, run in-process with the same options
(sim/program.py ProgramPlant): the emulator must deliver exactly the CNC's changes,
each with the index of the first sample it holds for, in stream order.
"""

from __future__ import annotations

import socket
import subprocess
import time

from millsense.drivers.protocol import CAP_CONTEXT, Context, Descriptor, Samples, StreamDecoder
from millsense.sim.program_plant import ProgramPlant
from tests.drivers.emulator_proc import SIM_CMD, Emulator

PROGRAM = ["--scenario", "part-program", "--parts", "2"]


def _expected_changes(n_samples: int) -> list[tuple[int, tuple[int, int, int, int]]]:
    plant = ProgramPlant(parts=2)
    first = [(0, plant.context())]
    plant.step(n_samples)
    return first + plant.drain_context()


def _walk(frames, into: dict) -> None:
    """Follow the stream: sample indices, and every CONTEXT with the index of the next sample then."""
    for f in frames:
        if isinstance(f, Descriptor):
            into["descriptor"] = f
        elif isinstance(f, Samples):
            if into["next"] is not None:
                assert f.first_index == into["next"], "samples lost or reordered"
            else:
                into["first"] = f.first_index
            into["next"] = (f.first_index + len(f.counts)) % 2**32  # the index wraps at 2^32
            into["count"] = into.get("count", 0) + len(f.counts)
        elif isinstance(f, Context):
            into["contexts"].append((f, into["next"]))


def _changes(contexts) -> list[tuple[Context, int | None]]:
    out = []
    for ctx, at in contexts:
        if not out or ctx != out[-1][0]:
            out.append((ctx, at))
    return out


def test_context_frames_arrive_over_tcp_just_before_the_sample_they_hold_for(tmp_path, port):
    emu = Emulator(tmp_path, *PROGRAM, "--tcp", f"127.0.0.1:{port}")
    seen = {"descriptor": None, "next": None, "first": None, "contexts": []}
    dec = StreamDecoder()
    want_index = 6500  # past the first cut and into the second tool's change (about 6.5 s of samples)
    try:
        emu.start()
        with socket.create_connection(("127.0.0.1", port), timeout=10) as sock:
            deadline = time.monotonic() + 60
            while (seen["next"] is None or seen["next"] < want_index) and time.monotonic() < deadline:
                data = sock.recv(65536)
                assert data, "the emulator closed the connection"
                _walk(dec.feed(data), seen)
    finally:
        assert emu.stop() is not None
    assert seen["next"] >= want_index
    desc = seen["descriptor"]
    assert desc.protocol_version == 2 and desc.capabilities & CAP_CONTEXT  # protocol 2 by default here
    assert "fx_rate" in desc.names
    expected = [(k, ctx) for k, ctx in _expected_changes(seen["next"]) if k < seen["next"]]
    got = _changes(seen["contexts"])
    # the client connected after the start: it sees the context holding then (sent on connect), and
    # from there every change, each just before its first sample
    (ctx0, _), later = got[0], got[1:]
    k0, held = [(k, ctx) for k, ctx in expected if k <= seen["first"]][-1]
    assert (ctx0.index, (ctx0.program, ctx0.tool, ctx0.operation, ctx0.flags)) == (k0, held)
    assert [(c.index, (c.program, c.tool, c.operation, c.flags)) for c, _ in later] == [
        (k, ctx) for k, ctx in expected if k > ctx0.index]
    assert len(later) >= 4 and len({c.tool for c, _ in later}) >= 2  # monitor on/off and a tool change
    assert all(c.index == at for c, at in later)
    # and once a second the same CONTEXT again (with the DESCRIPTOR)
    assert len(seen["contexts"]) > len(got)
    assert dec.stats.dropped_bytes == 0


def test_a_capture_holds_every_context_change_in_stream_order(tmp_path):
    cap, truth = tmp_path / "p.cap", tmp_path / "p.jsonl"
    res = subprocess.run([*SIM_CMD, *PROGRAM, "--capture", str(cap), "--truth", str(truth),
                          "--start-index", str(2**32 - 5000)], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    seen = {"descriptor": None, "next": None, "first": None, "contexts": []}
    dec = StreamDecoder()
    _walk(dec.feed(cap.read_bytes()), seen)
    start = 2**32 - 5000
    plant = ProgramPlant(parts=2)
    total = round(plant.scenario.duration_s * 1000)
    expected = [((start + k) % 2**32, ctx) for k, ctx in _expected_changes(total)]
    got = _changes(seen["contexts"])
    assert [(c.index, (c.program, c.tool, c.operation, c.flags)) for c, _ in got] == expected
    # the first one comes before any sample; each later one right before its first sample (the index wraps)
    assert got[0][1] is None
    assert all(c.index == at for c, at in got[1:])
    assert seen["count"] == total and any(c.index < start for c, _ in got)  # some after the wrap


def test_modbus_input_registers_8_to_15_follow_the_program(tmp_path, port):
    from pymodbus.client import ModbusTcpClient

    emu = Emulator(tmp_path, *PROGRAM, "--modbus-tcp", f"127.0.0.1:{port}")
    client = ModbusTcpClient("127.0.0.1", port=port, timeout=2)
    expected = _expected_changes(3000)
    monitor_on = next(k for k, ctx in expected if ctx[3] & 0x02)
    try:
        emu.start()
        assert client.connect()
        assert client.read_input_registers(0, count=1, device_id=1).registers == [2]
        seen_flags = set()
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            regs = client.read_input_registers(4, count=12, device_id=1).registers  # one read: head and context
            head = regs[0] << 16 | regs[1]
            assert regs[3] & CAP_CONTEXT
            program, tool = regs[4] << 16 | regs[5], regs[6] << 16 | regs[7]
            operation, flags, index = regs[8], regs[9], regs[10] << 16 | regs[11]
            k, ctx = [(k, ctx) for k, ctx in expected if k < head][-1]  # the context of the last sample made
            assert (index, (program, tool, operation, flags)) == (k, ctx), head
            seen_flags.add(flags)
            if head > monitor_on + 100:
                break
            time.sleep(0.05)
        # cycle off, cycle (tool change), cycle and monitor and adaptive feed allowed (T11's cut)
        assert {0, 0x01, 0x07} <= seen_flags
    finally:
        client.close()
        emu.stop()


def test_the_in_process_sim_driver_passes_each_context_before_its_samples():
    from millsense.drivers.base import SampleBlock
    from millsense.drivers.sim_driver import SimDriver

    drv = SimDriver("part-program", realtime=False)  # the config's transport = "sim" (protocol 1 asked)
    seen = {"next": None, "contexts": []}
    try:
        drv.start()
        assert drv.wait_connected(10)
        deadline = time.monotonic() + 60
        while (seen["next"] is None or seen["next"] < 6500) and time.monotonic() < deadline:
            ev = drv.get(0.1)
            if isinstance(ev, SampleBlock):
                assert seen["next"] in (None, ev.index)
                seen["next"] = ev.index + len(ev.counts)
            elif isinstance(ev, Context):
                seen["contexts"].append((ev, seen["next"]))
    finally:
        drv.close()
    assert drv.descriptor.has_context  # protocol 2 for a part program
    expected = [(k, ctx) for k, ctx in _expected_changes(seen["next"]) if k < seen["next"]]
    got = seen["contexts"]
    assert [(c.index, (c.program, c.tool, c.operation, c.flags)) for c, _ in got] == expected
    assert all(c.index == at for c, at in got[1:])  # each change just before its first sample


def test_write_capture_writes_a_part_program_as_the_emulator_does(tmp_path):
    from millsense.sim import write_capture

    ours, theirs = tmp_path / "w.cap", tmp_path / "s.cap"
    n = write_capture("part-program", ours, parts=1, seed=3, per_frame=7)
    res = subprocess.run([*SIM_CMD, "--scenario", "part-program", "--parts", "1", "--seed", "3", "--per-frame", "7",
                          "--capture", str(theirs)], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    walks = []
    for path in (ours, theirs):
        seen = {"descriptor": None, "next": None, "first": None, "contexts": []}
        frames = StreamDecoder().feed(path.read_bytes())
        _walk(frames, seen)
        samples = [f.counts for f in frames if isinstance(f, Samples)]
        walks.append((seen, samples))
    (a, sa), (b, sb) = walks
    assert a["descriptor"] == b["descriptor"] and a["count"] == b["count"] == n
    assert all((x == y).all() for x, y in zip(sa, sb, strict=True))
    assert _changes(a["contexts"]) == _changes(b["contexts"])
    assert len(_changes(a["contexts"])) == 1 + len(ProgramPlant(parts=1).program.operations) * 3 + 1
