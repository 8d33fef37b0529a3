"""`millsense test-trip`: the proof test of the feed-hold path on real processes.

The emulator serves the DAQ over TCP and logs every output change; the daemon
runs from a config file with its state directory in tmp_path; the CLI talks
to it through the local control socket (`--local`), as an operator at the
machine would (same uid as the daemon here).
"""

from __future__ import annotations

import json
import re
import signal
import subprocess

import pytest

from tests.conftest import free_tcp_port
from tests.e2e.helpers import CMD, Procs, read_jsonl, wait_for, write_config


def _outputs(log):
    return [e for e in log if e.get("event") == "outputs"]


def _start(procs, tmp_path, machine, protocol_args=()):
    daq_port = free_tcp_port()
    cfg = write_config(
        tmp_path / "d.toml",
        machine=machine,
        daq=f'transport = "tcp"\nhost = "127.0.0.1"\ntcp_port = {daq_port}',
        interlock='enabled = true\nheartbeat_ms = 50\nwatchdog_ms = 1000\nreset = "off"',
    )
    log_path = tmp_path / "status.jsonl"
    sim = procs.start("sim", ["sim", "--scenario", "step", "--loop", "--tcp", f"127.0.0.1:{daq_port}", "--realtime",
                              "--status-log", str(log_path), "--watchdog-ms", "1000", *protocol_args])
    wait_for(lambda: "serving" in procs.text("sim"), 60.0, "emulator serving")
    state = tmp_path / "state"
    env = {"STATE_DIRECTORY": str(state)}
    daemon = procs.start("daemon", ["run", "--config", str(cfg)], env_extra=env)
    wait_for(lambda: (state / "control.sock").exists() or daemon.poll() is not None, 60.0, "control socket")
    assert daemon.poll() is None, procs.text("daemon", "out") + procs.text("daemon")
    wait_for(lambda: '"daemon.ready"' in procs.text("daemon", "out"), 60.0, "daemon ready")
    return sim, daemon, cfg, log_path, env


def _test_trip(cfg, env):
    import os

    return subprocess.run(CMD + ["test-trip", "--local", "--config", str(cfg)], capture_output=True, text=True,
                          timeout=60, env=dict(os.environ, **env))


def test_test_trip_local_holds_measures_and_resets_even_with_network_reset_off(tmp_path):
    machine = "tt-local"
    with Procs(tmp_path) as procs:
        sim, daemon, cfg, log_path, env = _start(procs, tmp_path, machine)
        p = _test_trip(cfg, env)
        assert p.returncode == 0, p.stdout + p.stderr
        m = re.search(r"DAQ status shows feed hold after: ([0-9.]+) ms", p.stdout)
        assert m and float(m.group(1)) > 0, p.stdout
        assert "not measured" in p.stdout  # protocol 1: no CNC context
        assert "reset granted" in p.stdout
        outs = wait_for(lambda: len(_outputs(read_jsonl(log_path))) >= 2 and _outputs(read_jsonl(log_path)), 5.0,
                        "hold and release on the emulator")
        assert [o["feed_hold"] for o in outs] == [True, False], outs
        assert all(o["cause"] == "command" for o in outs)
        # the audit log has both commands, from this uid
        audit = [json.loads(x) for x in (tmp_path / "state" / "audit.log").read_text().splitlines()]
        assert [(a["command"], a["granted"]) for a in audit] == [("test-trip", True), ("reset", True)]
        # the daemon's own account: one trip through the interlock, reason test-trip
        log = procs.text("daemon", "out")
        assert '"reason": "test-trip"' in log and '"interlock.test_trip_result"' in log
        daemon.send_signal(signal.SIGTERM)
        assert daemon.wait(10) == 0
        sim.send_signal(signal.SIGTERM)
        sim.wait(10)


def test_test_trip_fails_without_a_daemon(tmp_path):
    import os

    p = subprocess.run(CMD + ["test-trip", "--local", "--machine", "nobody-here"], capture_output=True, text=True,
                       timeout=60, env=dict(os.environ, STATE_DIRECTORY=str(tmp_path / "none")))
    assert p.returncode == 1 and "no daemon" in p.stderr and "Traceback" not in p.stderr


@pytest.mark.quick
def test_test_trip_on_a_protocol_2_daq_measures_the_cnc_feed_held(tmp_path):
    lag_ms = 40.0
    machine = "tt-v2"
    with Procs(tmp_path) as procs:
        sim, daemon, cfg, log_path, env = _start(procs, tmp_path, machine,
                                                 ("--protocol", "2", "--cnc-hold-lag-ms", f"{lag_ms:g}"))
        p = _test_trip(cfg, env)
        assert p.returncode == 0, p.stdout + p.stderr
        daq = float(re.search(r"DAQ status shows feed hold after: ([0-9.]+) ms", p.stdout).group(1))
        cnc = float(re.search(r"CNC reports feed held after: +([0-9.]+) ms", p.stdout).group(1))
        # the CNC answers its lag after the DAQ's output changed, so never before it
        print(f"test-trip on protocol 2: DAQ confirmed {daq:.1f} ms, CNC {cnc:.1f} ms (lag {lag_ms:g} ms)")
        assert cnc >= lag_ms and cnc > daq, p.stdout
        outs = wait_for(lambda: len(_outputs(read_jsonl(log_path))) >= 2 and _outputs(read_jsonl(log_path)), 5.0,
                        "hold and release on the emulator")
        assert [o["feed_hold"] for o in outs] == [True, False]
        daemon.send_signal(signal.SIGTERM)
        assert daemon.wait(10) == 0
        sim.send_signal(signal.SIGTERM)
        sim.wait(10)


def _connected_unix_socket(pid: int) -> bool:
    """Whether process `pid` holds a connected Unix socket (/proc/net/unix state 03)."""
    import os

    try:
        inodes = {os.readlink(f"/proc/{pid}/fd/{fd}")[8:-1] for fd in os.listdir(f"/proc/{pid}/fd")}
    except OSError:
        return False
    with open("/proc/net/unix") as f:
        rows = [line.split() for line in f.readlines()[1:]]
    return any(len(r) >= 7 and r[5] == "03" and r[6] in inodes for r in rows)


def test_local_reset_waits_for_a_daemon_slow_to_answer_and_names_one_that_does_not(tmp_path):
    """A loaded edge box answers late, not never: the client at the machine waits (30 s by default).

    The daemon is stopped (SIGSTOP) for 3 s, longer than the client's old 2 s, while a reset is
    asked; it answers once it runs again. Stopped for longer than the client's --timeout, it is
    named as running but not answering.
    """
    import os
    import time

    machine = "tt-slow"
    with Procs(tmp_path) as procs:
        sim, daemon, cfg, log_path, env = _start(procs, tmp_path, machine)
        run_env = dict(os.environ, **env)
        reset = CMD + ["reset", "--local", "--config", str(cfg)]
        os.kill(daemon.pid, signal.SIGSTOP)
        try:
            late = subprocess.Popen(reset, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=run_env)
            # from its connect (the kernel queues it for the stopped daemon) longer than the old 2 s
            wait_for(lambda: _connected_unix_socket(late.pid) or late.poll() is not None, 60.0, "the client connected")
            time.sleep(3.0)
            assert late.poll() is None, late.communicate()  # still waiting, not given up
        finally:
            os.kill(daemon.pid, signal.SIGCONT)
        out, err = late.communicate(timeout=120)
        assert late.returncode == 0 and json.loads(out)["ok"] is True, out + err

        os.kill(daemon.pid, signal.SIGSTOP)
        try:
            hung = subprocess.run([*reset, "--timeout", "1"], capture_output=True, text=True, timeout=60, env=run_env)
        finally:
            os.kill(daemon.pid, signal.SIGCONT)
        assert hung.returncode == 1 and "did not answer within 1 s" in hung.stderr, hung.stderr
        assert "hung or starved of CPU" in hung.stderr and "Traceback" not in hung.stderr, hung.stderr
        daemon.send_signal(signal.SIGTERM)
        assert daemon.wait(60) == 0
