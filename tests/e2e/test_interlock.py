"""Feed hold on real processes: overload and crash trips, measured on the emulator's side.

The emulator's status log records each output change with its monotonic time;
its truth gives the revolution ends (sample indices) and the crash-power
event. `tests/e2e/truth.Timebase` turns an index into the monotonic time the
sample was due (nominal) and the earliest it can have left the emulator (its
pacer sends samples in 10 ms batches, as a DAQ sending 10-sample frames does).
"""

from __future__ import annotations

import json
import signal
import subprocess
import time

import numpy as np

from tests.conftest import free_tcp_port
from tests.e2e.helpers import CMD, Procs, Subscriber, read_jsonl, tcp, wait_for, write_config
from tests.e2e.truth import Timebase, match_estimates, truth_events, truth_revs

TOKEN = "s3cret-token-of-at-least-32-characters-0123456789"
# Deadlines below detect a failure; they are no budget (CI is a loaded 2-core box): how fast is
# bench/'s business (docs/performance.md). The daemon's DAQ start window likewise.
SLOW_S = 60.0
CONNECT_WINDOW = ["--connect-timeout", "120"]
CRASH_SCENARIO = "crash"


def _holds(log, on=True):
    return [e for e in log if e.get("event") == "outputs" and bool(e.get("feed_hold")) == on]


def _reset(machine, z_port, token):
    return subprocess.run(
        CMD + ["reset", "--machine", machine, "--connect", tcp(z_port), "--no-scouting", "--token", token, "--timeout", "5"],
        capture_output=True,
        text=True,
        timeout=60,
    )


def _reset_when_allowed(machine, z_port, token, log_path, timeout_s=SLOW_S):
    """Reset as an operator does: ask again while the daemon refuses because the condition persists.

    Until one is granted, no refused reset may have released the feed."""
    deadline = time.monotonic() + timeout_s
    while True:
        p = _reset(machine, z_port, token)
        if p.returncode == 0:
            return p
        assert not _holds(read_jsonl(log_path), on=False), "a refused reset released the feed: " + p.stderr
        assert time.monotonic() < deadline, p.stdout + p.stderr
        time.sleep(0.2)


def _plateaus(truth):
    """Torque of the steady cutting revolutions, in order of first appearance (rounded to 0.1 N·m)."""
    seen: list[float] = []
    for r in truth_revs(truth):
        if r.get("steady") and r.get("cutting"):
            v = round(float(r["torque_nm"]), 1)
            if not any(abs(v - s) < 0.3 for s in seen):
                seen.append(v)
    return seen


def _start(procs, tmp_path, scenario, machine, alarms, watchdog_ms=1000):
    daq_port, z_port = free_tcp_port(), free_tcp_port()
    cfg = write_config(
        tmp_path / "d.toml",
        machine=machine,
        daq=f'transport = "tcp"\nhost = "127.0.0.1"\ntcp_port = {daq_port}',
        zenoh_listen=[tcp(z_port)],
        alarms=alarms,
        interlock=f'enabled = true\nheartbeat_ms = 50\nwatchdog_ms = {watchdog_ms}\nreset = "token"\nreset_token = "{TOKEN}"',
    )
    truth_path, log_path = tmp_path / "truth.jsonl", tmp_path / "status.jsonl"
    sim = procs.start(
        "sim",
        ["sim", "--scenario", scenario, "--tcp", f"127.0.0.1:{daq_port}", "--realtime", "--truth", str(truth_path),
         "--status-log", str(log_path), "--watchdog-ms", str(watchdog_ms)],
    )
    wait_for(lambda: "serving" in procs.text("sim"), 60.0, "emulator serving")
    daemon = procs.start("daemon", ["run", "--config", str(cfg), *CONNECT_WINDOW])
    sub = Subscriber([tcp(z_port)], machine)
    return sim, daemon, sub, z_port, truth_path, log_path


def test_overload_trips_within_a_revolution_and_reset_clears_it(tmp_path, step_capture):
    _, truth0 = step_capture
    levels = _plateaus(truth0)
    assert len(levels) >= 2, f"the step scenario has no second cutting plateau in its first seconds: {levels}"
    limit = (levels[0] + levels[1]) / 2  # over the limit from the second plateau on
    machine = "ilk-ovl"
    with Procs(tmp_path) as procs:
        sim, daemon, sub, z_port, truth_path, log_path = _start(
            procs, tmp_path, "step", machine, f"torque_limit_nm = {limit:.3f}\nrevolutions = 2\nbreakage_drop_pct = 95"
        )
        try:
            alarm = wait_for(
                lambda: next((a for a in sub.get("alarm") if a["level"] == "overload"), None) or daemon.poll() is not None,
                60.0,
                "overload alarm at the subscriber",
            )
            assert daemon.poll() is None, procs.text("daemon")
            hold = wait_for(lambda: _holds(read_jsonl(log_path)), SLOW_S, "feed hold on the emulator")[0]
            assert alarm["interlock"] == "feed_hold" and alarm["quantity"] == "torque_nm" and alarm["value"] > limit

            wrong = _reset(machine, z_port, "not-the-token")
            assert wrong.returncode == 3, wrong.stdout + wrong.stderr  # its refusal unverifiable: outcome unknown
            time.sleep(0.3)
            assert not _holds(read_jsonl(log_path), on=False), "a wrong token released the feed"
            _reset_when_allowed(machine, z_port, TOKEN, log_path)
            wait_for(lambda: _holds(read_jsonl(log_path), on=False), SLOW_S, "feed hold released by reset")
            estimates = sub.get("estimate")
            t_term = time.monotonic()
            daemon.send_signal(signal.SIGTERM)
            assert daemon.wait(SLOW_S) == 0
            time.sleep(0.3)
            assert not [e for e in _holds(read_jsonl(log_path), on=False) if e["mono"] > t_term], "a stop must not release the feed"
        finally:
            sub.close()
        sim.send_signal(signal.SIGTERM)
        sim.wait(SLOW_S)
    truth, log = read_jsonl(truth_path), read_jsonl(log_path)
    tb = Timebase.from_status_log(log)
    matched = match_estimates(estimates, truth, tb)
    (offset,) = {e["rev"] - r["rev"] for e, r, _ in matched}
    # The daemon splits revolutions at the encoder phase it first saw, so its revolution k
    # ends inside truth revolution k - offset, up to half a revolution either side of its end.
    over = next(r for r in truth_revs(truth) if r["rev"] == alarm["rev"] - offset)
    period_s = 60.0 / over["spindle_rpm"]
    delay_s = hold["mono"] - tb.nominal_mono(int(over["index_end"]))
    own_end_mono = alarm["t"] - tb.wall0 + tb.mono0  # the daemon's own end of that revolution
    print(
        f"overload: feed hold {delay_s * 1e3:.1f} ms after the matching truth revolution ended, "
        f"{(hold['mono'] - own_end_mono) * 1e3:.1f} ms after the daemon's revolution ended (rev {period_s * 1e3:.0f} ms)"
    )
    # What the product guarantees, whatever the load (a latency budget is bench/'s): the hold follows
    # the revolution it was decided on (not before it ended, but for the daemon's own split of half
    # a revolution), and that revolution is the `revolutions = 2`-th over the limit: the second truth
    # revolution over it, or the one after where the daemon's split straddles the step.
    assert -period_s / 2 < delay_s, delay_s
    first_over = next(r["rev"] for r in truth_revs(truth) if r["rev"] > 0 and r["torque_nm"] > limit)
    assert first_over <= over["rev"] <= first_over + 2, (over["rev"], first_over)


def test_crash_trips_at_sample_level_and_alarm_reaches_subscriber(tmp_path):
    machine = "ilk-crash"
    with Procs(tmp_path) as procs:
        sim, daemon, sub, z_port, truth_path, log_path = _start(procs, tmp_path, CRASH_SCENARIO, machine, CRASH_ALARMS)
        try:
            alarm = wait_for(
                lambda: next((a for a in sub.get("alarm") if a["level"] == "crash"), None) or daemon.poll() is not None,
                60.0,
                "crash alarm at the subscriber",
            )
            assert daemon.poll() is None, procs.text("daemon")
            hold = wait_for(lambda: _holds(read_jsonl(log_path)), SLOW_S, "feed hold on the emulator")[0]
            assert alarm["interlock"] == "feed_hold" and alarm["value"] > alarm["limit"]
            (st,) = sub.query(f"millsense/{machine}/status")
            _reset_when_allowed(machine, z_port, TOKEN, log_path)
            wait_for(lambda: _holds(read_jsonl(log_path), on=False), SLOW_S, "feed hold released by reset")
            daemon.send_signal(signal.SIGTERM)
            assert daemon.wait(SLOW_S) == 0
        finally:
            sub.close()
        sim.send_signal(signal.SIGTERM)
        sim.wait(SLOW_S)
    truth, log = read_jsonl(truth_path), read_jsonl(log_path)
    tb = Timebase.from_status_log(log)
    (crossing, *_) = truth_events(truth, "crash_power")
    idx = int(crossing["index"])
    after_due = hold["mono"] - tb.nominal_mono(idx)
    after_sent = hold["mono"] - tb.emitted_mono(idx)
    print(
        f"crash: feed hold {after_due * 1e3:.1f} ms after the crossing sample was due, {after_sent * 1e3:.1f} ms after "
        f"it was sent; inside the daemon {st['last_trip_ms']} ms from block hand-over to the output written"
    )
    # How fast is a benchmark's business (docs/performance.md): on a loaded CI box a wall-clock
    # budget here fails for the box's sake. What the product guarantees, whatever the load: the
    # hold was decided on the crossing sample itself (a sample-level crash alarm stamped with that
    # sample's revolution, not a revolution's overload), and the daemon measured its own share.
    assert alarm["level"] == "crash" and alarm["quantity"] == "p_gap_w", alarm
    assert st["last_trip_ms"] is not None and st["last_trip_ms"] >= 0.0, st
    assert np.isfinite(after_due) and np.isfinite(after_sent)


CRASH_ALARMS = "crash_power_w = 15000.0\nbreakage_drop_pct = 95"


def test_reset_refused_while_the_overload_persists_and_the_latch_survives_a_kill(tmp_path):
    """Finding 4 and 5: power_limit_w below the air-cut power, so the overload persists with the feed held.

    No reset may release the feed, not even for the 112–173 ms the old code did (the emulator's
    output log went 3 → 0 → 3). Then SIGKILL the daemon, restart the emulator (its output back to
    0, as after a power cut) and start the daemon again: the feed is held at start and the log says
    why and since when.
    """
    from millsense.daemon.local_socket import local_command

    machine = "ilk-persist"
    state = tmp_path / "state"
    env = {"STATE_DIRECTORY": str(state)}
    daq_port = free_tcp_port()
    cfg = write_config(
        tmp_path / "d.toml",
        machine=machine,
        daq=f'transport = "tcp"\nhost = "127.0.0.1"\ntcp_port = {daq_port}',
        alarms="power_limit_w = 200.0\nrevolutions = 2",  # air cut at 600 rpm is about 325 W
        interlock='enabled = true\nheartbeat_ms = 50\nwatchdog_ms = 1000\nreset = "open"',
    )

    def start_sim(log_path):
        sim = procs.start(f"sim-{log_path.stem}", ["sim", "--scenario", "step", "--loop", "--tcp", f"127.0.0.1:{daq_port}",
                                                   "--realtime", "--status-log", str(log_path), "--watchdog-ms", "1000"])
        wait_for(lambda: "serving" in procs.text(f"sim-{log_path.stem}"), 60.0, "emulator serving")
        return sim

    def start_daemon(name):
        d = procs.start(name, ["run", "--config", str(cfg), *CONNECT_WINDOW], env_extra=env)
        wait_for(lambda: (state / "control.sock").exists() or d.poll() is not None, SLOW_S, "control socket")
        assert d.poll() is None, procs.text(name, "out") + procs.text(name)
        return d

    with Procs(tmp_path) as procs:
        log1, log2 = tmp_path / "status1.jsonl", tmp_path / "status2.jsonl"
        sim = start_sim(log1)
        daemon = start_daemon("daemon1")
        wait_for(lambda: _holds(read_jsonl(log1)), SLOW_S, "feed hold from the overload")
        revs_at_hold = local_command(state, "status")["revolutions"]
        wait_for(lambda: local_command(state, "status")["revolutions"] >= revs_at_hold + 3, SLOW_S, "revolutions since")
        for _ in range(3):
            r = local_command(state, "reset")
            assert r["ok"] is False and r["condition"] == "overload" and "p_gap_w" in r["error"], r
        time.sleep(0.3)
        assert not _holds(read_jsonl(log1), on=False), "a reset released the feed while the overload persisted"
        wait_for(lambda: (state / "latch.json").exists(), SLOW_S, "the latch on disk")
        latch = json.loads((state / "latch.json").read_text())
        assert latch["latched"] and latch["reason"].startswith("overload p_gap_w")

        daemon.send_signal(signal.SIGKILL)
        daemon.wait(SLOW_S)
        sim.send_signal(signal.SIGTERM)
        sim.wait(SLOW_S)
        (state / "control.sock").unlink(missing_ok=True)  # a dead daemon leaves its socket file
        sim = start_sim(log2)
        daemon = start_daemon("daemon2")
        hold = wait_for(lambda: _holds(read_jsonl(log2)), SLOW_S, "feed hold asserted at start")[0]
        assert hold["cause"] == "command"
        starts = [json.loads(x) for x in procs.text("daemon2", "out").splitlines()
                  if '"interlock.latched_at_start"' in x]
        assert starts and starts[0]["reason"] == latch["reason"] and starts[0]["since"] == latch["since"]
        st = local_command(state, "status")
        assert st["interlock"] == "feed_hold" and st["interlock_detail"]["since"] == latch["since"]
        # still over the limit after the restart: still refused
        revs = st["revolutions"]
        wait_for(lambda: local_command(state, "status")["revolutions"] >= revs + 3, SLOW_S, "revolutions after restart")
        r = local_command(state, "reset")
        assert r["ok"] is False and r["condition"] == "overload", r
        time.sleep(0.3)
        assert not _holds(read_jsonl(log2), on=False), "the feed was released after the restart"
        daemon.send_signal(signal.SIGTERM)
        assert daemon.wait(SLOW_S) == 0
        sim.send_signal(signal.SIGTERM)
        sim.wait(SLOW_S)
