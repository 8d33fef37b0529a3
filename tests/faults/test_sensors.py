"""Issue 10, finding 2, live: a DAQ whose every channel is stuck is not a machine running unwatched.

The emulator (`millsense sim --pin`) stands in for a front end whose inputs all
stick at the rail; the real daemon (`millsense run`, interlock on, the default
`on_blind = "hold"`) must publish no valid estimate, say fault `signals` naming
a channel within a second of samples, and hold the feed (the emulator's own
output log says so).
"""

from __future__ import annotations

from tests.conftest import free_tcp_port
from tests.e2e.helpers import Procs, Subscriber, read_jsonl, tcp, wait_for, write_config
from tests.faults.helpers import outputs, status, wait_status

ALL = ("v_uv", "v_vw", "v_wu", "i_u", "i_v", "i_w", "sp_rpm", "sp_enc")


def test_all_channels_pinned_live_fault_signals_and_the_feed_held(tmp_path):
    daq_port, z_port = free_tcp_port(), free_tcp_port()
    machine = "pinned-01"
    sim_log = tmp_path / "sim.jsonl"
    cfg = write_config(
        tmp_path / "d.toml",
        machine=machine,
        daq=f'transport = "tcp"\nhost = "127.0.0.1"\ntcp_port = {daq_port}',
        zenoh_listen=[tcp(z_port)],
        alarms="crash_current_a = 60",
        interlock='enabled = true\nheartbeat_ms = 50\nwatchdog_ms = 1000\nreset = "open"',
    )
    pins = [f"--pin={name}=32767" for name in ALL]
    with Procs(tmp_path) as procs:
        procs.start("sim", ["sim", "--scenario", "step", "--loop", "--tcp", f"127.0.0.1:{daq_port}", "--realtime",
                            "--watchdog-ms", "1000", "--status-log", str(sim_log), *pins])
        wait_for(lambda: "serving" in procs.text("sim"), 60.0, "emulator serving")
        daemon = procs.start("daemon", ["run", "--config", str(cfg)])
        sub = Subscriber([tcp(z_port)], machine)
        try:
            st = wait_status(sub, machine, lambda s: "signals" in s.get("faults", {}) or s["samples_received"] > 5000,
                             60.0, "fault signals")
            assert daemon.poll() is None, procs.text("daemon", "out")[-3000:]
            reason = st["faults"].get("signals", "")
            assert "i_u: at raw_max 32767" in reason and "v_uv: at raw_max 32767" in reason, st["faults"]
            # counted in samples: raised before a second of them had arrived
            assert st["samples_received"] < 1000 + 2 * 1000, st["samples_received"]  # status ticks once a second
            held = wait_for(lambda: outputs(read_jsonl(sim_log), feed_hold=True, cause="command"), 10.0,
                            "the daemon holds the feed (on_blind = hold)")
            assert held
            assert status(sub, machine)["state"] != "running"
            assert not [e for e in sub.get("estimate") if e.get("valid")]
        finally:
            sub.close()
