"""The firmware's host build on a raw TCP link: the frames as docs/protocol.md lays them out, every
command, the watchdog, the override's bounds, corrupted bytes, the ring under a stalled host, restarts.

Every test but the vectors runs on the plain build and on the ASan + UBSan build (`any_build`); each ends
with a SIGTERM whose exit code must be 0 (a sanitizer's report makes it fail). Times come from the device's
own log (monotonic clock), never from the test's sleeps.
"""

from __future__ import annotations

import os
import signal
import subprocess
import termios
import tty

import pytest

from tests.e2e.helpers import wait_for
from tests.firmware import frames
from tests.firmware.conftest import ramp_counts
from tests.firmware.device import Firmware, Link

T_SAMPLES, T_DESCRIPTOR, T_STATUS = 0x01, 0x02, 0x03


def _stop_clean(fw: Firmware) -> dict:
    code = fw.stop()
    assert code == 0, f"firmware exit {code}:\n{fw.stderr()[-4000:]}"
    assert "runtime error" not in fw.stderr() and "Sanitizer" not in fw.stderr(), fw.stderr()[-4000:]
    return fw.events("stop")[-1]


@pytest.mark.quick
def test_crc_and_frame_vectors_from_the_doc(plain_build):
    # the catalogue's check value of CRC-16/MODBUS, and docs/protocol.md's worked example, typed in by hand
    assert frames.crc16(b"123456789") == 0x4B37
    assert frames.heartbeat(0x0102) == bytes.fromhex("a55a 10 0300 020201 27eb")
    body = b"\x10\x02\x00\x01\x01"                                 # type, length 2, set outputs, hold
    assert frames.set_outputs(1) == b"\xa5\x5a" + body + frames.crc16(body).to_bytes(2, "little")
    # the firmware's own CRC and frame layout against the same vectors (a C program, no Python in between)
    p = subprocess.run([str(plain_build / "msfw-selftest")], capture_output=True, text=True, timeout=30)
    assert p.returncode == 0 and "selftest passed" in p.stdout, p.stdout


def test_stream_frames_are_laid_out_as_the_doc_says(any_build, ramp_capture, tmp_path, port):
    capture_descriptor = next(f for f in frames.Decoder().feed(ramp_capture.read_bytes()) if f.type == T_DESCRIPTOR)
    with Firmware(any_build / "msfw-host", tmp_path, ramp_capture, port, "--wait-client") as fw:
        link = Link(port)
        link.wait(lambda f: f.type == T_SAMPLES and f.samples()[0] >= 200)
        desc = link.of_type(T_DESCRIPTOR)[0].descriptor()
        # version 2, the capture's rate and channels, capabilities: a feed-override output (no CNC context
        # in a ramp), and nothing more: 4 + 9 C + 1 bytes
        assert desc["version"] == 2 and desc["rate"] == 1000
        assert desc["channels"] == capture_descriptor.descriptor()["channels"] and len(desc["channels"]) == 8
        assert desc["capabilities"] == 0x01 and desc["length"] == 4 + 9 * 8 + 1
        assert link.frames[0].type == T_DESCRIPTOR, "a DESCRIPTOR first"
        status = link.of_type(T_STATUS)[0].status()
        assert status == {"outputs": 0, "flags": 0, "heartbeat": 0, "length": 6, "override": 1000}
        # SAMPLES: whole frames of 10 from index 0, every count the ramp's, none missing or twice
        expected = 0
        for f in link.of_type(T_SAMPLES):
            first, c, s, samples = f.samples()
            assert (first, c, s) == (expected, 8, 10)
            assert samples == [ramp_counts(first + k) for k in range(s)]
            expected += s
        assert link.decoder.bad == 0
        link.close()
        _stop_clean(fw)


def test_the_index_wraps_at_2_32_without_a_gap(any_build, ramp_capture, tmp_path, port):
    start = 2**32 - 250
    with Firmware(any_build / "msfw-host", tmp_path, ramp_capture, port, "--wait-client", "--start-index",
                  str(start)) as fw:
        link = Link(port)
        link.wait(lambda f: f.type == T_SAMPLES and f.samples()[0] < start and f.samples()[0] >= 200)
        samples = [f.samples() for f in link.of_type(T_SAMPLES)]
        firsts = [s[0] for s in samples]
        assert firsts == [(start + 10 * k) % 2**32 for k in range(len(firsts))]
        # sample k of the device is the capture's sample (k - start) mod 2^32: the ramp's values
        assert all(s[3] == [ramp_counts(((s[0] - start) % 2**32 + j) % 3000) for j in range(10)] for s in samples)
        link.close()
        _stop_clean(fw)


@pytest.mark.serial
def test_a_feed_hold_command_is_on_the_output_within_one_tick(any_build, ramp_capture, tmp_path, port):
    with Firmware(any_build / "msfw-host", tmp_path, ramp_capture, port) as fw:
        link = Link(port)
        link.wait(lambda f: f.type == T_SAMPLES)
        n = len(link.frames)
        link.send(frames.set_outputs(0x01))
        out = fw.wait_event("outputs", lambda e: e["cause"] == "command" and e["feed_hold"])
        cmd = fw.wait_event("command", lambda e: e["command"] == 1 and e["argument"] == 1)
        # written in the poll that decoded it: the same sample tick, well within the 1 ms tick
        assert out["index"] - cmd["index"] <= 1 and out["mono"] - cmd["mono"] < 0.001, (cmd, out)
        reply = link.wait(lambda f: f.type == T_STATUS, start=n).status()
        assert reply["outputs"] & 0x01 and not reply["flags"] & 0x01
        link.send(frames.set_outputs(0x00))
        fw.wait_event("outputs", lambda e: e["cause"] == "command" and not e["feed_hold"])
        link.close()
        _stop_clean(fw)


def test_corrupted_bytes_from_the_host_are_counted_and_skipped(any_build, ramp_capture, tmp_path, port):
    with Firmware(any_build / "msfw-host", tmp_path, ramp_capture, port) as fw:
        link = Link(port)
        garbage = bytes(range(0x10, 0x10 + 40))                      # no sync byte in it: 40 skipped bytes
        bad_crc = bytearray(frames.heartbeat(5))
        bad_crc[-1] ^= 0xFF                                          # heartbeat 5 must not count
        too_long = b"\xa5\x5a\x10\xff\x7f" + bytes(8)                # a length no command has
        wrong_type = frames.frame(0x01, bytes(6))                    # a good frame of a type a board never takes
        unknown_cmd = frames.frame(0x10, b"\x7f\x00")                # a good frame, a command that does not exist
        link.send(frames.heartbeat(4) + garbage + bytes(bad_crc) + too_long + wrong_type + unknown_cmd
                  + frames.heartbeat(6))
        fw.wait_event("heartbeat", lambda e: e["counter"] == 6)
        assert [e["counter"] for e in fw.events("heartbeat")] == [4, 6]
        assert fw.events("bad_command")[-1]["command"] == 0x7F
        link.close()
        stop = _stop_clean(fw)
        assert stop["bad_frames"] == 3 and stop["bad_commands"] == 1, stop
        # the 40 garbage bytes, and every byte of the three bad frames: each one's first byte dropped as it
        # failed, the rest skipped in the hunt for the next sync
        assert stop["skipped_bytes"] == 40 + len(bad_crc) + len(too_long) + len(wrong_type), stop
        assert stop["commands"] == 2


def test_the_device_bounds_the_feed_override_itself(any_build, ramp_capture, tmp_path, port):
    with Firmware(any_build / "msfw-host", tmp_path, ramp_capture, port) as fw:
        link = Link(port)
        link.wait(lambda f: f.type == T_SAMPLES)
        for value in (2001, 65535, 2000, 0, 1000):
            n = len(link.frames)
            link.send(frames.set_override(value))
            reply = link.wait(lambda f: f.type == T_STATUS, start=n).status()
            expected = value if value <= 2000 else {2001: 1000, 65535: 1000}[value]
            assert reply["override"] == expected, (value, reply)
        refused = [(e["value"], e["why"]) for e in fw.events("feed_override_refused")]
        assert refused == [(2001, "range"), (65535, "range")]
        assert [e["value"] for e in fw.events("feed_override") if e["cause"] == "command"] == [2000, 0, 1000]
        link.close()
        stop = _stop_clean(fw)
        assert stop["override_refused"] == 2


WATCHDOG_MS = 200
# The device's clock counts whole milliseconds: a period of 200 ms is 200 of its ticks after the tick in which the
# heartbeat came, so between 199 and 200 ms on the log's finer clock, and up to 50 ms later on a loaded box.
CLOCK_RESOLUTION_S = 0.001


def _in_watchdog_time(late_s: float) -> bool:
    return WATCHDOG_MS / 1000 - CLOCK_RESOLUTION_S <= late_s <= WATCHDOG_MS / 1000 + 0.05


@pytest.mark.serial
def test_silence_trips_the_watchdog_which_holds_and_sets_100_percent_until_the_hosts_clear(
        any_build, ramp_capture, tmp_path, port):
    with Firmware(any_build / "msfw-host", tmp_path, ramp_capture, port, "--watchdog-ms", str(WATCHDOG_MS)) as fw:
        link = Link(port)
        link.wait(lambda f: f.type == T_SAMPLES)
        link.send(frames.set_override(800))
        fw.wait_event("feed_override", lambda e: e["value"] == 800)
        for counter in range(1, 4):
            link.send(frames.heartbeat(counter))
            fw.wait_event("heartbeat", lambda e, c=counter: e["counter"] == c)
        # a counter that does not change proves nothing: it is taken as a command, not as a heartbeat
        n_commands = len(link.of_type(T_STATUS))
        link.send(frames.heartbeat(3))
        link.wait(lambda f: f.type == T_STATUS and len(link.of_type(T_STATUS)) > n_commands)
        # the host falls silent
        trip = fw.wait_event("watchdog")
        assert [e["counter"] for e in fw.events("heartbeat")] == [1, 2, 3]
        late_s = trip["mono"] - trip["last_heartbeat_mono"]
        assert _in_watchdog_time(late_s), f"tripped {late_s * 1e3:.1f} ms after the last heartbeat"
        held = fw.wait_event("outputs", lambda e: e["cause"] == "watchdog")
        assert held["feed_hold"] and held["watchdog"]
        assert fw.wait_event("feed_override", lambda e: e["cause"] == "watchdog")["value"] == 1000
        status = link.wait(lambda f: f.type == T_STATUS and f.status()["flags"] & 0x01).status()
        assert status["outputs"] & 0x01 and status["override"] == 1000
        # a heartbeat does not release it, nor may the override go above 100 % while it holds
        n = len(link.frames)
        link.send(frames.heartbeat(10) + frames.set_override(1500) + frames.set_override(900))
        fw.wait_event("feed_override", lambda e: e["value"] == 900)
        assert [e["value"] for e in fw.events("feed_override_refused") if e["why"] == "watchdog"] == [1500]
        status = link.wait(lambda f: f.type == T_STATUS and f.status()["override"] == 900, start=n).status()
        assert status["outputs"] & 1
        assert len(fw.events("watchdog")) == 1 and not [e for e in fw.events("outputs") if not e["feed_hold"]
                                                        and e["mono"] > trip["mono"]]
        # the host's clear releases it, and the watchdog counts again from the last heartbeat heard
        link.send(frames.set_outputs(0))
        fw.wait_event("outputs", lambda e: e["cause"] == "command" and not e["feed_hold"])
        second = fw.wait_event("watchdog", lambda e: e["mono"] > trip["mono"])
        hb10 = fw.wait_event("heartbeat", lambda e: e["counter"] == 10)
        assert second["last_heartbeat_mono"] == pytest.approx(hb10["mono"], abs=0.002)
        assert _in_watchdog_time(second["mono"] - hb10["mono"]), second
        link.close()
        stop = _stop_clean(fw)
        assert stop["watchdog_trips"] == 2


def test_ring_overflows_under_a_stalled_host_are_counted_never_silent(any_build, ramp_capture, tmp_path, port):
    # a 64-sample ring and small socket buffers: a host that stops reading fills them within a second or two
    with Firmware(any_build / "msfw-host", tmp_path, ramp_capture, port, "--ring", "64", "--sndbuf", "4096") as fw:
        link = Link(port, rcvbuf=4096)
        link.wait(lambda f: f.type == T_SAMPLES)
        fw.wait_event("overrun", timeout_s=30.0)          # the host reads nothing meanwhile
        lost_so_far = fw.wait_event("counters", lambda e: e["overrun_samples"] > 0)["overrun_samples"]
        link.wait(lambda f: f.type == T_STATUS and f.status()["flags"] & 0x02)
        stop = _stop_clean(fw)
        # read to the end: every index the stream skipped is a sample the device counted as dropped
        while True:
            try:
                data = link.sock.recv(65536)
            except (TimeoutError, OSError):
                continue
            if not data:
                break
            link.frames += link.decoder.feed(data)
        samples = [f.samples() for f in link.of_type(T_SAMPLES)]
        gaps = [b[0] - (a[0] + a[2]) for a, b in zip(samples, samples[1:])]
        assert min(gaps) >= 0, "no sample twice, none out of order"
        assert sum(gaps) == stop["overrun_samples"] >= lost_so_far > 0, (sum(gaps), stop)
        assert stop["overrun_events"] >= 1 and link.decoder.bad == 0
        # the ring keeps the newest: after the stall the stream goes on at the head, not from where it stopped
        assert all(samples[k][3] == [ramp_counts((samples[k][0] + j) % 3000) for j in range(10)]
                   for k in (0, -1))
        link.close()


def test_a_restart_sends_a_descriptor_first_counts_from_0_and_puts_the_outputs_safe(any_build, ramp_capture,
                                                                                    tmp_path, port):
    with Firmware(any_build / "msfw-host", tmp_path, ramp_capture, port) as fw:
        link = Link(port)
        link.send(frames.set_override(700) + frames.set_outputs(0x03))
        fw.wait_event("outputs", lambda e: e["cause"] == "command" and e["outputs"] == 3)
        link.wait(lambda f: f.type == T_SAMPLES and f.samples()[0] >= 1000)
        n = len(link.frames)
        fw.signal(signal.SIGUSR1)                          # the board resets under a link that stays up
        first = link.wait(lambda f: f.type == T_DESCRIPTOR or (f.type == T_SAMPLES and f.samples()[0] < 1000), start=n)
        assert first.type == T_DESCRIPTOR, "a board that restarts sends a DESCRIPTOR first"
        link.wait(lambda f: f.type == T_SAMPLES and f.samples()[0] == 0, start=n)
        status = link.wait(lambda f: f.type == T_STATUS, start=n).status()
        assert status["outputs"] == 0 and status["override"] == 1000 and status["flags"] == 0
        assert fw.wait_event("feed_override", lambda e: e["cause"] == "restart" and e["mono"] > 0)["value"] == 1000
        link.close()
        _stop_clean(fw)


T_CONTEXT = 0x04
CYCLE, MONITOR, FEED_HELD = 0x01, 0x02, 0x08


def test_context_goes_out_with_each_descriptor_and_on_every_change(any_build, ramp_capture_v2, tmp_path, port):
    with Firmware(any_build / "msfw-host", tmp_path, ramp_capture_v2, port, "--cnc-hold-lag-ms", "30") as fw:
        link = Link(port)
        # version 2 with both capabilities; the CNC's context right after the DESCRIPTOR, and again a second later
        link.wait(lambda f: f.type == T_DESCRIPTOR)
        assert link.of_type(T_DESCRIPTOR)[0].descriptor()["capabilities"] == 0x03
        first = link.wait(lambda f: f.type == T_CONTEXT).context()
        assert (first["program"], first["tool"], first["operation"], first["flags"]) == (1234, 12, 3, CYCLE | MONITOR)
        link.wait(lambda f: f.type == T_DESCRIPTOR, start=link.frames.index(link.of_type(T_DESCRIPTOR)[0]) + 1)
        kinds = [f.type for f in link.frames]
        assert all(kinds[i + 1] == T_CONTEXT for i, k in enumerate(kinds[:-1]) if k == T_DESCRIPTOR)
        # the CNC reports the feed held (the host board's CNC, 30 ms after the output): a CONTEXT at once, whose
        # index is the first sample at which it holds, with nothing else changed
        n = len(link.frames)
        link.send(frames.set_outputs(0x01))
        held_frame = link.wait(lambda f: f.type == T_CONTEXT and f.context()["flags"] & FEED_HELD, start=n)
        held = held_frame.context()
        i = link.frames.index(held_frame)
        link.wait(lambda f: True, start=i + 1)
        # on the change, not with the next once-a-second DESCRIPTOR: alone, or (when that DESCRIPTOR went out
        # just then) the change first and the repeat after it
        assert link.frames[i - 1].type != T_DESCRIPTOR or link.frames[i + 1].type == T_CONTEXT, kinds
        cnc = fw.wait_event("cnc_feed_held", lambda e: e["feed_held"])
        assert held["index"] == fw.wait_event("context", lambda e: e["flags"] & FEED_HELD)["from_index"]
        assert cnc["index"] <= held["index"] <= cnc["index"] + 1
        assert (held["program"], held["tool"], held["operation"]) == (1234, 12, 3)
        n = len(link.frames)
        link.send(frames.set_outputs(0x00))
        link.wait(lambda f: f.type == T_CONTEXT and not f.context()["flags"] & FEED_HELD, start=n)
        link.close()
        _stop_clean(fw)


def test_a_board_for_a_machine_holds_the_feed_from_power_up_until_the_first_heartbeat(any_build, ramp_capture,
                                                                                       tmp_path, port):
    with Firmware(any_build / "msfw-host", tmp_path, ramp_capture, port, "--hold-until-heartbeat") as fw:
        link = Link(port)
        assert link.wait(lambda f: f.type == T_STATUS).status()["outputs"] == 0x01
        assert fw.events("outputs")[0]["feed_hold"] and fw.events("outputs")[0]["cause"] == "restart"
        n = len(link.frames)
        link.send(frames.heartbeat(1))
        released = fw.wait_event("outputs", lambda e: not e["feed_hold"])
        assert released["cause"] == "heartbeat"
        assert link.wait(lambda f: f.type == T_STATUS, start=n).status()["outputs"] == 0
        link.close()
        _stop_clean(fw)


def test_the_stream_on_a_pty_carries_the_same_frames_and_commands(plain_build, ramp_capture, tmp_path):
    link = tmp_path / "daq-link"
    with Firmware(plain_build / "msfw-host", tmp_path, ramp_capture, 0, transport="--pty", address=str(link)) as fw:
        fd = os.open(link, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        tty.setraw(fd)
        termios.tcflush(fd, termios.TCIFLUSH)          # what queued before we opened: a serial line's past
        os.write(fd, frames.send_descriptor() + frames.heartbeat(42) + frames.set_outputs(0x01))
        dec = frames.Decoder()
        got: list[frames.Frame] = []

        def read() -> bool:
            try:
                got.extend(dec.feed(os.read(fd, 65536)))
            except BlockingIOError:
                pass
            return any(f.type == T_STATUS and f.status()["heartbeat"] == 42 and f.status()["outputs"] & 1 for f in got)

        wait_for(read, 20.0, "a STATUS with heartbeat 42 and the feed held")
        wait_for(lambda: read() is not None and any(f.type == T_DESCRIPTOR for f in got), 20.0,
                 "the DESCRIPTOR asked for")
        n = len(got)
        wait_for(lambda: read() is not None and any(f.type == T_SAMPLES for f in got[n:]), 20.0, "samples")
        samples = [f.samples() for f in got if f.type == T_SAMPLES]
        assert samples and all(s[3] == [ramp_counts((s[0] + k) % 3000) for k in range(s[2])] for s in samples)
        assert any(e["feed_hold"] for e in fw.events("outputs"))
        os.close(fd)
        _stop_clean(fw)
    assert not link.exists(), "the link is removed when the firmware stops"
