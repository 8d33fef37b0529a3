"""status / config / cmd/reset queryables: answers, refusals, garbage that never crashes, floods that change nothing."""

from __future__ import annotations

import json
import threading

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from millsense.daemon.publish.command_auth import CommandError, FailureLimiter, send_command
from millsense.daemon.publish.payload import MAX_QUERY_BYTES
from millsense.daemon.publish.sink import ZenohSink

from .helpers import FakeInterlock, open_pair, wait_for

pytestmark = pytest.mark.quick


@pytest.fixture
def daemon(port):
    a, b = open_pair(port)
    controls = FakeInterlock()
    sink = ZenohSink(a, "m1", controls)
    sink.gate.limiter = FailureLimiter(max_failures=10**6)  # garbage must not pause the commands of the next test
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
    with pytest.raises(CommandError, match="the proof does not match"):
        send_command(b, "m1", "reset", "wrong-" + controls.token)
    assert controls.latched
    assert send_command(b, "m1", "reset", controls.token) == {"ok": True, "interlock": "clear"}
    assert not controls.latched
    assert controls.requesters == [f"zid:{b.zid()} (self-declared)"]  # only the authorised one reached controls
    assert ask(b, "millsense/m1/status")[0][1]["interlock"] == "clear"  # no stale cached status after a command


def test_a_cached_status_is_never_served_once_the_interlock_changed(daemon, monkeypatch):
    """A burst of status queries costs one `status()`, but never past a change of what the status says of the
    feed: a trip from the estimator (no command through the sink) shows at the next query, not up to
    STATUS_CACHE_S later (a test read `armed` from the cache after the DAQ had already taken the hold)."""
    from millsense.daemon.publish import queryables

    monkeypatch.setattr(queryables, "STATUS_CACHE_S", 60.0)   # the cache's lifetime out of the race
    sink, controls, b = daemon
    controls.latched = False
    assert ask(b, "millsense/m1/status")[0][1]["interlock"] == "clear"
    calls = controls.status_calls
    assert ask(b, "millsense/m1/status")[0][1]["interlock"] == "clear"
    assert controls.status_calls == calls     # unchanged: served from the cache
    controls.latched = True                   # the trip, outside any command
    assert ask(b, "millsense/m1/status")[0][1]["interlock"] == "feed_hold"


def test_exception_inside_controls_is_a_signed_result_and_the_daemon_lives_on(daemon):
    sink, controls, b = daemon
    controls.fail_with = RuntimeError("DAQ link down, cannot release feed hold")
    result = send_command(b, "m1", "reset", controls.token)  # verified: the daemon's MAC is on it
    assert result == {"ok": False, "error": "RuntimeError: DAQ link down, cannot release feed hold"}
    controls.fail_with = None
    assert send_command(b, "m1", "reset", controls.token) == {"ok": True, "interlock": "clear"}
    assert ask(b, "millsense/m1/status")[0][0] == "ok"


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
    st.sampled_from([b"", b"  \n", b"[]", b"null", b"42", b'"token"', b"{", b"\xff\xfe{}", b"[" * 5000, b'{"token": 1}',
                     b'{"token": "s3cret"}', b'{"step": "prove"}', b'{"step": "challenge", "client_nonce": "xyz"}',
                     b'{"step": "prove", "client_nonce": "' + b"a" * 32 + b'", "server_nonce": "' + b"b" * 64 + b'"}',
                     b"x" * 5000]),
))
def test_garbage_payloads_get_one_error_reply_and_never_crash(daemon, payload):
    sink, controls, b = daemon
    controls.latched = True
    replies = ask(b, "millsense/m1/cmd/reset", payload)
    assert len(replies) == 1
    kind, body = replies[0]
    assert kind == "err" and isinstance(body, dict)
    assert controls.latched and controls.requesters == []  # nothing reached the interlock
    if len(payload) > MAX_QUERY_BYTES:
        assert body["error"].startswith(f"payload over {MAX_QUERY_BYTES} bytes")  # refused unread
    elif not _is_json_object(payload):
        assert body["ok"] is False and body["error"].startswith("payload ")
    elif "result" in body:  # a prove with well-formed nonces: a signed refusal
        assert json.loads(body["result"])["ok"] is False and body["server_mac"]
    else:
        assert body["ok"] is False and body["error"]
    # and the daemon still answers
    assert ask(b, "millsense/m1/status")[0][0] == "ok"


def test_a_flood_of_large_queries_does_not_stop_a_legit_command(daemon):
    """Finding 4: 100 KB queries fired without waiting, on the command key itself and on status.

    The rings drop what the worker cannot take; the legit exchange still completes (retrying its
    challenge, or resending the same proof, when a flood pushed it out). Outcomes, not timings.
    """
    sink, controls, b = daemon
    blob = b"\x00" * 100_000
    stop = threading.Event()
    answers = {"ok": 0, "err": 0}
    lock = threading.Lock()

    def count(reply):
        with lock:
            answers["ok" if reply.ok is not None else "err"] += 1

    def flood(key):
        while not stop.is_set():
            b.get(key, count, payload=blob, timeout=5.0)  # a callback: returns at once, nothing awaited

    threads = [threading.Thread(target=flood, args=(k,), daemon=True)
               for k in ("millsense/m1/cmd/reset", "millsense/m1/cmd/reset", "millsense/m1/status")]
    for t in threads:
        t.start()
    try:
        wait_for(lambda: sink.stats()["queries_too_large"] >= 200, 30.0, "the flood reaching the daemon")
        result = send_command(b, "m1", "reset", controls.token, timeout_s=20.0)
        status_replies = wait_for(lambda: ask(b, "millsense/m1/status"), 20.0, "a status answer during the flood")
    finally:
        stop.set()
        for t in threads:
            t.join(10)
    assert result == {"ok": True, "interlock": "clear"} and not controls.latched
    assert len(controls.requesters) == 1  # ran once
    assert status_replies == [("ok", {"state": "running", "interlock": "clear"})]
    assert answers["ok"] == 0  # not one flood query was answered as if it were a request


def test_every_query_worker_carries_its_name_into_the_os(daemon):
    """`top -H` shows which queryable costs what (docs/architecture.md, the thread table)."""
    import os
    from pathlib import Path

    sink, controls, b = daemon

    def names() -> set[str]:
        out = set()
        for task in os.listdir("/proc/self/task"):
            try:
                out.add(Path(f"/proc/self/task/{task}/comm").read_text().strip())
            except OSError:
                pass  # a thread that ended meanwhile
        return out

    want = {"ms-q-status", "ms-q-config", "ms-c-reset", "ms-zenoh-sink"}
    wait_for(lambda: want <= names(), 5.0, f"threads named {sorted(want)}")
