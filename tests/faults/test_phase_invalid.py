"""While the wiring check holds fault `signals`, no revolution is published valid.

The phase check (`phase_check.py`) judges the raw samples: two current channels swapped leave every
torque, force and depth wrong while each channel swings like a live one. Before this test the daemon
said `degraded: signals` and held the feed (blind), and went on publishing those wrong numbers as
`valid: true`: learning, AFC, the dashboard and every subscriber took them for measurements. Now every
revolution closed while the fault holds is `valid: false` with `invalid: "phase"`, live and in replay,
and the revolutions after it clears (sound wiring again) are valid.
"""

from __future__ import annotations

import time

import numpy as np

from millsense.daemon.config.load import load_config
from millsense.drivers.base import SampleBlock
from millsense.sim.emulator.source import make_source
from tests.e2e.helpers import write_config
from tests.faults.helpers import INTERLOCK_OPEN, runner_on_the_sim


def _swapped_then_sound(names: list[str], swapped_s: float, sound_s: float) -> tuple[np.ndarray, int]:
    counts = np.array(make_source("step", seed=3).step(int((swapped_s + sound_s) * 1000)), dtype=np.int16, copy=True)
    u, v = names.index("i_u"), names.index("i_v")
    cut = int(swapped_s * 1000)
    counts[:cut, [u, v]] = counts[:cut, [v, u]]
    return counts, cut


def test_revolutions_closed_while_the_wiring_fault_holds_are_invalid_and_valid_again_after(tmp_path):
    cfg = write_config(tmp_path / "swap.toml", machine="swap-02", daq='transport = "sim"\nscenario = "step"',
                       interlock=INTERLOCK_OPEN)
    with runner_on_the_sim(load_config(cfg)) as (runner, drv, sink):
        counts, cut = _swapped_then_sound(list(drv.descriptor.names), 4.0, 5.0)
        raised_at = cleared_at = None
        for k in range(0, len(counts), 100):
            runner.handle(SampleBlock(k, k, counts[k : k + 100], 0, False), time.monotonic())
            held = "signals" in runner.faults
            if held and raised_at is None:
                raised_at = len(sink.of("estimate"))
            if not held and raised_at is not None and cleared_at is None and k >= cut:
                cleared_at = len(sink.of("estimate"))
        estimates = [p for p, _ in sink.of("estimate")]
        assert raised_at is not None and cleared_at is not None, runner.faults
        during = estimates[raised_at:cleared_at]
        assert during, "revolutions closed while the fault held"
        assert [(e["valid"], e["invalid"]) for e in during] == [(False, "phase")] * len(during)
        assert all(e["torque_nm"] is None for e in during)
        after = estimates[cleared_at + 2:]   # the block that cleared it, then sound revolutions
        assert after and all(e["valid"] for e in after), [(e["rev"], e["invalid"]) for e in after]


def test_replay_publishes_them_invalid_from_the_sample_the_check_decided(tmp_path):
    """`millsense replay` cuts its 16-s blocks where the check changed: not one revolution after the raise valid."""
    import io
    import re

    from millsense.daemon.commands.replay import Replay
    from tests.estimator import simcase

    cap, _ = simcase.capture(tmp_path, "step", seed=5)   # the one test_power_check.py replays
    cfg = write_config(tmp_path / "d.toml", machine="wire-02", daq='transport = "tcp"\nhost = "127.0.0.1"\ntcp_port = 1')
    cfg.write_text(cfg.read_text().replace("[channels.i_u]\nscale = 0.002", "[channels.i_u]\nscale = -0.002", 1))
    payloads: list[dict] = []
    replay = Replay(load_config(cfg), io.StringIO(), on_payload=payloads.append)
    replay.feed(cap.read_bytes())
    raised = [w for w in replay.warnings if "the line currents do not sum to zero" in w]
    assert len(raised) == 1, replay.warnings
    t_raised = float(re.search(r"from t=([0-9.]+) s", raised[0]).group(1))
    estimates = [p for p in payloads if p.get("type") == "estimate"]
    after = [e for e in estimates if e["t"] > t_raised]
    before = [e for e in estimates if e["t"] <= t_raised]
    assert after and [(e["valid"], e["invalid"]) for e in after] == [(False, "phase")] * len(after)
    assert [e for e in before if e["valid"]], "revolutions before the check decided are judged as before"
    assert not [e for e in before if e["invalid"] == "phase"]


def test_current_sensors_turned_round_the_power_check_makes_them_invalid_too(tmp_path):
    """All three current sensors turned round: the phase check sees nothing wrong (they still sum to zero and turn
    with the voltages), the power check (negative input power, 20 steady revolutions) raises the fault; from the
    next block every revolution is `invalid: "wiring"`, and what the check reads of it is never published."""
    cfg = write_config(tmp_path / "rev.toml", machine="wire-03", daq='transport = "sim"\nscenario = "step"',
                       interlock=INTERLOCK_OPEN)
    text = cfg.read_text()
    for name in ("i_u", "i_v", "i_w"):
        text = text.replace(f"[channels.{name}]\nscale = 0.002", f"[channels.{name}]\nscale = -0.002")
    assert text.count("scale = -0.002") == 3
    cfg.write_text(text)
    with runner_on_the_sim(load_config(cfg)) as (runner, drv, sink):
        counts = np.array(make_source("step", seed=3).step(8000), dtype=np.int16, copy=True)
        raised_at = None
        for k in range(0, len(counts), 100):
            runner.handle(SampleBlock(k, k, counts[k : k + 100], 0, False), time.monotonic())
            if raised_at is None and runner.power_check.faulted:
                raised_at = len(sink.of("estimate"))
        estimates = [p for p, _ in sink.of("estimate")]
        assert raised_at is not None, runner.faults
        assert "input power negative" in runner.faults.get("signals", ""), runner.faults
        after = estimates[raised_at:]
        assert after and [(e["valid"], e["invalid"]) for e in after] == [(False, "wiring")] * len(after)
        assert not [e for e in estimates if "wiring_p_in_w" in e or "wiring_rpm" in e]


def test_the_power_check_clears_on_revolutions_it_made_invalid():
    from millsense.daemon.pipeline.power_check import REVOLUTIONS, PowerSignCheck

    check = PowerSignCheck()
    wrong = {"valid": True, "spindle_rpm": 600.0, "p_in_w": -400.0, "accelerating": False}
    verdicts = [check.update(wrong) for _ in range(REVOLUTIONS)]
    assert verdicts[-1] and check.faulted
    right = {"valid": False, "invalid": "wiring", "wiring_rpm": 600.0, "wiring_p_in_w": 900.0, "accelerating": False}
    verdicts = [check.update(right) for _ in range(REVOLUTIONS)]
    assert verdicts[-1] == "" and not check.faulted
    damaged = {"valid": False, "invalid": "lost_samples", "accelerating": False}   # nothing to judge on
    assert check.update(damaged) is None
