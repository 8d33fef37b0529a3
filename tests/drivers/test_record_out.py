"""Where `millsense record` writes: the capture alone on `--out`, never the link it was named through.

Found while fixing issue 39's record wording: record's log lines went to stdout (structlog unconfigured),
so `--out /dev/stdout | …` carried them inside the capture; and `--out` naming a symbolic link had the
link replaced by the capture file: as root, `--out /dev/stdout > file` put a regular file in place of
the host's /dev/stdout. Real `record` subprocesses on the simulated DAQ (the demo's config).
"""

from __future__ import annotations

import subprocess

from millsense.drivers.protocol import Descriptor, Samples, StreamDecoder
from tests.config.helpers import DEMO_TOML
from tests.e2e.helpers import CMD


def _record(out: str, **kw) -> subprocess.CompletedProcess:
    return subprocess.run(CMD + ["record", "--config", str(DEMO_TOML), "--out", out, "--seconds", "1"],
                          capture_output=True, timeout=60, **kw)


def _frames(data: bytes) -> list:
    decoder = StreamDecoder()
    frames = decoder.feed(data)
    assert decoder.stats.dropped_bytes == 0, decoder.stats  # nothing but frames
    return frames


def test_a_capture_to_stdout_holds_frames_only_and_the_log_goes_to_stderr():
    p = _record("/dev/stdout")  # stdout is a pipe here: written directly
    assert p.returncode == 0, p.stderr.decode()
    assert b"daq.link" not in p.stdout
    frames = _frames(p.stdout)
    assert isinstance(frames[0], Descriptor) and any(isinstance(f, Samples) for f in frames)
    assert b"daq.link_down" in p.stderr and b"samples in" in p.stderr


def test_a_link_named_as_out_stays_a_link_and_its_file_gets_the_capture(tmp_path):
    runs = tmp_path / "runs"
    runs.mkdir()
    real = runs / "older.cap"
    real.write_bytes(b"an older capture, longer than nothing " * 1000)
    link = tmp_path / "latest.cap"
    link.symlink_to(real)
    p = _record(str(link))
    assert p.returncode == 0, p.stderr.decode()
    assert link.is_symlink() and link.resolve() == real.resolve()
    frames = _frames(real.read_bytes())
    assert isinstance(frames[0], Descriptor) and any(isinstance(f, Samples) for f in frames)
    assert sorted(x.name for x in runs.iterdir()) == ["older.cap"]  # no temporary file left
    assert sorted(x.name for x in tmp_path.iterdir()) == ["latest.cap", "runs"]
