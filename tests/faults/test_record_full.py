"""`millsense record` when the disk fills: a clear message, exit 1, and a capture valid to its last whole frame.

Two real ways to run out of room: a 64 KiB tmpfs (needs root to mount), and a
file-size limit on the process (RLIMIT_FSIZE: EFBIG, Python ignores SIGXFSZ),
which works for anyone. The emulator serves the ramp, whose values are a
function of the index, so every sample in the capture can be checked.
"""

from __future__ import annotations

import os
import resource
import subprocess
import sys

import numpy as np
import pytest

from millsense.drivers.protocol import Descriptor, Samples, StreamDecoder
from tests.drivers.emulator_proc import Emulator, ramp
from tests.drivers.test_record import CONFIG

RECORD = [sys.executable, "-m", "millsense.daemon", "record"]
LIMIT = 64 * 1024


def _record(tmp_path, port, out, preexec=None) -> subprocess.CompletedProcess:
    cfg = tmp_path / "daq.toml"
    cfg.write_text(CONFIG.format(transport="tcp", port=port))
    return subprocess.run([*RECORD, "--config", str(cfg), "--out", str(out), "--seconds", "30"],
                          capture_output=True, text=True, timeout=90, preexec_fn=preexec)


def _check_capture(path, res, message: str) -> None:
    assert res.returncode == 1, res.stderr
    assert "Traceback" not in res.stderr
    data = path.read_bytes()
    dec = StreamDecoder()
    frames = dec.feed(data)
    # valid to its end: every byte belongs to a whole frame, nothing torn at the end
    assert dec.buffered == 0 and dec.stats.dropped_bytes == 0 and dec.stats.bad_crc == 0, dec.stats
    assert isinstance(frames[0], Descriptor)
    samples = [f for f in frames if isinstance(f, Samples)]
    n = sum(len(s.counts) for s in samples)
    for s in samples:
        np.testing.assert_array_equal(s.counts, ramp(s.first_index, len(s.counts)))
    # the summary tells what is in the file, not what was meant to be
    assert f"millsense record: {n} samples in " in res.stderr, (n, res.stderr)
    assert f"{len(data)} bytes -> {path}" in res.stderr
    assert len(data) > LIMIT - 4096  # it wrote until the room ran out, and lost at most the last frames
    assert message in res.stderr and "the capture ends with the last whole frame written" in res.stderr, res.stderr


def _mount_small_tmpfs(mnt) -> None:
    """Mount a LIMIT-byte tmpfs at `mnt`, or skip saying why it cannot be done here.

    Root is not enough: root in an unprivileged container (no CAP_SYS_ADMIN in the
    init user namespace) gets EPERM from mount(2). Whether it is permitted is known
    only by trying; the RLIMIT_FSIZE test below covers the same path for anyone."""
    if os.geteuid() != 0:
        pytest.skip("mounting a tmpfs needs root (the RLIMIT_FSIZE case runs for anyone)")
    try:
        res = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={LIMIT}", "tmpfs", str(mnt)],
                             capture_output=True, text=True, timeout=30)
    except FileNotFoundError:
        pytest.skip("no mount(8) binary on this host (the RLIMIT_FSIZE case runs for anyone)")
    if res.returncode != 0:
        pytest.skip(f"mounting a tmpfs is not permitted here (an unprivileged container?): {res.stderr.strip()} "
                    "(the RLIMIT_FSIZE case runs for anyone)")


def test_record_on_a_full_tmpfs(tmp_path, port):
    mnt = tmp_path / "small"
    mnt.mkdir()
    _mount_small_tmpfs(mnt)
    try:
        with Emulator(tmp_path, "--tcp", f"127.0.0.1:{port}"):
            res = _record(tmp_path, port, mnt / "cap.bin")
        _check_capture(mnt / "cap.bin", res, "No space left on device")
    finally:
        subprocess.run(["umount", str(mnt)], check=False, timeout=30)


def test_record_past_its_file_size_limit(tmp_path, port):
    def limit() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (LIMIT, LIMIT))

    out = tmp_path / "cap.bin"
    with Emulator(tmp_path, "--tcp", f"127.0.0.1:{port}"):
        res = _record(tmp_path, port, out, preexec=limit)
    _check_capture(out, res, "File too large")
