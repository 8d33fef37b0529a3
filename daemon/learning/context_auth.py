"""Who vouches for a Zenoh context: the adapter's MAC, the router's ACL, or nobody (issue 36). Pure: no I/O, no clock.

Anyone who can put on `millsense/<m>/context` may label the cut (which process,
which envelope): a wrong label costs learning, never the machine. What may let
adaptive feed control raise the feed is stricter: a context counts as vouched
for only when it carries a MAC under the adapter key (`[context]
adapter_key_file`, distinct from the reset token) or when `[context] trust =
"acl"` says the router lets only adapters put it (docs/zenoh.md, "Signed
context"; docs/security.md, "Who may publish context").

Replay: the MAC covers this daemon's `run_id` (random at each start, in
`status`) and a sequence number that must rise within the run. A put captured in
an earlier run fails at once (another run_id), one captured in this run fails
its sequence; an adapter that restarts reads `run_id` and `context_auth.seq`
from `status` and goes on above it. No clock is involved on either side.
"""

from __future__ import annotations

import hashlib
import hmac
import re
from typing import Any

LABEL = "millsense-context-v1"
AUTH_FIELDS = ("run_id", "seq", "mac")     # a signed put carries all three, an unsigned one none
TRUST = ("none", "acl")                    # `[context] trust`
AUTHORITIES = ("daq", "mac", "acl", "none")  # who vouches for a context in force (`Ctx.authority`)
MAX_SEQ = 2**53 - 1                        # a JSON integer every language reads exactly (JavaScript's too)
FLAGS = ("cycle", "monitor", "afc_allowed", "feed_held")
_MAC_RE = re.compile(r"^[0-9a-f]{64}\Z")
_RUN_RE = re.compile(r"^[0-9a-f]{1,64}\Z")


def message(machine: str, run_id: str, seq: int, program: int, tool: int, operation: int,
            flags: dict[str, bool]) -> bytes:
    """The MAC input: the label and the fields, one per line (LF, no trailing LF), UTF-8; flags as 1 or 0.
    The flags are the ones in force after their defaults (cycle, monitor true; afc_allowed, feed_held false),
    so a flag left out is signed as the value the daemon takes for it."""
    parts = [LABEL, machine, run_id, str(seq), str(program), str(tool), str(operation)]
    parts += ["1" if flags[name] else "0" for name in FLAGS]
    return "\n".join(parts).encode("utf-8")


def mac_hex(key: str, msg: bytes) -> str:
    """HMAC-SHA256 keyed with the adapter key's UTF-8 bytes (its text as it is, not decoded), as 64 hex digits."""
    return hmac.new(key.encode("utf-8"), msg, hashlib.sha256).hexdigest()


class ContextAuth:
    """One daemon run's judge of Zenoh contexts: which authority a put has, or why it is refused.

    `judge` reads only (the Zenoh thread asks it first, to count a refusal as one); `take` also spends the
    sequence number (the estimator thread, when it applies the context). Sequence numbers are ints written
    whole, so that the two threads need no lock.
    """

    def __init__(self, machine: str, run_id: str, key: str = "", trust: str = "none"):
        if trust not in TRUST:
            raise ValueError(f"context trust {trust!r} is not one of {', '.join(TRUST)}")
        self.machine, self.run_id, self._key, self.trust = machine, run_id, key, trust
        self.last_seq = 0   # the highest sequence number taken in this run (0: none yet)

    @property
    def signed(self) -> bool:
        """True when an adapter key is configured (a signed put can be checked)."""
        return bool(self._key)

    def judge(self, payload: dict, fields: dict[str, Any]) -> tuple[str, str | None]:
        """(authority, None) or ("none", the refusal). `fields`: program, tool, operation and the flags in force.

        Unsigned: "acl" under `trust = "acl"`, else "none" (it labels, it never lets AFC run). Signed, with a
        key configured: "mac" when the MAC verifies for this machine and run and the sequence rises; refused
        otherwise (never taken as unsigned: a replayed or forged put changes nothing). Signed, with no key:
        the MAC cannot be checked, so the put counts as unsigned."""
        given = [name for name in AUTH_FIELDS if name in payload]
        if not given:
            return self.trust, None
        if len(given) != len(AUTH_FIELDS):
            missing = [name for name in AUTH_FIELDS if name not in payload]
            return "none", (f"context refused: {', '.join(given)} without {', '.join(missing)} "
                            "(a signed context carries run_id, seq and mac)")
        if not self._key:
            return self.trust, None
        run_id, seq, mac = payload["run_id"], payload["seq"], payload["mac"]
        if not isinstance(run_id, str) or not _RUN_RE.match(run_id):
            return "none", f"context refused: run_id must be 1 … 64 hex digits, not {run_id!r}"
        if isinstance(seq, bool) or not isinstance(seq, int) or not 1 <= seq <= MAX_SEQ:
            return "none", f"context refused: seq must be a whole number 1 … {MAX_SEQ}, not {seq!r}"
        if not isinstance(mac, str) or not _MAC_RE.match(mac):
            return "none", "context refused: mac must be 64 lowercase hex digits (HMAC-SHA256)"
        if run_id != self.run_id:
            return "none", (f"context refused: signed for run {run_id}, this daemon's run is {self.run_id} "
                            "(an old put replayed, or an adapter that has not read status since the daemon restarted)")
        expected = mac_hex(self._key, message(self.machine, self.run_id, seq, fields["program"], fields["tool"],
                                              fields["operation"], fields))
        if not hmac.compare_digest(mac, expected):
            return "none", "context refused: its MAC does not verify (another key, another machine, or a field changed)"
        if seq <= self.last_seq:
            return "none", (f"context refused: seq {seq} is not above {self.last_seq}, the last taken in this run "
                            "(a replay; an adapter that restarted goes on from status's context_auth.seq)")
        return "mac", None

    def take(self, payload: dict, fields: dict[str, Any]) -> tuple[str, str | None]:
        """`judge`, and a signed put's sequence number spent: the same put cannot be taken twice."""
        authority, refusal = self.judge(payload, fields)
        if refusal is None and authority == "mac":
            self.last_seq = int(payload["seq"])
        return authority, refusal

    def status(self) -> dict[str, Any]:
        """For `status`: what an adapter needs to sign (`run_id` is the status's own) and what is trusted."""
        return {"key": self.signed, "trust": self.trust, "seq": self.last_seq}


UNTRUSTED = "context not authenticated"  # AFC's idle reason under a context nobody vouches for


def untrusted_reason(ctx: Any) -> str | None:
    """Why adaptive feed control may not follow the context in force (`Ctx` or None), or None: it may.
    No context at all is the config's call (`[afc] allow`), not an outsider's."""
    if ctx is None or ctx.trusted:
        return None
    return UNTRUSTED


def from_settings(settings: Any, run_id: str) -> ContextAuth:
    """The judge for one daemon run from `[context]` (settings built in code without it: nobody vouched for)."""
    context = getattr(settings, "context", None)
    key = getattr(context, "adapter_key", None)
    return ContextAuth(str(getattr(settings, "machine", "")), run_id,
                       key.get_secret_value() if key is not None else "",
                       str(getattr(context, "trust", "none") or "none"))
