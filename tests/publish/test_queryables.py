"""status / config / cmd/reset queryables: answers, refusals, and garbage that never crashes."""

from __future__ import annotations

import json

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from millsense.daemon.publish.sink import ZenohSink

from .helpers import FakeInterlock, open_pair, wait_for


@pytest.fixture
def daemon(port):
    a, b = open_pair(port)
    controls = FakeInterlock(token="s3cret")
    sink = ZenohSink(a, "m1", controls)
    # B must know A's queryables before asking.
    q = b.declare_querier("millsense/m1/cmd/reset")
    wait_for(lambda: q.matching_status.matching, 5.0, "queryable known")
    q.undeclare()
    yield sink, controls, b
    sink.close()
    b.close()
    a.close()


def ask(session, key: str, payload: bytes | None = None) -> list[tuple[str, object]]:
    """Every reply as ("ok" | "err", decoded JSON)."""
    out = []
    for r in session.get(key, payload=payload, timeout=3.0):
        if r.ok is not None:
            assert str(r.ok.encoding) == "application/json"
            out.append(("ok", json.loads(r.ok.payload.to_bytes())))
        else:
            out.append(("err", json.loads(r.err.payload.to_bytes())))
    return out


def test_status_and_config_queries(daemon):
    sink, controls, b = daemon
    assert ask(b, "millsense/m1/status") == [("ok", {"state": "running", "interlock": "feed_hold"})]
    assert ask(b, "millsense/m1/config") == [("ok", controls.config())]


def test_reset_with_the_right_token_clears_the_latch(daemon):
    sink, controls, b = daemon
    assert ask(b, "millsense/m1/cmd/reset", b'{"token": "wrong"}') == [
        ("ok", {"ok": False, "error": "bad token", "interlock": "feed_hold"})
    ]
    assert controls.latched
    assert ask(b, "millsense/m1/cmd/reset", b'{"token": "s3cret"}') == [("ok", {"ok": True, "interlock": "clear"})]
    assert not controls.latched
    assert controls.reset_payloads == [b'{"token": "wrong"}', b'{"token": "s3cret"}']  # bytes passed through as sent
    assert ask(b, "millsense/m1/status")[0][1]["interlock"] == "clear"


def test_exception_inside_controls_is_an_error_reply_and_the_daemon_lives_on(daemon):
    sink, controls, b = daemon
    controls.fail_with = RuntimeError("DAQ link down, cannot release feed hold")
    [(kind, body)] = ask(b, "millsense/m1/cmd/reset", b"{}")
    assert kind == "err"
    assert body == {"ok": False, "error": "RuntimeError: DAQ link down, cannot release feed hold"}
    controls.fail_with = None
    controls.token = None
    assert ask(b, "millsense/m1/cmd/reset", b" ") == [("ok", {"ok": True, "interlock": "clear"})]
    assert controls.reset_payloads[-1] == b""
    assert sink.stats()["query_errors"] == 1


def test_without_controls_status_is_the_latest_published_and_reset_is_refused(port):
    a, b = open_pair(port)
    sink = ZenohSink(a, "m2", None)
    try:
        q = b.declare_querier("millsense/m2/status")
        wait_for(lambda: q.matching_status.matching, 5.0, "queryable known")
        assert ask(b, "millsense/m2/status") == [("err", {"ok": False, "error": "no status published yet"})]
        sink.status({"state": "running", "revolutions": 3})
        assert ask(b, "millsense/m2/status") == [("ok", {"state": "running", "revolutions": 3})]
        [(kind, body)] = ask(b, "millsense/m2/cmd/reset", b"{}")
        assert kind == "err" and "no interlock" in body["error"]
    finally:
        sink.close()
        b.close()
        a.close()


def _is_json_object(data: bytes) -> bool:
    try:
        return isinstance(json.loads(data.decode("utf-8")), dict)
    except (UnicodeDecodeError, ValueError, RecursionError):
        return False


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(payload=st.one_of(
    st.binary(max_size=200),
    st.text(max_size=50).map(str.encode),
    st.sampled_from([b"", b"  \n", b"[]", b"null", b"42", b'"token"', b"{", b"\xff\xfe{}", b"[" * 5000, b'{"token": 1}']),
))
def test_garbage_payloads_get_one_error_reply_and_never_crash(daemon, payload):
    sink, controls, b = daemon
    controls.latched = True
    before = len(controls.reset_payloads)
    replies = ask(b, "millsense/m1/cmd/reset", payload)
    assert len(replies) == 1
    kind, body = replies[0]
    assert isinstance(body, dict)
    if payload.strip() and not _is_json_object(payload):
        # refused before the interlock saw it, with a reason
        assert kind == "err" and body["ok"] is False and body["error"].startswith("payload ")
        assert len(controls.reset_payloads) == before
    else:
        assert kind == "ok" and body["ok"] is False and controls.latched  # no token → refused by the interlock
    # and the daemon still answers
    assert ask(b, "millsense/m1/status")[0][0] == "ok"
