"""`cmd/afc` on real Zenoh sessions (loopback, scouting off) and `afc` on the real local control socket.

The Controls here is the test's own small object around a real FeedController (the Runner's
afc_command contract: args {"action"}, reply {"ok", "afc", "reason"?}); what is under test is the
surfaces' side: authorisation with the action bound in the MAC, the audit trail, the args check,
and the local socket's peer-uid rule.
"""

from __future__ import annotations

import json
import os
import secrets
from types import SimpleNamespace

import pytest

from millsense.daemon.audit import AuditLog
from millsense.daemon.config.models import AfcSettings
from millsense.daemon.afc.controller import FeedController
from millsense.daemon.local_socket import local_command
from millsense.daemon.runtime.local_control import LocalControl
from millsense.daemon.publish.command_auth import CommandError, command_message, exchange, mac_hex
from millsense.daemon.publish.sink import ZenohSink

from .helpers import open_pair, wait_for

pytestmark = pytest.mark.quick

TOKEN = "afc-t0ken-" + "c" * 40


class AfcControls:
    """A daemon's `afc_command` as the Runner does it, around a real controller."""

    def __init__(self, audit: AuditLog) -> None:
        self.settings = SimpleNamespace(interlock=SimpleNamespace(reset="token", token=lambda: TOKEN),
                                        context=SimpleNamespace(source="off"))
        self.audit = audit
        self.feed = FeedController(AfcSettings())
        self.calls: list[tuple[dict, str]] = []
        self.faults: list[tuple[str, str]] = []

    def status(self) -> dict:
        return {"state": "running", "afc": self.feed.status()}

    def config(self) -> dict:
        return {"machine": "m1"}

    def reset(self, requester: str = "") -> dict:
        return {"ok": True}

    def fault(self, name: str, detail: str, **_: object) -> None:
        self.faults.append((name, detail))

    def afc_command(self, args: dict, requester: str = "") -> dict:
        self.calls.append((dict(args), requester))
        action = args["action"]
        if action == "on" and not self.feed.available:
            return {"ok": False, "reason": "this DAQ has no feed-override output", "afc": self.feed.status()}
        if action in ("on", "off"):
            self.feed.switch(action == "on", 0.0)
        return {"ok": True, "afc": self.feed.status()}


@pytest.fixture
def setup(port, tmp_path):
    a, b = open_pair(port)
    audit = AuditLog(tmp_path / "audit.log", "m1")
    controls = AfcControls(audit)
    sink = ZenohSink(a, "m1", controls)
    yield controls, b, tmp_path / "audit.log"
    sink.close()
    b.close()
    a.close()


def _audit(path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()] if path.exists() else []


def test_cmd_afc_on_and_off_with_the_token_are_done_and_audited(setup):
    controls, b, audit_path = setup
    result = exchange(b, "m1", "afc", TOKEN, {"action": "on"}, timeout_s=5.0).result
    assert result["ok"] is True and result["action"] == "on"
    assert result["afc"]["enabled"] is True and controls.feed.enabled
    result = exchange(b, "m1", "afc", TOKEN, {"action": "off"}, timeout_s=5.0).result
    assert result["ok"] is True and result["afc"]["state"] == "off" and not controls.feed.enabled
    assert [a for a, _ in controls.calls] == [{"action": "on"}, {"action": "off"}]
    assert all(r.startswith("zid:") for _, r in controls.calls)
    lines = _audit(audit_path)
    assert [(x["command"], x["granted"], x["result"]["action"]) for x in lines] == [("afc", True, "on"),
                                                                                    ("afc", True, "off")]
    assert lines[0]["requester"].startswith("zid:")


def test_cmd_afc_is_refused_without_or_with_a_wrong_token_and_the_refusal_audited(setup):
    controls, b, audit_path = setup
    with pytest.raises(CommandError, match="requires a reset token"):
        exchange(b, "m1", "afc", None, {"action": "on"}, timeout_s=5.0)
    with pytest.raises(CommandError, match="does not match"):
        exchange(b, "m1", "afc", "wrong-" + "d" * 40, {"action": "on"}, timeout_s=5.0)
    assert controls.calls == [] and not controls.feed.enabled
    (line,) = _audit(audit_path)
    assert line["command"] == "afc" and line["granted"] is False and "does not match" in line["reason"]


def test_the_action_is_bound_in_the_mac(setup):
    """A proof made for "off" cannot switch AFC on: the daemon checks the MAC over the args it runs."""
    controls, b, audit_path = setup
    querier = b.declare_querier("millsense/m1/cmd/afc", timeout=5.0)
    try:
        wait_for(lambda: querier.matching_status.matching, 5.0, "the cmd/afc queryable")
        cn = secrets.token_hex(16)

        def ask(request: dict) -> tuple[bool, dict]:
            (reply,) = list(querier.get(payload=json.dumps(request).encode()))
            sample = reply.ok if reply.ok is not None else reply.err
            return reply.ok is not None, json.loads(sample.payload.to_bytes())

        ok, challenge = ask({"step": "challenge", "client_nonce": cn})
        assert ok and challenge["command"] == "afc" and challenge["policy"] == "token"
        sn = challenge["server_nonce"]
        mac_for_off = mac_hex(TOKEN, command_message("afc", "m1", sn, cn, {"action": "off"}))
        ok, body = ask({"step": "prove", "client_nonce": cn, "server_nonce": sn, "args": {"action": "on"},
                        "mac": mac_for_off})
        assert not ok and "does not match" in json.loads(body["result"])["error"]
    finally:
        querier.undeclare()
    assert controls.calls == [] and not controls.feed.enabled
    assert [x["granted"] for x in _audit(audit_path)] == [False]


def test_cmd_afc_status_and_bad_args(setup):
    controls, b, audit_path = setup
    result = exchange(b, "m1", "afc", TOKEN, {"action": "status"}, timeout_s=5.0).result
    assert result["ok"] is True and result["afc"]["state"] == "off" and result["afc"]["override_pct"] == 100.0
    for bad, says in (({"action": "faster"}, "action must be one of"), ({"action": "on", "pct": 120}, "only")):
        with pytest.raises(CommandError, match=says):
            exchange(b, "m1", "afc", TOKEN, bad, timeout_s=5.0)
    assert [a for a, _ in controls.calls] == [{"action": "status"}] and not controls.feed.enabled
    # refusals are written at most once per 10 s (with a count): the first is there, with its reason
    granted, refused = _audit(audit_path)
    assert granted["granted"] is True and granted["result"]["action"] == "status"
    assert refused["granted"] is False and "action must be one of" in refused["reason"]


def test_a_refusal_of_the_daemon_is_said_with_its_reason(setup):
    controls, b, _ = setup
    controls.feed.set_available(False)
    result = exchange(b, "m1", "afc", TOKEN, {"action": "on"}, timeout_s=5.0).result
    assert result["ok"] is False and "no feed-override output" in result["error"]
    assert result["afc"]["state"] == "unavailable" and not controls.feed.enabled


# ---- the local control socket -----------------------------------------------------------------
@pytest.fixture
def local(tmp_path):
    def start(allowed_uids: tuple[int, ...]):
        controls = AfcControls(AuditLog(tmp_path / "audit.log", "m1"))
        server = LocalControl(tmp_path / "state", controls, allowed_uids=allowed_uids)
        assert server.start(), controls.faults
        servers.append(server)
        return controls

    servers: list[LocalControl] = []
    yield start
    for s in servers:
        s.close()


def test_local_afc_switches_for_the_daemons_uid_and_is_audited(local, tmp_path):
    controls = local((os.getuid(),))
    state = tmp_path / "state"
    reply = local_command(state, "afc", 5.0, args={"action": "on"})
    assert reply["ok"] is True and reply["afc"]["enabled"] is True and controls.feed.enabled
    reply = local_command(state, "afc", 5.0, args={"action": "status"})
    assert reply["ok"] is True and reply["afc"]["enabled"] is True
    reply = local_command(state, "afc", 5.0, args={"action": "off"})
    assert reply["ok"] is True and not controls.feed.enabled
    reply = local_command(state, "afc", 5.0, args={"action": "up"})
    assert reply["ok"] is False and "action must be one of" in reply["error"]
    lines = _audit(tmp_path / "audit.log")
    # status reads leave no line; on, off and the bad request do
    assert [(x["command"], x["granted"]) for x in lines] == [("afc", True), ("afc", True), ("afc", False)]
    assert [x["result"]["action"] for x in lines[:2]] == ["on", "off"]
    assert lines[0]["requester"] == lines[1]["requester"] and lines[0]["requester"].startswith(
        f"local uid={os.getuid()} ")


def test_local_afc_is_refused_for_a_uid_it_does_not_know(local, tmp_path):
    controls = local((os.getuid() + 4242,))
    reply = local_command(tmp_path / "state", "afc", 5.0, args={"action": "on"})
    assert reply["ok"] is False and "may not command" in reply["error"]
    assert controls.calls == [] and not controls.feed.enabled
    (line,) = _audit(tmp_path / "audit.log")
    assert line["command"] == "afc" and line["granted"] is False


class _Dribbler:
    """A client of the local socket that sends a byte every `every_s` and never a whole line (a slow loris)."""

    def __init__(self, path, every_s: float = 0.3):
        import socket
        import threading

        self.sock = socket.socket(socket.AF_UNIX)
        self.sock.connect(str(path))
        self.stop = threading.Event()
        self.cut = threading.Event()      # the daemon closed it (or answered it)
        self.reply = b""
        self.thread = threading.Thread(target=self._run, args=(every_s,), daemon=True)
        self.thread.start()

    def _run(self, every_s: float) -> None:
        self.sock.settimeout(every_s)
        while not self.stop.is_set():
            try:
                self.sock.send(b" ")
                data = self.sock.recv(4096)
                self.reply += data
                if not data:
                    break
            except TimeoutError:
                continue
            except OSError:
                break
            if b"\n" in self.reply:
                break
        self.cut.set()

    def close(self) -> None:
        self.stop.set()
        self.thread.join(5.0)
        self.sock.close()


def test_a_client_that_dribbles_its_request_is_cut_off_and_the_next_is_served(local, tmp_path):
    """A byte a second, never a newline, held the one server thread for as long as it went on (a probe of stop 26):
    `millsense reset --local` at the machine timed out behind it. The whole request must now come within
    READ_DEADLINE_S of the connection."""
    from millsense.daemon.local_socket import SOCKET_NAME

    controls = local((os.getuid(),))
    state = tmp_path / "state"
    loris = _Dribbler(state / SOCKET_NAME)
    try:
        wait_for(lambda: loris.reply or loris.thread.is_alive(), 2.0, "the dribbler connected")
        reply = local_command(state, "afc", 8.0, args={"action": "status"})   # behind the dribbler
        assert reply["ok"] is True
        assert loris.cut.wait(5.0) and not loris.stop.is_set(), "the dribbler was cut off by the daemon"
    finally:
        loris.close()
    lines = _audit(tmp_path / "audit.log")
    assert any(x["command"] == "?" and not x["granted"] and "no complete request" in x["reason"] for x in lines), lines


def test_a_uid_that_may_not_command_is_refused_without_waiting_for_its_request(local, tmp_path):
    from millsense.daemon.local_socket import SOCKET_NAME

    local((os.getuid() + 4242,))
    loris = _Dribbler(tmp_path / "state" / SOCKET_NAME)
    try:
        assert loris.cut.wait(5.0), "refused at once"
        assert b"may not command" in loris.reply
    finally:
        loris.close()
    (line,) = _audit(tmp_path / "audit.log")
    assert line["command"] == "?" and line["granted"] is False
