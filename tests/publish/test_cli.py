"""`millsense watch`, `reset` and `token` as real subprocesses against sessions in the test."""

from __future__ import annotations

import json
import os
import pty
import re
import select
import signal
import stat
import subprocess
import time

import pytest

from millsense.daemon.publish.session import open_session
from millsense.daemon.publish.sink import ZenohSink

from .helpers import FakeInterlock, LineReader, kill, tcp, zsettings


@pytest.fixture
def daemon_session(port):
    """The daemon's side: a peer listening on loopback."""
    s = open_session(zsettings(listen=[tcp(port)]), retry_for_s=0)
    yield s
    s.close()


def _watch(millsense_cmd, port, *extra):
    return subprocess.Popen(
        [*millsense_cmd, "watch", "--no-scouting", "--connect", tcp(port), *extra],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )


def test_watch_json_shows_presence_estimates_alarms_and_departure(millsense_cmd, port, daemon_session):
    sink = ZenohSink(daemon_session, "mch10-01", None)
    proc = _watch(millsense_cmd, port, "--json", "--seconds", "30")
    try:
        out = LineReader(proc)
        alive = out.wait_json(lambda o: o["kind"] == "alive", 15.0, "alive (liveliness history)")
        assert alive == {"key": "millsense/mch10-01/alive", "kind": "alive", "payload": {"machine": "mch10-01"}}

        # The watcher's subscriptions reach us a moment after its token query: publish until seen.
        deadline = time.monotonic() + 10
        rev = 0
        while True:
            rev += 1
            sink.estimate({"machine": "mch10-01", "rev": rev, "torque_nm": float("nan"), "force_n": 452.6})
            try:
                est = out.wait_json(lambda o: o["kind"] == "estimate", 0.2, "estimate")
                break
            except AssertionError:
                if time.monotonic() > deadline:
                    raise
        assert est["key"] == "millsense/mch10-01/estimate"
        assert est["payload"]["torque_nm"] is None and est["payload"]["force_n"] == 452.6

        sink.alarm({"machine": "mch10-01", "level": "overload", "quantity": "torque_nm", "value": 31.7, "limit": 30.0, "interlock": "feed_hold"})
        alarm = out.wait_json(lambda o: o["kind"] == "alarm", 5.0, "alarm")
        assert alarm["payload"]["level"] == "overload" and alarm["payload"]["interlock"] == "feed_hold"

        sink.status({"state": "running"})
        assert out.wait_json(lambda o: o["kind"] == "status", 5.0, "status")["payload"] == {"state": "running"}

        sink.close()
        gone = out.wait_json(lambda o: o["kind"] == "gone", 5.0, "gone after the sink closed")
        assert gone["key"] == "millsense/mch10-01/alive"

        proc.send_signal(signal.SIGTERM)
        assert proc.wait(10) == 0
        assert "Traceback" not in proc.stderr.read()
    finally:
        sink.close()
        kill(proc)


def test_watch_filters_by_machine(millsense_cmd, port, daemon_session):
    other = ZenohSink(daemon_session, "other", None)
    mine = ZenohSink(daemon_session, "mine", None)
    proc = _watch(millsense_cmd, port, "--machine", "mine", "--seconds", "30")  # piped: JSON without --json
    try:
        out = LineReader(proc)
        out.wait_json(lambda o: o["kind"] == "alive", 15.0, "alive")
        deadline = time.monotonic() + 10
        while True:
            other.estimate({"rev": 1})
            mine.estimate({"rev": 2})
            try:
                out.wait_json(lambda o: o["kind"] == "estimate", 0.2, "estimate")
                break
            except AssertionError:
                if time.monotonic() > deadline:
                    raise
        time.sleep(0.3)
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(10) == 0
        rest = [json.loads(line) for line in out.seen]
        while not out.lines.empty():
            rest.append(json.loads(out.lines.get()))
        assert {o["key"].split("/")[1] for o in rest} == {"mine"}
    finally:
        other.close()
        mine.close()
        kill(proc)


def test_watch_stops_by_itself_after_seconds(millsense_cmd, port, daemon_session):
    started = time.monotonic()
    proc = _watch(millsense_cmd, port, "--seconds", "1")
    try:
        assert proc.wait(20) == 0
        assert time.monotonic() - started >= 1.0
    finally:
        kill(proc)


def test_watch_bad_machine_id_is_a_usage_error(millsense_cmd, port):
    proc = subprocess.run([*millsense_cmd, "watch", "--machine", "a/b", "--seconds", "1"], capture_output=True, text=True, timeout=30)
    assert proc.returncode == 2
    assert "--machine 'a/b'" in proc.stderr and "Traceback" not in proc.stderr


TOKEN = "Hk3vQ9xW2mPz7LcN5tRb8yFd4sGj6aUe1oKi0nVw_-E"


def _reset(millsense_cmd, port, *extra, timeout=30, token_env=None):
    env = {k: v for k, v in os.environ.items() if k != "MILLSENSE_RESET_TOKEN"}
    if token_env is not None:
        env["MILLSENSE_RESET_TOKEN"] = token_env
    return subprocess.run(
        [*millsense_cmd, "reset", "--no-scouting", "--connect", tcp(port), *extra],
        capture_output=True, text=True, timeout=timeout, env=env,
    )


@pytest.mark.quick
def test_reset_gets_the_daemons_verified_reply(millsense_cmd, port, daemon_session, tmp_path):
    controls = FakeInterlock(token=TOKEN)
    sink = ZenohSink(daemon_session, "mch10-01", controls)
    try:
        token_file = tmp_path / "token"
        token_file.write_text(TOKEN + "\n")
        proc = _reset(millsense_cmd, port, "--machine", "mch10-01", "--token-file", str(token_file))
        assert proc.returncode == 0, proc.stderr
        assert json.loads(proc.stdout) == {"ok": True, "interlock": "clear"}
        assert len(controls.requesters) == 1 and not controls.latched
        assert "cannot be verified" not in proc.stderr
        # the token from the environment, so that it is not on a command line
        controls.latched = True
        proc = _reset(millsense_cmd, port, "--machine", "mch10-01", token_env=TOKEN)
        assert proc.returncode == 0, proc.stderr
        assert len(controls.requesters) == 2 and not controls.latched
    finally:
        sink.close()


@pytest.mark.quick
def test_reset_refused_exits_1_with_the_reason(millsense_cmd, port, daemon_session):
    controls = FakeInterlock(token=TOKEN)
    sink = ZenohSink(daemon_session, "mch10-01", controls)
    try:
        # the daemon's refusal is signed with its token, which the requester's wrong one cannot verify: it is
        # said, but as an unknown outcome (exit 3), since a forged refusal would read the same
        proc = _reset(millsense_cmd, port, "--machine", "mch10-01", "--token", "guess-" + TOKEN)
        assert proc.returncode == 3
        assert "mch10-01 refused reset: the proof does not match (wrong or missing reset token)" in proc.stderr
        assert "the outcome is unknown" in proc.stderr and "Either the token is wrong" in proc.stderr
        assert controls.latched

        proc = _reset(millsense_cmd, port, "--machine", "mch10-01")
        assert proc.returncode == 1
        assert "mch10-01 requires a reset token for reset and none was given" in proc.stderr

        controls.fail_with = PermissionError("interlock disabled in config")
        proc = _reset(millsense_cmd, port, "--machine", "mch10-01", token_env=TOKEN)
        assert proc.returncode == 1
        assert json.loads(proc.stdout) == {"ok": False, "error": "PermissionError: interlock disabled in config"}
        assert "refused the reset: PermissionError: interlock disabled in config" in proc.stderr
        assert "Traceback" not in proc.stderr
    finally:
        sink.close()


def test_reset_without_machine_asks_the_only_daemon_alive(millsense_cmd, port, daemon_session):
    controls = FakeInterlock(token=TOKEN)
    sink = ZenohSink(daemon_session, "solo", controls)
    try:
        proc = _reset(millsense_cmd, port, token_env=TOKEN)
        assert proc.returncode == 0, proc.stderr
        assert json.loads(proc.stdout)["interlock"] == "clear"
        assert len(controls.requesters) == 1
        assert f"millsense reset: machine solo (the only daemon on {tcp(port)})" in proc.stderr  # said, not guessed
        second = ZenohSink(daemon_session, "duo", FakeInterlock(token=TOKEN))
        try:
            proc = _reset(millsense_cmd, port, token_env=TOKEN)
            assert proc.returncode == 1
            assert "several daemons are alive (duo, solo); choose one with --machine" in proc.stderr
        finally:
            second.close()
    finally:
        sink.close()


def test_reset_open_daemon_answer_is_marked_unverifiable(millsense_cmd, port, daemon_session):
    controls = FakeInterlock(token=None)  # policy "open"
    sink = ZenohSink(daemon_session, "mch10-01", controls)
    try:
        proc = _reset(millsense_cmd, port, "--machine", "mch10-01")
        assert proc.returncode == 0, proc.stderr
        assert json.loads(proc.stdout)["interlock"] == "clear"
        assert 'takes commands from anyone (reset = "open"): this answer cannot be verified' in proc.stderr
    finally:
        sink.close()


class _FakeDaemon:
    """Finding 1: a program that declares `cmd/reset` and an `alive` token, records what it gets, says ok."""

    def __init__(self, session, machine, challenge_policy=None):
        self.payloads: list[bytes] = []
        self.policy = challenge_policy
        self.q = session.declare_queryable(f"millsense/{machine}/cmd/reset", self._on)
        self.alive = session.liveliness().declare_token(f"millsense/{machine}/alive")
        self.machine = machine

    def _on(self, query):
        data = query.payload.to_bytes() if query.payload is not None else b""
        self.payloads.append(data)
        req = json.loads(data) if data.startswith(b"{") else {}
        if self.policy and req.get("step") == "challenge":
            body = {"step": "challenge", "machine": self.machine, "command": "reset", "policy": self.policy,
                    "server_nonce": "e" * 64, "expires_s": 10}
        elif self.policy == "token":  # a well-formed success, with a MAC it cannot compute
            body = {"result": json.dumps({"ok": True, "interlock": "clear"}), "server_mac": "0" * 64}
        else:
            body = {"ok": True, "interlock": "clear"}
        query.reply(f"millsense/{self.machine}/cmd/reset", json.dumps(body).encode())

    def close(self):
        self.alive.undeclare()
        self.q.undeclare()


@pytest.mark.parametrize("policy", [None, "open", "token"])
def test_reset_to_a_fake_daemon_sends_no_token_and_fails(millsense_cmd, port, daemon_session, policy):
    fake = _FakeDaemon(daemon_session, "mch10-01", policy)
    try:
        proc = _reset(millsense_cmd, port, token_env=TOKEN)  # no --machine: it picks the only one alive
    finally:
        fake.close()
    # a forged success is not believed, and with a token policy the outcome is unknown (exit 3): the proof went out
    assert proc.returncode == (3 if policy == "token" else 1), proc.stdout + proc.stderr
    assert '"ok": true' not in proc.stdout.lower()
    assert fake.payloads, "the fake daemon was never asked"
    assert not any(TOKEN.encode() in p for p in fake.payloads)
    expected = {None: "is not a millsense challenge", "open": "open to anyone",
                "token": "fails the daemon's MAC for this token (it says: success): the outcome is unknown"}[policy]
    assert expected in proc.stderr and "Traceback" not in proc.stderr


def test_reset_with_no_daemon_says_so_and_what_to_try(millsense_cmd, port, daemon_session):
    started = time.monotonic()
    proc = _reset(millsense_cmd, port, "--machine", "mch10-01")
    assert proc.returncode == 1
    first, hint = proc.stderr.strip().split("\n")
    assert first == "millsense reset: no daemon answered on millsense/mch10-01/cmd/reset within 2 s"
    assert hint.startswith("try: ") and "--connect" in hint and "millsense reset --local" in hint
    assert proc.stdout == ""
    assert time.monotonic() - started < 20


def _no_token_env():
    return {k: v for k, v in os.environ.items() if k != "MILLSENSE_RESET_TOKEN"}


def test_reset_with_config_connects_where_the_daemon_listens_but_never_takes_its_token(millsense_cmd, port,
                                                                                      daemon_session, tmp_path):
    """Issue 12, item 2: from the daemon's config only where to connect; its token is given on purpose."""
    controls = FakeInterlock(token=TOKEN)
    sink = ZenohSink(daemon_session, "cfg-01", controls)
    token_file = tmp_path / "token"
    token_file.write_text(TOKEN + "\n")
    cfg = tmp_path / "d.toml"
    cfg.write_text(f'machine = "cfg-01"\n[interlock]\nreset = "token"\nreset_token_file = "{token_file}"\n'
                   f'[zenoh]\nlisten = ["tcp/0.0.0.0:{port}"]\nmulticast_scouting = false\n')
    try:
        proc = subprocess.run([*millsense_cmd, "reset", "--config", str(cfg)], capture_output=True, text=True,
                              timeout=30, env=_no_token_env())
        assert proc.returncode == 1, proc.stderr
        assert "cfg-01 requires a reset token for reset and none was given" in proc.stderr
        assert f"try: --token-file {token_file}" in proc.stderr  # named, not read
        assert controls.latched and not controls.requesters
        proc = subprocess.run([*millsense_cmd, "reset", "-c", str(cfg), "--token-file", str(token_file)],
                              capture_output=True, text=True, timeout=30, env=_no_token_env())
        assert proc.returncode == 0, proc.stderr
        assert json.loads(proc.stdout) == {"ok": True, "interlock": "clear"} and not controls.latched
    finally:
        sink.close()


def _daemon_files(tmp_path, port, machine="cfg-02"):
    """A daemon config whose Zenoh part lives in a JSON5 file, as with TLS: the endpoint and scouting are
    there, next to the daemon's own identity and an ACL that denies everything. A tool that handed this
    file to Zenoh would fail on the key or be denied; one that takes only where to connect finds it."""
    json5 = tmp_path / "zenoh-daemon.json5"
    json5.write_text(
        "{\n"
        f'  listen: {{ endpoints: ["tcp/0.0.0.0:{port}"] }},\n'
        "  scouting: { multicast: { enabled: false } },\n"
        "  transport: { link: { tls: { connect_private_key: \"/nonexistent/daemon.key\",\n"
        "                              connect_certificate: \"/nonexistent/daemon.pem\" } } },\n"
        '  access_control: { enabled: true, default_permission: "deny" },\n'
        "}\n"
    )
    cfg = tmp_path / "d.toml"
    cfg.write_text(f'machine = "{machine}"\n[zenoh]\nconfig_file = "{json5.name}"\n')  # relative: beside the TOML
    return cfg


def test_watch_with_config_finds_the_daemon_from_its_zenoh_file_with_scouting_off(millsense_cmd, port,
                                                                                  daemon_session, tmp_path):
    cfg = _daemon_files(tmp_path, port)
    sink = ZenohSink(daemon_session, "cfg-02", None)
    proc = subprocess.Popen([*millsense_cmd, "watch", "-c", str(cfg), "--json", "--seconds", "30"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        out = LineReader(proc)
        alive = out.wait_json(lambda o: o["kind"] == "alive", 15.0, "alive, found through --config")
        assert alive["key"] == "millsense/cfg-02/alive"
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(10) == 0
        err = proc.stderr.read()
        assert "Traceback" not in err and "nothing seen" not in err, err
    finally:
        sink.close()
        kill(proc)


def test_watch_finding_nothing_says_what_to_try(millsense_cmd, port, tmp_path):
    """Issue 12, item 2: nothing within the wait is said once, with a `try:` naming --config / --connect."""
    cfg = _daemon_files(tmp_path, port)  # nobody listens on `port`
    proc = subprocess.run([*millsense_cmd, "watch", "-c", str(cfg), "--seconds", "1"],
                          capture_output=True, text=True, timeout=30)
    assert proc.returncode == 0, proc.stderr
    first, hint = proc.stderr.strip().split("\n")
    assert first == "millsense watch: nothing seen on millsense/*/** within 1 s"
    assert hint.startswith("try: ") and f"tcp/127.0.0.1:{port} (from --config)" in hint and "--connect" in hint
    bare = subprocess.run([*millsense_cmd, "watch", "--seconds", "1"], capture_output=True, text=True, timeout=30)
    hint = bare.stderr.strip().split("\n")[-1]
    assert hint.startswith("try: ") and "--config" in hint and "--connect" in hint and "scouting" in hint


def test_reset_with_config_and_no_daemon_names_the_endpoint_it_tried(millsense_cmd, port, tmp_path):
    cfg = _daemon_files(tmp_path, port)
    proc = subprocess.run([*millsense_cmd, "reset", "-c", str(cfg), "--timeout", "1"], capture_output=True,
                          text=True, timeout=30, env=_no_token_env())
    assert proc.returncode == 1
    first, hint = proc.stderr.strip().split("\n")
    assert first == "millsense reset: no daemon answered on millsense/cfg-02/cmd/reset within 1 s"
    assert f"tcp/127.0.0.1:{port} (from --config)" in hint and "--connect" in hint and "reset --local" in hint


@pytest.mark.parametrize("command", ["watch", "reset", "test-trip"])
@pytest.mark.parametrize("endpoint", ["garbage", "tcp/garbage", "tcp/127.0.0.1:99999", "foo/127.0.0.1:7447", "tcp/"])
def test_a_bad_endpoint_is_a_one_line_usage_error(millsense_cmd, command, endpoint):
    """Issue 12, item 9: exit 2, one line, no Rust source path (Zenoh's own error names one)."""
    proc = subprocess.run([*millsense_cmd, command, "--machine", "m1", "--no-scouting", "--connect", endpoint],
                          capture_output=True, text=True, timeout=30)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.count("\n") == 1 and proc.stderr.startswith(f"millsense {command}: error: --connect: ")
    assert json.dumps(endpoint) in proc.stderr
    assert ".rs" not in proc.stderr and "cargo" not in proc.stderr and "Traceback" not in proc.stderr


def test_reset_local_without_a_machine_is_a_usage_error(millsense_cmd):
    proc = subprocess.run([*millsense_cmd, "reset", "--local"], capture_output=True, text=True, timeout=30)
    assert proc.returncode == 2 and "--local needs --machine or --config" in proc.stderr


def test_reset_local_with_no_daemon_at_the_machine_says_so(millsense_cmd, tmp_path):
    env = dict(os.environ, STATE_DIRECTORY=str(tmp_path / "state"))
    proc = subprocess.run([*millsense_cmd, "reset", "--local", "--machine", "m1"], capture_output=True, text=True,
                          timeout=30, env=env)
    assert proc.returncode == 1 and "Traceback" not in proc.stderr
    assert proc.stderr.startswith("millsense reset: error: ") and str(tmp_path / "state") in proc.stderr


def test_reset_client_with_no_router_says_so(millsense_cmd, port):
    proc = _reset(millsense_cmd, port, "--machine", "m1", "--mode", "client", "--timeout", "0.5")
    assert proc.returncode == 1
    assert f"could not open a session to {tcp(port)}" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_token_new_prints_or_writes_a_43_character_token_and_never_overwrites(millsense_cmd, tmp_path):
    first = subprocess.run([*millsense_cmd, "token", "new"], capture_output=True, text=True, timeout=30)
    second = subprocess.run([*millsense_cmd, "token", "new"], capture_output=True, text=True, timeout=30)
    tokens = [first.stdout.strip(), second.stdout.strip()]
    assert first.returncode == second.returncode == 0
    assert all(len(t) == 43 and re.fullmatch(r"[A-Za-z0-9_-]{43}", t) for t in tokens) and tokens[0] != tokens[1]
    out = tmp_path / "reset.token"
    made = subprocess.run([*millsense_cmd, "token", "new", "--out", str(out)], capture_output=True, text=True, timeout=30)
    assert made.returncode == 0 and made.stdout == ""
    written = out.read_text()
    assert re.fullmatch(r"[A-Za-z0-9_-]{43}\n", written) and stat.S_IMODE(out.stat().st_mode) == 0o600
    again = subprocess.run([*millsense_cmd, "token", "new", "--out", str(out)], capture_output=True, text=True, timeout=30)
    assert again.returncode == 1 and "exists; not overwritten" in again.stderr and out.read_text() == written


def test_watch_on_a_terminal_draws_one_line_per_machine(millsense_cmd, port, daemon_session):
    sink = ZenohSink(daemon_session, "mch10-01", None)
    master, slave = pty.openpty()
    proc = subprocess.Popen(
        [*millsense_cmd, "watch", "--no-scouting", "--connect", tcp(port), "--seconds", "30"],
        stdout=slave, stderr=subprocess.PIPE, stdin=subprocess.DEVNULL,
    )
    os.close(slave)
    screen = b""
    try:
        deadline = time.monotonic() + 15

        def last_line() -> str:
            return screen.decode("utf-8", "replace").split("\x1b[2K")[-1]

        # until the line has all three: liveliness, an estimate and the alarm (on a loaded box the alarm can be
        # drawn before the liveliness token or the first estimate has arrived: a line of its own, then this one)
        while not all(part in last_line() for part in ("alive", "600 rpm", "alarm: overload")):
            assert time.monotonic() < deadline, f"no live line; terminal got {screen[-300:]!r}"
            sink.estimate({"spindle_rpm": 600.2, "torque_nm": 4.21, "torque_sigma_nm": 0.05, "force_n": 452.6,
                           "radial_depth_mm": 20.0, "axial_depth_mm": 2.03, "depth_status": "ok"})
            sink.alarm({"level": "overload", "quantity": "torque_nm", "value": 31.7, "interlock": "feed_hold"})
            while select.select([master], [], [], 0.1)[0]:
                try:
                    screen += os.read(master, 4096)
                except OSError:
                    break
        text = screen.decode("utf-8", "replace")
        last = last_line()
        assert last.startswith("mch10-01") and "alive" in last
        assert "600 rpm" in last and "T   4.21±0.05 N·m" in last and "F   452.6 N" in last
        assert "ae 20.00 ap 2.03 mm (ok)" in last and "alarm: overload torque_nm 31.7 [feed_hold]" in last
        assert "{" not in text  # not JSON on a terminal
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(10) == 0
    finally:
        sink.close()
        kill(proc)
        os.close(master)


def test_watch_on_a_terminal_says_feed_held_until_the_daq_confirms_the_release(millsense_cmd, port, daemon_session):
    """Issue 36, finding 7 in `watch`: a held machine reads as held (why, since when) after its alarm cleared,
    until a status says the DAQ released it; the clear reads as a clear, not as "value > limit"."""
    sink = ZenohSink(daemon_session, "mch10-01", None)
    master, slave = pty.openpty()
    proc = subprocess.Popen(
        [*millsense_cmd, "watch", "--no-scouting", "--connect", tcp(port), "--seconds", "60"],
        stdout=slave, stderr=subprocess.PIPE, stdin=subprocess.DEVNULL,
    )
    os.close(slave)
    screen = [b""]
    tripped_at = time.time() - 30.0
    since = time.strftime("%H:%M:%S", time.localtime(tripped_at))
    reason = "overload torque_nm 31.7 > 30.0"

    def status(t, interlock, **detail):
        return {"t": t, "state": "running", "interlock": interlock, "alarm": "ok",
                "interlock_detail": {"interlock": interlock, "enabled": True, "reason": None, "since": None,
                                     "daq_feed_hold": False, **detail}}

    def last_line_after(publish, wanted):
        deadline = time.monotonic() + 15
        while True:
            publish()
            while select.select([master], [], [], 0.1)[0]:
                try:
                    screen[0] += os.read(master, 4096)
                except OSError:
                    break
            last = screen[0].decode("utf-8", "replace").split("\x1b[2K")[-1]
            if wanted(last):
                return last
            assert time.monotonic() < deadline, f"never {wanted}; last line {last!r}"

    try:
        now = time.time()
        held = status(now, "feed_hold", reason=reason, since=tripped_at, daq_feed_hold=True)
        line = last_line_after(lambda: sink.status(held), lambda ln: "feed held" in ln)
        assert f"feed held: {reason}, since {since}" in line, line
        # The load is gone 0.2 s after the hold: the alarm clears, the feed stays held.
        clear = {"t": now + 0.2, "level": "clear", "quantity": "torque_nm", "value": 1.2, "limit": 30.0,
                 "interlock": "feed_hold"}
        overload = {"t": now - 0.1, "level": "overload", "quantity": "torque_nm", "value": 31.7, "limit": 30.0,
                    "interlock": "feed_hold"}
        sink.alarm(overload)
        line = last_line_after(lambda: sink.alarm(clear), lambda ln: "alarm: clear" in ln)
        assert "alarm: clear torque_nm (was overload)" in line and "1.2" not in line.split("alarm:")[1], line
        assert f"feed held: {reason}, since {since}" in line, line
        # Reset written, the DAQ's STATUS not yet showing the release: still held.
        releasing = status(now + 1, "armed", daq_feed_hold=True)
        line = last_line_after(lambda: sink.status(releasing), lambda ln: "not yet confirmed" in ln)
        assert "feed held: release not yet confirmed by the DAQ" in line, line
        released = status(now + 2, "armed", daq_feed_hold=False)
        line = last_line_after(lambda: sink.status(released), lambda ln: "feed held" not in ln)
        assert line.startswith("mch10-01") and "alarm: clear torque_nm" in line
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(10) == 0
    finally:
        sink.close()
        kill(proc)
        os.close(master)
