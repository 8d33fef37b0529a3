"""Interlock policy: latch, reset authority, heartbeats, start policy.

The DAQ side here is a recorder of the three output calls (the interface the
interlock drives); the real emulator on TCP is exercised in tests/e2e.
"""

from __future__ import annotations

import json
from types import SimpleNamespace

from millsense.daemon.pipeline.interlock import Interlock


class Outputs:
    def __init__(self, fail: bool = False, hold: bool = False):
        self.calls: list[tuple] = []
        self.fail = fail
        self.last_status = SimpleNamespace(feed_hold=hold, watchdog_tripped=hold)

    def set_outputs(self, feed_hold, alarm_lamp=False):
        if self.fail:
            raise ConnectionError("link down")
        self.calls.append(("outputs", feed_hold, alarm_lamp))

    def heartbeat(self):
        self.calls.append(("heartbeat",))

    def set_watchdog_ms(self, ms):
        self.calls.append(("watchdog", ms))


def cfg(**kw):
    base = dict(enabled=True, heartbeat_ms=100, watchdog_ms=500, reset="open", reset_token="")
    base.update(kw)
    return SimpleNamespace(**base)


def test_disabled_interlock_never_touches_the_daq():
    out = Outputs()
    il = Interlock(out, cfg(enabled=False))
    il.start()
    assert il.trip("overload") is None
    il.beat(True)
    assert il.reset(b"{}")["ok"] is True
    assert out.calls == [] and il.state == "disabled"


def test_trip_latches_and_writes_once():
    out = Outputs()
    il = Interlock(out, cfg())
    il.start()
    assert out.calls == [("watchdog", 500)]  # start writes no output
    assert il.trip("torque overload") == "feed_hold"
    assert il.trip("again") == "feed_hold"
    assert out.calls[1:] == [("outputs", True, True)]
    assert il.state == "feed_hold" and il.reason == "torque overload"
    r = il.reset(b"{}")
    assert r["ok"] is True and r["interlock"] == "armed"
    assert out.calls[-1] == ("outputs", False, False)


def test_token_policy_compares_the_token():
    out = Outputs()
    il = Interlock(out, cfg(reset="token", reset_token="s3cret"))
    il.trip("x")
    for bad in (b"", b"{}", json.dumps({"token": "nope"}).encode(), b"s3cre", b"{not json"):
        r = il.reset(bad)
        assert r["ok"] is False and r["interlock"] == "feed_hold", bad
    assert il.reset(json.dumps({"token": "s3cret"}).encode())["ok"] is True
    il.trip("y")
    assert il.reset(b"s3cret\n")["ok"] is True


def test_token_policy_with_empty_token_refuses_everything():
    il = Interlock(Outputs(), cfg(reset="token", reset_token=""))
    il.trip("x")
    assert il.reset(b"")["ok"] is False
    assert il.reset(json.dumps({"token": ""}).encode())["ok"] is False


def test_reset_off_refuses():
    il = Interlock(Outputs(), cfg(reset="off"))
    il.trip("x")
    r = il.reset(b"{}")
    assert r["ok"] is False and "off" in r["error"] and il.state == "feed_hold"


def test_heartbeats_only_while_healthy():
    out = Outputs()
    il = Interlock(out, cfg())
    il.beat(True)
    il.beat(True)
    il.beat(False)
    il.beat(False)
    assert out.calls.count(("heartbeat",)) == 2 and il.heartbeating is False
    il.beat(True)
    assert out.calls.count(("heartbeat",)) == 3 and il.heartbeating is True


def test_a_hold_found_at_start_is_left_alone_until_reset():
    out = Outputs(hold=True)
    il = Interlock(out, cfg())
    il.start()
    assert il.state == "held_by_device"
    assert not any(c[0] == "outputs" for c in out.calls)
    assert il.reset(b"{}")["interlock"] == "armed"
    assert out.calls[-1] == ("outputs", False, False)


def test_failed_write_keeps_the_latch_and_is_reasserted():
    out = Outputs(fail=True)
    il = Interlock(out, cfg())
    assert il.trip("crash") is None  # not asserted by us: the payload must not claim it
    assert il.state == "feed_hold" and il.write_errors == 1
    out.fail = False
    il.reassert()
    assert out.calls == [("outputs", True, True)]


def test_token_is_read_from_a_secret_not_its_mask():
    from pydantic import SecretStr

    il = Interlock(Outputs(), cfg(reset="token", reset_token=SecretStr("s3cret")))
    il.trip("x")
    assert il.reset(b'{"token": "**********"}')["ok"] is False
    assert il.reset(b'{"token": "s3cret"}')["ok"] is True
