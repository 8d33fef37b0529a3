"""Adaptive feed control with the target learned from good parts (issue 15: "or as a factor of the learned mean").

A daemon with `[afc] target_factor = 1.1` and no target in its config learns
the part program's three operations from the emulator (played as fast as the
daemon takes it, looping until each key's envelope is active), and keeps them
in its history database. A second daemon, started on the same database,
watches one part played by the emulator at `afc_run.SPEED` times real time
(the CNC's lags on the samples' clock, the daemon's sample-rate check off for
that stream), whose CNC follows the override: where the CONTEXT flag allows it (operations 10 and 20) the
controller holds the torque at 1.1 × the learned mean over the cut, read back
with `millsense limits show`; operation 30 (never allowed) runs at the
programmed feed. Before anything is learned the controller has no target and
never moves the feed.
"""

from __future__ import annotations

import json
import re
import signal
import statistics
import subprocess
from pathlib import Path

import pytest

from tests.conftest import free_tcp_port
from tests.e2e.afc_run import SPEED
from tests.e2e.helpers import CMD, Procs, Subscriber, tcp, wait_for

pytestmark = pytest.mark.slow  # over about 10 s each: handed out first (tests/parallel.py)

REPO = Path(__file__).resolve().parents[2]
FACTOR = 1.1
MACHINE = "mch10-p1001"


def _config(tmp: Path, daq_port: int, z_port: int, *, at_speed: bool = False) -> Path:
    """config/part-program.toml on free ports, its history in `tmp`, AFC on with a learned target. The
    envelope holds are off: the looping emulator ends a part mid-cut where it wraps, and a held feed is not
    what this test is about (test_learning_acceptance covers the alarms)."""
    text = (REPO / "config" / "part-program.toml").read_text()
    text = text.replace("tcp_port = 5556", f"tcp_port = {daq_port}")
    text = text.replace('listen = ["tcp/127.0.0.1:7449"]', f'listen = ["{tcp(z_port)}"]')
    text = re.sub(r'(\[history\]\nenabled = true\npath = )""', rf'\1"{tmp / "history.sqlite3"}"', text)
    text = text.replace("hold_high = true", "hold_high = false").replace("hold_low = true", "hold_low = false")
    assert str(tmp / "history.sqlite3") in text and f"tcp_port = {daq_port}" in text
    if at_speed:   # the parts are played faster than real time on purpose: not a DAQ stating a wrong rate
        text = text.replace("[daq]\n", "[daq]\ncheck_sample_rate = false\n", 1)
    path = tmp / ("pp-at-speed.toml" if at_speed else "pp.toml")
    path.write_text(text + f"\n[afc]\nenabled = true\ntarget_factor = {FACTOR}\n")
    return path


def _limits(cfg: Path, *args: str) -> dict:
    out = subprocess.run(CMD + ["limits", *args, "--config", str(cfg), "--json"], capture_output=True, text=True,
                         timeout=30)
    return json.loads(out.stdout) if out.returncode == 0 and out.stdout.strip() else {}


def _stop(p: subprocess.Popen) -> None:
    if p.poll() is None:
        p.send_signal(signal.SIGTERM)
        p.wait(30)


def test_the_target_is_the_factor_times_the_learned_mean_of_each_operation(tmp_path):
    daq_port, z_port = free_tcp_port(), free_tcp_port()
    cfg = _config(tmp_path, daq_port, z_port)
    with Procs(tmp_path) as procs:
        # 1. learn: five good parts of each operation, as fast as the daemon reads them
        sub = Subscriber([tcp(z_port)], MACHINE)
        daemon = procs.start("learn", ["run", "--config", str(_config(tmp_path, daq_port, z_port, at_speed=True)),
                                       "--connect-timeout", "60"])
        # Twelve parts a loop: learning is done after five or six, and the test stops the emulator long before it
        # wraps. (With six, the daemon got past the wrap in two CI runs of three at stop 19 and went blind at a
        # tool change of the second loop, a false verdict of the signal check fixed at stop 20: CHANGELOG,
        # tests/estimator/test_program_signals.py.) Played once instead, a daemon that connects late misses
        # the first parts and never learns.
        sim = procs.start("sim-learn", ["sim", "--scenario", "part-program", "--parts", "12", "--protocol", "2",
                                        "--tcp", f"127.0.0.1:{daq_port}", "--fast", "--loop", "--watchdog-ms", "1000"])
        wait_for(lambda: sum(k["state"] == "active" for k in _limits(cfg, "list").get("limits", [])) == 3, 120.0,
                 "three operations learned: " + procs.text("learn")[-2000:])
        _stop(sim)
        _stop(daemon)
        learning = sub.get("estimate")
        sub.close()
        assert learning, procs.text("learn")[-2000:]
        # no target before an envelope is learned: the controller never moved the feed
        assert all((e.get("afc") or {}).get("override_pct") == 100.0 for e in learning[:200]), learning[:3]
        assert {(e.get("afc") or {}).get("target") for e in learning[:200]} == {None}

        # 2. a part under control, the learned limits restored from the history database
        sub = Subscriber([tcp(z_port)], MACHINE)
        at_speed = _config(tmp_path, daq_port, z_port, at_speed=True)   # the same history database
        daemon = procs.start("control", ["run", "--config", str(at_speed), "--connect-timeout", "60"])
        sim = procs.start("sim", ["sim", "--scenario", "part-program", "--parts", "1", "--protocol", "2",
                                  "--tcp", f"127.0.0.1:{daq_port}", "--realtime", "--speed", repr(SPEED), "--once",
                                  "--watchdog-ms", "1000"])
        sim.wait(120)
        assert sim.returncode == 0, procs.text("sim")
        learned = {key: _limits(cfg, "show", key) for key in ("1001/11/10", "1001/4/20")}
        _stop(daemon)
        estimates = sub.get("estimate")
        sub.close()

    for key, shown in learned.items():
        _, tool, operation = (int(x) for x in key.split("/"))
        # the learned mean over the cut, as `limits show` gives the band: where its low side expects cutting
        cut = [m for m, low in zip(shown["torque_mean_nm"], shown["torque_low_nm"])
               if m is not None and low is not None and low > 0]
        expected = FACTOR * sum(cut) / len(cut)
        mine = [e for e in estimates if e.get("tool") == tool and e.get("operation") == operation]
        targets = {(e.get("afc") or {}).get("target") for e in mine}
        assert len(targets) == 1 and abs(targets.pop() - expected) <= 1e-3 * expected, (key, expected, targets)
        armed = [e for e in mine if e["afc"]["state"] == "armed"]
        assert len(armed) >= 10, (key, [e["afc"]["state"] for e in mine])
        ratio = statistics.median(e["torque_nm"] / e["afc"]["target"] for e in armed[len(armed) // 2:])
        assert abs(ratio - 1.0) <= 0.05, (key, ratio)
        assert max(e["afc"]["override_pct"] for e in armed) > 100.0  # 10 % above the mean: faster than programmed
    finishing = [e for e in estimates if e.get("operation") == 30]
    assert finishing and {e["afc"]["state"] for e in finishing} <= {"idle", "air"}, {e["afc"]["state"] for e in finishing}
    assert {e["afc"]["override_pct"] for e in finishing} == {100.0}
