"""The runner's side of adaptive feed control, against the real in-process DAQ (protocol 2 and 1).

The DAQ is the emulator's `DeviceModel` behind `SimDriver`: the override it holds
(`feed_override_commanded`) is what the daemon last wrote. The estimator is the
scripted one of test_runner.py (a revolution every 100 samples, 600 rpm, the
torque chosen by the test), so that each safety rule is checked on its own:
a fault from any thread brings the override to at most 100 % before `fault()`
returns; a trip too; the controller stays there until the condition is gone;
a version-1 DAQ and a daemon without its interlock refuse `afc on`, saying why.
"""

from __future__ import annotations

import json
import threading
from types import SimpleNamespace

import pytest

from millsense.daemon.config.models import AfcSettings
from millsense.daemon.runtime.runner import Runner
from millsense.sim.emulator.device import StatusLog
from millsense.drivers.sim_driver import SimDriver
from tests.runtime.test_runner import RecordingSink, ScriptedEstimator, wait_for

pytestmark = pytest.mark.quick

TARGET_NM = 20.0


class Rpm600(ScriptedEstimator):
    """The scripted revolutions with the speed the controller needs (100 samples at 1 kHz: 600 rpm)."""

    def process(self, block):
        out = super().process(block)
        for est in out.estimates:
            est["spindle_rpm"] = 600.0
        return out


def settings(*, interlock: bool = True, enabled: bool = False):
    return SimpleNamespace(
        machine="afc-rt",
        alarms=SimpleNamespace(torque_limit_nm=30.0, revolutions=2, crash_power_w=15000.0, hysteresis_pct=5.0,
                               breakage_drop_pct=0.0),
        interlock=SimpleNamespace(enabled=interlock, heartbeat_ms=20, watchdog_ms=500, reset="open", reset_token=""),
        afc=AfcSettings(enabled=enabled, allow=True, target_torque_nm=TARGET_NM),
    )


@pytest.fixture
def rig():
    made = []

    def make(torque, *, protocol: int = 2, **kw):
        return start_runner(made, settings(**kw), torque, protocol)

    yield make
    stop_runners(made)


def start_runner(made: list, config, torque, protocol: int = 2):
    """A runner on the simulated DAQ (ramp, real time) at 600 rpm with `torque`, started and past its first
    revolution; (runner, driver, sink), also appended to `made` for `stop_runners`."""
    drv = SimDriver("ramp", realtime=True, protocol=protocol)
    drv.start()
    assert drv.wait_connected(5)
    wait_for(lambda: drv.descriptor is not None, 5, "descriptor")
    runner = Runner(config, drv, estimator_factory=Rpm600(torque), check_descriptor=lambda s, d: None)
    sink = RecordingSink(lambda: drv.device)
    made.append((runner, drv))
    runner.start(sink)
    wait_for(lambda: sink.of("estimate"), 5, "a first revolution")
    return runner, drv, sink


def stop_runners(made: list) -> None:
    for runner, drv in made:
        runner.stop(1.0)
        drv.close()


def _above_100(runner, drv, sink):
    assert runner.controls.afc_command({"action": "on"}, "test")["ok"]
    wait_for(lambda: drv.device.feed_override_commanded > 1050, 5, "the controller raising the feed of a light cut")
    assert sink.of("estimate")[-1][0]["afc"]["state"] in ("armed", "saturated")


def test_a_fault_from_any_thread_brings_the_override_to_100_before_it_returns(rig):
    torque = {"nm": 10.0}  # half the target: the controller wants more feed
    runner, drv, sink = rig(lambda rev: torque["nm"])
    _above_100(runner, drv, sink)
    runner.board.fault("history", "test: the disk is full")  # this thread, not the estimator's
    assert drv.device.feed_override_commanded <= 1000
    wait_for(lambda: sink.of("estimate")[-1][0]["afc"]["state"] == "safe", 5, "estimates saying safe")
    n = len(sink.of("estimate"))
    wait_for(lambda: len(sink.of("estimate")) >= n + 5, 5, "revolutions while the fault lasts")
    assert drv.device.feed_override_commanded <= 1000  # nothing rises while it lasts
    runner.board.recover("history")
    wait_for(lambda: drv.device.feed_override_commanded > 1050, 5, "control again once the fault is gone")


def test_a_trip_holds_the_override_at_100_until_an_authorised_reset(rig):
    torque = {"nm": 10.0}
    runner, drv, sink = rig(lambda rev: torque["nm"])
    _above_100(runner, drv, sink)
    torque["nm"] = 35.0  # over the 30 N·m limit: overload trips
    wait_for(lambda: runner.interlock.latched, 5, "the overload trip")
    assert drv.device.feed_override_commanded <= 1000 and drv.device.feed_hold
    torque["nm"] = 10.0
    n = len(sink.of("estimate"))
    wait_for(lambda: len(sink.of("estimate")) >= n + 5, 5, "light revolutions while held")
    assert drv.device.feed_override_commanded <= 1000 and runner.controls.status()["afc"]["state"] == "safe"
    assert runner.controls.reset("test")["ok"]
    wait_for(lambda: drv.device.feed_override_commanded > 1050, 5, "control again after the reset")


def test_switching_off_returns_to_the_programmed_feed_at_once(rig):
    runner, drv, sink = rig(lambda rev: 10.0)
    _above_100(runner, drv, sink)
    reply = runner.controls.afc_command({"action": "off"}, "test")
    assert reply["ok"] and reply["afc"]["state"] == "off"
    assert drv.device.feed_override_commanded == 1000


def test_a_protocol_1_daq_refuses_afc_and_says_why(rig):
    runner, drv, sink = rig(lambda rev: 10.0, protocol=1)
    reply = runner.controls.afc_command({"action": "on"}, "test")
    assert reply["ok"] is False and "protocol version 1" in reply["reason"]
    status = runner.controls.status()["afc"]
    assert status["available"] is False and status["state"] == "unavailable"


def test_without_the_interlock_afc_is_refused(rig):
    runner, drv, sink = rig(lambda rev: 10.0, interlock=False)
    reply = runner.controls.afc_command({"action": "on"}, "test")
    assert reply["ok"] is False and "watchdog" in reply["reason"]
    assert drv.device.feed_override_commanded == 1000


def test_an_override_left_by_an_earlier_run_is_set_back_at_connection(rig_left_override):
    """A daemon restarted within the watchdog's period finds the DAQ at the last run's 140 %; AFC is off
    at start, so the feed must go back to the programmed one, not stay where nobody controls it."""
    runner, drv = rig_left_override(1400)
    wait_for(lambda: drv.device.feed_override_commanded == 1000, 5, "the programmed feed set again")
    assert runner.controls.status()["afc"]["state"] == "off"


@pytest.fixture
def rig_left_override():
    made = []

    def make(tenths: int):
        import time

        drv = SimDriver("ramp", realtime=True, protocol=2)
        drv.start()
        assert drv.wait_connected(5)
        wait_for(lambda: drv.descriptor is not None, 5, "descriptor")
        assert drv.device.set_feed_override(tenths, time.monotonic())  # what the earlier run left
        runner = Runner(settings(), drv, estimator_factory=Rpm600(lambda rev: 10.0),
                        check_descriptor=lambda s, d: None)
        made.append((runner, drv))
        runner.start(RecordingSink(lambda: drv.device))
        return runner, drv

    yield make
    for runner, drv in made:
        runner.stop(1.0)
        drv.close()


def test_a_cnc_that_does_not_follow_the_override_down_holds_the_feed(rig, monkeypatch):
    """The probe of stop 27: a DAQ that refuses the override command (or a stuck output, a PLC) left the CNC at
    150 % while the daemon commanded 100 % and said `safe`: the feed ran faster than programmed with nothing in
    control, and nothing said so. Now, AFC on, an applied override above both 100 % and the command for a second
    holds the feed, says why, and a reset is refused while it lasts."""
    from millsense.daemon.afc.supervisor import OVERRIDE_FOLLOW_S

    torque = {"nm": 10.0}
    runner, drv, sink = rig(lambda rev: torque["nm"])
    _above_100(runner, drv, sink)
    wait_for(lambda: (runner.afc.applied_override_pct or 0) > 105.0, 5, "the CNC applying more than 100 %")
    # from now on the DAQ takes no override command (it answers, but nothing changes): a failure a real emulator
    # cannot be made to have on cue
    monkeypatch.setattr(drv.device, "set_feed_override", lambda tenths, now, cause="command": True)
    runner.board.fault("history", "test: the disk is full")    # AFC goes safe: 100 % commanded
    assert runner.afc.feed_out.sent_pct <= 100.0 and not runner.interlock.latched
    wait_for(lambda: runner.interlock.latched, 5 + OVERRIDE_FOLLOW_S, "the feed held")
    assert runner.interlock.reason.startswith("afc: the CNC applies a ") and "nothing controls it" in runner.interlock.reason
    # the hold is written first, the alarm published just after it by the same thread: wait for it
    wait_for(lambda: [a for a, _ in sink.of("alarm") if a.get("quantity") == "feed_override_pct"], 5, "the alarm")
    alarm = [a for a, _ in sink.of("alarm") if a.get("quantity") == "feed_override_pct"]
    assert alarm and alarm[-1]["level"] == "overload" and alarm[-1]["value"] > 105.0
    runner.board.recover("history")
    n = len(sink.of("estimate"))
    wait_for(lambda: len(sink.of("estimate")) >= n + 3, 5, "revolutions since the hold (evidence for a reset)")
    r = runner.controls.reset("test")
    assert r["ok"] is False and r["condition"] == "feed_override", r


def test_a_trip_writes_the_override_down_itself_before_any_further_revolution(rig, tmp_path):
    """The trip's own `_afc_safe` (runner `_trip`): the hold is written, then the override at most 100 %, by the
    tripping thread. Not left to the next revolution's safe decision: that one would come a revolution later
    (the test above cannot tell the two apart). Here the estimator thread is parked inside a block, so no
    revolution can be processed until the test lets it go; the DAQ's own log orders the hold and the
    override commands, so nothing depends on timing (the watchdog's return to 100 % is logged apart, not as
    a command)."""
    gate, parked = threading.Event(), threading.Event()
    gate.set()

    def torque(rev):
        if not gate.is_set():  # the estimator thread, building a revolution: it waits here
            parked.set()
            gate.wait()
        return 10.0   # half the target: the controller raises the feed

    runner, drv, sink = rig(torque)
    try:
        _above_100(runner, drv, sink)
        log_path = tmp_path / "daq.jsonl"
        drv.device.log = StatusLog(str(log_path))   # from here on, the DAQ logs what it is told, in order
        gate.clear()
        assert parked.wait(10), "the estimator thread never came to the next revolution"
        revolutions = runner.live.revolutions
        assert drv.device.feed_override_commanded > 1000
        r = runner.controls.test_trip("pytest")
        assert r["ok"] is True, r
        assert runner.live.revolutions == revolutions and not gate.is_set()   # still parked: no revolution since
        events = [json.loads(line) for line in log_path.read_text().splitlines()]
        told = [e for e in events if e["event"] in ("outputs", "feed_override_command")]  # in the DAQ's order
        holds = [k for k, e in enumerate(told) if e["event"] == "outputs" and e["cause"] == "command"
                 and e["feed_hold"]]  # the trip's hold
        assert holds, f"no hold command in the DAQ's log: {told}"
        down = [e for e in told[holds[0] + 1:] if e["event"] == "feed_override_command" and e["value"] <= 1000]
        assert down, f"the trip wrote no override <= 100 % after the hold (the next revolution would): {told}"
    finally:
        gate.set()
