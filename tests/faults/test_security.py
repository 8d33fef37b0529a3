"""Who can do what to a running daemon: `reset = "off"` (and the local reset), and mutual TLS with an ACL.

Both run the real `millsense run` as a subprocess with the in-process
simulated DAQ (`transport = "sim"`). To have a feed hold to clear, the daemon is
stopped (SIGSTOP) for longer than the DAQ's watchdog: on SIGCONT the simulated
DAQ finds the heartbeats missing and holds the feed by itself.

The TLS case uses config/zenoh-tls.json5 itself (paths and port rewritten),
with certificates made in the test by the `cryptography` package (tests/publish/pki.py, through the
fixture of tests/publish/test_tls.py, which runs the same file against a `ZenohSink` in the
test process; this is the daemon-subprocess variant).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time

import pytest
import zenoh

from tests.conftest import free_tcp_port
from tests.e2e.helpers import CMD, Procs, Subscriber, tcp, wait_for, write_config
from tests.faults.helpers import assert_clean_exit, log_events, status, wait_status
from tests.publish.test_tls import _client, _daemon_config, pki  # noqa: F401 - pki is a fixture

WATCHDOG_MS = 200


def _hold_by_stopping(daemon, wait_hold) -> None:
    """SIGSTOP the daemon past the DAQ's watchdog; on SIGCONT the DAQ holds the feed."""
    os.kill(daemon.pid, signal.SIGSTOP)
    try:
        time.sleep(3 * WATCHDOG_MS / 1000)
    finally:
        os.kill(daemon.pid, signal.SIGCONT)
    wait_hold()


def test_reset_off_refuses_every_network_request_and_the_local_reset_still_works(tmp_path):
    z_port = free_tcp_port()
    machine = "off-01"
    cfg = write_config(
        tmp_path / "d.toml",
        machine=machine,
        daq='transport = "sim"\nscenario = "step"',
        zenoh_listen=[tcp(z_port)],
        interlock=f'enabled = true\nheartbeat_ms = 50\nwatchdog_ms = {WATCHDOG_MS}\nreset = "off"',
    )
    state = {"STATE_DIRECTORY": str(tmp_path / "state")}
    challenge = json.dumps({"step": "challenge", "client_nonce": "ab" * 16}).encode()
    with Procs(tmp_path) as procs:
        daemon = procs.start("daemon", ["run", "--config", str(cfg)], env_extra=state)
        sub = Subscriber([tcp(z_port)], machine)
        try:
            wait_for(lambda: len(sub.get("estimate")) >= 3 or daemon.poll() is not None, 60.0, "estimates")
            assert daemon.poll() is None, procs.text("daemon", "out")[-3000:]
            _hold_by_stopping(daemon, lambda: wait_status(sub, machine, lambda s: s["interlock"] == "held_by_device",
                                                          5.0, "hold by the DAQ's watchdog"))
            replies = [sub.query(f"millsense/{machine}/cmd/reset", p) for p in (challenge, b"{}", b'{"token": "anything"}')]
            cli = subprocess.run([*CMD, "reset", "--machine", machine, "--connect", tcp(z_port), "--no-scouting",
                                  "--timeout", "5"], capture_output=True, text=True, timeout=60)
            time.sleep(0.5)
            after = status(sub, machine)
            # at the machine the operator keeps control: the local socket, whatever the network policy
            local = subprocess.run([*CMD, "reset", "--local", "--config", str(cfg)], capture_output=True, text=True,
                                   timeout=60, env=dict(os.environ, **state))
            cleared = wait_status(sub, machine, lambda s: s["interlock"] != "held_by_device", 5.0, "local reset")
            daemon.send_signal(signal.SIGTERM)
            assert daemon.wait(10) == 0
        finally:
            sub.close()
    for (wrapped,) in replies:
        reply = wrapped["error"]  # an error reply (the Subscriber wraps those)
        assert reply["ok"] is False and reply["error"].startswith("commands over the network are off on off-01"), reply
        assert reply["error"].endswith("millsense reset --local") and reply["policy"] == "off"
    assert cli.returncode == 1 and "commands over the network are off" in cli.stderr, cli.stderr
    assert after["interlock"] == "held_by_device" and after["interlock_detail"]["device_feed_hold"] is True
    assert local.returncode == 0, local.stderr
    assert json.loads(local.stdout)["ok"] is True and cleared["interlock"] == "armed"
    # four refusals (three queries and the CLI's challenge), logged as counts, not a line each
    events = log_events(procs.text("daemon", "out"))
    refused = [e for e in events if e["event"] == "audit.refused"]
    assert 1 <= len(refused) <= 2 and sum(e["refused_since_last"] for e in refused) == 4, refused
    assert all(e["command"] == "reset" for e in refused)
    assert_clean_exit(procs, "daemon")




def _operator_json5(pki_dir, port: int):
    path = pki_dir / f"operator-{port}.json5"
    path.write_text(json.dumps({
        "mode": "client",
        "connect": {"endpoints": [f"tls/localhost:{port}"]},
        "scouting": {"multicast": {"enabled": False}},
        "transport": {"link": {"tls": {
            "root_ca_certificate": str(pki_dir / "ca.pem"), "enable_mtls": True,
            "connect_private_key": str(pki_dir / "operator.key"), "connect_certificate": str(pki_dir / "operator.pem"),
        }}},
    }))
    return path


def test_daemon_behind_mutual_tls_and_acl(pki, tmp_path):  # noqa: F811 - the fixture
    port = free_tcp_port()
    machine = "mch10-01"
    cfg = write_config(
        tmp_path / "d.toml",
        machine=machine,
        daq='transport = "sim"\nscenario = "step"',
        interlock=f'enabled = true\nheartbeat_ms = 50\nwatchdog_ms = {WATCHDOG_MS}\nreset = "open"',
    )
    zenoh_file = _daemon_config(pki, port)
    cfg.write_text(cfg.read_text().replace("[zenoh]\n", f'[zenoh]\nconfig_file = "{zenoh_file}"\n', 1))
    sessions: list[zenoh.Session] = []
    seen: dict[str, list] = {"hmi": [], "intruder": []}
    with Procs(tmp_path) as procs:
        daemon = procs.start("daemon", ["run", "--config", str(cfg)])
        try:
            hmi = wait_for(lambda: _try_client(pki, port, "hmi") or daemon.poll() is not None, 60.0, "TLS listener up")
            assert daemon.poll() is None, procs.text("daemon", "out")[-3000:]
            intruder = _client(pki, port, "intruder")  # a certificate from the right CA, in no policy
            sessions += [hmi, intruder]
            for name, s in (("hmi", hmi), ("intruder", intruder)):
                s.declare_subscriber(f"millsense/{machine}/**", lambda smp, n=name: seen[n].append(str(smp.key_expr)))
            wait_for(lambda: any(k.endswith("/estimate") for k in seen["hmi"]), 30.0, "hmi-01 receives estimates over TLS")

            # no client certificate, or plain TCP: no session at all
            with pytest.raises(zenoh.ZError, match="Unable to connect"):
                _client(pki, port, None)
            plain = zenoh.Config()
            plain.insert_json5("mode", '"client"')
            plain.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
            plain.insert_json5("scouting/multicast/enabled", "false")
            with pytest.raises(zenoh.ZError, match="Unable to connect"):
                zenoh.open(plain)

            def ask(s, key, payload=None):
                return [r for r in s.get(f"millsense/{machine}/{key}", payload=payload, timeout=1.5)]

            def interlock() -> str | None:
                """The daemon's interlock state as hmi-01 reads it; None if no reply came in time
                (right after SIGCONT the daemon may still be catching up with the DAQ)."""
                replies = ask(hmi, "status")
                return json.loads(replies[0].ok.payload.to_bytes())["interlock"] if replies else None

            def held() -> bool:
                return interlock() == "held_by_device"

            _hold_by_stopping(daemon, lambda: wait_for(held, 5.0, "hold by the DAQ's watchdog"))
            # the intruder gets nothing and can do nothing; a viewer can read but not reset
            assert ask(intruder, "status") == [] and ask(intruder, "cmd/reset", b"{}") == []
            assert ask(hmi, "cmd/reset", b"{}") == []
            time.sleep(0.3)
            assert wait_for(interlock, 5.0, "status") == "held_by_device", "a reset got through the ACL"
            assert seen["intruder"] == []
            # the operator, through the real `millsense reset` with its own TLS identity
            op = subprocess.run([*CMD, "reset", "--machine", machine, "--zenoh-config", str(_operator_json5(pki, port)),
                                 "--timeout", "10"], capture_output=True, text=True, timeout=60)
            assert op.returncode == 0, op.stderr
            assert json.loads(op.stdout)["interlock"] == "armed"
            assert wait_for(interlock, 5.0, "status") == "armed"
            assert seen["intruder"] == []
            daemon.send_signal(signal.SIGTERM)
            assert daemon.wait(10) == 0
        finally:
            for s in sessions:
                s.close()
    assert_clean_exit(procs, "daemon")


def _try_client(pki_dir, port: int, stem: str):
    try:
        return _client(pki_dir, port, stem)
    except zenoh.ZError:
        time.sleep(0.2)
        return None
