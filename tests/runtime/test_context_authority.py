"""Issue 36 in the runner, against the real in-process DAQ (protocol 2): who may let AFC raise the feed.

The context arrives as the sink's subscriber hands it over (`Runner.on_context_payload`, Zenoh's thread);
the DAQ is the emulator's `DeviceModel` behind `SimDriver`, whose `feed_override_commanded` is what the
daemon last wrote. The scripted cut is half the target, so that a controller allowed to run raises the feed
at once. An unsigned put with `afc_allowed: true` leaves it idle at ≤ 100 %; the same context signed with
the adapter key (the doc's reference signer) lets it run; `[context] trust = "acl"` does too; a signed put
naming a tool whose `[afc.targets]` entry says `allow = false` does not.
"""

from __future__ import annotations

import json
from types import SimpleNamespace

import pytest
from pydantic import SecretStr

from millsense.daemon.config.models import AfcSettings, AfcTargetSettings
from tests.learning.doc_signer import signer
from tests.runtime.test_afc_runner import TARGET_NM, start_runner, stop_runners
from tests.runtime.test_runner import wait_for

MACHINE = "ctx-rt"
KEY = "adapter-key-of-at-least-32-characters-0123456789"
UNTRUSTED = "context not authenticated"  # the reason docs/afc.md names
CUT = {"program": 1234, "tool": 3, "operation": 1, "cycle": True, "monitor": True, "afc_allowed": True}
REVS = 20  # revolutions watched after a context is applied: the old code raised the feed within 2


def settings(*, key: str = KEY, trust: str = "none"):
    return SimpleNamespace(
        machine=MACHINE,
        alarms=SimpleNamespace(torque_limit_nm=30.0, revolutions=2, crash_power_w=15000.0, hysteresis_pct=5.0,
                               breakage_drop_pct=0.0),
        interlock=SimpleNamespace(enabled=True, heartbeat_ms=20, watchdog_ms=500, reset="open", reset_token=""),
        context=SimpleNamespace(source="zenoh", trust=trust, adapter_key=SecretStr(key) if key else None),
        afc=AfcSettings(enabled=True, target_torque_nm=TARGET_NM,
                        targets={"7/*": AfcTargetSettings(allow=False)}),   # tool 7: tapping, never
    )


@pytest.fixture
def rig():
    made = []

    def make(**kw):
        return start_runner(made, settings(**kw), lambda rev: TARGET_NM / 2)

    yield make
    stop_runners(made)


def put(runner, payload: dict) -> None:
    """What the sink's context subscriber does with one put (a refusal raises ValueError there)."""
    runner.controls.on_context_payload(json.loads(json.dumps(payload)), "zid:test")


def sign(runner, seq: int, **over) -> dict:
    return json.loads(signer()(KEY, MACHINE, runner.active_alarms.run_id, seq, {**CUT, **over}))


def revolutions_under(sink, tool: int, n: int = REVS) -> list[dict]:
    """Wait for `n` estimates published under `tool`; the estimates since it came into force."""
    def under() -> list[dict]:
        return [p for p, _ in sink.of("estimate") if p.get("tool") == tool]
    wait_for(lambda: len(under()) >= n, 10, f"{n} revolutions under tool {tool}")
    return under()


def test_an_unsigned_context_never_lets_afc_raise_the_feed(rig):
    runner, drv, sink = rig()
    put(runner, CUT)
    for est in revolutions_under(sink, 3):
        assert est["afc"]["state"] == "idle" and est["afc"]["override_pct"] <= 100.0, est["afc"]
    assert drv.device.feed_override_commanded <= 1000
    status = runner.controls.status()
    assert status["afc"]["reason"] == UNTRUSTED and status["context"]["authority"] == "none"


def test_a_signed_context_lets_afc_run_and_a_replay_or_an_unsigned_one_does_not(rig):
    runner, drv, sink = rig()
    first = sign(runner, 1)
    put(runner, first)
    wait_for(lambda: drv.device.feed_override_commanded > 1050, 10, "the controller raising the feed of a light cut")
    assert runner.controls.status()["context"]["authority"] == "mac"
    assert runner.controls.status()["context_auth"] == {"key": True, "trust": "none", "seq": 1}
    # the same context unsigned: AFC stops following, the feed back to 100 % at once
    put(runner, {**CUT, "program": 1235})
    wait_for(lambda: runner.controls.status()["afc"]["reason"] == UNTRUSTED, 10, "idle under the unsigned context")
    assert drv.device.feed_override_commanded <= 1000
    # the first signed put again: refused on Zenoh's thread, so the sink counts it; nothing changes
    with pytest.raises(ValueError, match="not above 1"):
        put(runner, first)
    for est in revolutions_under(sink, 3, n=len([p for p, _ in sink.of("estimate") if p.get("tool") == 3]) + REVS):
        if est.get("program") == 1235:
            assert est["afc"]["override_pct"] <= 100.0, est["afc"]
    assert drv.device.feed_override_commanded <= 1000


def test_a_signed_context_cannot_lift_a_targets_allow_false(rig):
    runner, drv, sink = rig()
    put(runner, sign(runner, 1, tool=7))
    for est in revolutions_under(sink, 7):
        assert est["afc"]["state"] == "idle" and est["afc"]["override_pct"] <= 100.0, est["afc"]
    assert runner.controls.status()["afc"]["reason"] == "not allowed" and drv.device.feed_override_commanded <= 1000


def test_trust_acl_lets_an_unsigned_context_steer_afc(rig):
    runner, drv, sink = rig(key="", trust="acl")
    put(runner, CUT)
    wait_for(lambda: drv.device.feed_override_commanded > 1050, 10, "the controller raising the feed under the ACL")
    assert runner.controls.status()["context"]["authority"] == "acl"
