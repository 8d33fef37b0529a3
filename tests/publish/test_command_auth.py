"""The command exchange (daemon/publish/command_auth.py): proofs, replays, impostors, rate limits, the wire.

The daemon side is a real `ZenohSink` with a small Controls object; the
requester is `send_command` on a second real session; both on loopback.
"""

from __future__ import annotations

import base64
import json
import threading

import pytest

from millsense.daemon.audit import AuditLog
from millsense.daemon.publish import command_auth as ca
from millsense.daemon.publish.command_auth import CommandError, FailureLimiter, NonceStore, exchange, send_command
from millsense.daemon.publish.sink import ZenohSink

from .helpers import FakeInterlock, open_pair, wait_for

pytestmark = pytest.mark.quick

TOKEN = "Hk3vQ9xW2mPz7LcN5tRb8yFd4sGj6aUe1oKi0nVw_-E"  # 43 characters, as `millsense token new` makes


class Clock:
    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


@pytest.fixture
def linked(port):
    a, b = open_pair(port)
    yield a, b
    b.close()
    a.close()


def _sink(a, controls, **gate):
    sink = ZenohSink(a, "m1", controls)
    for name, value in gate.items():
        setattr(sink.gate, name, value)
    return sink


# ---------------------------------------------------------------- pure parts
def test_nonces_are_single_use_expire_and_are_bounded():
    clock = Clock()
    store = NonceStore(ttl_s=10.0, capacity=3, mono=clock)
    n1 = store.issue()
    assert len(n1) == 64 and int(n1, 16) >= 0
    assert store.take(n1) and not store.take(n1)  # single use
    n2 = store.issue()
    clock.t += 10.0
    assert not store.take(n2)  # expired
    kept = [store.issue() for _ in range(5)]
    assert len(store) == 3  # bounded: the oldest went
    assert not store.take(kept[0]) and store.take(kept[-1])


def test_an_operators_nonce_outlives_a_second_of_challenges_from_a_flood():
    """A probe of stop 26: two peers asking for challenges as fast as the daemon answers (about 1000 a second)
    evicted a genuine operator's server nonce between its challenge and its proof (64 were kept)."""
    store = NonceStore()
    mine = store.issue()
    for _ in range(1000):
        store.issue()
    assert store.take(mine)


def test_failure_limiter_pauses_after_n_failures_in_the_window():
    clock = Clock()
    lim = FailureLimiter(max_failures=3, window_s=10.0, cooldown_s=30.0, mono=clock)
    lim.failed()
    clock.t += 11  # out of the window: forgotten
    lim.failed()
    lim.failed()
    assert lim.paused_for() == 0
    lim.failed()
    assert lim.paused_for() == 30.0
    clock.t += 30
    assert lim.paused_for() == 0


def test_canonical_json_sorts_keys_escapes_non_ascii_and_refuses_fractions():
    assert ca.canonical_json({"b": 1, "a": [True, None, "é"]}) == '{"a":[true,null,"\\u00e9"],"b":1}'
    assert ca.canonical_json({}) == "{}"
    with pytest.raises(ValueError, match="fractional"):
        ca.canonical_json({"feed_pct": 50.5})


def test_the_two_labels_keep_a_requester_mac_from_being_a_daemon_mac():
    sn, cn = "a" * 64, "b" * 32
    assert ca.command_message("reset", "m1", sn, cn, {}) == f"millsense-cmd-v1\nreset\nm1\n{sn}\n{cn}\n{{}}".encode()
    assert ca.mac_hex(TOKEN, ca.command_message("reset", "m1", sn, cn, {})) != \
        ca.mac_hex(TOKEN, ca.reply_message("reset", "m1", sn, cn, "{}"))


# ---------------------------------------------------------------- over Zenoh
def test_exchange_verifies_both_ways_and_audits_the_requester(linked):
    a, b = linked
    controls = FakeInterlock(token=TOKEN)
    controls.audit = AuditLog(None, "m1")
    sink = _sink(a, controls)
    try:
        out = exchange(b, "m1", "reset", TOKEN)
        assert out.result == {"ok": True, "interlock": "clear"} and out.verified and out.policy == "token"
        assert controls.requesters == [f"zid:{b.zid()} (self-declared)"]
        assert controls.audit.records == 1 and controls.audit.refusals == 0
    finally:
        sink.close()


def test_token_never_crosses_the_wire_and_a_replayed_exchange_is_refused(linked):
    """An observer's queryable on the same keys sees every query payload; it never replies."""
    a, b = linked
    controls = FakeInterlock(token=TOKEN)
    sink = _sink(a, controls)
    seen: list[bytes] = []
    lock = threading.Lock()

    def observe(query):
        with lock:
            seen.append(query.payload.to_bytes() if query.payload is not None else b"")

    spy = a.declare_queryable("millsense/m1/cmd/**", observe)
    try:
        send_command(b, "m1", "reset", TOKEN)
        assert not controls.latched
        wait_for(lambda: len(seen) >= 2, 5.0, "the observer saw both steps")
        steps = [json.loads(p) for p in seen]
        assert [s["step"] for s in steps] == ["challenge", "prove"]
        encodings = (TOKEN, TOKEN.encode().hex(), base64.b64encode(TOKEN.encode()).decode())
        assert not any(e in p.decode() for p in seen for e in encodings), "the token went on the wire"

        # replay the captured proof: its server nonce is spent
        controls.latched = True
        prove = seen[1]
        replies = list(b.get("millsense/m1/cmd/reset", payload=prove, timeout=3.0))
        bodies = [json.loads((r.ok or r.err).payload.to_bytes()) for r in replies]
        assert len(bodies) == 1 and bodies[0]["server_mac"] is not None
        assert json.loads(bodies[0]["result"]) == {"ok": False, "error": "unknown, used or expired server_nonce: "
                                                                         "ask for a new challenge"}
        assert replies[0].err is not None and controls.latched and len(controls.requesters) == 1
    finally:
        spy.undeclare()
        sink.close()


def test_wrong_token_is_refused_then_all_proofs_pause(linked):
    a, b = linked
    controls = FakeInterlock(token=TOKEN)
    controls.audit = AuditLog(None, "m1")
    sink = _sink(a, controls, limiter=FailureLimiter(max_failures=3, window_s=60.0, cooldown_s=60.0))
    try:
        for _ in range(3):
            with pytest.raises(CommandError, match="refused reset: the proof does not match"):
                send_command(b, "m1", "reset", "W" * 43)
        # now even the right token is refused, and the daemon says why (verified with the right token)
        with pytest.raises(CommandError, match="too many failed proofs") as err:
            send_command(b, "m1", "reset", TOKEN)
        assert "millsense reset --local" in str(err.value)
        assert controls.latched and controls.requesters == []
        assert controls.audit.refusals == 3  # the paused one was refused at the challenge, before a proof
    finally:
        sink.close()


def test_an_impostor_that_fakes_success_is_not_believed(linked):
    """A program answering like the daemon, but without the token: it cannot make a server_mac."""
    a, b = linked
    got: list[dict] = []

    def impostor(query):
        req = json.loads(query.payload.to_bytes())
        got.append(req)
        if req["step"] == "challenge":
            body = {"step": "challenge", "machine": "m1", "command": "reset", "policy": "token",
                    "server_nonce": "c" * 64, "expires_s": 10}
        else:
            body = {"result": json.dumps({"ok": True, "interlock": "clear"}), "server_mac": "d" * 64}
        query.reply("millsense/m1/cmd/reset", json.dumps(body).encode())

    fake = a.declare_queryable("millsense/m1/cmd/reset", impostor)
    try:
        q = b.declare_querier("millsense/m1/cmd/reset")
        wait_for(lambda: q.matching_status.matching, 5.0, "impostor known")
        q.undeclare()
        with pytest.raises(CommandError, match="fails the daemon's MAC"):
            send_command(b, "m1", "reset", TOKEN)
        assert TOKEN not in json.dumps(got) and got[-1]["mac"] != TOKEN
    finally:
        fake.undeclare()


def test_open_policy_needs_no_mac_and_says_it_is_unverified(linked):
    a, b = linked
    controls = FakeInterlock(token=None)  # policy "open"
    sink = _sink(a, controls)
    try:
        out = exchange(b, "m1", "reset", None)
        assert out.result["ok"] is True and out.policy == "open" and not out.verified
        # a requester holding a token does not accept an unverifiable "open" daemon
        controls.latched = True
        with pytest.raises(CommandError, match="open to anyone"):
            send_command(b, "m1", "reset", TOKEN)
        assert controls.latched
    finally:
        sink.close()


def test_off_policy_refuses_every_network_command(linked):
    a, b = linked
    controls = FakeInterlock(token=None, policy="off")
    sink = _sink(a, controls)
    try:
        with pytest.raises(CommandError, match="off on m1.*millsense reset --local"):
            send_command(b, "m1", "reset", None)
        assert controls.latched and controls.requesters == []
    finally:
        sink.close()


def test_command_args_are_refused_when_the_command_takes_none(linked):
    a, b = linked
    controls = FakeInterlock(token=TOKEN)
    sink = _sink(a, controls)
    try:
        with pytest.raises(CommandError, match="reset takes no args"):
            send_command(b, "m1", "reset", TOKEN, args={"force": True})
        assert controls.latched
    finally:
        sink.close()


_STALE = {"step": "prove", "server_nonce": "5e" * 32, "client_nonce": "00" * 16, "args": {}, "mac": "0" * 64}


@pytest.mark.parametrize("proof, refusal", [
    # a spent or unknown nonce (a replay, or one a challenge flood evicted): before, five in 10 s paused commands
    (_STALE, "unknown, used or expired server_nonce"),
    # garbled (an HMI loop, a curious laptop: no challenge, no round trip): the same before stop 28
    ({"step": "prove"}, "server_nonce (64 hex digits) and client_nonce"),
    (dict(_STALE, server_nonce="zz"), "server_nonce (64 hex digits) and client_nonce"),
    (dict(_STALE, server_nonce="ab" * 32 + "\n"), "server_nonce (64 hex digits) and client_nonce"),  # a newline after
])
def test_a_proof_that_tried_no_token_is_not_counted_against_the_operator(linked, proof, refusal):
    """Refused, but not a failed proof: only a MAC compared with the token's and not matching is one."""
    a, b = linked
    controls = FakeInterlock(token=TOKEN)
    sink = _sink(a, controls, limiter=FailureLimiter(max_failures=1, window_s=60.0, cooldown_s=60.0))
    try:
        q = b.declare_querier("millsense/m1/cmd/reset")
        wait_for(lambda: q.matching_status.matching, 5.0, "queryable known")
        q.undeclare()
        replies = list(b.get("millsense/m1/cmd/reset", payload=json.dumps(proof).encode(), timeout=3.0))
        assert replies and replies[0].err is not None
        assert refusal in replies[0].err.payload.to_bytes().decode()
        assert send_command(b, "m1", "reset", TOKEN) == {"ok": True, "interlock": "clear"}
    finally:
        sink.close()


@pytest.mark.parametrize("text", ["1/2/3\n", "١/٢/٣", "1/2/3 "])
def test_a_process_key_is_ascii_digits_and_nothing_after(text):
    """`$` matches before a final newline and `\\d` matches any script's digits: both were taken before stop 28."""
    from millsense.daemon.learning import actions
    from millsense.daemon.learning.keys import KEY_RE
    from millsense.daemon.publish.limits_args import parse_key

    with pytest.raises(ValueError, match="key must be program/tool/operation"):
        parse_key(text)
    assert KEY_RE.match(text) is None
    assert actions.KEY_RE is KEY_RE   # the operator's actions check keys with the same, one pattern
    for pattern in (ca.CLIENT_NONCE_RE, ca.SERVER_NONCE_RE, ca.MAC_RE):
        assert pattern.match("ab" * 32 + "\n") is None
