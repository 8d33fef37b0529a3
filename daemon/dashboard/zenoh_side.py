"""The dashboard's Zenoh session: discovery by liveliness, the publications, and the reset relay.

Machines are found by their liveliness tokens `millsense/*/alive`, with
history, so that daemons already running are seen at once and a restarted one
reappears when its new token arrives. The publications are subscribed with
one wildcard per kind: a daemon that restarts needs nothing redeclared here.

The reset relay carries the page's two queries to `millsense/<m>/cmd/reset`
and the daemon's replies back, untouched: the page computes and checks the
MACs (docs/zenoh.md), so this process never sees the token and cannot forge a
daemon's answer. It accepts only the two steps' own fields, so the page cannot
be used to send anything else on the plant's network.
"""

from __future__ import annotations

import json
import re
from typing import Any

from millsense.daemon.dashboard.book import Book

KINDS = ("estimate", "alarm", "status", "process")
MACHINE_RE = re.compile(r"^[A-Za-z0-9_-]{1,64}\Z")
HEX_RE = re.compile(r"^[0-9a-f]{1,128}\Z")
RELAY_TIMEOUT_S = 3.0
# The fields each step may carry (docs/zenoh.md, "Commands"); `args` of a reset is always {}.
STEP_FIELDS = {
    "challenge": {"step", "client_nonce"},
    "prove": {"step", "client_nonce", "server_nonce", "args", "mac"},
}


class RelayRefused(ValueError):
    """The page's request is not a reset step this relay forwards; the message says why."""


def _no_constant(name: str) -> None:
    """NaN and Infinity are not JSON: a page could not read them, so they become null."""
    return None


def machine_of(key: str) -> str | None:
    parts = key.split("/")
    if len(parts) == 3 and parts[0] == "millsense" and MACHINE_RE.match(parts[1]):
        return parts[1]
    return None


class ZenohSide:
    """Declares the subscribers on `session` and feeds `book`; `relay_reset` for the page's reset."""

    def __init__(self, session: Any, book: Book):
        self.session, self.book = session, book
        self.bad_payloads = 0
        self._subs = [session.declare_subscriber(f"millsense/*/{kind}", self._on(kind)) for kind in KINDS]
        self._subs.append(session.liveliness().declare_subscriber("millsense/*/alive", self._on_alive, history=True))

    def _on(self, kind: str):
        def callback(sample: Any) -> None:
            name = machine_of(str(sample.key_expr))
            if name is None:
                return
            try:
                payload = json.loads(sample.payload.to_bytes(), parse_constant=_no_constant)
            except (UnicodeDecodeError, ValueError):
                self.bad_payloads += 1
                return
            if isinstance(payload, dict):
                self.book.publication(name, kind, payload)
            else:
                self.bad_payloads += 1

        return callback

    def _on_alive(self, sample: Any) -> None:
        name = machine_of(str(sample.key_expr))
        if name is not None:
            import zenoh

            self.book.alive(name, sample.kind == zenoh.SampleKind.PUT)

    def relay_reset(self, machine: str, request: Any) -> list[dict]:
        """Forward one step of the reset exchange; the replies as `{"ok": bool, "body": ...}`.

        Raises RelayRefused for a machine name or a request that is not one of the two steps.
        """
        import zenoh

        if not isinstance(machine, str) or not MACHINE_RE.match(machine):
            raise RelayRefused("machine: letters, digits, _ and - only")
        if not isinstance(request, dict) or request.get("step") not in STEP_FIELDS:
            raise RelayRefused('step must be "challenge" or "prove"')
        extra = set(request) - STEP_FIELDS[request["step"]]
        if extra:
            raise RelayRefused(f"fields not allowed in a {request['step']}: {', '.join(sorted(extra))}")
        for name in ("client_nonce", "server_nonce", "mac"):
            if name in request and not (isinstance(request[name], str) and HEX_RE.match(request[name])):
                raise RelayRefused(f"{name} must be lowercase hex")
        if request.get("args", {}) != {}:
            raise RelayRefused("a reset takes no args")
        body = dict(request, client_zid=str(self.session.zid()))  # who relayed: this dashboard (self-declared)
        out: list[dict] = []
        # Every queryable asked and every answer kept apart, as `command_auth.exchange` does: with Zenoh's default
        # (the best-matching queryable, answers consolidated) a second program answering as the daemon was hidden
        # from the page, which refuses to prove when two answer (issue 36, finding 6).
        replies = self.session.get(f"millsense/{machine}/cmd/reset", payload=json.dumps(body).encode(),
                                   encoding=zenoh.Encoding.APPLICATION_JSON, timeout=RELAY_TIMEOUT_S,
                                   target=zenoh.QueryTarget.ALL, consolidation=zenoh.ConsolidationMode.NONE)
        for reply in replies:
            sample = reply.ok if reply.ok is not None else reply.err
            try:
                answer: Any = json.loads(sample.payload.to_bytes())
            except (UnicodeDecodeError, ValueError):
                answer = None
            out.append({"ok": reply.ok is not None, "body": answer})
        return out

    def close(self) -> None:
        for s in self._subs:
            try:
                s.undeclare()
            except Exception:  # noqa: BLE001 - the session may be closing
                pass
