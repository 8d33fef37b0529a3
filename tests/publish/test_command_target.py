"""Issue 36, finding 5: a command that changes or reads one machine never guesses it.

`--machine`, or `--config`'s; else the only daemon on a network the user named (endpoints, scouting off);
else the default config's machine, the demo's. The CLI runs as real subprocesses; the daemons are real
`ZenohSink`s on real sessions. Where scouting is the point, the sessions scout on a multicast group and port
of this test's own, on loopback only, so that nothing else on the box takes part.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess

import pytest

from millsense.daemon.audit import AuditLog
from millsense.daemon.publish.cli_args import Target, command_target, default_machine
from millsense.daemon.publish.session import open_session
from millsense.daemon.publish.sink import ZenohSink
from tests.conftest import free_tcp_port

from .helpers import OperatorControls, tcp, zsettings


def _args(**given) -> argparse.Namespace:
    base = dict(machine=None, config=None, local=False, timeout=None, connect=[], no_scouting=False,
                zenoh_config="", mode=None)
    return argparse.Namespace(**{**base, **given})


def test_the_target_is_named_or_the_defaults_never_the_only_one_scouting_found():
    target = command_target(_args(), "millsense limits", 2.0, 30.0)
    assert target == Target(None, default_machine(), why=target.why) and default_machine() == "mch10-demo"
    assert "no --machine or --config given" in target.why
    # a network named by the user: its only daemon, found once the session is open
    named = command_target(_args(connect=["tcp/127.0.0.1:7447"], no_scouting=True), "millsense limits", 2.0, 30.0)
    assert named.machine is None and named.network == "tcp/127.0.0.1:7447"
    # endpoints given but scouting on: scouting may find anything, so that is not a named network
    assert command_target(_args(connect=["tcp/127.0.0.1:7447"]), "p", 2.0, 30.0).machine == "mch10-demo"
    assert command_target(_args(machine="m7"), "p", 2.0, 30.0) == Target(None, "m7")


@pytest.fixture
def scouting(tmp_path):
    """A Zenoh JSON5 file scouting on a multicast port of this test's own, on loopback."""
    path = tmp_path / "scouting.json5"
    path.write_text('{ mode: "peer", scouting: { multicast: { enabled: true, interface: "lo", '
                    f'address: "224.0.0.224:{free_tcp_port()}" }} }} }}\n')
    return path


def _scouting_daemon(scouting, machine, tmp_path):
    session = open_session(zsettings(listen=[tcp(free_tcp_port())], multicast_scouting=True,
                                     config_file=str(scouting)), retry_for_s=0)
    controls = OperatorControls(None, AuditLog(tmp_path / f"{machine}.audit.log", machine), machine=machine)
    return session, controls, ZenohSink(session, machine, controls)


def _cli(millsense_cmd, *args):
    env = {k: v for k, v in os.environ.items() if k != "MILLSENSE_RESET_TOKEN"}
    return subprocess.run([*millsense_cmd, *args], capture_output=True, text=True, timeout=60, env=env)


def test_a_daemon_scouting_found_is_not_taken_for_the_one_meant(millsense_cmd, scouting, tmp_path):
    """Finding 5: on a host where scouting found another daemon, `limits list` answered for it."""
    session, controls, sink = _scouting_daemon(scouting, "mch10-01", tmp_path)
    try:
        p = _cli(millsense_cmd, "limits", "list", "--zenoh-config", str(scouting))
        assert p.returncode == 1 and p.stdout == "", p.stdout + p.stderr
        assert ("no daemon mch10-demo alive (the demo's, the default config: no --machine or --config given); "
                "alive: mch10-01: choose one with --machine, or give its --config") in p.stderr, p.stderr
        p = _cli(millsense_cmd, "limits", "list", "--zenoh-config", str(scouting), "--machine", "mch10-01")
        assert p.returncode == 0 and p.stdout.startswith("mch10-01: 1 process key(s)"), p.stdout + p.stderr
    finally:
        sink.close()
        session.close()


def test_beside_the_demo_reset_with_no_arguments_clears_its_hold_and_says_which(millsense_cmd, scouting,
                                                                                 tmp_path):
    """The README's first steps: `millsense run` (the demo, reset "open") and `millsense reset` beside it."""
    session, controls, sink = _scouting_daemon(scouting, "mch10-demo", tmp_path)
    try:
        p = _cli(millsense_cmd, "reset", "--zenoh-config", str(scouting))
        assert p.returncode == 0, p.stdout + p.stderr
        assert json.loads(p.stdout) == {"ok": True, "interlock": "clear"} and not controls.latched
        assert "millsense reset: machine mch10-demo (the demo's, the default config" in p.stderr
    finally:
        sink.close()
        session.close()


def test_two_daemons_on_the_named_network_are_named_and_none_is_chosen(millsense_cmd, port, tmp_path):
    session = open_session(zsettings(listen=[tcp(port)]), retry_for_s=0)
    sinks = [ZenohSink(session, m, OperatorControls(None, AuditLog(None, m), machine=m)) for m in ("cell-a", "cell-b")]
    try:
        for command in (["limits", "list"], ["afc", "status"], ["reset"], ["test-trip"]):
            p = _cli(millsense_cmd, *command, "--connect", tcp(port), "--no-scouting")
            assert p.returncode == 1 and p.stdout == "", (command, p.stdout + p.stderr)
            assert "several daemons are alive (cell-a, cell-b); choose one with --machine" in p.stderr, p.stderr
        assert all(s._controls.ran == [] and s._controls.latched for s in sinks)
        sinks.pop().close()
        p = _cli(millsense_cmd, "limits", "list", "--connect", tcp(port), "--no-scouting")
        assert p.returncode == 0 and p.stdout.startswith("cell-a:"), p.stdout + p.stderr
        assert f"millsense limits: machine cell-a (the only daemon on {tcp(port)})" in p.stderr
    finally:
        for s in sinks:
            s.close()
        session.close()
