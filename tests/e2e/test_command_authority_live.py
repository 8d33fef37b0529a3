"""Issue 36 against real daemons: loosening needs authority on every transport; the CLI never guesses the
machine and never reports the wrong outcome.

The daemon runs from a config file with its state directory in tmp_path; the CLI runs as subprocesses, as
an operator would. The requester runs as the same uid as the daemon here (root): over Zenoh that gives it
nothing, since Zenoh carries no uid; what matters is that without the token nothing loosens over Zenoh,
while the local socket (uid-checked: root or the daemon's user) takes it. An impostor is a real second
Zenoh session answering on `millsense/<m>/cmd/*` (tests/publish/helpers.py).
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess

from tests.conftest import free_tcp_port
from tests.e2e.helpers import CMD, Procs, Subscriber, tcp, wait_for, write_config
from millsense.daemon.publish.session import open_session
from tests.publish.helpers import Impostor, zsettings

TOKEN = "authority-token-of-at-least-32-characters-01234"
SLOW_S = 60.0  # detects a hang; no budget
KEY = "4321/7/2"


def _cli(args: list[str], env: dict[str, str]) -> subprocess.CompletedProcess:
    clean = {k: v for k, v in os.environ.items() if k != "MILLSENSE_RESET_TOKEN"}
    return subprocess.run(CMD + args, capture_output=True, text=True, timeout=SLOW_S, env={**clean, **env})


def _audit(state) -> list[dict]:
    path = state / "audit.log"
    return [json.loads(x) for x in path.read_text().splitlines()] if path.exists() else []


def test_a_loopback_daemon_with_no_reset_key_takes_no_loosening_over_zenoh_and_all_at_the_machine(tmp_path):
    """Finding 3: no `reset` key, loopback only: the policy is "open", and it took widen, relearn and afc on/off
    from anyone over Zenoh. Now reset and test-trip still work there; the rest only with --local."""
    machine = "auth-open"
    daq_port, z_port = free_tcp_port(), free_tcp_port()
    cfg = write_config(
        tmp_path / "d.toml", machine=machine,
        daq=f'transport = "tcp"\nhost = "127.0.0.1"\ntcp_port = {daq_port}',
        zenoh_listen=[tcp(z_port)],   # loopback only, so that the left-out reset resolves to "open"
        # (write_config adds reset = "open" unless "reset" is named here: it is left out on purpose)
        interlock="enabled = true\nheartbeat_ms = 50\nwatchdog_ms = 1000\n# reset: left out",
        extra="\n[afc]\nallow = true\ntarget_torque_nm = 5.0\n",
    )
    state = tmp_path / "state"
    env = {"STATE_DIRECTORY": str(state)}
    where = ["--machine", machine, "--connect", tcp(z_port), "--no-scouting", "--timeout", "10"]

    p = _cli(["check-config", str(cfg)], env)
    assert p.returncode == 0, p.stderr
    assert ("reset and test-trip open to anyone who reaches it over Zenoh, limits changes and afc on/off only at "
            'the machine (--local) (reset = "open", no token)') in p.stdout, p.stdout
    with Procs(tmp_path) as procs:
        daemon = procs.start("daemon", ["run", "--config", str(cfg), "--connect-timeout", "60"], env_extra=env)
        sub = Subscriber([tcp(z_port)], machine)
        try:
            procs.start("sim", ["sim", "--scenario", "step", "--loop", "--protocol", "2", "--tcp",
                                f"127.0.0.1:{daq_port}", "--realtime", "--watchdog-ms", "1000"])
            wait_for(lambda: any("afc" in e for e in sub.get("estimate")) or daemon.poll() is not None, SLOW_S,
                     "estimates with the controller's state")
            assert daemon.poll() is None, procs.text("daemon", "out")[-3000:]

            # -- over Zenoh, without a token: refused, pointing to the local socket; nothing ran
            for command in (["limits", "widen", KEY, "--pct", "300"], ["limits", "relearn", KEY], ["afc", "on"],
                            ["afc", "off"]):
                p = _cli([*command, *where], env)
                assert p.returncode == 1, (command, p.stdout + p.stderr)
                assert "needs the reset token over the network" in p.stderr and "add --local" in p.stderr, p.stderr
                assert "root or the daemon's user" in p.stderr
            # refusals are written at most once per 10 s with a count (audit.py): the first now, the rest at stop
            (first,) = wait_for(lambda: _audit(state), 10.0, "the first refusal audited")
            assert first["command"] == "limits" and not first["granted"], first
            assert "needs the reset token over the network" in first["reason"]
            (status,) = sub.query(f"millsense/{machine}/status")
            assert status["afc"]["enabled"] is False

            # -- reset and test-trip still work over Zenoh under "open": the proof test holds and releases
            p = _cli(["test-trip", *where], env)
            assert p.returncode == 0 and "reset granted" in p.stdout, p.stdout + p.stderr
            assert [(a["command"], a["granted"]) for a in _audit(state)[1:]] == [("test-trip", True), ("reset", True)]

            # -- at the machine (root): the local socket takes them, audited with the uid
            p = _cli(["afc", "on", "--local", "--config", str(cfg), "--json"], env)
            assert p.returncode == 0 and json.loads(p.stdout)["afc"]["enabled"] is True, p.stdout + p.stderr
            for command in (["limits", "widen", KEY, "--pct", "10"], ["limits", "relearn", KEY]):
                p = _cli([*command, "--local", "--config", str(cfg), "--json"], env)
                reply = json.loads(p.stdout)
                assert reply["action"] == command[1] and reply["key"] == KEY, reply
            local = [a for a in _audit(state)[3:] if a["requester"].startswith(f"local uid={os.getuid()} ")]
            assert [(a["command"], a["granted"]) for a in local] == [("afc", True), ("limits", True), ("limits", True)]
            (status,) = sub.query(f"millsense/{machine}/status")
            assert status["afc"]["enabled"] is True

            daemon.send_signal(signal.SIGTERM)
            assert daemon.wait(SLOW_S) == 0
            refused = [a for a in _audit(state) if not a["granted"]]
            assert sum(a.get("refused_since_last", 1) for a in refused) == 4, refused
            assert {a["command"] for a in refused} <= {"limits", "afc"} and len(_audit(state)) - len(refused) == 5
        finally:
            sub.close()


def test_the_cli_never_guesses_the_machine_nor_the_outcome_beside_an_impostor(tmp_path):
    """Findings 5 and 6 with a real daemon (token policy): a second program answering on its cmd/* is said and
    no proof is sent; with a second daemon alive nothing is chosen; an unsigned answer is an unknown outcome."""
    machine = "auth-real"
    z_port = free_tcp_port()
    # Every node a client of one router, as on the shop network (security.md): a node that connects is told
    # every queryable at once, so the CLI meets the impostor's with the daemon's, not later by gossip.
    router = open_session(zsettings("router", listen=[tcp(z_port)]), retry_for_s=0)
    cfg = write_config(
        tmp_path / "d.toml", machine=machine, daq='transport = "sim"\nscenario = "step"',
        zenoh_mode="client", zenoh_connect=[tcp(z_port)],
        interlock=f'enabled = true\nreset = "token"\nreset_token = "{TOKEN}"',
    )
    token_file = tmp_path / "token"
    token_file.write_text(TOKEN + "\n")
    state = tmp_path / "state"
    env = {"STATE_DIRECTORY": str(state)}
    network = ["--mode", "client", "--connect", tcp(z_port), "--no-scouting", "--timeout", "10"]
    with Procs(tmp_path) as procs, contextlib.closing(router):
        daemon = procs.start("daemon", ["run", "--config", str(cfg)], env_extra=env)
        sub = Subscriber([tcp(z_port)], machine, mode="client")
        impostor = None
        try:
            wait_for(lambda: sub.get("estimate") or daemon.poll() is not None, SLOW_S, "estimates")
            assert daemon.poll() is None, procs.text("daemon", "out")[-3000:]
            impostor = Impostor(z_port, machine)
            impostor.alive_as("auth-other")
            impostor.known_to(sub.session)   # the router has it: a client connecting now is told at once

            # -- an impostor on cmd/* beside the real daemon: said, nothing sent, nothing ran
            p = _cli(["afc", "on", "--machine", machine, "--token-file", str(token_file), *network], env)
            assert p.returncode == 1, p.stdout + p.stderr
            assert f"2 programs answer on millsense/{machine}/cmd/afc" in p.stderr and "nothing was sent" in p.stderr
            assert impostor.steps() == ["challenge"] and TOKEN not in json.dumps(impostor.got)
            assert _audit(state) == []
            (status,) = sub.query(f"millsense/{machine}/status")
            assert status["afc"]["enabled"] is False

            # -- two daemons alive on the network named, no --machine: named, none chosen
            p = _cli(["limits", "list", *network], env)
            assert p.returncode == 1 and p.stdout == "", p.stdout + p.stderr
            assert f"several daemons are alive (auth-other, {machine}); choose one with --machine" in p.stderr

            # -- alone on a key, an answer that fails the MAC: the outcome is unknown (exit 3), said how to check
            ghost = Impostor(z_port, "auth-ghost")
            try:
                ghost.known_to(sub.session)
                p = _cli(["afc", "on", "--machine", "auth-ghost", "--token-file", str(token_file), *network], env)
            finally:
                ghost.close()
            assert p.returncode == 3, p.stdout + p.stderr
            assert "the outcome is unknown" in p.stderr and "millsense afc status --machine auth-ghost" in p.stderr
            assert "audit.log" in p.stderr

            # -- the impostor gone: the real daemon takes a command with the proof
            impostor.close()
            impostor = None
            p = _cli(["limits", "new-tool", "7", "--machine", machine, "--token-file", str(token_file), "--json",
                      *network], env)
            assert p.returncode == 0 and json.loads(p.stdout)["ok"] is True, p.stdout + p.stderr
            assert [(a["command"], a["granted"]) for a in _audit(state)] == [("limits", True)]

            daemon.send_signal(signal.SIGTERM)
            assert daemon.wait(SLOW_S) == 0
        finally:
            if impostor is not None:
                impostor.close()
            sub.close()
