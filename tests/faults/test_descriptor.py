"""A DAQ whose channel count changes under a running stream.

A TCP proxy (tests/faults/netfault.py) carries the daemon's connection from one
emulator over to another without a break, dropping the newcomer's greeting, so
the daemon first meets SAMPLES with the new channel count and only then, within
a second, the new DESCRIPTOR — as a DAQ reconfigured while streaming would do
it. The configuration uses the dynamometer channels `fx`, `fy`, which the
13-channel `fig5` DAQ has and the 8-channel `step` DAQ has not.
"""

from __future__ import annotations

import signal
import time

from tests.conftest import free_tcp_port
from tests.e2e.helpers import Procs, Subscriber, tcp, wait_for, write_config
from tests.faults.helpers import (
    assert_clean_exit,
    assert_no_damaged_estimate_looks_valid,
    assert_revs_contiguous,
    log_events,
    status,
    wait_status,
)
from tests.faults.netfault import StreamProxy

DYNAMOMETER = "[channels.fx]\nscale = 0.5\n[channels.fy]\nscale = 0.5\n\n"


def test_channel_count_changes_mid_stream_refused_then_recovered(tmp_path):
    wide_port, narrow_port, z_port = free_tcp_port(), free_tcp_port(), free_tcp_port()
    machine = "desc-01"
    with Procs(tmp_path) as procs:
        common = ["--loop", "--realtime", "--watchdog-ms", "1000"]
        procs.start("wide", ["sim", "--scenario", "fig5", "--tcp", f"127.0.0.1:{wide_port}", *common])  # 13 channels
        procs.start("narrow", ["sim", "--scenario", "step", "--tcp", f"127.0.0.1:{narrow_port}", *common])  # 8 channels
        wait_for(lambda: "serving" in procs.text("wide") and "serving" in procs.text("narrow"), 30.0, "emulators serving")
        proxy = StreamProxy(wide_port)
        cfg = write_config(
            tmp_path / "d.toml",
            machine=machine,
            daq=f'transport = "tcp"\nhost = "127.0.0.1"\ntcp_port = {proxy.port}',
            zenoh_listen=[tcp(z_port)],
            alarms="breakage_drop_pct = 0",
            interlock='enabled = true\nheartbeat_ms = 50\nwatchdog_ms = 1000\nreset = "open"',
        )
        cfg.write_text(cfg.read_text().replace("[motor]", DYNAMOMETER + "[motor]", 1))
        daemon = procs.start("daemon", ["run", "--config", str(cfg)])
        sub = Subscriber([tcp(z_port)], machine)
        try:
            wait_for(lambda: len(sub.get("estimate")) >= 5 or daemon.poll() is not None, 60.0, "estimates")
            assert daemon.poll() is None, procs.text("daemon", "out")[-3000:]
            before = status(sub, machine)
            assert before["state"] == "running" and before["bad_frames"] == 0 and before["heartbeating"]

            # -- 13 -> 8 channels under the running stream: fx, fy are gone
            proxy.splice(narrow_port)
            refused = wait_status(sub, machine, lambda s: "descriptor" in s["faults"], 5.0, "the new descriptor refused")
            n_est = len(sub.get("estimate"))
            time.sleep(2.0)
            quiet = status(sub, machine)
            assert len(sub.get("estimate")) == n_est, "estimates from a DAQ that does not fit the configuration"
            mismatch = proxy.tap.decoder_stats()["descriptor_mismatch"]

            # -- back to 13 channels: the configuration fits again
            proxy.splice(wide_port)
            back = wait_status(sub, machine, lambda s: s["state"] == "running" and not s["faults"], 10.0, "recovered")
            wait_for(lambda: len(sub.get("estimate")) > n_est + 5, 20.0, "estimates again")
            wait_status(sub, machine, lambda s: s["heartbeating"], 5.0, "heartbeats again")
            estimates = sub.get("estimate")
            daemon.send_signal(signal.SIGTERM)
            assert daemon.wait(10) == 0
        finally:
            sub.close()
            proxy.close()
    print(f"refused after {refused['uptime_s']} s uptime; {mismatch} SAMPLES frames of the wrong width refused")
    # the 8-channel frames that came before the 8-channel DESCRIPTOR were refused and counted as bad frames
    assert mismatch > 0
    assert quiet["daq"]["decoder_descriptor_mismatch"] >= mismatch
    assert quiet["bad_frames"] == quiet["daq"]["decoder_descriptor_mismatch"]
    # then the descriptor was read, found not to fit, and said so, naming the keys
    assert "channels.fx" in refused["faults"]["descriptor"] and "channels.fy" in refused["faults"]["descriptor"]
    assert refused["state"] == "degraded"
    # no heartbeats for a DAQ the daemon cannot use: its watchdog may stop the feed
    assert quiet["heartbeating"] is False and quiet["state"] == "degraded"
    assert back["daq_link"] == "up"
    # no estimate from the mixed stream: the revolution open at a switch is dropped with the estimator;
    # the numbering goes on (a new estimator does not start again at rev 1)
    assert_revs_contiguous(estimates)
    assert_no_damaged_estimate_looks_valid(estimates)
    assert back["lost_samples"] >= quiet["lost_samples"] >= before["lost_samples"]  # counts never go back
    assert any(e.get("force_n") is not None for e in estimates[n_est:])
    events = log_events(procs.text("daemon", "out"))
    descs = [e["channels"] for e in events if e["event"] == "daq.descriptor"]
    # the one taken when the 13-channel DAQ came back (the 8-channel one was never taken; the first is taken at start)
    assert len(descs) == 1 and len(descs[0]) == 13, descs
    faults = [e for e in events if e["event"] == "fault"]
    assert [e["kind"] for e in faults] == ["descriptor"], faults
    assert any(e["event"] == "recovered" and e["kind"] == "descriptor" for e in events)
    assert_clean_exit(procs, "daemon")
