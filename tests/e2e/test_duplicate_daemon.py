"""One daemon a machine: a second one for the same machine is refused at start, naming why (exit 78).

The probe of stop 27 started a second daemon for the same DAQ and state directory: it took over the first
one's local control socket (`reset --local` then reached nobody once it stopped, and the first one's hold could
not be cleared at the machine), and subscribers got two interleaved estimate streams on one key. Two machines
with one copied configuration (the same `machine` on one Zenoh network) merged their status answers and
answered each other's challenges: a network reset failed every time, pointing at the nonce.
"""

from __future__ import annotations

import json
import os
import subprocess

import pytest
import zenoh

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


def _other_host(tmp_path_factory) -> str:
    """Another box's state directory. Short: a control socket's path must fit AF_UNIX's 108 bytes, and a test's
    own tmp_path (its long name, and a parallel worker's folder) leaves no room for `millsense/<machine>/control.sock`."""
    return str(tmp_path_factory.mktemp("oh"))


def test_a_second_daemon_with_the_same_name_on_the_network_is_refused(tmp_path, tmp_path_factory):
    machine = "dup-02"
    port = free_tcp_port()
    first = write_config(tmp_path / "a.toml", machine=machine, daq=SIM, zenoh_listen=[tcp(port)])
    copied = write_config(tmp_path / "b.toml", machine=machine, daq=SIM, zenoh_connect=[tcp(port)])
    with Procs(tmp_path) as procs:
        daemon = procs.start("a", ["run", "--config", str(first)])
        sub = Subscriber([tcp(port)], machine)
        try:
            wait_for(lambda: status(sub, machine)["state"] == "running", 60.0, "the first daemon running")
            other_state = {**os.environ, "XDG_STATE_HOME": _other_host(tmp_path_factory)}   # another box
            p = subprocess.run([*CMD, "run", "--config", str(copied), "--seconds", "5"], capture_output=True,
                               text=True, timeout=60, env=other_state)
            assert p.returncode == 78, (p.returncode, p.stderr[-2000:])
            assert f"machine: a daemon is already alive as '{machine}'" in p.stderr, p.stderr
            assert "Traceback" not in p.stderr
            assert daemon.poll() is None and status(sub, machine)["state"] == "running"
        finally:
            sub.close()


@pytest.mark.slow
def test_two_daemons_with_one_name_on_networks_joined_later_say_so(tmp_path, tmp_path_factory):
    """Two machines with a copied configuration, each on its own network segment: neither saw the other at start.
    A router, or a laptop with a peer session, joins the segments later: from then on both names' keys carry two
    daemons (interleaved estimates, commands by name reaching both). Each daemon looks for another answering as its
    machine while it runs: fault `machine` (status `degraded`), naming the other's Zenoh id; cleared when it is gone."""
    machine = "dup-03"
    port_a, port_b = free_tcp_port(), free_tcp_port()
    first = write_config(tmp_path / "a.toml", machine=machine, daq=SIM, zenoh_listen=[tcp(port_a)])
    copied = write_config(tmp_path / "b.toml", machine=machine, daq=SIM, zenoh_listen=[tcp(port_b)])
    with Procs(tmp_path) as procs:
        procs.start("a", ["run", "--config", str(first)])
        other = procs.start("b", ["run", "--config", str(copied)],
                            env_extra={"XDG_STATE_HOME": _other_host(tmp_path_factory)})   # another box
        # clients: a peer session would listen and introduce the two daemons to each other at once
        sub_a, sub_b = (_client(port, machine) for port in (port_a, port_b))
        try:
            for name, sub in (("a", sub_a), ("b", sub_b)):
                seen: list[dict] = []
                try:
                    wait_for(lambda sub=sub, seen=seen: seen.append(status(sub, machine)) or seen[-1]["state"] == "running",
                             60.0, "both daemons running")
                except AssertionError:   # say what it was doing instead, and what it logged
                    last = {k: seen[-1].get(k) for k in ("state", "daq_link", "faults", "samples_received")} if seen else None
                    raise AssertionError(f"daemon {name} not running in 60 s: {last}\n{procs.text(name)[-3000:]}") from None
            assert all("machine" not in status(sub, machine)["faults"] for sub in (sub_a, sub_b))
            bridge = Subscriber([tcp(port_a), tcp(port_b)], machine, read=False)   # the segments joined
            try:
                def statuses() -> list[dict]:   # both daemons' answers: unconsolidated, each its own
                    return [json.loads(r.ok.payload.to_bytes()) for r in bridge.session.get(
                        f"millsense/{machine}/status", target=zenoh.QueryTarget.ALL,
                        consolidation=zenoh.ConsolidationMode.NONE, timeout=2.0) if r.ok is not None]

                wait_for(lambda: [("machine" in r["faults"]) for r in statuses()] == [True, True], 60.0,
                         "fault `machine` on both daemons")
                for r in statuses():
                    assert r["state"] == "degraded", r
                    assert f"another daemon is alive as '{machine}'" in r["faults"]["machine"], r["faults"]
            finally:
                bridge.close()
            other.terminate()
            other.wait(30)
            wait_for(lambda: "machine" not in status(sub_a, machine)["faults"], 60.0, "the fault cleared once it left")
            assert status(sub_a, machine)["state"] == "running"
            assert "Traceback" not in procs.text("a", "out") + procs.text("a", "err")
        finally:
            sub_a.close()
            sub_b.close()


def _client(port: int, machine: str) -> Subscriber:
    """A client session of the daemon listening on `port`, once it listens."""
    opened: list[Subscriber] = []

    def connect() -> bool:
        try:
            opened.append(Subscriber([tcp(port)], machine, mode="client"))
        except zenoh.ZError:
            return False
        return True

    wait_for(connect, 60.0, f"the daemon listening on {port}")
    return opened[0]
