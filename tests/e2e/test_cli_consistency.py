"""Issue 12, items 7 and 9: the commands agree with each other and say things once, as real subprocesses.

- `millsense sim` serving loops by default (a daemon started later finds it),
  `--once` stops after one pass, a capture is one pass;
- `-c` is `--config` wherever a command takes a config file;
- `calibrate --out DIR` is a usage error that leaves nothing behind;
- a DAQ that cannot be reached is a warning in the log, and a missing serial
  port is named once in it.
"""

from __future__ import annotations

import json
import socket
import subprocess

import pytest

from millsense.drivers.protocol import Samples, StreamDecoder
from millsense.sim import SCENARIOS
from tests.conftest import free_tcp_port
from tests.e2e.helpers import CMD, tcp, wait_for, write_config

SHORT = "speed-2500"  # the shortest scenario: one pass is a few seconds at 1 kHz
RATE_HZ = 1000


def _one_pass_samples() -> int:
    return round(SCENARIOS[SHORT].duration_s * RATE_HZ)


def _serve(tmp_path, name: str, port: int, *extra: str) -> tuple[subprocess.Popen, object]:
    err = open(tmp_path / f"{name}.err", "w")  # noqa: SIM115 - closed by the caller
    proc = subprocess.Popen([*CMD, "sim", "--scenario", SHORT, "--tcp", f"127.0.0.1:{port}", *extra],
                            stdout=subprocess.DEVNULL, stderr=err)
    wait_for(lambda: "serving" in (tmp_path / f"{name}.err").read_text() or proc.poll() is not None, 30.0,
             f"{name} serving")
    assert proc.poll() is None, (tmp_path / f"{name}.err").read_text()
    return proc, err


class _Reader:
    """A TCP client of the emulator: the highest sample index seen, and whether the stream ended."""

    def __init__(self, port: int) -> None:
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=5)
        self.sock.settimeout(0.2)
        self.decoder = StreamDecoder()
        self.last_index = -1
        self.ended = False

    def poll(self) -> None:
        if self.ended:
            return
        try:
            data = self.sock.recv(65536)
        except TimeoutError:
            return
        except OSError:
            data = b""
        if not data:
            self.ended = True
            return
        for frame in self.decoder.feed(data):
            if isinstance(frame, Samples):
                self.last_index = max(self.last_index, frame.first_index + len(frame.counts) - 1)

    def close(self) -> None:
        self.sock.close()


def test_sim_serving_loops_by_default_and_once_stops_after_one_pass(tmp_path):
    one_pass = _one_pass_samples()
    loop_port, once_port = free_tcp_port(), free_tcp_port()
    looping, err1 = _serve(tmp_path, "loop", loop_port)
    once, err2 = _serve(tmp_path, "once", once_port, "--once")
    readers = [_Reader(loop_port), _Reader(once_port)]
    try:
        def progressed() -> bool:
            for r in readers:
                r.poll()
            return readers[0].last_index >= one_pass + 500 and readers[1].ended

        wait_for(progressed, 90.0, "the default server past its first pass, the --once one ended")
        assert looping.poll() is None, "the default server stopped after its pass"
        assert once.wait(30) == 0, (tmp_path / "once.err").read_text()
        assert 0 < readers[1].last_index < one_pass
    finally:
        for r in readers:
            r.close()
        for p in (looping, once):
            if p.poll() is None:
                p.terminate()
                p.wait(10)
        err1.close()
        err2.close()


def test_sim_capture_is_one_pass_and_loop_is_still_accepted(tmp_path):
    out = tmp_path / "one.cap"
    res = subprocess.run([*CMD, "sim", "--scenario", SHORT, "--capture", str(out)], capture_output=True, text=True,
                         timeout=120)
    assert res.returncode == 0, res.stderr
    frames = StreamDecoder().feed(out.read_bytes())
    assert sum(len(f.counts) for f in frames if isinstance(f, Samples)) == _one_pass_samples()
    # `--loop` as old command lines give it: parsed, and a looping capture still needs its length
    res = subprocess.run([*CMD, "sim", "--scenario", SHORT, "--capture", str(tmp_path / "l.cap"), "--loop"],
                         capture_output=True, text=True, timeout=60)
    assert res.returncode == 2 and "never ends: give --duration-s" in res.stderr, res.stderr


@pytest.mark.parametrize("command", [
    ["run"],
    ["record", "--out", "{tmp}/x.cap", "--seconds", "1"],
    ["calibrate", "{tmp}/a.cap", "--out", "{tmp}/cal.toml"],
    ["watch", "--seconds", "1"],
    ["reset", "--timeout", "1"],
    ["test-trip", "--timeout", "1"],
])
def test_dash_c_is_config_on_every_command_that_takes_one(tmp_path, command):
    missing = tmp_path / "no-such.toml"
    argv = [a.format(tmp=tmp_path) for a in command]
    res = subprocess.run([*CMD, *argv, "-c", str(missing)], capture_output=True, text=True, timeout=60)
    assert res.returncode == 78, res.stderr  # the file was taken as the config: a config error
    assert str(missing) in res.stderr and "Traceback" not in res.stderr


def test_calibrate_out_a_directory_is_a_usage_error_and_leaves_nothing(tmp_path):
    cfg = write_config(tmp_path / "d.toml", machine="cal-dir", daq='transport = "sim"\nscenario = "step"')
    target = tmp_path / "out"
    target.mkdir()
    cap = tmp_path / "air.cap"
    cap.write_bytes(b"")
    res = subprocess.run([*CMD, "calibrate", str(cap), "-c", str(cfg), "--out", str(target)], capture_output=True,
                         text=True, timeout=60)
    assert res.returncode == 2, res.stderr
    assert res.stderr.strip() == (f"millsense calibrate: error: --out {target} is a directory: give a file name, "
                                  f"e.g. {target / 'calibration.toml'}")
    assert list(target.iterdir()) == []
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]


def _link_down(stdout: str) -> dict:
    events = [json.loads(line) for line in stdout.splitlines() if line.startswith("{")]
    downs = [e for e in events if e.get("event") == "daq.link_down"]
    assert downs, stdout
    return downs[0]


def test_a_missing_serial_port_is_named_once_in_a_warning(tmp_path):
    port = str(tmp_path / "ttyNOPE")
    cfg = write_config(tmp_path / "d.toml", machine="ser-gone", daq=f'transport = "serial"\nport = "{port}"',
                       zenoh_listen=[tcp(free_tcp_port())])
    res = subprocess.run([*CMD, "run", "-c", str(cfg), "--connect-timeout", "1"], capture_output=True, text=True,
                         timeout=60)
    assert res.returncode == 69, res.stdout + res.stderr
    down = _link_down(res.stdout)
    assert down["level"] == "warning", down
    assert down["reason"].count(port) == 1 and "No such file or directory" in down["reason"], down


def test_a_refused_daq_connection_is_a_warning(tmp_path):
    daq_port = free_tcp_port()  # nothing listens: refused
    cfg = write_config(tmp_path / "d.toml", machine="tcp-gone",
                       daq=f'transport = "tcp"\nhost = "127.0.0.1"\ntcp_port = {daq_port}',
                       zenoh_listen=[tcp(free_tcp_port())])
    res = subprocess.run([*CMD, "run", "-c", str(cfg), "--connect-timeout", "1"], capture_output=True, text=True,
                         timeout=60)
    assert res.returncode == 69, res.stdout + res.stderr
    down = _link_down(res.stdout)
    assert down["level"] == "warning" and "refused" in down["reason"].lower(), down


@pytest.mark.parametrize("seconds", ["nan", "inf", "0", "-1"])
@pytest.mark.parametrize("option", ["--seconds", "--connect-timeout"])
@pytest.mark.parametrize("command", [["run"], ["record", "-c", "{tmp}/d.toml", "--out", "{tmp}/x.cap"]])
def test_run_and_record_refuse_the_same_bad_seconds(tmp_path, command, option, seconds):
    """`run --connect-timeout nan` waited "within nan s" (a probe of stop 26): refused as `record` refuses it."""
    write_config(tmp_path / "d.toml", machine="secs", daq='transport = "sim"\nscenario = "step"')
    argv = [a.format(tmp=tmp_path) for a in command]
    res = subprocess.run([*CMD, *argv, option, seconds], capture_output=True, text=True, timeout=60)
    assert res.returncode == 2, res.stdout + res.stderr
    assert res.stderr.startswith(f"millsense {argv[0]}: error: {option} must be positive"), res.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d.toml"]
