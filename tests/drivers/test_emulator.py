"""The emulator's own promises: captures, several TCP clients, a pty that survives reopening."""

from __future__ import annotations

import subprocess
import time

import numpy as np
import pytest

from millsense.drivers import create_driver
from millsense.drivers.base import SampleBlock
from millsense.drivers.protocol import Descriptor, Samples, StreamDecoder
from millsense.drivers.sim_driver import SimDriver
from tests.drivers.emulator_proc import SIM_CMD, Emulator, ramp
from tests.drivers.test_contract import Collector, check_every_sample_once


@pytest.mark.quick
def test_capture_fast_is_exact_and_repeats_the_descriptor(tmp_path):
    out = tmp_path / "ramp.cap"
    res = subprocess.run(
        [*SIM_CMD, "--scenario", "ramp", "--capture", str(out), "--duration-s", "5",
         "--start-index", str(2**32 - 2500)],
        capture_output=True, text=True, timeout=60,
    )
    assert res.returncode == 0, res.stderr
    dec = StreamDecoder()
    frames = dec.feed(out.read_bytes())
    assert sum(isinstance(f, Descriptor) for f in frames) == 5  # at start and once a second of sample time
    samples = [f for f in frames if isinstance(f, Samples)]
    assert sum(len(s.counts) for s in samples) == 5000
    k = 2**32 - 2500
    for s in samples:
        assert s.first_index == k % 2**32
        np.testing.assert_array_equal(s.counts, ramp(s.first_index, len(s.counts)))
        k += len(s.counts)
    assert dec.stats.dropped_bytes == 0


def test_list_and_bad_arguments_are_clear():
    res = subprocess.run([*SIM_CMD, "--list"], capture_output=True, text=True, timeout=30)
    assert res.returncode == 0 and "ramp" in res.stdout
    res = subprocess.run([*SIM_CMD, "--scenario", "no-such", "--tcp", "127.0.0.1:1"], capture_output=True, text=True,
                         timeout=30)
    assert res.returncode == 2 and "no-such" in res.stderr and "Traceback" not in res.stderr
    res = subprocess.run([*SIM_CMD, "--scenario", "ramp", "--tcp", "nonsense"], capture_output=True, text=True,
                         timeout=30)
    assert res.returncode == 2 and "HOST:PORT" in res.stderr


def test_tcp_serves_several_clients_and_obeys_any(tmp_path, port):
    emu = Emulator(tmp_path, "--tcp", f"127.0.0.1:{port}")
    a = create_driver("tcp", host="127.0.0.1", tcp_port=port)
    b = create_driver("tcp", host="127.0.0.1", tcp_port=port)
    try:
        emu.start()
        a.start()
        assert a.wait_connected(10)
        ca = Collector(a)
        ca.pump(1.0)
        b.start()  # joins later: gets the stream from its connect on
        assert b.wait_connected(10)
        cb = Collector(b)
        cb.pump(1.0)
        b.set_outputs(True)
        assert ca.pump(1.0, until=lambda: a.last_status and a.last_status.feed_hold), "A did not see B's command"
        ca.pump(0.5)
        cb.pump(0.1)
        blocks_a = [x for _, x in ca.blocks]
        blocks_b = [x for _, x in cb.blocks]
        check_every_sample_once(blocks_a)
        check_every_sample_once(blocks_b)
        assert blocks_b[0].index > blocks_a[0].index + 500
    finally:
        a.close()
        b.close()
        assert emu.stop() == 0  # SIGTERM: a clean exit


def test_pty_survives_the_reader_closing_and_reopening(tmp_path):
    link = str(tmp_path / "link")
    emu = Emulator(tmp_path, "--pty", link)
    try:
        emu.start()
        for _ in range(2):
            drv = create_driver("serial", port=link)
            drv.start()
            try:
                assert drv.wait_connected(10)
                col = Collector(drv)
                # 800 samples (0.8 s of the stream) arriving is the event; the wait's bound is only a backstop
                assert col.pump(30.0, until=lambda: sum(len(x.counts) for _, x in col.blocks) >= 800)
                blocks = [x for _, x in col.blocks]
                check_every_sample_once(blocks)
            finally:
                drv.close()
            time.sleep(0.5)  # nobody reads for a while
        # a pyserial URL works as a port too
    finally:
        assert emu.stop() == 0


@pytest.mark.quick
def test_serial_driver_takes_a_socket_url(tmp_path, port):
    emu = Emulator(tmp_path, "--tcp", f"127.0.0.1:{port}")
    drv = create_driver("serial", port=f"socket://127.0.0.1:{port}")
    try:
        emu.start()
        drv.start()
        assert drv.wait_connected(10)
        col = Collector(drv)
        col.pump(1.0)
        check_every_sample_once([x for _, x in col.blocks])
    finally:
        drv.close()
        emu.stop()


@pytest.mark.quick
def test_full_queue_drops_newest_and_carries_the_count():
    drv = SimDriver("ramp", queue_size=5)
    drv.start()
    try:
        assert drv.wait_connected(2)
        # nobody consumes: the queue of 5 fills and the driver drops and counts what follows (the event waited
        # for, not a time: a loaded box may read fewer frames in a given half second)
        deadline = time.monotonic() + 30.0
        while drv.stats().get("queue_dropped_samples", 0) < 300 and time.monotonic() < deadline:
            time.sleep(0.02)
        got = []
        deadline = time.monotonic() + 1.0
        while time.monotonic() < deadline:
            ev = drv.get(0.05)
            if isinstance(ev, SampleBlock):
                got.append(ev)
        dropped = drv.stats()["queue_dropped_samples"]
        assert dropped >= 300
        gaps = [b for b in got if b.lost_before]
        assert sum(b.lost_before for b in gaps) == dropped
        for prev, b in zip(got, got[1:]):
            assert b.seq == prev.seq + len(prev.counts) + b.lost_before
            np.testing.assert_array_equal(b.counts, ramp(b.index, len(b.counts)))
    finally:
        drv.close()


@pytest.mark.quick
def test_modbus_register_map_is_the_spec(tmp_path, port):
    """Read the map with a plain pymodbus client, decoding by daq-protocol.md alone."""
    from pymodbus.client import ModbusTcpClient

    emu = Emulator(tmp_path, "--modbus-tcp", f"127.0.0.1:{port}", "--ring-depth", "1000", "--start-index", "70000")
    client = ModbusTcpClient("127.0.0.1", port=port, timeout=2)
    try:
        emu.start()
        assert client.connect()
        version, c, rate, depth = client.read_input_registers(0, count=4, device_id=1).registers
        assert (version, c, rate, depth) == (1, 8, 1000, 1000)
        table = client.read_input_registers(16, count=5 * c, device_id=1).registers
        assert table[0] == 1  # voltage
        assert table[1:5] == [ord("v") << 8 | ord("_"), ord("u") << 8 | ord("v"), 0, 0]  # "v_uv", first byte high
        assert table[5 * 7] == 4  # sp_enc is an encoder
        hi, lo = client.read_input_registers(4, count=2, device_id=1).registers
        head = hi << 16 | lo
        assert 70000 < head < 70000 + 5000
        k = head - 10
        regs = client.read_input_registers(1000 + (k % depth) * c, count=c, device_id=1).registers
        assert np.array(regs, dtype=np.uint16).view(np.int16).tolist() == ramp(k, 1)[0].tolist()
        # outputs: coil 0 -> discrete input 0; holding 100/101 are the host's
        client.write_coil(0, True, device_id=1)
        assert client.read_discrete_inputs(0, count=1, device_id=1).bits[0]
        client.write_coil(0, False, device_id=1)
        assert not client.read_discrete_inputs(0, count=1, device_id=1).bits[0]
        client.write_register(101, 250, device_id=1)
        client.write_register(100, 7, device_id=1)
        assert client.read_holding_registers(100, count=2, device_id=1).registers == [7, 250]
        changes = [e for e in emu.events() if e["event"] in ("outputs", "watchdog_period", "heartbeat")]
        assert [e["event"] for e in changes] == ["outputs", "outputs", "watchdog_period", "heartbeat"]
    finally:
        client.close()
        emu.stop()


def test_a_plant_scenario_serves_and_writes_its_truth(tmp_path):
    """The emulator around the real plant simulator: a capture plus per-revolution truth."""
    import json

    out, truth = tmp_path / "step.cap", tmp_path / "step.jsonl"
    res = subprocess.run(
        [*SIM_CMD, "--scenario", "step", "--capture", str(out), "--truth", str(truth), "--duration-s", "2"],
        capture_output=True, text=True, timeout=120,
    )
    assert res.returncode == 0, res.stderr
    frames = StreamDecoder().feed(out.read_bytes())
    assert sum(len(f.counts) for f in frames if isinstance(f, Samples)) == 2000
    revs = [json.loads(line) for line in truth.read_text().splitlines()]
    assert revs and all("torque_nm" in r or "event" in r for r in revs)


def _capture_frames(tmp_path, name, *flags):
    out = tmp_path / f"{name}.cap"
    res = subprocess.run([*SIM_CMD, "--scenario", "step", "--capture", str(out), "--duration-s", "2", *flags],
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    frames = StreamDecoder().feed(out.read_bytes())
    desc = next(f for f in frames if isinstance(f, Descriptor))
    counts = np.concatenate([f.counts for f in frames if isinstance(f, Samples)])
    return desc, counts


def test_sensor_fault_flags_change_only_what_they_say(tmp_path):
    desc, clean = _capture_frames(tmp_path, "clean")
    col = {ch.name: k for k, ch in enumerate(desc.channels)}
    cur = [col[n] for n in ("i_u", "i_v", "i_w")]
    assert np.abs(clean[:, cur]).max() > 1000  # the plant's currents swing thousands of counts

    _, pinned = _capture_frames(tmp_path, "pinned", "--pin", "i_v=1234", "--pin", "sp_enc=-7")
    assert (pinned[:, col["i_v"]] == 1234).all() and (pinned[:, col["sp_enc"]] == -7).all()
    others = [k for k in range(clean.shape[1]) if k not in (col["i_v"], col["sp_enc"])]
    np.testing.assert_array_equal(pinned[:, others], clean[:, others])  # same seed, same plant

    _, clipped = _capture_frames(tmp_path, "clipped", "--clip-currents", "900")
    assert np.abs(clipped[:, cur]).max() == 900
    np.testing.assert_array_equal(clipped[:, cur], np.clip(clean[:, cur], -900, 900))

    _, gained = _capture_frames(tmp_path, "gained", "--current-gain", "20")
    assert gained[:, cur].max() == 32767 and gained[:, cur].min() == -32768

    lying, samples = _capture_frames(tmp_path, "lying", "--descriptor-rate", "500")
    assert lying.sample_rate_hz == 500 and desc.sample_rate_hz == 1000
    assert len(samples) == 2000  # 2 s of samples at the rate the DAQ really samples at
    np.testing.assert_array_equal(samples, clean)


def test_sensor_fault_flags_refuse_nonsense():
    for flags, expected in ((["--pin", "nope=1"], "cannot pin nope"), (["--pin", "i_u"], "CHANNEL=COUNT"),
                            (["--pin", "i_u=40000"], "CHANNEL=COUNT"), (["--clip-currents", "0"], "1..32767"),
                            (["--current-gain", "-1"], "> 0"), (["--descriptor-rate", "0"], "1..65535")):
        res = subprocess.run([*SIM_CMD, "--scenario", "step", "--capture", "/dev/null", "--duration-s", "0.1",
                              *flags], capture_output=True, text=True, timeout=60)
        assert res.returncode == 2 and expected in res.stderr and "Traceback" not in res.stderr, (flags, res.stderr)


def test_modbus_a_clear_arms_the_watchdog_without_a_heartbeat_after_it(tmp_path, port):
    """A device's watchdog runs on its own. A heartbeat that comes while the watchdog has tripped, then the
    clear (coil 0) and no heartbeat more: the device must trip again one period after that heartbeat. The
    Modbus emulator armed its timer only on register writes, so after this clear it never tripped (the stream
    server arms after every command): the contract test's modbus cases then waited in vain (issue 37)."""
    from pymodbus.client import ModbusTcpClient

    emu = Emulator(tmp_path, "--modbus-tcp", f"127.0.0.1:{port}")
    client = ModbusTcpClient("127.0.0.1", port=port, timeout=2)

    def trips():
        return [e for e in emu.events("outputs") if e["cause"] == "watchdog"]

    def wait_trips(n):
        # only so that a device that never trips fails instead of hanging: 25 periods
        deadline = time.monotonic() + 5.0
        while len(trips()) < n:
            assert time.monotonic() < deadline, f"no watchdog trip {n}: {emu.events()}"
            time.sleep(0.01)

    try:
        emu.start()
        assert client.connect()
        client.write_register(101, 200, device_id=1)  # the period, ms
        client.write_register(100, 1, device_id=1)    # the first heartbeat arms it
        wait_trips(1)
        client.write_register(100, 2, device_id=1)    # a heartbeat to a tripped watchdog: heard, arms nothing
        client.write_coil(0, False, device_id=1)      # the clear: armed again, from that heartbeat
        wait_trips(2)
        beat = emu.events("heartbeat")[-1]
        second = trips()[-1]
        assert second["last_heartbeat_mono"] == beat["mono"] and second["mono"] - beat["mono"] >= 0.2
        assert client.read_discrete_inputs(0, count=2, device_id=1).bits[:2] == [True, True]
    finally:
        client.close()
        emu.stop()
