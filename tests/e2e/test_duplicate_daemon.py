"""One daemon a machine: a second one for the same machine is refused at start, naming why (exit 78).

The probe of stop 27 started a second daemon for the same DAQ and state directory: it took over the first
one's local control socket (`reset --local` then reached nobody once it stopped, and the first one's hold could
not be cleared at the machine), and subscribers got two interleaved estimate streams on one key. Two machines
with one copied configuration (the same `machine` on one Zenoh network) merged their status answers and
answered each other's challenges: a network reset failed every time, pointing at the nonce.
"""

from __future__ import annotations

import os
import subprocess

from tests.conftest import free_tcp_port
from tests.e2e.helpers import CMD, Procs, Subscriber, tcp, wait_for, write_config
from tests.faults.helpers import status

SIM = 'transport = "sim"\nscenario = "step"'


def test_a_second_daemon_for_the_same_state_directory_is_refused(tmp_path):
    machine = "dup-01"
    first = write_config(tmp_path / "a.toml", machine=machine, daq=SIM, zenoh_listen=[tcp(free_tcp_port())])
    second = write_config(tmp_path / "b.toml", machine=machine, daq=SIM, zenoh_listen=[tcp(free_tcp_port())])
    with Procs(tmp_path) as procs:
        daemon = procs.start("a", ["run", "--config", str(first)])
        sub = Subscriber([tcp(int(first.read_text().split("tcp/127.0.0.1:")[1].split('"')[0]))], machine)
        try:
            wait_for(lambda: status(sub, machine)["state"] == "running", 60.0, "the first daemon running")
            p = subprocess.run([*CMD, "run", "--config", str(second), "--seconds", "5"], capture_output=True,
                               text=True, timeout=60, env={**os.environ})
            assert p.returncode == 78, (p.returncode, p.stderr[-2000:])
            assert "machine: another millsense daemon (pid" in p.stderr and "Traceback" not in p.stderr, p.stderr
            assert daemon.poll() is None
            # the first one still answers at the machine: its control socket was not taken over
            r = subprocess.run([*CMD, "afc", "status", "--local", "--machine", machine], capture_output=True,
                               text=True, timeout=30)
            assert r.returncode == 0, r.stderr
        finally:
            sub.close()


def test_a_second_daemon_with_the_same_name_on_the_network_is_refused(tmp_path):
    machine = "dup-02"
    port = free_tcp_port()
    first = write_config(tmp_path / "a.toml", machine=machine, daq=SIM, zenoh_listen=[tcp(port)])
    copied = write_config(tmp_path / "b.toml", machine=machine, daq=SIM, zenoh_connect=[tcp(port)])
    with Procs(tmp_path) as procs:
        daemon = procs.start("a", ["run", "--config", str(first)])
        sub = Subscriber([tcp(port)], machine)
        try:
            wait_for(lambda: status(sub, machine)["state"] == "running", 60.0, "the first daemon running")
            other_state = {**os.environ, "XDG_STATE_HOME": str(tmp_path / "other-host")}   # another box
            p = subprocess.run([*CMD, "run", "--config", str(copied), "--seconds", "5"], capture_output=True,
                               text=True, timeout=60, env=other_state)
            assert p.returncode == 78, (p.returncode, p.stderr[-2000:])
            assert f"machine: a daemon is already alive as '{machine}'" in p.stderr, p.stderr
            assert "Traceback" not in p.stderr
            assert daemon.poll() is None and status(sub, machine)["state"] == "running"
        finally:
            sub.close()
