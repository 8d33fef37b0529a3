"""`millsense sim` + `millsense run` as real processes, a Zenoh subscriber in the test.

Every revolution gets an estimate (contiguous `rev`), live `t` is the time of
the revolution's last sample, and torque is within 2 % + 0.03 N·m of the
emulator's truth wherever the cut is steady — over the TCP stream and over
Modbus TCP.
"""

from __future__ import annotations

import signal
import time

import numpy as np
import pytest

from tests.conftest import free_tcp_port
from tests.e2e.helpers import Procs, Subscriber, read_jsonl, tcp, wait_for, write_config
from tests.e2e.truth import Timebase, match_estimates, steady_torque_misses

SCENARIO = "step"
# 8 s of stream after the first estimate (14 s before issue 37): about 80 revolutions, 42 of them in the step
# scenario's steady first cut (37 with 7 s, measured at load 5), against the 20 the check below asks for.
RUN_S = 8.0


def _daq(transport: str, port: int) -> str:
    if transport == "tcp":
        return f'transport = "tcp"\nhost = "127.0.0.1"\ntcp_port = {port}'
    return f'transport = "modbus-tcp"\nhost = "127.0.0.1"\ntcp_port = {port}\nunit = 1\npoll_ms = 20'


def _run_live(tmp_path, transport: str):
    daq_port, z_port = free_tcp_port(), free_tcp_port()
    machine = f"acc-{transport.replace('-', '')}"
    cfg = write_config(tmp_path / "d.toml", machine=machine, daq=_daq(transport, daq_port), zenoh_listen=[tcp(z_port)])
    truth_path, log_path = tmp_path / "truth.jsonl", tmp_path / "status.jsonl"
    serve = ["--tcp" if transport == "tcp" else "--modbus-tcp", f"127.0.0.1:{daq_port}"]
    with Procs(tmp_path) as procs:
        sim = procs.start(
            "sim",
            ["sim", "--scenario", SCENARIO, *serve, "--realtime", "--truth", str(truth_path), "--status-log", str(log_path)],
        )
        wait_for(lambda: "serving" in procs.text("sim"), 60.0, "emulator serving")
        daemon = procs.start("daemon", ["run", "--config", str(cfg)])
        sub = Subscriber([tcp(z_port)], machine)
        try:
            wait_for(lambda: sub.get("estimate") or daemon.poll() is not None, 40.0, "first estimate")
            assert daemon.poll() is None, procs.text("daemon")
            time.sleep(RUN_S)
            status = sub.query(f"millsense/{machine}/status")
            daemon.send_signal(signal.SIGTERM)
            t_term = time.monotonic()
            code = daemon.wait(5)
            stop_s = time.monotonic() - t_term
            time.sleep(0.3)
        finally:
            estimates = sub.get("estimate")
            alive = list(sub.alive)
            sub.close()
        sim.send_signal(signal.SIGTERM)
        sim.wait(10)
    assert code == 0, procs.text("daemon")
    return estimates, status, read_jsonl(truth_path), read_jsonl(log_path), stop_s, alive, procs.text("daemon")


@pytest.mark.serial
@pytest.mark.parametrize("transport", ["tcp", "modbus-tcp"])
def test_every_revolution_estimated_and_torque_matches_truth(tmp_path, transport):
    estimates, status, truth, log, stop_s, alive, daemon_log = _run_live(tmp_path, transport)

    revs = [e["rev"] for e in estimates]
    assert len(revs) > 20
    assert revs == list(range(revs[0], revs[0] + len(revs))), "rev numbers must be contiguous, none missing"
    assert all(e["machine"] for e in estimates)

    tb = Timebase.from_status_log(log)
    matched = match_estimates(estimates, truth, tb)
    assert len(matched) >= 0.9 * len(estimates), f"only {len(matched)} of {len(estimates)} estimates matched a truth revolution"
    # Live t is the time of the revolution's last sample, taken from the sample index, not
    # from arrival: at constant speed the daemon's revolution ends sit at a fixed phase from
    # the truth's, so t − t_truth is constant to well under the 10 ms frame period.
    dts = np.array([dt for e, r, dt in matched if r.get("steady")])
    spread_ms = (np.percentile(dts, 95) - np.percentile(dts, 5)) * 1e3
    assert spread_ms < 3.0, f"live t jitters by {spread_ms:.1f} ms against the sample clock"

    steady, bad = steady_torque_misses(matched, truth)
    assert len(steady) >= 20, f"only {len(steady)} steady cutting revolutions in the window"
    assert not bad, f"{len(bad)}/{len(steady)} steady revolutions off truth (rev, est, truth): {bad[:8]}"

    assert status and status[0]["state"] == "running" and status[0]["daq_link"] == "up"
    assert status[0]["revolutions"] >= len(revs) - 30
    assert stop_s < 2.0, f"SIGTERM took {stop_s:.2f} s"
    assert alive and alive[-1][1].endswith("DELETE"), f"liveliness token not dropped: {alive}"
    assert "Traceback" not in daemon_log
