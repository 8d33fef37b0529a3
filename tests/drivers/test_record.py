"""`millsense record` against the emulator: a capture that replays through the decoder."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from millsense.drivers.protocol import Descriptor, Samples, StreamDecoder
from tests.drivers.emulator_proc import Emulator, ramp
from tests.e2e.helpers import SIM_CHANNELS, SIM_MACHINE

CONFIG = """
machine = "rec-test"

[daq]
transport = "{transport}"
host = "127.0.0.1"
tcp_port = {port}
unit = 1
poll_ms = 20
""" + SIM_CHANNELS + SIM_MACHINE

RECORD = [sys.executable, "-m", "millsense.daemon", "record"]


def _record(tmp_path, transport, port, out, seconds="2"):
    cfg = tmp_path / "daq.toml"
    cfg.write_text(CONFIG.format(transport=transport, port=port))
    return subprocess.run(
        [*RECORD, "--config", str(cfg), "--out", str(out), "--seconds", seconds],
        capture_output=True, text=True, timeout=60,
    )


def test_record_tcp_and_modbus_write_a_replayable_capture(tmp_path, port):
    for transport, flag in (("tcp", "--tcp"), ("modbus-tcp", "--modbus-tcp")):
        with Emulator(tmp_path, flag, f"127.0.0.1:{port}", name=transport):
            out = tmp_path / f"{transport}.cap"
            res = _record(tmp_path, transport, port, out)
        assert res.returncode == 0, res.stderr
        frames = StreamDecoder().feed(out.read_bytes())
        assert isinstance(frames[0], Descriptor) and frames[0].channel_count == 8
        samples = [f for f in frames if isinstance(f, Samples)]
        n = sum(len(s.counts) for s in samples)
        assert 1500 <= n <= 2500, n
        for s in samples:
            np.testing.assert_array_equal(s.counts, ramp(s.first_index, len(s.counts)))
        assert f"{n} samples" in res.stderr


def test_record_to_a_full_disk_fails_clearly(tmp_path, port):
    with Emulator(tmp_path, "--tcp", f"127.0.0.1:{port}"):
        res = _record(tmp_path, "tcp", port, "/dev/full", seconds="3")
    assert res.returncode == 1
    assert "No space left on device" in res.stderr
    assert "samples in" in res.stderr  # the counts are still printed
    assert "Traceback" not in res.stderr


@pytest.mark.parametrize("seconds", ["-1", "0", "nan", "inf"])
def test_record_refuses_a_bad_duration_and_writes_nothing(tmp_path, port, seconds):
    """Issue 12, item 5: refused as `run` refuses it (exit 2, one clear line), before anything is opened."""
    out = tmp_path / "cap.bin"
    res = _record(tmp_path, "tcp", port, out, seconds=seconds)
    assert res.returncode == 2, res.stderr
    assert res.stderr.startswith("millsense record: error: --seconds must be positive, got ")
    assert "Traceback" not in res.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["daq.toml"]


@pytest.mark.parametrize("timeout_flag", ["--connect-timeout", "--connect-timeout-s"])
def test_record_with_an_unreachable_daq_leaves_no_file_and_keeps_an_older_one(tmp_path, port, timeout_flag):
    """Issue 12, items 5 and 9: nothing written when the DAQ never answers; an older capture stays
    as it was; `--connect-timeout` as `run` spells it, the old `--connect-timeout-s` still works."""
    older = tmp_path / "older.cap"
    older.write_bytes(b"an older capture")
    cfg = tmp_path / "daq.toml"
    cfg.write_text(CONFIG.format(transport="tcp", port=port))  # nothing listens on `port`
    for out in (tmp_path / "new.cap", older):
        res = subprocess.run([*RECORD, "-c", str(cfg), "--out", str(out), "--seconds", "5", timeout_flag, "0.5"],
                             capture_output=True, text=True, timeout=60)
        assert res.returncode == 69, res.stderr
        # the driver's last reason too, so the message says what to check
        assert (f"millsense record: error: DAQ unreachable: no connection to tcp 127.0.0.1:{port} within 0.5 s "
                f"([Errno 111] Connection refused); "
                f"nothing written to {out}") in res.stderr, res.stderr
        assert "Traceback" not in res.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["daq.toml", "older.cap"]  # no new file, no .tmp
    assert older.read_bytes() == b"an older capture"


def test_record_to_a_directory_is_a_usage_error(tmp_path, port):
    res = _record(tmp_path, "tcp", port, tmp_path)
    assert res.returncode == 2 and f"--out {tmp_path} is a directory" in res.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["daq.toml"]
