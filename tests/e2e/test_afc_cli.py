"""`millsense afc` against a real daemon and the real emulator (protocol 2: a DAQ with the feed override).

The daemon connects over TCP to `millsense sim --protocol 2`; the CLI runs as subprocesses, as an
operator would: `status` reads without a token, `on` is refused without the token and with a wrong
one (audited), granted with it (audited with the Zenoh id), `off` at the machine through the control
socket (audited with the uid). The estimates then carry the override and the controller's state, and
`watch`'s line and the daemon's status line show them.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess

import pytest

from millsense.daemon.commands.watch import _TtyView
from millsense.daemon.status_text import status_line
from tests.conftest import free_tcp_port
from tests.e2e.helpers import CMD, Procs, Subscriber, tcp, wait_for, write_config

pytestmark = pytest.mark.slow  # over about 10 s each: handed out first (tests/parallel.py)

TOKEN = "afc-token-of-at-least-32-characters-0123456789ab"
SLOW_S = 60.0  # detects a hang; no budget


def _cli(args: list[str], env: dict[str, str]) -> subprocess.CompletedProcess:
    return subprocess.run(CMD + ["afc", *args], capture_output=True, text=True, timeout=SLOW_S,
                          env=dict(os.environ, **env))


def _audit(state) -> list[dict]:
    path = state / "audit.log"
    return [json.loads(x) for x in path.read_text().splitlines()] if path.exists() else []


def test_afc_cli_switches_authorised_and_audited_against_a_real_daemon(tmp_path):
    machine = "afc-e2e"
    daq_port, z_port = free_tcp_port(), free_tcp_port()
    cfg = write_config(
        tmp_path / "d.toml", machine=machine,
        daq=f'transport = "tcp"\nhost = "127.0.0.1"\ntcp_port = {daq_port}',
        zenoh_listen=[tcp(z_port)],
        interlock=f'enabled = true\nheartbeat_ms = 50\nwatchdog_ms = 1000\nreset = "token"\nreset_token = "{TOKEN}"',
        extra="\n[afc]\nallow = true\ntarget_torque_nm = 5.0\n",
    )
    token_file = tmp_path / "token"
    token_file.write_text(TOKEN + "\n")
    wrong_file = tmp_path / "wrong"
    wrong_file.write_text("w" * 48 + "\n")
    state = tmp_path / "state"
    env = {"STATE_DIRECTORY": str(state)}
    where = ["--machine", machine, "--connect", tcp(z_port), "--no-scouting", "--timeout", "10"]
    with Procs(tmp_path) as procs:
        daemon = procs.start("daemon", ["run", "--config", str(cfg), "--connect-timeout", "60"], env_extra=env)
        sub = Subscriber([tcp(z_port)], machine)
        try:
            procs.start("sim", ["sim", "--scenario", "step", "--protocol", "2", "--tcp", f"127.0.0.1:{daq_port}",
                                "--realtime", "--watchdog-ms", "1000"])
            wait_for(lambda: any("afc" in e for e in sub.get("estimate")) or daemon.poll() is not None, SLOW_S,
                     "estimates with the controller's state")
            assert daemon.poll() is None, procs.text("daemon", "out")[-3000:]

            # -- status reads without a token: off at start, the DAQ can take an override
            p = _cli(["status", "--json", *where], env)
            assert p.returncode == 0, p.stderr
            afc = json.loads(p.stdout)["afc"]
            assert afc["enabled"] is False and afc["state"] == "off" and afc["available"] is True, afc
            p = _cli(["status", *where], env)
            assert p.returncode == 0 and p.stdout.startswith(f"{machine}: adaptive feed control off"), p.stdout

            # -- on: refused without the token and with a wrong one (audited), granted with it
            p = _cli(["on", *where], env)
            assert p.returncode == 1 and "requires a reset token" in p.stderr, p.stderr
            p = _cli(["on", "--token-file", str(wrong_file), *where], env)
            # a wrong token cannot verify the daemon's signed refusal: said, as an unknown outcome (exit 3)
            assert p.returncode == 3 and "refused afc" in p.stderr and "outcome is unknown" in p.stderr, p.stderr
            refused = wait_for(lambda: [a for a in _audit(state) if a["command"] == "afc"], 10.0, "the refusal")
            assert refused[0]["granted"] is False and "does not match" in refused[0]["reason"]
            p = _cli(["on", "--token-file", str(token_file), *where], env)
            assert p.returncode == 0 and "switched on" in p.stdout, p.stdout + p.stderr
            granted = [a for a in _audit(state) if a["command"] == "afc" and a["granted"]]
            assert len(granted) == 1 and granted[0]["requester"].startswith("zid:"), granted
            assert granted[0]["result"]["action"] == "on" and granted[0]["result"]["afc"]["enabled"] is True

            # -- the estimates carry the override and the controller's state; watch and the status line show them
            try:
                est = wait_for(lambda: [e for e in sub.get("estimate")
                                        if isinstance(e.get("afc"), dict) and e["afc"]["state"] != "off"], SLOW_S,
                               "an estimate with AFC on")[-1]
            except AssertionError:
                seen = sub.get("estimate")
                raise AssertionError(f"{len(seen)} estimates, the last: {[e.get('afc') for e in seen[-3:]]}; "
                                     f"status: {sub.query(f'millsense/{machine}/status')[0].get('afc')}") from None
            line = _TtyView._line(machine, {"alive": True, "estimate": est})
            assert f"ovr {est['feed_override_pct']:.0f} %" in line and f"AFC {est['afc']['state']}" in line, line
            (status,) = sub.query(f"millsense/{machine}/status")
            assert status["afc"]["enabled"] is True
            assert f"AFC {status['afc']['state']} override" in status_line(status), status_line(status)

            # -- off at the machine: the control socket, audited with the local uid
            p = _cli(["off", "--local", "--config", str(cfg), "--json"], env)
            assert p.returncode == 0, p.stderr
            reply = json.loads(p.stdout)
            assert reply["ok"] is True and reply["afc"]["enabled"] is False and reply["afc"]["override_pct"] == 100.0
            local = [a for a in _audit(state) if a["command"] == "afc" and a["requester"].startswith("local uid=")]
            assert len(local) == 1 and local[0]["result"]["action"] == "off", local
            p = _cli(["status", "--local", "--config", str(cfg), "--json"], env)
            assert p.returncode == 0 and json.loads(p.stdout)["afc"]["enabled"] is False, p.stderr
            (status,) = sub.query(f"millsense/{machine}/status")
            assert "AFC" not in status_line(status)

            # -- bad arguments: usage errors, nothing sent
            before = len(_audit(state))
            for bad in (["faster", *where], ["on", "--pct", "120", *where], ["status", "--local"]):
                p = _cli(bad, env)
                assert p.returncode == 2 and "Traceback" not in p.stderr, (bad, p.stderr)
            assert len(_audit(state)) == before

            daemon.send_signal(signal.SIGTERM)
            assert daemon.wait(SLOW_S) == 0
        finally:
            sub.close()
