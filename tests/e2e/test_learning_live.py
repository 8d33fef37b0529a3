"""Learned limits on the live path: the DAQ's context over TCP, an envelope that holds the feed, the
history on disk, and the limits still there after a restart.

The real emulator plays the part program (protocol 2, the CNC's context in
its CONTEXT frames) over TCP; the real daemon learns T11's operation from two
good parts; in part 3 a flute of T11 breaks. With the fixed breakage check
left out of the config, only the learned envelope can see it: `envelope_low`
must hold the feed (the emulator's status log shows the output), the
summaries and the alarm must be in the history database, and a restarted
daemon must answer the `limits` query with the envelope it learned.

The emulator plays from its first client's connect on (`--start-on-connect`): the daemon, started after it,
must see part 1 from its start (its first process "learning", not cut into from the middle), however long
its own start-up takes on a loaded box.
"""

from __future__ import annotations

import json
import signal
import subprocess
import tomllib

import pytest

from tests.conftest import free_tcp_port
from tests.config.helpers import dumps
from tests.e2e.helpers import CMD, Procs, Subscriber, read_jsonl, tcp, wait_for
from tests.e2e.learning_run import CONFIG

SLOW_S = 120.0
KEY = "1001/11/10"


def _config(path, daq_port, z_port, machine):
    doc = tomllib.loads(CONFIG.read_text())
    doc["machine"] = machine
    doc["daq"].update(host="127.0.0.1", tcp_port=daq_port)
    doc["alarms"].pop("breakage_drop_pct", None)  # the envelope alone must catch the broken flute
    doc["learning"] = {"processes": 2}
    doc["interlock"] = {"enabled": True, "heartbeat_ms": 50, "watchdog_ms": 1000, "reset": "open"}
    doc["zenoh"] = {"mode": "peer", "listen": [tcp(z_port)], "connect": [], "multicast_scouting": False}
    doc["log"] = {"level": "info", "format": "json"}
    path.write_text(dumps(doc))
    return path


@pytest.mark.slow
def test_an_envelope_learned_live_holds_the_feed_and_outlives_a_restart(tmp_path):
    daq_port, z_port = free_tcp_port(), free_tcp_port()
    machine = "learn-live"
    cfg = _config(tmp_path / "d.toml", daq_port, z_port, machine)
    log_path = tmp_path / "status.jsonl"
    with Procs(tmp_path) as procs:
        procs.start("sim", ["sim", "--scenario", "part-program", "--parts", "3", "--broken-flute", "3:11",
                            "--tcp", f"127.0.0.1:{daq_port}", "--realtime", "--once", "--start-on-connect", "--watchdog-ms", "1000",
                            "--status-log", str(log_path)])
        wait_for(lambda: "serving" in procs.text("sim"), 60.0, "emulator serving")
        daemon = procs.start("daemon", ["run", "--config", str(cfg), "--connect-timeout", "120"])
        sub = Subscriber([tcp(z_port)], machine)
        try:
            # two good parts teach T11's operation; every estimate names what the CNC said it was doing
            learned = wait_for(lambda: [p for p in sub.get("process") if p["key"] == KEY and p["envelope"] == "active"],
                               SLOW_S, f"{KEY} learned from two parts")
            assert learned[0]["verdict"] == "learning" and learned[0]["learned"] == 2
            cutting = [e for e in sub.get("estimate") if e.get("process_rev") is not None]
            assert cutting and {e["program"] for e in cutting} == {1001}
            assert {e["tool"] for e in cutting} <= {11, 4, 27}
            # part 3: the flute breaks; the envelope holds the feed through the DAQ
            try:
                alarm = wait_for(lambda: [a for a in sub.get("alarm") if a["level"] == "envelope_low"], SLOW_S,
                                 "envelope_low on the broken flute")[0]
            except AssertionError as exc:
                raise AssertionError(f"{exc}; alarms {sub.get('alarm')}; processes {sub.get('process')}") from None
            assert alarm["tool"] == 11 and alarm["interlock"] == "feed_hold", alarm
            wait_for(lambda: [e for e in read_jsonl(log_path) if e.get("event") == "outputs" and e.get("feed_hold")],
                     30.0, "the emulated DAQ's feed-hold output")
            limits = sub.query(f"millsense/{machine}/limits")
            assert limits and any(e["key"] == KEY and e["state"] == "active" for e in limits[0]["limits"])
        finally:
            sub.close()
            daemon.send_signal(signal.SIGTERM)
            daemon.wait(30)
        assert daemon.returncode == 0, procs.text("daemon")
        # the history has the process summaries and the alarm; the export reads them back
        out = subprocess.run(CMD + ["history", "--config", str(cfg), "--what", "processes", "--format", "jsonl",
                                    "--tool", "11"], capture_output=True, text=True, timeout=60)
        assert out.returncode == 0, out.stderr
        rows = [json.loads(line) for line in out.stdout.splitlines()]
        assert [r["verdict"] for r in rows if r["key"] == KEY][:2] == ["learning", "learning"]
        alarms = subprocess.run(CMD + ["history", "--config", str(cfg), "--what", "alarms", "--format", "jsonl"],
                                capture_output=True, text=True, timeout=60)
        assert any(json.loads(line)["level"] == "envelope_low" for line in alarms.stdout.splitlines()), alarms.stdout
        # restarted, the daemon answers with the envelope it learned (no DAQ needed for that)
        daemon = procs.start("daemon2", ["run", "--config", str(cfg), "--connect-timeout", "120"])
        sub = Subscriber([tcp(z_port)], machine)
        try:
            def restored():
                answer = sub.query(f"millsense/{machine}/limits")
                return answer and [e for e in answer[0]["limits"] if e["key"] == KEY and e["state"] == "active"]

            (entry,) = wait_for(restored, SLOW_S, "the learned envelope after a restart", step_s=0.5)
            assert entry["learned"] == 2
        finally:
            sub.close()


def test_the_context_comes_through_modbus_registers_too(tmp_path):
    """The same program behind a Modbus TCP DAQ: input registers 8-15 carry the context (protocol 2)."""
    daq_port, z_port = free_tcp_port(), free_tcp_port()
    machine = "learn-modbus"
    cfg = _config(tmp_path / "d.toml", daq_port, z_port, machine)
    doc = tomllib.loads(cfg.read_text())
    doc["daq"] = {"transport": "modbus-tcp", "host": "127.0.0.1", "tcp_port": daq_port, "unit": 1, "poll_ms": 20,
                  "filter_cutoff_hz": 200, "filter_order": 2}
    doc["interlock"] = {"enabled": False, "reset": "open"}
    cfg.write_text(dumps(doc))
    with Procs(tmp_path) as procs:
        procs.start("sim", ["sim", "--scenario", "part-program", "--parts", "1", "--modbus-tcp", f"127.0.0.1:{daq_port}",
                            "--realtime", "--once", "--start-on-connect"])
        wait_for(lambda: "serving" in procs.text("sim"), 60.0, "emulator serving")
        procs.start("daemon", ["run", "--config", str(cfg), "--connect-timeout", "120"])
        sub = Subscriber([tcp(z_port)], machine)
        try:
            first = wait_for(lambda: sub.get("process"), SLOW_S, "the first process over Modbus")[0]
            assert (first["key"], first["verdict"], first["learned"]) == (KEY, "learning", 1)
            cutting = [e for e in sub.get("estimate") if e.get("process_rev") is not None]
            assert cutting and {(e["program"], e["tool"], e["operation"]) for e in cutting} == {(1001, 11, 10)}
        finally:
            sub.close()
