"""A current sensor of the wrong scale, all three line currents measured, is named by the phase check.

A hall sensor of twice (or half) the gain the configuration says (another model fitted, a range jumper set
wrong) leaves every current swinging and the input power positive: the power check and the signal check see
nothing. Only Kirchhoff does: the three line currents no longer sum to zero, their sum swinging half a phase
(at half the gain: the missing half; at twice: the extra whole, against a phase now read twice as large).
That is under a whole phase: only the check's quarter of a phase (`KIRCHHOFF_SHARE`) catches it; a sensor
turned round (a sum of twice a phase, tests/faults/test_phase_order.py) does not tell the two apart.
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from millsense.daemon.config.load import load_config
from millsense.daemon.pipeline.phase_check import PhaseCheck
from millsense.drivers.base import SampleBlock
from millsense.sim.emulator.source import make_source
from tests.e2e.helpers import write_config
from tests.faults.helpers import INTERLOCK_OPEN, runner_on_the_sim


def _plant(seconds: float) -> np.ndarray:
    return np.array(make_source("step", seed=3).step(int(seconds * 1000)), dtype=np.int16, copy=True)


@pytest.mark.parametrize("gain", [2.0, 0.5])
def test_a_current_sensor_of_the_wrong_scale_is_named(gain):
    """The plant's own samples, i_u's counts scaled by `gain` (the sensor's, the configured scale unchanged):
    every window the drive runs in is judged wrong, none while the sensors are sound."""
    from tests.config.helpers import DEMO_TOML

    source = make_source("step", seed=3)
    check = PhaseCheck(load_config(DEMO_TOML), source.descriptor)
    sound = np.array(source.step(8000), dtype=np.int16, copy=True)[2000:]
    u = list(source.descriptor.names).index("i_u")
    wrong = sound.copy()
    wrong[:, u] = np.round(sound[:, u].astype(np.float64) * gain).astype(np.int16)   # step's currents: no overflow
    w = check.window
    windows = range(0, len(sound) - w + 1, w)
    assert [check.problem(sound[k : k + w]) for k in windows] == [""] * len(windows)   # judged, and sound
    problems = [check.problem(wrong[k : k + w]) for k in windows]
    assert all("the line currents do not sum to zero" in (p or "") for p in problems), problems
    assert "or of the wrong scale" in problems[0]


def test_a_current_scale_configured_wrong_is_blind_and_holds_the_feed(tmp_path):
    """The real runner on the simulated DAQ, `[channels.i_u] scale` twice the sensor's: fault `signals` from the
    phase check, the feed held, no reset while it stands."""
    cfg = write_config(tmp_path / "scale.toml", machine="scale-01", daq='transport = "sim"\nscenario = "step"',
                       interlock=INTERLOCK_OPEN)
    text = cfg.read_text()
    assert "[channels.i_u]\nscale = 0.002" in text
    cfg.write_text(text.replace("[channels.i_u]\nscale = 0.002", "[channels.i_u]\nscale = 0.004"))
    with runner_on_the_sim(load_config(cfg)) as (runner, drv, sink):
        counts = _plant(4.0)
        for k in range(0, len(counts), 100):
            runner.handle(SampleBlock(k, k, counts[k : k + 100], 0, False), time.monotonic())
        assert runner.phase_check is not None and runner.phase_check.faulted
        assert "the line currents do not sum to zero" in runner.faults.get("signals", ""), runner.faults
        assert runner.interlock.latched and runner.interlock.reason.startswith("blind: signals:")
        assert drv.device.feed_hold
        r = runner.controls.reset("pytest")
        assert r["ok"] is False and r["condition"] == "blind"
