"""Real Zenoh sessions on loopback for the publication tests (multicast scouting off)."""

from __future__ import annotations

import json
import queue
import subprocess
import threading
import time
from collections.abc import Callable
from types import SimpleNamespace
from typing import Any

import zenoh

from millsense.daemon.publish.session import open_session


def zsettings(mode: str = "peer", *, listen: list[str] | None = None, connect: list[str] | None = None, **extra: Any) -> SimpleNamespace:
    fields = {"mode": mode, "listen": listen or [], "connect": connect or [], "multicast_scouting": False, "config_file": ""}
    fields.update(extra)
    return SimpleNamespace(**fields)


def tcp(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


def open_pair(port: int) -> tuple[zenoh.Session, zenoh.Session]:
    """Two peers: the first listens on `port`, the second connects to it; returns once linked."""
    a = open_session(zsettings(listen=[tcp(port)]), retry_for_s=0)
    b = open_session(zsettings(connect=[tcp(port)]), retry_for_s=0)
    wait_for(lambda: len(list(b.info.peers_zid())) > 0, 5.0, "second peer never connected")
    return a, b


def wait_for(predicate: Callable[[], Any], timeout_s: float, what: str) -> Any:
    deadline = time.monotonic() + timeout_s
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s} s: {what}")
        time.sleep(0.01)


class Collector:
    """Subscriber callback that keeps (key, decoded JSON, sample) in arrival order."""

    def __init__(self) -> None:
        self.items: list[tuple[str, Any, Any]] = []
        self.lock = threading.Lock()

    def __call__(self, sample: Any) -> None:
        entry = (str(sample.key_expr), json.loads(sample.payload.to_bytes()), sample)
        with self.lock:
            self.items.append(entry)

    def payloads(self, suffix: str = "") -> list[Any]:
        with self.lock:
            return [p for k, p, _ in self.items if k.endswith(suffix)]


class FakeInterlock:
    """A Controls object with real behaviour: a latched feed hold that an authorised reset clears.

    Authorisation is the sink's (daemon/publish/command_auth.py): like the Runner, this object
    only carries `settings.interlock` (the policy, and the token it reads). `token=None`: policy "open".
    """

    def __init__(self, token: str | None = "s3cret-" + "0" * 32, policy: str | None = None) -> None:
        self.token = token
        policy = policy or ("token" if token else "open")
        self.settings = SimpleNamespace(interlock=SimpleNamespace(reset=policy, token=lambda: self.token or ""))
        self.latched = True
        self.requesters: list[str] = []
        self.reset_payloads = self.requesters  # the old name (tests/publish/test_tls.py)
        self.fail_with: Exception | None = None

    def status(self) -> dict:
        self.status_calls = getattr(self, "status_calls", 0) + 1
        return {"state": "running", "interlock": "feed_hold" if self.latched else "clear"}

    def status_version(self) -> tuple:
        return (self.latched,)

    def config(self) -> dict:
        return {"machine": "m1", "interlock": {"enabled": True}}

    def reset(self, requester: str = "") -> dict:
        self.requesters.append(requester)
        if self.fail_with is not None:
            raise self.fail_with
        self.latched = False
        return {"ok": True, "interlock": "clear"}


KEY = "1234/12/3"  # a process key program/tool/operation


class OperatorControls(FakeInterlock):
    """Every command the sink can serve, each call recorded: what ran is what is in `ran`."""

    def __init__(self, token: str | None, audit: Any, machine: str = "m1") -> None:
        super().__init__(token=token)
        self.audit, self.machine = audit, machine
        self.ran: list[tuple[str, dict]] = []

    def test_trip(self, requester: str = "") -> dict:
        self.ran.append(("test-trip", {}))
        return {"ok": True, "daq_confirm_ms": 1.0, "cnc_confirm_ms": None}

    def limits(self) -> dict:
        return {"machine": self.machine, "enabled": True, "limits": [{"key": KEY, "state": "active", "high_nm": 5.0}]}

    def limits_command(self, args: dict, requester: str = "") -> dict:
        self.ran.append(("limits", dict(args)))
        return {"ok": True}

    def afc_command(self, args: dict, requester: str = "") -> dict:
        self.ran.append(("afc", dict(args)))
        return {"ok": True, "afc": {"enabled": args["action"] == "on"}}


class Impostor:
    """A second real Zenoh session answering on `millsense/<m>/cmd/*` like a daemon without the token:
    a well-formed challenge, then a success it cannot sign. It records what it was sent."""

    def __init__(self, port: int, machine: str, *, answer_prove: bool = True, answer_challenge: bool = True) -> None:
        from tests.conftest import free_tcp_port

        # it listens too, so that the requester (linked to the daemon only) learns of it by gossip and links to it
        self.session = open_session(zsettings(connect=[tcp(port)], listen=[tcp(free_tcp_port())]), retry_for_s=0)
        self.machine, self.answer_prove, self.answer_challenge = machine, answer_prove, answer_challenge
        self.got: list[dict] = []
        self.lock = threading.Lock()
        self.q = self.session.declare_queryable(f"millsense/{machine}/cmd/*", self._on)
        self.others: list[Any] = []

    def alive_as(self, machine: str) -> None:
        """Look like a second daemon too: `machine`'s alive token and a `status` that answers."""
        self.others.append(self.session.liveliness().declare_token(f"millsense/{machine}/alive"))
        self.others.append(self.session.declare_queryable(
            f"millsense/{machine}/status", lambda q: q.reply(str(q.key_expr), json.dumps({"state": "running"}))))

    def _on(self, query) -> None:
        request = json.loads(query.payload.to_bytes())
        command = str(query.key_expr).rsplit("/", 1)[-1]
        with self.lock:
            self.got.append(request)
        if request.get("step") == "challenge":
            if not self.answer_challenge:
                return
            body = {"step": "challenge", "machine": self.machine, "command": command, "policy": "token",
                    "server_nonce": "c" * 64, "expires_s": 10}
        elif self.answer_prove:
            body = {"result": json.dumps({"ok": True, "afc": {"enabled": True}}), "server_mac": "d" * 64}
        else:
            return
        query.reply(str(query.key_expr), json.dumps(body).encode())

    def known_to(self, session: Any, timeout_s: float = 5.0) -> None:
        """Wait until `session` knows this impostor's queryable (a key only it answers: the daemon has no
        `cmd/zz-probe`), so that a command from `session` reaches it too."""
        querier = session.declare_querier(f"millsense/{self.machine}/cmd/zz-probe")
        try:
            wait_for(lambda: querier.matching_status.matching, timeout_s, "the impostor's queryable is known")
        finally:
            querier.undeclare()

    def steps(self) -> list[str]:
        with self.lock:
            return [r.get("step") for r in self.got]

    def close(self) -> None:
        for entity in [*self.others, self.q]:
            entity.undeclare()
        self.session.close()


class LineReader:
    """Reads a subprocess's stdout lines on a thread, so waits can have deadlines."""

    def __init__(self, proc: subprocess.Popen) -> None:
        self.lines: queue.SimpleQueue[str] = queue.SimpleQueue()
        self.seen: list[str] = []
        self.proc = proc
        self.thread = threading.Thread(target=self._pump, args=(proc,), daemon=True)
        self.thread.start()

    def _pump(self, proc: subprocess.Popen) -> None:
        for line in proc.stdout:
            self.lines.put(line)

    def wait_json(self, predicate: Callable[[dict], bool], timeout_s: float, what: str) -> dict:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            try:
                line = self.lines.get(timeout=0.05)
            except queue.Empty:
                if not self.thread.is_alive() and self.lines.empty():  # stdout closed: it exited
                    err = self.proc.stderr.read() if self.proc.stderr else ""
                    raise AssertionError(f"process ended (rc={self.proc.wait(5)}) before {what}; stderr: {err[-800:]}")
                continue
            self.seen.append(line)
            obj = json.loads(line)
            if predicate(obj):
                return obj
        raise AssertionError(f"timed out after {timeout_s} s waiting for {what}; saw {self.seen[-5:]}")


def kill(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.kill()
    try:
        proc.wait(5)
    except subprocess.TimeoutExpired:
        pass
