"""`millsense run` start-up paths: the demo, a client behind a router, exit codes 69 and 78."""

from __future__ import annotations

import json
import signal
import subprocess
import time

import pytest
import zenoh

from tests.conftest import free_tcp_port
from tests.e2e.helpers import CMD, Procs, Subscriber, tcp, wait_for, write_config


@pytest.mark.xdist_group("demo")  # one demo at a time: two (mch10-demo, scouting on) find each other and one exits 78
def test_demo_prints_a_summary_line_per_second_and_exits(tmp_path):
    p = subprocess.run(CMD + ["run", "--seconds", "4"], capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stderr
    lines = [ln for ln in p.stdout.splitlines() if "rpm" in ln]
    assert len(lines) >= 2, p.stdout + p.stderr
    assert "\r" not in p.stdout  # not a TTY: one line per second, no in-place refresh
    assert any("alarm" in ln and "N·m" in ln for ln in lines)
    assert "Traceback" not in p.stderr
    # The daemon closes its driver and says so (issue 39: `record`, which is not the daemon, says its own).
    downs = [json.loads(ln) for ln in p.stderr.splitlines() if '"daq.link_down"' in ln]
    assert [d["detail"] for d in downs] == ["the driver is closing, as asked (the daemon is stopping)"], p.stderr


@pytest.mark.serial
def test_client_mode_daemon_reaches_subscribers_through_a_router(tmp_path):
    router_port = free_tcp_port()
    conf = zenoh.Config()
    conf.insert_json5("mode", '"router"')
    conf.insert_json5("listen/endpoints", json.dumps([tcp(router_port)]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    router = zenoh.open(conf)
    machine = "client-01"
    cfg = write_config(
        tmp_path / "d.toml",
        machine=machine,
        daq='transport = "sim"\nscenario = "step"',
        zenoh_mode="client",
        zenoh_connect=[tcp(router_port)],
    )
    try:
        with Procs(tmp_path) as procs:
            daemon = procs.start("daemon", ["run", "--config", str(cfg)])
            sub = Subscriber([tcp(router_port)], machine, mode="client")
            try:
                wait_for(lambda: len(sub.get("estimate")) >= 3 or daemon.poll() is not None, 40.0, "estimates via the router")
                assert daemon.poll() is None, procs.text("daemon")
                wait_for(lambda: sub.get("status"), 5.0, "a status publication")
                (cfg_reply,) = sub.query(f"millsense/{machine}/config")
                assert cfg_reply.get("machine") == machine, cfg_reply
                daemon.send_signal(signal.SIGTERM)
                t0 = time.monotonic()
                assert daemon.wait(5) == 0, procs.text("daemon")
                assert time.monotonic() - t0 < 2.0
                wait_for(lambda: sub.alive and sub.alive[-1][1].endswith("DELETE"), 5.0, "liveliness DELETE")
            finally:
                sub.close()
    finally:
        router.close()
    revs = [e["rev"] for e in sub.get("estimate")]
    assert revs == list(range(revs[0], revs[0] + len(revs)))


def test_daq_that_never_connects_exits_69(tmp_path):
    port = free_tcp_port()  # nothing listens here
    cfg = write_config(
        tmp_path / "d.toml", machine="m69", daq=f'transport = "tcp"\nhost = "127.0.0.1"\ntcp_port = {port}', zenoh_listen=[]
    )
    t0 = time.monotonic()
    p = subprocess.run(CMD + ["run", "--config", str(cfg), "--connect-timeout", "1.5"], capture_output=True, text=True, timeout=60)
    assert p.returncode == 69, p.stderr
    assert f"127.0.0.1:{port}" in p.stderr and "unreachable" in p.stderr
    assert "Traceback" not in p.stderr
    assert time.monotonic() - t0 < 30


def test_bad_config_exits_78_naming_the_key(tmp_path):
    cfg = tmp_path / "bad.toml"
    cfg.write_text('machine = "m78"\n[daq]\ntransport = "tcp"\nhost = "127.0.0.1"\ntcp_port = 1\n[alarms]\ntorque_limt_nm = 3\n')
    p = subprocess.run(CMD + ["run", "--config", str(cfg)], capture_output=True, text=True, timeout=60)
    assert p.returncode == 78, p.stderr
    assert "torque_limt_nm" in p.stderr and "Traceback" not in p.stderr


@pytest.mark.xdist_group("demo")  # one demo at a time: two (mch10-demo, scouting on) find each other and one exits 78
def test_demo_on_a_terminal_refreshes_one_line(tmp_path):
    import os
    import select

    master, slave = os.openpty()
    p = subprocess.Popen(CMD + ["run", "--seconds", "4"], stdout=slave, stderr=subprocess.PIPE)
    os.close(slave)
    out = b""
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            r, _, _ = select.select([master], [], [], 0.2)
            if r:
                try:
                    chunk = os.read(master, 4096)
                except OSError:  # the child closed the terminal
                    break
                if not chunk:
                    break
                out += chunk
            elif p.poll() is not None:
                break
        assert p.wait(10) == 0
    finally:
        if p.poll() is None:
            p.kill()
        os.close(master)
    text = out.decode("utf-8", "replace")
    assert text.count("\r") >= 2 and "rpm" in text, text  # refreshed in place, not a new line each second
    assert text.rstrip("\r\n").count("\n") <= 1
