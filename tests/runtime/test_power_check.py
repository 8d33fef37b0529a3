"""Wrong cable: current sensors turned round make the input power negative, and the daemon says so.

The plant (drivers/sim) is wired right; the *configuration* turns the three
current channels round (negative scales), which is what a current sensor
mounted the wrong way does to the numbers. Through the real estimator, then
through a real `millsense run`.
"""

from __future__ import annotations

import dataclasses
import subprocess

from millsense.daemon.pipeline.estimator import Estimator
from millsense.daemon.pipeline.power_check import MARGIN_W, REVOLUTIONS, PowerSignCheck
from millsense.drivers.base import SampleBlock
from millsense.sim import Plant
from millsense.sim.scenarios import get_scenario
from tests.e2e.helpers import CMD, Procs, write_config
from tests.estimator import simcase
from tests.faults.helpers import log_events

CURRENTS = ("i_u", "i_v", "i_w")


def _estimates(scenario, tmp_path, reversed_currents: bool = False) -> list[dict]:
    plant = Plant(scenario, seed=5, extra_channels=True)
    settings = simcase.settings_for("step", tmp_path, method="auto")
    if reversed_currents:
        channels = {k: v.model_copy(update={"scale": -v.scale}) if k in CURRENTS else v for k, v in settings.channels.items()}
        settings = settings.model_copy(update={"channels": channels})
    est = Estimator(settings, plant.descriptor, plant.sample_rate_hz)
    n = int(min(plant.duration_s, 20.0) * plant.sample_rate_hz)
    raw = plant.step(n)
    out: list[dict] = []
    for a in range(0, n, 10):
        out += est.process(SampleBlock(a, a, raw[a : a + 10], 0, False)).estimates
    return out


def _verdicts(estimates: list[dict], check: PowerSignCheck | None = None) -> list[tuple[int, str]]:
    check = check or PowerSignCheck()
    return [(e["rev"], v) for e in estimates if (v := check.update(e)) is not None]


def test_right_wiring_never_raises_it_even_through_speed_steps_and_braking(tmp_path):
    start_stop = dataclasses.replace(get_scenario("aircut-low"), name="start-stop", duration_s=7.0,
                                     spindle_schedule=((0.0, 0.0), (1.0, 600.0), (4.0, 0.0)))
    braking = [e for e in _estimates(start_stop, tmp_path) if e["valid"] and e["p_in_w"] < -MARGIN_W]
    assert len(braking) >= 5, "the stop should feed power back for several revolutions"
    for scenario in ("step", "aircut-low", "crash", start_stop):
        assert _verdicts(_estimates(scenario, tmp_path)) == [], scenario


def test_reversed_current_sensors_raise_it_after_the_revolutions_and_clear_when_fixed(tmp_path):
    wrong = _estimates("step", tmp_path, reversed_currents=True)
    assert all(e["p_in_w"] < 0 for e in wrong if e["valid"])
    check = PowerSignCheck()
    (rev, reason), = _verdicts(wrong, check)
    assert rev == wrong[0]["rev"] + REVOLUTIONS - 1  # on the 20th negative revolution in a row
    assert "current sensor turned round" in reason and "rpm" in reason
    # fixed (a restart of the estimate stream with the right scales): clears after as many good revolutions
    right = _estimates("step", tmp_path)
    assert [v for _, v in _verdicts(right, check)] == [""]


def _reversed_config(tmp_path, daq: str):
    cfg = write_config(tmp_path / "d.toml", machine="wire-01", daq=daq)
    text = cfg.read_text()
    for name in CURRENTS:
        text = text.replace(f"[channels.{name}]\nscale = 0.002", f"[channels.{name}]\nscale = -0.002")
    assert text.count("scale = -0.002") == 3
    cfg.write_text(text)
    return cfg


def test_replay_warns_of_it(tmp_path):
    cap, _ = simcase.capture(tmp_path, "step", seed=5)
    cfg = _reversed_config(tmp_path, 'transport = "tcp"\nhost = "127.0.0.1"\ntcp_port = 1')
    p = subprocess.run([*CMD, "replay", str(cap), "--config", str(cfg)], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    warnings = [line for line in p.stderr.splitlines() if "warning:" in line]
    assert len(warnings) == 1 and "current sensor turned round" in warnings[0], p.stderr


def test_the_daemon_reports_it_as_a_fault_and_keeps_running(tmp_path):
    cfg = _reversed_config(tmp_path, 'transport = "sim"\nscenario = "step"')
    with Procs(tmp_path) as procs:
        daemon = procs.start("daemon", ["run", "--config", str(cfg), "--seconds", "6"])
        assert daemon.wait(30) == 0, procs.text("daemon", "err")[-2000:]
    faults = [e for e in log_events(procs.text("daemon", "out")) if e["event"] == "fault"]
    assert [f["kind"] for f in faults] == ["signals"], faults
    assert "current sensor turned round" in faults[0]["reason"]
    assert "Traceback" not in procs.text("daemon", "err")
