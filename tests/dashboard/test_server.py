"""The dashboard server without a browser: bounds, discovery, and what the reset relay refuses.

Real Zenoh sessions on loopback (scouting off), a real HTTP server on a free port.
"""

from __future__ import annotations

import json
import threading
import urllib.error
import urllib.request

import pytest
import zenoh

from millsense.daemon.dashboard import book as book_mod
from millsense.daemon.dashboard.book import Book
from millsense.daemon.publish.alarm_state import ActiveAlarms
from millsense.daemon.dashboard.server import DashboardServer
from millsense.daemon.dashboard.zenoh_side import ZenohSide
from tests.conftest import free_tcp_port
from tests.e2e.helpers import tcp, wait_for

pytestmark = pytest.mark.quick


def _session(listen=None, connect=None):
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", json.dumps(listen or []))
    conf.insert_json5("connect/endpoints", json.dumps(connect or []))
    return zenoh.open(conf)


@pytest.fixture
def dashboard():
    """(server, publisher session): a dashboard on 127.0.0.1 and a peer that plays the daemons.
    `server.zenoh_port`: the dashboard session's Zenoh listener."""
    port = free_tcp_port()
    dash_session = _session(listen=[tcp(port)])
    pub = _session(connect=[tcp(port)])
    book = Book()
    side = ZenohSide(dash_session, book)
    server = DashboardServer(("127.0.0.1", 0), book, side, https=False)
    server.zenoh_port = port  # where another peer (an impostor) joins the dashboard's session
    thread = threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True)
    thread.start()
    try:
        yield server, pub
    finally:
        server.shutdown()
        server.server_close()
        side.close()
        pub.close()
        dash_session.close()


def _url(server, path):
    return f"http://127.0.0.1:{server.server_address[1]}{path}"


def _get(server, path):
    with urllib.request.urlopen(_url(server, path), timeout=10) as r:
        return json.loads(r.read())


def _post(server, path, body: bytes, headers=None):
    req = urllib.request.Request(_url(server, path), data=body, method="POST",
                                 headers={"Content-Type": "application/json", **(headers or {})})
    try:
        with urllib.request.urlopen(req, timeout=10) as r:
            return r.status, json.loads(r.read())
    except urllib.error.HTTPError as exc:
        return exc.code, json.loads(exc.read())


def _machine(server, name):
    return next((m for m in _get(server, "/api/snapshot")["machines"] if m["machine"] == name), None)


def test_a_machine_is_found_by_liveliness_and_comes_back_after_a_restart(dashboard):
    server, pub = dashboard
    token = pub.liveliness().declare_token("millsense/m-1/alive")
    wait_for(lambda: (_machine(server, "m-1") or {}).get("alive"), 10, "m-1 alive")
    token.undeclare()
    wait_for(lambda: _machine(server, "m-1")["alive"] is False, 10, "m-1 gone")
    assert _machine(server, "m-1")["gone_since"] is not None
    token = pub.liveliness().declare_token("millsense/m-1/alive")  # the daemon restarted
    wait_for(lambda: _machine(server, "m-1")["alive"], 10, "m-1 alive again")
    token.undeclare()


def test_publications_reach_the_snapshot_cut_to_the_drawn_fields(dashboard):
    server, pub = dashboard
    est = {"machine": "m-2", "rev": 7, "t": 1.0, "valid": True, "torque_nm": 4.2, "samples": 100, "big": "x" * 500}
    wait_for(lambda: (pub.put("millsense/m-2/estimate", json.dumps(est)) or True) and _machine(server, "m-2"), 10,
             "m-2 estimate seen")
    kept = _machine(server, "m-2")["estimates"][0]
    assert kept["torque_nm"] == 4.2 and kept["rev"] == 7
    assert "big" not in kept and "samples" not in kept
    pub.put("millsense/m-2/alarm", b'{"level": "overload", "value": NaN}')
    got = wait_for(lambda: _get(server, "/api/snapshot")["recent_alarms"], 10, "the alarm")
    assert got[0]["machine"] == "m-2" and got[0]["level"] == "overload" and got[0]["value"] is None


def test_a_dashboard_that_missed_an_alarm_lists_it_from_the_status(dashboard):
    """The daemon's overload went out before this dashboard heard the daemon: the next status lists it
    (`active_alarms`), and the page gets it once; cleared while away, it gets the clear."""
    server, pub = dashboard
    table = ActiveAlarms()
    missed = table.stamp({"machine": "m-3", "t": 5.0, "rev": 40, "level": "overload", "quantity": "torque_nm",
                          "value": 31.7, "limit": 30.0, "interlock": "feed_hold"})

    def status():
        return json.dumps({"machine": "m-3", "t": 6.0, "state": "running", "alarm": "overload", **table.snapshot()})

    def alarms():
        return [a for a in _get(server, "/api/snapshot")["recent_alarms"] if a["machine"] == "m-3"]

    got = wait_for(lambda: (pub.put("millsense/m-3/status", status()) or True) and alarms(), 10, "the missed alarm")
    assert [(a["level"], a["rev"], a["value"]) for a in got] == [("overload", 40, 31.7)]
    pub.put("millsense/m-3/alarm", json.dumps(missed))  # the publication, late: not listed twice
    pub.put("millsense/m-3/status", status())
    table.stamp({"machine": "m-3", "t": 7.0, "rev": 45, "level": "clear", "quantity": "torque_nm", "value": 1.0,
                 "limit": 30.0, "interlock": "feed_hold"})  # missed too
    got = wait_for(lambda: (pub.put("millsense/m-3/status", status()) or True) and len(alarms()) > 1 and alarms(),
                   10, "the clear")
    assert [a["level"] for a in got] == ["overload", "clear"], got
    assert got[1]["was"] == "overload" and "was" not in got[0]  # the page says "clear torque_nm (was overload, ...)"


def test_memory_is_bounded_per_machine_and_in_machines():
    book = Book()
    for i in range(book_mod.ESTIMATES_PER_MACHINE + 50):
        book.publication("m", "estimate", {"rev": i, "t": float(i)})
    kept = book.snapshot()["machines"][0]["estimates"]
    assert len(kept) == book_mod.ESTIMATES_PER_MACHINE and kept[-1]["rev"] == book_mod.ESTIMATES_PER_MACHINE + 49
    for i in range(book_mod.MAX_MACHINES + 5):
        book.alive(f"x{i}", True)
    assert len(book.machines) == book_mod.MAX_MACHINES and book.ignored_machines == 6
    client = book.subscribe()
    for i in range(book_mod.CLIENT_QUEUE + 3):
        book.publication("m", "estimate", {"rev": i, "t": float(i)})
    updates = client.take(0)
    assert len(updates) == book_mod.CLIENT_QUEUE and client.dropped == 3
    assert updates[-1]["payload"]["rev"] == book_mod.CLIENT_QUEUE + 2


def test_the_relay_forwards_only_the_two_reset_steps(dashboard):
    server, _ = dashboard
    h = {"X-Millsense": "reset"}
    good = json.dumps({"step": "challenge", "client_nonce": "ab" * 16}).encode()
    assert _post(server, "/api/reset/m-1", good)[0] == 403  # no header: another site's form
    status, body = _post(server, "/api/reset/m-1", json.dumps({"step": "challenge", "client_nonce": "ab" * 16,
                                                               "args": {"action": "on"}}).encode(), h)
    assert status == 400 and "args" in body["error"]
    status, body = _post(server, "/api/reset/m-1", json.dumps({"step": "prove", "client_nonce": "ab" * 16,
                                                               "server_nonce": "cd" * 32, "args": {"x": 1},
                                                               "mac": "00" * 32}).encode(), h)
    assert status == 400 and "no args" in body["error"]
    assert _post(server, "/api/reset/a%2Fb", good, h)[0] == 400
    assert _post(server, "/api/reset/m-1", b"x" * 5000, h)[0] == 413
    assert _post(server, "/api/reset/m-1", b"{not json", h)[0] == 400
    status, body = _post(server, "/api/reset/m-1", good, h)  # well formed: relayed, nobody answers
    assert status == 200 and body["replies"] == []


def test_the_relay_hands_the_page_every_program_that_answers_as_the_machine(dashboard):
    """Issue 36, finding 6: an impostor answering on `cmd/reset` beside the daemon must reach the page, which then
    sends no proof ("several programs answer"). Zenoh's default query (the best-matching queryable, answers
    consolidated) handed the relay one of the two."""
    server, daemon_like = dashboard
    impostor = _session(connect=[tcp(server.zenoh_port)])

    def answer(nonce):
        def handler(query):
            body = {"step": "challenge", "machine": "m-1", "command": "reset", "policy": "open",
                    "server_nonce": nonce, "expires_s": 10}
            query.reply(query.key_expr, json.dumps(body).encode())
        return handler

    queryables = [daemon_like.declare_queryable("millsense/m-1/cmd/reset", answer("aa" * 32)),
                  impostor.declare_queryable("millsense/m-1/cmd/reset", answer("bb" * 32))]
    try:
        challenge = json.dumps({"step": "challenge", "client_nonce": "ab" * 16}).encode()

        def both():
            status, body = _post(server, "/api/reset/m-1", challenge, {"X-Millsense": "reset"})
            assert status == 200, body
            return sorted(r["body"]["server_nonce"] for r in body["replies"]) == ["aa" * 32, "bb" * 32]
        wait_for(both, 10, "the relay hands over both programs' answers")
    finally:
        for q in queryables:
            q.undeclare()
        impostor.close()


def test_the_reset_is_not_offered_over_plain_http_off_localhost():
    book = Book()
    server = DashboardServer(("0.0.0.0", 0), book, relay=None, https=False)
    thread = threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True)
    thread.start()
    try:
        assert _get(server, "/api/info")["reset_offered"] is False
        status, body = _post(server, "/api/reset/m-1", b'{"step": "challenge"}', {"X-Millsense": "reset"})
        assert status == 403 and "HTTPS" in body["error"]
    finally:
        server.shutdown()
        server.server_close()


def test_a_loopback_dashboard_answers_only_to_a_loopback_host(dashboard):
    server, _ = dashboard
    req = urllib.request.Request(_url(server, "/api/snapshot"), headers={"Host": "attacker.example:80"})
    with pytest.raises(urllib.error.HTTPError) as refused:
        urllib.request.urlopen(req, timeout=10)
    assert refused.value.code == 421
    for host in ("localhost:8470", "127.0.0.1", "[::1]:8470"):
        req = urllib.request.Request(_url(server, "/api/info"), headers={"Host": host})
        with urllib.request.urlopen(req, timeout=10) as r:
            assert r.status == 200
