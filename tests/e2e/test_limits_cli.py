"""`millsense limits` against a real daemon: reads over Zenoh, changes authorised, audited, and at the machine.

The daemon runs the in-process simulated DAQ (`transport = "sim"`, which
reports no context) with `[context] source = "zenoh"`, a token policy and its
state directory in tmp_path. A CNC adapter's context is put on
`millsense/<m>/context` by a Zenoh session of the test, and the daemon's
estimates must carry it. The CLI runs as subprocesses, as an operator would.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess

import zenoh

from tests.conftest import free_tcp_port
from tests.e2e.helpers import CMD, Procs, Subscriber, tcp, wait_for, write_config

TOKEN = "limits-token-of-at-least-32-characters-0123456789"
SLOW_S = 60.0  # detects a hang; no budget


def _cli(args: list[str], env: dict[str, str]) -> subprocess.CompletedProcess:
    return subprocess.run(CMD + ["limits", *args], capture_output=True, text=True, timeout=SLOW_S,
                          env=dict(os.environ, **env))


def _audit(state) -> list[dict]:
    path = state / "audit.log"
    return [json.loads(x) for x in path.read_text().splitlines()] if path.exists() else []


def test_limits_cli_reads_changes_and_audits_against_a_real_daemon(tmp_path):
    machine = "lim-e2e"
    z_port = free_tcp_port()
    cfg = write_config(
        tmp_path / "d.toml", machine=machine, daq='transport = "sim"\nscenario = "step"',
        zenoh_listen=[tcp(z_port)],
        interlock=f'enabled = true\nreset = "token"\nreset_token = "{TOKEN}"',
        extra='\n[context]\nsource = "zenoh"\n',
    )
    token_file = tmp_path / "token"
    token_file.write_text(TOKEN + "\n")
    wrong_file = tmp_path / "wrong"
    wrong_file.write_text("w" * 48 + "\n")
    state = tmp_path / "state"
    env = {"STATE_DIRECTORY": str(state)}
    where = ["--machine", machine, "--connect", tcp(z_port), "--no-scouting", "--timeout", "10"]
    with Procs(tmp_path) as procs:
        daemon = procs.start("daemon", ["run", "--config", str(cfg)], env_extra=env)
        sub = Subscriber([tcp(z_port)], machine)
        try:
            wait_for(lambda: sub.get("estimate") or daemon.poll() is not None, SLOW_S, "estimates")
            assert daemon.poll() is None, procs.text("daemon", "out")[-3000:]

            # -- reads: no token; the CLI shows what the queryable holds
            p = _cli(["list", "--json", *where], env)
            assert p.returncode == 0, p.stderr
            listed = json.loads(p.stdout)
            (direct,) = sub.query(f"millsense/{machine}/limits")
            assert listed["machine"] == machine and listed == direct
            p = _cli(["list", *where], env)
            assert p.returncode == 0 and p.stdout.startswith(f"{machine}:"), p.stdout + p.stderr

            # -- a CNC adapter's context reaches the daemon over Zenoh: the estimates carry it
            pub = sub.session.declare_publisher(f"millsense/{machine}/context",
                                                encoding=zenoh.Encoding.APPLICATION_JSON)
            wait_for(lambda: pub.matching_status.matching, SLOW_S, "the daemon's context subscriber")
            ctx = {"program": 4321, "tool": 7, "operation": 2, "cycle": True, "monitor": True, "afc_allowed": False}
            pub.put(json.dumps(ctx).encode())
            wait_for(lambda: any(e.get("program") == 4321 and e.get("tool") == 7 and e.get("operation") == 2
                                 for e in sub.get("estimate")), SLOW_S, "estimates with the adapter's context")
            pub.undeclare()

            # -- changes: refused without the token, and with a wrong one (audited); granted with it
            p = _cli(["new-tool", "7", *where], env)
            assert p.returncode == 1 and "requires a reset token" in p.stderr, p.stderr
            p = _cli(["new-tool", "7", "--token-file", str(wrong_file), *where], env)
            assert p.returncode == 3 and "refused limits" in p.stderr, p.stderr  # unverifiable: outcome unknown
            refused = wait_for(lambda: [a for a in _audit(state) if a["command"] == "limits"], 10.0, "the refusal")
            assert refused[0]["granted"] is False and "does not match" in refused[0]["reason"]
            p = _cli(["new-tool", "7", "--json", "--token-file", str(wrong_file).replace("wrong", "token"), *where],
                     env)
            result = json.loads(p.stdout)
            assert result["action"] == "new_tool" and result["tool"] == 7
            assert p.returncode == (0 if result.get("ok") else 1), p.stderr
            granted = [a for a in _audit(state) if a["command"] == "limits" and a["granted"]]
            assert len(granted) == 1 and granted[0]["requester"].startswith("zid:"), granted
            assert granted[0]["result"]["action"] == "new_tool" and granted[0]["result"]["tool"] == 7

            # -- a key nobody learned: the daemon says so, exit 1, nothing changed
            p = _cli(["show", "1/2/3", *where], env)
            assert p.returncode == 1 and "refused show" in p.stderr, p.stdout + p.stderr

            # -- at the machine: the control socket, the same audit trail with the local uid
            p = _cli(["widen", "4321/7/2", "--pct", "10", "--local", "--config", str(cfg), "--json"], env)
            reply = json.loads(p.stdout)
            assert reply["action"] == "widen" and reply["key"] == "4321/7/2" and reply["pct"] == 10
            assert p.returncode == (0 if reply.get("ok") else 1), p.stderr
            local = [a for a in _audit(state) if a["command"] == "limits" and a["requester"].startswith("local uid=")]
            assert len(local) == 1 and local[0]["result"]["action"] == "widen", local
            p = _cli(["list", "--local", "--config", str(cfg), "--json"], env)
            assert p.returncode == 0 and json.loads(p.stdout)["machine"] == machine, p.stderr

            # -- bad arguments: usage errors, nothing sent
            before = len(_audit(state))
            for bad in (["widen", "4321/7/2", *where], ["widen", "4321/7", "--pct", "5", *where],
                        ["new-tool", "T7", *where], ["widen", "4321/7/2", "--pct", "12.5", *where]):
                p = _cli(bad, env)
                assert p.returncode == 2 and "Traceback" not in p.stderr, (bad, p.stderr)
            assert len(_audit(state)) == before

            daemon.send_signal(signal.SIGTERM)
            assert daemon.wait(SLOW_S) == 0
        finally:
            sub.close()
