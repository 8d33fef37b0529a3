"""Current sensors that do not fit each other or the voltages are blind, live and in replay.

A probe of stop 26 found two installation mistakes the power check (a negative input power, test_power_check.py)
does not see, every revolution published valid and the 3 mm overload unseen: one current sensor turned round with
all three measured (the input power stays positive, about a third of the true one), and two current channels
swapped (it averages to about zero). `phase_check.py` judges the raw samples: the three line currents must sum to
zero, and the current space vector must turn with the voltage space vector.
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from millsense.daemon.config.load import load_config
from millsense.daemon.pipeline.phase_check import WINDOWS, PhaseCheck
from millsense.drivers.base import SampleBlock
from millsense.sim.emulator.source import make_source
from tests.e2e.helpers import read_jsonl, wait_for, write_config
from tests.faults.helpers import INTERLOCK_OPEN, live_daemon, outputs, runner_on_the_sim, wait_status


def test_a_current_sensor_turned_round_live_is_blind_and_holds_the_feed(tmp_path):
    """The real daemon on the emulator, `[channels.i_u] scale` negative: fault `signals`, the feed held."""
    def reverse_i_u(text: str) -> str:
        assert "[channels.i_u]\nscale = 0.002" in text
        return text.replace("[channels.i_u]\nscale = 0.002", "[channels.i_u]\nscale = -0.002")

    machine = "phase-01"
    with live_daemon(tmp_path, machine, [], edit_config=reverse_i_u) as (procs, daemon, sub, sim_log):
        st = wait_status(sub, machine, lambda s: "signals" in s.get("faults", {}) or s["samples_received"] > 15000,
                         90.0, "fault signals")
        assert daemon.poll() is None, procs.text("daemon", "out")[-3000:]
        assert "the line currents do not sum to zero" in st["faults"].get("signals", ""), st["faults"]
        assert wait_for(lambda: outputs(read_jsonl(sim_log), feed_hold=True, cause="command"), 10.0,
                        "the daemon holds the feed (on_blind = hold)")


def _plant(seconds: float, scenario: str = "step") -> np.ndarray:
    return np.array(make_source(scenario, seed=3).step(int(seconds * 1000)), dtype=np.int16, copy=True)


def test_two_current_channels_swapped_are_blind_and_hold_the_feed(tmp_path):
    """The real runner on the simulated DAQ, the plant's own samples with i_u and i_v swapped."""
    cfg = write_config(tmp_path / "swap.toml", machine="swap-01", daq='transport = "sim"\nscenario = "step"', interlock=INTERLOCK_OPEN)
    with runner_on_the_sim(load_config(cfg)) as (runner, drv, sink):
        names = list(drv.descriptor.names)
        counts = _plant(4.0)
        u, v = names.index("i_u"), names.index("i_v")
        counts[:, [u, v]] = counts[:, [v, u]]
        for k in range(0, len(counts), 100):
            runner.handle(SampleBlock(k, k, counts[k : k + 100], 0, False), time.monotonic())
        assert "the current space vector turns against the voltages'" in runner.faults.get("signals", ""), runner.faults
        assert runner.interlock.latched and runner.interlock.reason.startswith("blind: signals:")
        assert drv.device.feed_hold
        r = runner.controls.reset("pytest")
        assert r["ok"] is False and r["condition"] == "blind"


@pytest.mark.parametrize("scenario", ["step", "crash", "aircut-high", "part-program", "breakage"])
def test_sound_wiring_is_never_a_problem(scenario):
    """The plant's own samples, cut as the live daemon's blocks: no window is judged wrong (starts, stops,
    gear changes, a crash, a breakage, tool changes)."""
    from tests.config.helpers import DEMO_TOML

    source = make_source(scenario, seed=3)
    check = PhaseCheck(load_config(DEMO_TOML), source.descriptor)
    counts = np.array(source.step(40_000), dtype=np.int16, copy=True)
    judged = [check.problem(counts[k : k + check.window]) for k in range(0, len(counts), check.window)]
    assert all(p in (None, "") for p in judged), [p for p in judged if p][:1]
    assert judged.count("") >= 10   # it did judge: the drive ran


def test_a_fault_needs_windows_in_a_row_and_clears_as_it_came():
    from tests.config.helpers import DEMO_TOML

    source = make_source("step", seed=3)
    check = PhaseCheck(load_config(DEMO_TOML), source.descriptor)
    good = np.array(source.step(8000), dtype=np.int16, copy=True)[2000:]
    bad = good.copy()
    bad[:, 3] = -bad[:, 3]
    w = check.window
    verdicts = [check.update(bad[k : k + w]) for k in range(0, WINDOWS * w, w)]
    assert verdicts[:-1] == [None] * (WINDOWS - 1) and "do not sum to zero" in verdicts[-1]
    verdicts = [check.update(good[k : k + w]) for k in range(0, WINDOWS * w, w)]
    assert verdicts == [None] * (WINDOWS - 1) + [""] and not check.faulted


def test_replay_says_where_the_wiring_is_wrong(tmp_path, millsense_cmd):
    import subprocess

    from tests.config.helpers import DEMO_TOML

    cap = tmp_path / "step.cap"
    subprocess.run(millsense_cmd + ["sim", "--scenario", "step", "--once", "--duration-s", "8", "--capture", str(cap),
                                    "--fast"], check=True, capture_output=True)
    text = DEMO_TOML.read_text()
    i = text.index("[channels.i_u]")
    j = text.index("scale", i)
    k = text.index("\n", j)
    scale = float(text[j:k].split("=")[1].split("#")[0])
    cfg = tmp_path / "reversed.toml"
    cfg.write_text(text[:j] + f"scale = {-scale!r}" + text[k:])
    p = subprocess.run(millsense_cmd + ["replay", "--config", str(cfg), str(cap)], capture_output=True, text=True,
                       timeout=120)
    assert p.returncode == 0, p.stderr
    assert "warning: fault signals from t=" in p.stderr and "the line currents do not sum to zero" in p.stderr, p.stderr
    sound = subprocess.run(millsense_cmd + ["replay", "--config", str(DEMO_TOML), str(cap)], capture_output=True,
                           text=True, timeout=120)
    assert sound.returncode == 0 and "warning" not in sound.stderr, sound.stderr


def test_a_stuck_sensor_is_left_to_the_signal_check():
    """A current sensor stuck at a count breaks Kirchhoff too; it is named `flat` by the signal check, and a second
    reason ("turned round") would mislead (the CI of stop 26: replay warned twice for one stuck i_u)."""
    from tests.config.helpers import DEMO_TOML

    source = make_source("step", seed=3)
    check = PhaseCheck(load_config(DEMO_TOML), source.descriptor)
    counts = np.array(source.step(6000), dtype=np.int16, copy=True)[2000:]
    counts[:, list(source.descriptor.names).index("i_u")] = 1234
    assert [check.problem(counts[k : k + 1000]) for k in range(0, 4000, 1000)] == [None] * 4


def test_a_fault_two_checks_hold_names_the_one_still_holding_it(tmp_path):
    """Fault `signals` raised by the loss check, then held by the phase check too: when the stream heals, the
    fault stays (the wiring is still wrong) and says why. Before, it kept the loss check's reason ("… of the DAQ's
    samples lost"), sending the electrician to the cable instead of the current sensor."""
    cfg = write_config(tmp_path / "two.toml", machine="two-01", daq='transport = "sim"\nscenario = "step"',
                       interlock=INTERLOCK_OPEN)
    with runner_on_the_sim(load_config(cfg)) as (runner, drv, sink):
        counts = _plant(9.0)
        u = list(drv.descriptor.names).index("i_u")
        counts[:, u] = -counts[:, u]   # a current sensor turned round, all along

        def feed(first: int, last: int, run: int = 0) -> int:
            """Blocks of 100 from sample `first`; with `run`, 300 samples lost after each run of that many.
            Returns the sample after the last block."""
            k, since_gap = first, 0
            while k < last:
                lost = 300 if run and since_gap == run else 0
                k, since_gap = k + lost, (0 if lost else since_gap) + 100
                runner.handle(SampleBlock(k, k, counts[k : k + 100], lost, False), time.monotonic())
                k += 100
            return k

        healed = feed(0, 3900, run=1000)   # 23 % lost: the loss check raises first; whole seconds: the phase check too
        assert "samples over the last 2 s lost" in runner.faults.get("signals", ""), runner.faults
        assert runner.phase_check is not None and runner.phase_check.faulted
        feed(healed, healed + 4000)      # the stream heals; the sensor is still turned round
        assert not runner.loss_check.faulted
        reason = runner.faults.get("signals", "")
        assert "the line currents do not sum to zero" in reason and "lost" not in reason, runner.faults
        assert runner.interlock.latched


def test_a_new_descriptor_goes_on_judging_the_fault_it_inherits(tmp_path):
    """The DAQ restarts announcing another descriptor (here: protocol 2) while the phase fault stands. The check is
    made again for the new columns; it must go on from the fault, or nothing is left to clear it: blind for good,
    the feed held and no reset possible until the daemon restarts."""
    import dataclasses

    cfg = write_config(tmp_path / "desc.toml", machine="desc-01", daq='transport = "sim"\nscenario = "step"',
                       interlock=INTERLOCK_OPEN)
    with runner_on_the_sim(load_config(cfg)) as (runner, drv, sink):
        counts = _plant(6.0)
        u = list(drv.descriptor.names).index("i_u")
        wrong = counts.copy()
        wrong[:, u] = -wrong[:, u]
        for k in range(0, 3000, 100):
            runner.handle(SampleBlock(k, k, wrong[k : k + 100], 0, False), time.monotonic())
        assert "do not sum to zero" in runner.faults.get("signals", ""), runner.faults
        restarted = dataclasses.replace(drv.descriptor, protocol_version=2)
        assert runner.core.on_descriptor(restarted)
        for k in range(3000, 6000, 100):   # rewired right while the DAQ was off
            runner.handle(SampleBlock(k, k, counts[k : k + 100], 0, k == 3000), time.monotonic())
        assert "signals" not in runner.faults, runner.faults


@pytest.mark.parametrize("refused_first", [False, True])
def test_a_new_descriptor_goes_on_judging_a_stuck_sensor(tmp_path, refused_first):
    """The same for the signal check (a stuck current sensor, fault `signals` from the plausibility source): the
    estimator made for the new descriptor must clear it when the samples are sound again, also when a descriptor
    the configuration does not fit came in between (no estimator for a while)."""
    import dataclasses

    cfg = write_config(tmp_path / "stuck.toml", machine="stuck-01", daq='transport = "sim"\nscenario = "step"',
                       interlock=INTERLOCK_OPEN)
    with runner_on_the_sim(load_config(cfg)) as (runner, drv, sink):
        counts = _plant(8.0)
        stuck = counts.copy()
        stuck[:, list(drv.descriptor.names).index("i_u")] = 1234
        for k in range(0, 3000, 100):
            runner.handle(SampleBlock(k, k, stuck[k : k + 100], 0, False), time.monotonic())
        assert "i_u" in runner.faults.get("signals", ""), runner.faults
        if refused_first:   # the DAQ came back without i_u: fault `descriptor`, no estimator
            without = dataclasses.replace(drv.descriptor, channels=tuple(c for c in drv.descriptor.channels
                                                                         if c.name != "i_u"))
            runner.handle(without, time.monotonic())
            assert runner.core.estimator is None and "descriptor" in runner.faults
        runner.handle(dataclasses.replace(drv.descriptor, protocol_version=2), time.monotonic())
        assert runner.core.estimator is not None and "descriptor" not in runner.faults
        for k in range(3000, 8000, 100):   # a sound sensor in its place
            runner.handle(SampleBlock(k, k, counts[k : k + 100], 0, k == 3000), time.monotonic())
        assert "signals" not in runner.faults, runner.faults


def test_large_currents_are_judged_too():
    """Currents swinging more than half the int16 range (a heavy cut: over 33 A at 0.002 A a count), not clipped:
    their peak-to-peak in counts overflowed int16, read as a drive not running, and the window was not judged."""
    from tests.config.helpers import DEMO_TOML

    source = make_source("step", seed=3)
    check = PhaseCheck(load_config(DEMO_TOML), source.descriptor)
    names = list(source.descriptor.names)
    cols = [names.index(n) for n in ("i_u", "i_v", "i_w")]
    counts = np.array(source.step(6000), dtype=np.int16, copy=True)[4000:5000]
    big = counts.astype(np.float64)
    big[:, cols] *= 25000.0 / np.abs(big[:, cols]).max()    # ±25000 counts: 50 A, under the sensors' limits
    big = big.astype(np.int16)
    assert check.problem(big) == ""
    big[:, cols[0]] = -big[:, cols[0]]
    assert "the line currents do not sum to zero" in (check.problem(big) or ""), check.problem(big)


def test_a_large_block_reports_every_change_where_it_was_decided():
    """Replay hands the check blocks of many windows, the live daemon a window's worth in ten blocks: the same
    changes (sound, one sensor turned round, two swapped, stopped, sound), each reported where it was decided; a
    block that raised and cleared the fault reports both (before, replay heard only the last)."""
    from tests.config.helpers import DEMO_TOML

    source = make_source("step", seed=3)
    names = list(source.descriptor.names)
    u, v = names.index("i_u"), names.index("i_v")
    good = np.array(source.step(9000), dtype=np.int16, copy=True)[1000:]
    turned, swapped = good.copy(), good.copy()
    turned[:, u] = -turned[:, u]
    swapped[:, [u, v]] = swapped[:, [v, u]]
    stopped = np.zeros_like(good)
    w = 1000
    parts = [good[:2 * w], turned[2 * w : 5 * w], swapped[5 * w : 6 * w], stopped[:w], good[6 * w : 8 * w]]
    counts = np.concatenate(parts)
    one = PhaseCheck(load_config(DEMO_TOML), source.descriptor)
    singly = [one.problem(counts[k : k + w]) for k in range(0, len(counts), w)]
    assert singly.count(None) == 1 and any("sum to zero" in (p or "") for p in singly)
    assert any("turns against" in (p or "") for p in singly)
    live, replay = PhaseCheck(load_config(DEMO_TOML), source.descriptor), PhaseCheck(load_config(DEMO_TOML),
                                                                                      source.descriptor)
    changes_live = []
    for k in range(0, len(counts), 100):
        if live.update(counts[k : k + 100]) is not None:
            changes_live.append((k + live.changes[-1][0], live.changes[-1][1]))
    replay.update(counts)
    assert [verdict for _, verdict in changes_live] == [verdict for _, verdict in replay.changes]
    assert [at for at, _ in changes_live] == [at for at, _ in replay.changes]
    assert len(changes_live) == 2 and changes_live[1][1] == ""   # raised, cleared: both within the one large block
