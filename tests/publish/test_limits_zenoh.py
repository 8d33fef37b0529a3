"""The issue-14 surfaces of ZenohSink on real sessions (loopback, scouting off): `process`, `limits`,
`cmd/limits` and the `context` subscriber.

The Controls here is a small object of the test's own with real behaviour (limits that a widen
really widens, a context log), not the Runner: what is under test is the sink's side of the contract.
"""

from __future__ import annotations

import json
import threading
import time
from types import SimpleNamespace

import pytest
import zenoh

from millsense.daemon.audit import AuditLog
from millsense.daemon.publish.command_auth import CommandError, send_command
from millsense.daemon.publish.sink import ZenohSink

from .helpers import Collector, open_pair, wait_for

pytestmark = pytest.mark.quick

TOKEN = "t0ken-" + "a" * 40
KEY = "1234/12/3"


class LimitsControls:
    """Learned limits of one key and one tool, changed by limits_command as the Runner would."""

    def __init__(self, audit: AuditLog, source: str = "auto") -> None:
        self.settings = SimpleNamespace(interlock=SimpleNamespace(reset="token", token=lambda: TOKEN),
                                        context=SimpleNamespace(source=source))
        self.audit = audit
        self.high_nm = {KEY: 5.0}
        self.tools = {12: {"processes": 7, "wear_pct": 4.0}}
        self.commands: list[tuple[dict, str]] = []
        self.contexts: list[tuple[dict, str]] = []
        self.context_seen = threading.Event()

    def status(self) -> dict:
        return {"state": "running"}

    def config(self) -> dict:
        return {"machine": "m1"}

    def reset(self, requester: str = "") -> dict:
        return {"ok": True, "interlock": "armed"}

    def limits(self) -> dict:
        return {"machine": "m1", "enabled": True,
                "limits": [{"key": k, "state": "active", "high_nm": h} for k, h in self.high_nm.items()],
                "tools": {str(t): dict(v) for t, v in self.tools.items()}}

    def limits_command(self, args: dict, requester: str = "") -> dict:
        self.commands.append((dict(args), requester))
        action, key = args["action"], args.get("key")
        if action == "show":
            if key not in self.high_nm:
                return {"ok": False, "error": f"no limits for {key}"}
            return {"ok": True, "key": key, "high_nm": self.high_nm[key], "mean_nm": [1.0, 2.0, 3.0]}
        if action == "widen":
            if key not in self.high_nm:
                return {"ok": False, "error": f"no limits for {key}"}
            self.high_nm[key] *= 1 + args["pct"] / 100
            return {"ok": True, "high_nm": self.high_nm[key]}
        if action == "new_tool":
            self.tools[args["tool"]] = {"processes": 0, "wear_pct": None}
            return {"ok": True}
        return {"ok": False, "error": f"{action} is not done by this test's controls"}

    def on_context_payload(self, payload: dict, source: str) -> None:
        self.contexts.append((payload, source))
        self.context_seen.set()


class Log:
    """A structlog-like logger that keeps (level, event, fields)."""

    def __init__(self) -> None:
        self.lines: list[tuple[str, str, dict]] = []

    def warning(self, event: str, **fields) -> None:
        self.lines.append(("warning", event, fields))

    def info(self, event: str, **fields) -> None:
        self.lines.append(("info", event, fields))

    def events(self, name: str) -> list[dict]:
        return [f for _, e, f in self.lines if e == name]


@pytest.fixture
def pair(port):
    a, b = open_pair(port)
    yield a, b
    b.close()
    a.close()


@pytest.fixture
def setup(pair, tmp_path):
    a, b = pair
    audit = AuditLog(tmp_path / "audit.log", "m1")
    controls = LimitsControls(audit)
    log = Log()
    sink = ZenohSink(a, "m1", controls, log=log)
    yield sink, controls, b, log, tmp_path / "audit.log"
    sink.close()


def _audit(path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()] if path.exists() else []


def _get(session, key: str, payload: bytes | None = None) -> list[tuple[bool, dict]]:
    querier = session.declare_querier(key, timeout=3.0)
    try:
        wait_for(lambda: querier.matching_status.matching, 5.0, f"the {key} queryable")
        out = []
        for reply in querier.get(payload=payload):
            sample = reply.ok if reply.ok is not None else reply.err
            out.append((reply.ok is not None, json.loads(sample.payload.to_bytes())))
        return out
    finally:
        querier.undeclare()


def test_a_finished_process_is_published_on_process_reliably(setup):
    sink, _, b, _, _ = setup
    got = Collector()
    sub = b.declare_subscriber("millsense/m1/process", got)
    try:
        summary = {"machine": "m1", "t": 1.5, "process": 4, "key": KEY, "program": 1234, "tool": 12, "operation": 3,
                   "revolutions": 40, "energy_j": 812.25, "verdict": "good", "energy_ratio": None}
        # The subscription must be known to the sink's session before the summary goes: publish until it is.
        calls = []

        def warm_up():
            calls.append(1)
            sink.process(dict(summary, process=0))
            return got.payloads()

        wait_for(warm_up, 5.0, "the subscription")
        sink.process(summary)
        wait_for(lambda: summary in got.payloads(), 5.0, "the process summary")
        sample = [s for _, p, s in got.items if p == summary][0]
        assert sample.congestion_control == zenoh.CongestionControl.BLOCK
        assert str(sample.encoding) == "application/json"
        # Every summary handed over went out (those before the subscription was known reached nobody).
        wait_for(lambda: sink.stats()["process_published"] == len(calls) + 1, 5.0, "all counted as published")
        assert sink.stats()["process_dropped"] == 0
    finally:
        sub.undeclare()


def test_process_summaries_after_close_are_counted_as_dropped(setup):
    sink, *_ = setup
    sink.close()
    sink.process({"process": 1})
    assert sink.stats()["process_dropped"] == 1


def test_limits_query_reads_without_a_token(setup):
    _, controls, b, _, audit_path = setup
    (ok, body), = _get(b, "millsense/m1/limits")
    assert ok and body == controls.limits()
    (ok, body), = _get(b, "millsense/m1/limits", json.dumps({"key": KEY}).encode())
    assert ok and body["high_nm"] == 5.0 and body["mean_nm"] == [1.0, 2.0, 3.0]
    (ok, body), = _get(b, "millsense/m1/limits", json.dumps({"key": "9/9/9"}).encode())
    assert not ok and "no limits for 9/9/9" in body["error"]
    (ok, body), = _get(b, "millsense/m1/limits", json.dumps({"key": "12/x"}).encode())
    assert not ok and "program/tool/operation" in body["error"]
    assert [a for a, _ in controls.commands] == [{"action": "show", "key": KEY}, {"action": "show", "key": "9/9/9"}]
    assert _audit(audit_path) == []  # reads leave no audit line


def test_cmd_limits_runs_with_the_token_and_is_audited(setup):
    _, controls, b, _, audit_path = setup
    result = send_command(b, "m1", "limits", TOKEN, {"action": "widen", "key": KEY, "pct": 10}, timeout_s=5.0)
    assert result["ok"] is True and result["action"] == "widen" and result["key"] == KEY
    assert controls.high_nm[KEY] == pytest.approx(5.5)
    (args, requester), = controls.commands
    assert args == {"action": "widen", "key": KEY, "pct": 10} and requester.startswith("zid:")
    (line,) = _audit(audit_path)
    assert line["command"] == "limits" and line["granted"] is True
    assert line["result"]["action"] == "widen" and line["result"]["key"] == KEY and line["result"]["pct"] == 10


def test_cmd_limits_is_refused_without_or_with_a_wrong_token(setup):
    _, controls, b, _, audit_path = setup
    with pytest.raises(CommandError, match="requires a reset token"):
        send_command(b, "m1", "limits", None, {"action": "widen", "key": KEY, "pct": 10}, timeout_s=5.0)
    with pytest.raises(CommandError, match="does not match"):
        send_command(b, "m1", "limits", "wrong-" + "b" * 40, {"action": "widen", "key": KEY, "pct": 10},
                     timeout_s=5.0)
    assert controls.high_nm[KEY] == 5.0 and controls.commands == []
    lines = _audit(audit_path)
    assert lines and lines[0]["command"] == "limits" and lines[0]["granted"] is False
    assert "does not match" in lines[0]["reason"]


def test_cmd_limits_args_are_bound_in_the_mac_and_checked(setup):
    sink, controls, b, _, audit_path = setup
    # Args the daemon refuses by their content: a signed refusal, audited, the Runner never asked.
    with pytest.raises(CommandError, match="pct must be between 1 and 90"):
        send_command(b, "m1", "limits", TOKEN, {"action": "narrow", "key": KEY, "pct": 95}, timeout_s=5.0)
    with pytest.raises(CommandError, match="action must be one of"):
        send_command(b, "m1", "limits", TOKEN, {"action": "forget_everything"}, timeout_s=5.0)
    assert controls.commands == []
    assert [a["granted"] for a in _audit(audit_path)] == [False]  # the second refusal is counted, written later
    # A proof made for other args than those sent fails: the MAC covers them.
    from millsense.daemon.publish.command_auth import command_message, mac_hex

    cn = "c" * 32
    (ok, challenge), = _get(b, "millsense/m1/cmd/limits",
                            json.dumps({"step": "challenge", "client_nonce": cn}).encode())
    sn = challenge["server_nonce"]
    proved = {"action": "widen", "key": KEY, "pct": 10}
    sent = dict(proved, pct=300)
    prove = {"step": "prove", "client_nonce": cn, "server_nonce": sn, "args": sent,
             "mac": mac_hex(TOKEN, command_message("limits", "m1", sn, cn, proved))}
    (ok, body), = _get(b, "millsense/m1/cmd/limits", json.dumps(prove).encode())
    assert not ok and "does not match" in json.loads(body["result"])["error"]
    assert controls.high_nm[KEY] == 5.0 and controls.commands == []


def _context_publisher(b):
    pub = b.declare_publisher("millsense/m1/context")
    wait_for(lambda: pub.matching_status.matching, 5.0, "the daemon's context subscriber")
    return pub


def test_context_good_oversized_and_malformed(setup):
    sink, controls, b, log, _ = setup
    pub = _context_publisher(b)
    try:
        pub.put(b'{"program": 1, "tool": 2, "operation": 3, "pad": "' + b"x" * 5000 + b'"}')
        pub.put(b'{"program": 1234, "tool": ')
        pub.put(b"[1, 2]")
        good = {"program": 1234, "tool": 12, "operation": 3, "cycle": True, "monitor": True, "afc_allowed": False}
        pub.put(json.dumps(good).encode())
        assert controls.context_seen.wait(5.0)
        wait_for(lambda: sink.stats()["context_refused"] == 3, 5.0, "three refusals counted")
        assert controls.contexts == [(good, "zenoh")]
        assert sink.stats()["context_taken"] == 1
        # Logged once for the three (once per 10 s), the first reason named; the rest come at close.
        (first,) = log.events("zenoh.context_refused")
        assert first["count"] == 1 and "over 4096 bytes" in first["last"]
        sink.close()
        last = log.events("zenoh.context_refused")[-1]
        assert last["count"] == 2 and "JSON object" in last["last"]
    finally:
        pub.undeclare()


def test_a_context_flood_ends_with_the_newest_context(setup):
    """Under a flood the ring drops the oldest: whatever was lost, the last context put is the one taken."""
    sink, controls, b, _, _ = setup
    pub = _context_publisher(b)
    try:
        for program in range(500):
            pub.put(json.dumps({"program": program, "tool": 1, "operation": 1}).encode())
        wait_for(lambda: controls.contexts and controls.contexts[-1][0]["program"] == 499, 10.0, "the newest context")
        programs = [c["program"] for c, _ in controls.contexts]
        assert programs == sorted(programs)  # in order, never an older one after a newer
        assert sink.stats()["context_refused"] == 0
    finally:
        pub.undeclare()


def test_no_context_subscriber_when_the_daq_is_the_only_source(pair, tmp_path):
    a, b = pair
    controls = LimitsControls(AuditLog(None, "m1"), source="daq")
    sink = ZenohSink(a, "m1", controls)
    try:
        pub = b.declare_publisher("millsense/m1/context")
        # The status queryable is there (the sink is up and known to b) ...
        wait_for(lambda: _get(b, "millsense/m1/status"), 5.0, "the sink's status")
        time.sleep(0.3)
        # ... and still nobody subscribes to context.
        assert pub.matching_status.matching is False
        pub.undeclare()
    finally:
        sink.close()


def test_watch_shows_the_process_its_band_the_last_summary_and_an_envelope_alarm(millsense_cmd, port):
    """`millsense watch` on a real terminal (a pty) against a sink on a real session: issue 14's fields."""
    import os
    import pty
    import select
    import signal
    import subprocess

    from millsense.daemon.publish.session import open_session

    from .helpers import kill, tcp, zsettings

    session = open_session(zsettings(listen=[tcp(port)]), retry_for_s=0)
    sink = ZenohSink(session, "mch10-01", None)
    master, slave = pty.openpty()
    proc = subprocess.Popen([*millsense_cmd, "watch", "--no-scouting", "--connect", tcp(port), "--seconds", "30"],
                            stdout=slave, stderr=subprocess.PIPE, stdin=subprocess.DEVNULL)
    os.close(slave)
    screen = b""
    try:
        deadline = time.monotonic() + 15
        while b"wear +16.2 %" not in screen or b"envelope_low" not in screen:
            assert time.monotonic() < deadline, f"no live line; terminal got {screen[-400:]!r}"
            sink.estimate({"spindle_rpm": 600.0, "torque_nm": 1.2, "program": 1234, "tool": 12, "operation": 3,
                           "process_rev": 9, "envelope_low_nm": 3.1, "envelope_high_nm": 5.25})
            sink.process({"key": KEY, "verdict": "good", "energy_j": 812.4, "tool_wear_pct": 16.24,
                          "tool_processes": 31, "envelope": "active"})
            sink.alarm({"level": "envelope_low", "quantity": "torque_nm", "value": 1.2, "program": 1234, "tool": 12,
                        "operation": 3, "process": 40, "process_rev": 9, "interlock": "feed_hold"})
            while select.select([master], [], [], 0.1)[0]:
                try:
                    screen += os.read(master, 4096)
                except OSError:
                    break
        last = screen.decode("utf-8", "replace").split("\x1b[2K")[-1]
        assert "T   1.20±– N·m [3.10..5.25]" in last
        assert "P1234 T12 op3 r9" in last
        assert f"last {KEY}: good 812 J wear +16.2 % life 31" in last
        assert f"alarm: envelope_low torque_nm 1.2 {KEY} rev 9 [feed_hold]" in last
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(10) == 0
    finally:
        sink.close()
        kill(proc)
        os.close(master)
        session.close()


def test_peer_tls_example_lets_adapters_put_context_and_operators_run_cmd_limits(tmp_path, port):
    """config/zenoh-tls.json5 (no router): the daemon's own ACL, by certificate CN, for the issue-14 keys."""
    from millsense.daemon.publish.session import open_session

    from .pki import Pki
    from .test_tls import _client, _daemon_config, _from_file

    pki = tmp_path / "pki"
    pki.mkdir()
    ca = Pki(pki)
    for stem, cn in {"daemon": "mch10-01", "hmi": "hmi-01", "operator": "operator-01",
                     "adapter": "cnc-adapter-01"}.items():
        ca.issue(stem, cn)
    daemon = open_session(_from_file(_daemon_config(pki, port)), retry_for_s=0)
    controls = LimitsControls(AuditLog(tmp_path / "audit.log", "mch10-01"))
    sink = ZenohSink(daemon, "mch10-01", controls)
    sessions = []
    try:
        hmi, operator, adapter = (_client(pki, port, s) for s in ("hmi", "operator", "adapter"))
        sessions += [hmi, operator, adapter]
        key = "millsense/mch10-01/context"
        for _ in range(10):  # the viewer's puts: dropped by the daemon's ACL, whenever they come
            hmi.put(key, json.dumps({"program": 6666, "tool": 66, "operation": 6}).encode())
        adapter_pub = adapter.declare_publisher(key)
        wait_for(lambda: adapter_pub.matching_status.matching, 10.0, "the daemon's context subscriber, seen by the adapter")
        adapter_pub.put(json.dumps({"program": 4321, "tool": 7, "operation": 2}).encode())
        assert controls.context_seen.wait(10.0)
        for _ in range(10):
            hmi.put(key, json.dumps({"program": 6666, "tool": 66, "operation": 6}).encode())
        operator.put(key, json.dumps({"program": 4322, "tool": 7, "operation": 2}).encode())
        wait_for(lambda: len(controls.contexts) >= 2, 10.0, "the operator's context")
        assert [c["program"] for c, _ in controls.contexts] == [4321, 4322]
        adapter_pub.undeclare()

        # cmd/limits: not for viewers, even with the token; operators with it
        assert [r for r in hmi.get("millsense/mch10-01/cmd/limits", payload=b"{}", timeout=1.0)] == []
        with pytest.raises(CommandError):
            send_command(hmi, "mch10-01", "limits", TOKEN, {"action": "new_tool", "tool": 7}, timeout_s=1.0)
        assert controls.commands == []
        assert send_command(operator, "mch10-01", "limits", TOKEN, {"action": "new_tool", "tool": 7})["ok"] is True
        # the limits read: for viewers too
        (reply,) = [r for r in hmi.get("millsense/mch10-01/limits", timeout=3.0)]
        assert json.loads(reply.ok.payload.to_bytes())["tools"]["7"] == {"processes": 0, "wear_pct": None}
    finally:
        sink.close()
        for s in sessions:
            s.close()
        daemon.close()


# -- issue 36: no non-finite number gets in (Python's json takes NaN, Infinity and 1e999 as floats) -------------

@pytest.mark.parametrize("policy", ["token", "open"])
@pytest.mark.parametrize("literal", ["NaN", "Infinity", "-Infinity", "1e999"])
def test_cmd_limits_refuses_json_nan_and_infinity_with_a_clear_message(pair, tmp_path, policy, literal):
    from millsense.daemon.publish.command_auth import command_message, mac_hex

    a, b = pair
    audit_path = tmp_path / "audit.log"
    controls = LimitsControls(AuditLog(audit_path, "m1"))
    controls.settings.interlock.reset = policy
    sink = ZenohSink(a, "m1", controls, log=Log())
    try:
        cn = "d" * 32
        (ok, challenge), = _get(b, "millsense/m1/cmd/limits",
                                json.dumps({"step": "challenge", "client_nonce": cn}).encode())
        assert ok and challenge["policy"] == policy
        sn = challenge["server_nonce"]
        # the proof as a peer could make it: over the args with a whole number, then the number swapped
        mac = mac_hex(TOKEN, command_message("limits", "m1", sn, cn, {"action": "widen", "key": KEY, "pct": 10}))
        text = (f'{{"step": "prove", "client_nonce": "{cn}", "server_nonce": "{sn}", '
                f'"args": {{"action": "widen", "key": "{KEY}", "pct": {literal}}}, "mac": "{mac}"}}')
        (ok, body), = _get(b, "millsense/m1/cmd/limits", text.encode())
        assert not ok, body
        error = json.loads(body["result"])["error"]
        # token: the MAC's canonical JSON takes no such number; open: a widen never passes over Zenoh (issue 36,
        # finding 3), whatever its args (the local socket, below, is where it goes and where they are checked)
        assert error == ("payload: args may not hold fractional numbers (use an integer in a stated unit)"
                         if policy == "token" else
                         'limits widen needs the reset token over the network, and m1 has none (reset = "open" '
                         "lets anyone clear or test a hold, nothing more): at the machine, as root or the daemon's "
                         "user, add --local (the daemon's control socket: no token needed there)"), error
        assert controls.commands == [] and controls.high_nm[KEY] == 5.0
    finally:
        sink.close()


@pytest.mark.parametrize("literal", ["NaN", "Infinity", "-Infinity", "1e999"])
def test_the_local_socket_refuses_json_nan_and_infinity_with_a_clear_message(tmp_path, literal):
    """Where a limits change goes under "open": the control socket's one args check names what is wrong."""
    import os
    import socket

    from millsense.daemon.local_socket import socket_path
    from millsense.daemon.runtime.local_control import LocalControl

    controls = LimitsControls(AuditLog(tmp_path / "audit.log", "m1"))
    server = LocalControl(tmp_path / "state", controls, allowed_uids=(os.getuid(),))
    assert server.start()
    try:
        line = f'{{"command": "limits", "args": {{"action": "widen", "key": "{KEY}", "pct": {literal}}}}}\n'
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
            sock.settimeout(30.0)
            sock.connect(str(socket_path(tmp_path / "state")))
            sock.sendall(line.encode())
            reply = json.loads(sock.makefile("rb").readline())
        assert reply == {"ok": False, "error": f"pct must be a finite whole number, not {float(literal)!r}"}, reply
        assert controls.commands == [] and controls.high_nm[KEY] == 5.0
    finally:
        server.close()
