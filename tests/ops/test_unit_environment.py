"""The daemon as its systemd unit runs it: with the unit's `Environment=` (PYTHONOPTIMIZE=2, Python's -OO).

-OO drops docstrings and assert statements. So the service's code may neither rely on an assert nor read a
docstring, and the daemon must do its whole job so: every DAQ transport, the history and learned limits on,
estimates published, a clean stop, and a bad config still a clear exit 78.
"""

from __future__ import annotations

import ast
import os
import signal
import subprocess

import pytest

from millsense.daemon.cli import COMMANDS
from tests.conftest import REPO, free_tcp_port
from tests.e2e.helpers import CMD, Procs, Subscriber, tcp, wait_for, write_config
from tests.ops.unit_file import unit_environment

SERVICE_CODE = [REPO / "daemon", REPO / "drivers"]


def _unit_env() -> dict[str, str]:
    env = dict(os.environ, **unit_environment())
    assert env.get("PYTHONOPTIMIZE") == "2", "the unit no longer runs Python with -OO: this file tests that it does"
    return env


def _offences(path, root) -> list[str]:
    tree = ast.parse(path.read_text(), str(path))
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Assert):
            found.append(f"{path.relative_to(root)}:{node.lineno}: assert (gone under -O)")
        elif (isinstance(node, ast.Attribute) and node.attr == "__doc__") or (
                isinstance(node, ast.Name) and node.id == "__doc__"):
            found.append(f"{path.relative_to(root)}:{node.lineno}: __doc__ (None under -OO)")
    return found


def test_the_service_code_neither_asserts_nor_reads_docstrings():
    found = [o for root in SERVICE_CODE for path in sorted(root.rglob("*.py")) for o in _offences(path, REPO)]
    assert not found, "\n".join(found)


def test_the_check_sees_both(tmp_path):
    """The check above would see an assert and a docstring read."""
    bad = tmp_path / "probe.py"
    bad.write_text('"""doc"""\nassert True\nHELP = __doc__.split()\n')
    assert [o.split(": ", 1)[1] for o in _offences(bad, tmp_path)] == ["assert (gone under -O)", "__doc__ (None under -OO)"]


def _daq(transport: str, tmp_path, port: int) -> tuple[str, list[str]]:
    """(the config's [daq] body, the emulator's arguments) for one transport."""
    if transport == "tcp":
        return f'transport = "tcp"\nhost = "127.0.0.1"\ntcp_port = {port}', ["--tcp", f"127.0.0.1:{port}"]
    if transport == "serial":
        link = tmp_path / "daq-link"
        return f'transport = "serial"\nport = "{link}"\nbaudrate = 921600', ["--pty", str(link)]
    if transport == "modbus-rtu":
        link = tmp_path / "rtu-link"
        return (f'transport = "modbus-rtu"\nport = "{link}"\nbaudrate = 921600\nunit = 1\npoll_ms = 20',
                ["--modbus-rtu", str(link)])
    return (f'transport = "modbus-tcp"\nhost = "127.0.0.1"\ntcp_port = {port}\nunit = 1\npoll_ms = 20',
            ["--modbus-tcp", f"127.0.0.1:{port}"])


@pytest.mark.parametrize("transport", ["tcp", "serial", "modbus-tcp", "modbus-rtu"])
def test_the_daemon_runs_as_the_unit_runs_it(tmp_path, transport):
    """Learned limits and the history on (their defaults), for each transport: estimates reach a
    subscriber, the status answers, SIGTERM stops it cleanly, and no traceback."""
    daq_port, z_port = free_tcp_port(), free_tcp_port()
    machine = f"unit-env-{transport}"
    daq, sim_args = _daq(transport, tmp_path, daq_port)
    cfg = write_config(tmp_path / "d.toml", machine=machine, daq=daq, zenoh_listen=[tcp(z_port)])
    _unit_env()  # the unit still asks for -OO
    with Procs(tmp_path) as procs:
        procs.start("sim", ["sim", "--scenario", "step", "--loop", "--realtime", "--watchdog-ms", "1000", *sim_args])
        daemon = procs.start("daemon", ["run", "--config", str(cfg), "--connect-timeout", "30"],
                             env_extra=unit_environment())
        sub = Subscriber([tcp(z_port)], machine)
        try:
            wait_for(lambda: len(sub.get("estimate")) >= 5 or daemon.poll() is not None, 60.0, "estimates")
            assert daemon.poll() is None, procs.text("daemon")
            assert any(e.get("valid") for e in sub.get("estimate")), sub.get("estimate")[-3:]

            def history_written() -> dict | None:
                (status,) = sub.query(f"millsense/{machine}/status")
                written = ((status.get("history") or {}).get("written") or {}).get("revolutions", 0)
                return status if status.get("state") == "running" and written > 0 else None

            wait_for(history_written, 20.0, "the daemon running, its history written")
            daemon.send_signal(signal.SIGTERM)
            assert daemon.wait(10) == 0, procs.text("daemon")
        finally:
            sub.close()
        log = procs.text("daemon") + procs.text("daemon", "out")
    assert "Traceback" not in log, log[-3000:]


def test_a_bad_config_is_still_a_clear_exit_78(tmp_path):
    """Config errors are pydantic's and our own messages, never a docstring: the same text under -OO."""
    cfg = tmp_path / "bad.toml"
    cfg.write_text('machine = "m"\n[daq]\ntransport = "tcp"\nhost = "127.0.0.1"\ntcp_port = 7\n'
                   '[alarms]\noverload_torque_nm = "x"\n')
    plain = subprocess.run(CMD + ["run", "--config", str(cfg)], capture_output=True, text=True, timeout=60)
    as_unit = subprocess.run(CMD + ["run", "--config", str(cfg)], capture_output=True, text=True, timeout=60,
                             env=_unit_env())
    assert as_unit.returncode == plain.returncode == 78, as_unit.stderr
    assert "alarms.overload_torque_nm: unknown key" in as_unit.stderr
    assert as_unit.stderr == plain.stderr
    assert "Traceback" not in as_unit.stderr


def test_every_subcommand_builds_its_help_under_the_unit_environment():
    """An operator's `millsense limits --help` inherits nothing from the unit, but a script run with -OO
    might: no subcommand's parser may need its module's docstring."""
    env = _unit_env()
    for name in COMMANDS:
        p = subprocess.run(CMD + [name, "--help"], capture_output=True, text=True, timeout=60, env=env)
        assert p.returncode == 0 and "Traceback" not in p.stderr, (name, p.stderr[-2000:])
