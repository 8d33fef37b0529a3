"""Commands that change the machine (`cmd/*`): a challenge–response that never sends the token.

docs/zenoh.md describes the exchange for other implementations; this module is
both sides of it. In short, for `millsense/<m>/cmd/<command>`:

1. challenge: the requester sends `{"step": "challenge", "client_nonce": CN}`;
   the daemon answers `{"step": "challenge", "machine", "command", "policy",
   "server_nonce": SN, "expires_s"}` and remembers SN (single use, expiring,
   bounded in number);
2. prove: the requester sends `{"step": "prove", "client_nonce": CN,
   "server_nonce": SN, "args": {...}, "mac": M}` with
   M = HMAC-SHA256(token, "millsense-cmd-v1\\n<command>\\n<machine>\\nSN\\nCN\\n<canonical args>");
   the daemon checks M in constant time, consumes SN, runs the command and
   answers `{"result": R, "server_mac": S}` where R is the result as JSON text
   and S = HMAC-SHA256(token, "millsense-reply-v1\\n<command>\\n<machine>\\nSN\\nCN\\nR").

The two labels keep a requester's MAC from ever being valid as a daemon's, and
both nonces bind every MAC to one exchange: a captured exchange replays to
nothing (SN is spent), and a daemon without the token can neither learn it
(HMAC, 256-bit tokens) nor forge S. The same idea as SCRAM's proofs.

Policies (`[interlock] reset`): "token" as above; "open" (no MAC either way:
whoever reaches the queryable may clear or test a hold, `OPEN_COMMANDS`, and
nothing more: every command that may loosen protection or raise the feed is
refused, since no token exists to prove, and the refusal points to the local
socket; the requester cannot verify the answer); "off" (every network command
refused: the local reset at the machine).

The requester asks every queryable on the key and keeps every answer apart
(`QueryTarget.ALL`, no consolidation): two programs answering the challenge
are said, and no proof is sent; an answer to the proof that fails the daemon's
MAC leaves the outcome unknown (`CommandError.unknown`), never reported as a
refusal or a success.

Zenoh cannot tell requesters apart reliably, so failed proofs are limited
globally: after `max_failures` within `window_s`, every proof is refused for
`cooldown_s`, and the refusal says so. The local reset keeps the operator in
control meanwhile.
"""

from __future__ import annotations

import collections
import hashlib
import hmac
import json
import re
import secrets
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

CMD_LABEL = "millsense-cmd-v1"
REPLY_LABEL = "millsense-reply-v1"
POLICIES = ("token", "open", "off")
NONCE_BYTES = 32  # the daemon's server nonce (and the client's here): 256 bits, 64 hex digits
CLIENT_NONCE_RE = re.compile(r"^[0-9a-f]{32,128}\Z")  # at least 128 bits, lowercase hex
SERVER_NONCE_RE = re.compile(r"^[0-9a-f]{64}\Z")
MAC_RE = re.compile(r"^[0-9a-f]{64}\Z")
ZID_RE = re.compile(r"^[0-9a-f]{1,32}\Z")
LOCAL_HINT = "use the local reset at the machine: millsense reset --local"

# What `reset = "open"` lets anyone who reaches the queryable do: clear a hold, prove the hold path, and read.
# An allow-list, so that whatever else `cmd/*` takes needs the token's proof (or the local socket): every action
# that widens, accepts, relearns, marks an alarm false, starts a tool afresh or turns a check off, `afc on` (it
# raises the feed) and `afc off` (it too may raise the feed: from a reduced override back to 100 %), and any
# action added later, the day it is added. None: the command takes no args (checked by the command itself).
OPEN_COMMANDS: dict[str, tuple[str, ...] | None] = {
    "reset": None,
    "test-trip": None,
    "limits": ("list", "show"),
    "afc": ("status",),
}
LOCAL_SOCKET_HINT = ("at the machine, as root or the daemon's user, add --local (the daemon's control socket: "
                     "no token needed there)")


def open_to_anyone(command: str, args: Any) -> bool:
    """May `command` with `args` run under `reset = "open"`, with no proof? Only what `OPEN_COMMANDS` names."""
    if command not in OPEN_COMMANDS:
        return False
    actions = OPEN_COMMANDS[command]
    if actions is None:
        return True
    return isinstance(args, dict) and args.get("action") in actions


def command_words(command: str, args: Any) -> str:
    """`limits widen`, `afc on`, `reset`: a command as an operator types it."""
    action = args.get("action") if isinstance(args, dict) else None
    return f"{command} {action.replace('_', '-')}" if isinstance(action, str) and action else command


def policy_summary(policy: str, has_token: bool) -> str:
    """Who may do what over which transport under `policy`, in one phrase (check-config's summary line).

    Reads (`status`, `config`, `limits`, `afc status`) need nothing; the local socket (root or the daemon's
    user, `--local`) takes every command whatever the policy: neither is repeated here.
    """
    changes = "limits changes and afc on/off"
    if policy == "token" and has_token:
        return 'commands over Zenoh with the token\'s proof (reset = "token")'
    if policy == "open":
        return (f'reset and test-trip open to anyone who reaches it over Zenoh, {changes} only at the machine '
                '(--local) (reset = "open", no token)')
    why = 'reset = "token" without a token' if policy == "token" else f'reset = "{policy}"'
    return f"no command over Zenoh, every command only at the machine (--local) ({why})"


# --------------------------------------------------------------------------- encodings
def canonical_json(value: Any) -> str:
    """The one text of `value` both sides MAC: keys sorted, no spaces, ASCII only.

    Fractional numbers are refused: their text differs between languages, and
    no command argument needs one (send integers of a stated unit).
    """
    _check_canonical(value, 0)
    return json.dumps(value, sort_keys=True, separators=(",", ":"), ensure_ascii=True, allow_nan=False)


def _check_canonical(value: Any, depth: int) -> None:
    if depth > 16:
        raise ValueError("args are nested too deeply (16 levels at most)")
    if isinstance(value, float):
        raise ValueError("args may not hold fractional numbers (use an integer in a stated unit)")
    if isinstance(value, dict):
        for k, v in value.items():
            if not isinstance(k, str):
                raise ValueError("args keys must be strings")
            _check_canonical(v, depth + 1)
    elif isinstance(value, list):
        for v in value:
            _check_canonical(v, depth + 1)
    elif not (value is None or isinstance(value, (str, int, bool))):
        raise ValueError(f"args may not hold a {type(value).__name__}")


def command_message(command: str, machine: str, server_nonce: str, client_nonce: str, args: dict) -> bytes:
    """What the requester MACs (docs/zenoh.md, "The proof")."""
    return "\n".join((CMD_LABEL, command, machine, server_nonce, client_nonce, canonical_json(args))).encode("utf-8")


def reply_message(command: str, machine: str, server_nonce: str, client_nonce: str, result_text: str) -> bytes:
    """What the daemon MACs: the result exactly as the JSON text it sends."""
    return "\n".join((REPLY_LABEL, command, machine, server_nonce, client_nonce, result_text)).encode("utf-8")


def mac_hex(token: str, message: bytes) -> str:
    """HMAC-SHA256 keyed with the token's UTF-8 bytes, as 64 lowercase hex digits."""
    return hmac.new(token.encode("utf-8"), message, hashlib.sha256).hexdigest()


def _json_text(result: dict) -> str:
    from millsense.daemon.publish.payload import dumps  # strict JSON (NaN -> null), numpy scalars welcome

    return dumps(result).decode("utf-8")


# --------------------------------------------------------------------------- daemon side
# Outstanding server nonces. Anyone may ask for a challenge: a flood of them evicts the oldest. 64 went in about
# 64 ms of a 1000-a-second flood, sooner than an operator's proof came back on a loaded box (a probe of stop 26:
# 3 genuine resets in 20 failed). 1024 last a second of the daemon's whole query budget (~200 kB at most).
NONCE_CAPACITY = 1024


class NonceStore:
    """Server nonces: single use, expiring after `ttl_s`, at most `capacity` outstanding (oldest evicted)."""

    def __init__(self, ttl_s: float = 10.0, capacity: int = NONCE_CAPACITY, mono: Callable[[], float] = time.monotonic):
        self.ttl_s, self.capacity, self._mono = ttl_s, capacity, mono
        self._live: collections.OrderedDict[str, float] = collections.OrderedDict()
        self._lock = threading.Lock()

    def issue(self) -> str:
        nonce = secrets.token_hex(NONCE_BYTES)
        now = self._mono()
        with self._lock:
            while self._live and (len(self._live) >= self.capacity or next(iter(self._live.values())) <= now):
                self._live.popitem(last=False)
            self._live[nonce] = now + self.ttl_s
        return nonce

    def take(self, nonce: str) -> bool:
        """True once for a nonce issued less than `ttl_s` ago; it is spent either way."""
        with self._lock:
            expires = self._live.pop(nonce, None)
        return expires is not None and self._mono() < expires

    def __len__(self) -> int:
        return len(self._live)


class FailureLimiter:
    """Global brake on failed proofs: `max_failures` within `window_s` pauses all proofs for `cooldown_s`."""

    def __init__(self, max_failures: int = 5, window_s: float = 10.0, cooldown_s: float = 30.0,
                 mono: Callable[[], float] = time.monotonic):
        self.max_failures, self.window_s, self.cooldown_s, self._mono = max_failures, window_s, cooldown_s, mono
        self._failures: collections.deque[float] = collections.deque()
        self._paused_until = -1e18
        self.pauses = 0

    def paused_for(self) -> float:
        """Seconds of pause left (0 when proofs are accepted)."""
        return max(0.0, self._paused_until - self._mono())

    def failed(self) -> None:
        now = self._mono()
        self._failures.append(now)
        while self._failures and self._failures[0] <= now - self.window_s:
            self._failures.popleft()
        if len(self._failures) >= self.max_failures:
            self._paused_until = now + self.cooldown_s
            self._failures.clear()
            self.pauses += 1


@dataclass
class Answer:
    """What the queryable sends back: `ok` picks reply() or reply_err(); `body` is the JSON bytes."""

    ok: bool
    body: bytes
    ran: bool = False  # a command ran (caches of status may be stale)


def policy_and_token(controls: Any) -> tuple[str, str]:
    """The `[interlock] reset` policy and token of a Controls object that carries `settings` (the daemon's OperatorControls).

    A policy left unresolved (settings not from config.py) is "token" when a token
    exists, else "off": when in doubt, nothing is commanded over the network.
    """
    interlock = getattr(getattr(controls, "settings", None), "interlock", None)
    reader = getattr(interlock, "token", None)
    token = str(reader() or "") if callable(reader) else ""
    policy = getattr(interlock, "reset", None)
    if policy not in POLICIES:
        policy = "token" if token else "off"
    return policy, token


class CommandGate:
    """The daemon's side of the exchange for every `cmd/*` of one machine. Thread-safe.

    `audit`: an object with `record(command, requester, granted, reason=None,
    result=None)` (daemon/audit.py `AuditLog`), which counts refusals and writes
    them at most once per 10 s.
    """

    def __init__(self, machine: str, policy: str, token: str, audit: Any, *, nonces: NonceStore | None = None,
                 limiter: FailureLimiter | None = None):
        if policy not in POLICIES:
            raise ValueError(f"policy must be one of {POLICIES}, not {policy!r}")
        if policy == "token" and not token:
            policy = "off"  # a token policy without a token: nobody can prove, so nobody may command
        self.machine, self.policy, self._token, self.audit = machine, policy, token, audit
        self.nonces = nonces or NonceStore()
        self.limiter = limiter or FailureLimiter()
        self._lock = threading.Lock()
        self.granted = 0
        self.refused = 0

    def handle(self, command: str, request: dict[str, Any], run: Callable[[dict, str], dict]) -> Answer:
        """One parsed request on `cmd/<command>`; `run(args, requester)` performs the command."""
        requester = _requester(request)
        step = request.get("step")
        if self.policy == "off":
            return self._refuse(command, requester, f"commands over the network are off on {self.machine} "
                                f'(interlock.reset = "off"): {LOCAL_HINT}', with_policy=True)
        if step == "challenge":
            return self._challenge(command, request, requester)
        if step == "prove":
            return self._prove(command, request, requester, run)
        return self._refuse(command, requester, 'payload: "step" must be "challenge" or "prove" (docs/zenoh.md)')

    def refuse_unparsed(self, command: str, reason: str) -> Answer:
        """A request refused before parsing (too large, not JSON): audited, counted, never MACed."""
        return self._refuse(command, "unknown", reason)

    def _challenge(self, command: str, request: dict, requester: str) -> Answer:
        cn = request.get("client_nonce")
        if not isinstance(cn, str) or not CLIENT_NONCE_RE.match(cn):
            return self._refuse(command, requester, "payload: client_nonce must be 32 to 128 lowercase hex digits")
        body = {"step": "challenge", "machine": self.machine, "command": command, "policy": self.policy,
                "server_nonce": self.nonces.issue(), "expires_s": self.nonces.ttl_s}
        paused = self.limiter.paused_for()
        if paused:
            body["paused_s"] = round(paused, 1)  # the proof would be refused: say so before it is sent
        return Answer(True, _dumps(body))

    def _prove(self, command: str, request: dict, requester: str, run: Callable[[dict, str], dict]) -> Answer:
        sn, cn, args = request.get("server_nonce"), request.get("client_nonce"), request.get("args", {})
        if not (isinstance(sn, str) and SERVER_NONCE_RE.match(sn) and isinstance(cn, str) and CLIENT_NONCE_RE.match(cn)):
            # not a failed proof: no token was tried in it (a garbled HMI loop must not pause the operator's commands)
            return self._refuse(command, requester, "payload: server_nonce (64 hex digits) and client_nonce "
                                "(32 to 128 lowercase hex digits) are required")
        with self._lock:
            fresh = self.nonces.take(sn)  # spent whatever follows: one nonce, one try
            paused = self.limiter.paused_for()
            if paused:
                return self._signed_refusal(command, requester, sn, cn,
                                            f"too many failed proofs: commands over the network are refused for "
                                            f"{paused:.0f} s more; {LOCAL_HINT}")
            if not fresh:   # not a failed proof: no token was tried (a flood of challenges may have evicted it)
                return self._signed_refusal(command, requester, sn, cn, "unknown, used or expired server_nonce: "
                                            "ask for a new challenge")
            # a failed proof (counted by the limiter) is one whose MAC was compared and did not match: only a token
            # guess; a garbled payload tried none
            if not isinstance(args, dict):
                return self._signed_refusal(command, requester, sn, cn, "payload: args must be an object")
            if self.policy == "open" and not open_to_anyone(command, args):
                # not a failed proof either: no token exists to try
                return self._signed_refusal(
                    command, requester, sn, cn,
                    f"{command_words(command, args)} needs the reset token over the network, and {self.machine} "
                    f'has none (reset = "open" lets anyone clear or test a hold, nothing more): '
                    f"{LOCAL_SOCKET_HINT}")
            if self.policy == "token":
                given = request.get("mac")
                try:
                    expected = mac_hex(self._token, command_message(command, self.machine, sn, cn, args))
                except ValueError as exc:
                    return self._signed_refusal(command, requester, sn, cn, f"payload: {exc}")
                if not (isinstance(given, str) and MAC_RE.match(given) and hmac.compare_digest(given, expected)):
                    return self._signed_refusal(command, requester, sn, cn,
                                                "the proof does not match (wrong or missing reset token)", failed=True)
        try:
            result = run(args, requester)
            if not isinstance(result, dict):
                raise TypeError(f"the command returned {type(result).__name__}, expected a dict")
        except ValueError as exc:  # the command's own refusal of its arguments
            return self._signed_refusal(command, requester, sn, cn, str(exc))
        except Exception as exc:  # noqa: BLE001 - a command must never kill the daemon
            result = {"ok": False, "error": f"{type(exc).__name__}: {exc}"}
        self.granted += 1
        self._record(command, requester, True, None, result)
        return Answer(True, self._signed(command, sn, cn, result), ran=True)

    # -- replies ---------------------------------------------------------------------
    def _signed(self, command: str, sn: str, cn: str, result: dict) -> bytes:
        text = _json_text(result)
        server_mac = mac_hex(self._token, reply_message(command, self.machine, sn, cn, text)) \
            if self.policy == "token" else None
        return _dumps({"result": text, "server_mac": server_mac})

    def _signed_refusal(self, command: str, requester: str, sn: str, cn: str, reason: str,
                        failed: bool = False) -> Answer:
        if failed:
            self.limiter.failed()
        self.refused += 1
        self._record(command, requester, False, reason, None)
        return Answer(False, self._signed(command, sn, cn, {"ok": False, "error": reason}))

    def _refuse(self, command: str, requester: str, reason: str, failed: bool = False,
                with_policy: bool = False) -> Answer:
        if failed:
            self.limiter.failed()
        self.refused += 1
        self._record(command, requester, False, reason, None)
        body: dict[str, Any] = {"ok": False, "error": reason}
        if with_policy:
            body["policy"] = self.policy
        return Answer(False, _dumps(body))

    def _record(self, command: str, requester: str, granted: bool, reason: str | None, result: dict | None) -> None:
        try:
            self.audit.record(command, requester, granted, reason=reason, result=result)
        except Exception:  # noqa: BLE001 - a broken audit trail must not block a reset
            pass


def _requester(request: dict) -> str:
    """Who asked, as far as known: Zenoh gives a queryable no source, so the requester's own word."""
    zid = request.get("client_zid")
    if isinstance(zid, str) and ZID_RE.match(zid):
        return f"zid:{zid} (self-declared)"
    return "unknown"


def _dumps(body: dict) -> bytes:
    return json.dumps(body, separators=(",", ":")).encode("utf-8")


# --------------------------------------------------------------------------- requester side
class CommandError(Exception):
    """The command was not confirmed: no answer, a refusal, or an answer that failed the daemon's MAC.

    `result`: the daemon's verified (or, with policy "open", unverifiable) refusal, when there is one.
    `no_answer`: nobody answered at all.
    `unknown`: the proof went out and no answer came back that can be trusted (none, or one that fails the
    daemon's MAC): the command may have run. The CLI exits `EXIT_UNKNOWN` (3) and says how to check.
    """

    def __init__(self, message: str, result: dict | None = None, no_answer: bool = False, unknown: bool = False):
        super().__init__(message)
        self.result, self.no_answer, self.unknown = result, no_answer, unknown


@dataclass
class Outcome:
    result: dict
    policy: str  # "token": verified by server_mac; "open": the daemon's word, unverifiable
    verified: bool
    # Other programs that answered the proof beside the daemon's signed answer (their Zenoh ids, "(unknown)"
    # for one that names none): ignored, but something else answers as the machine, which the user is told.
    others: list[str] = field(default_factory=list)


def send_command(session: Any, machine: str, command: str, token: str | None, args: dict | None = None,
                 timeout_s: float = 2.0) -> dict:
    """Run `command` on `machine`'s daemon through the challenge–response; its verified result.

    The result may say `"ok": false` (the command ran and declined, e.g. a reset while
    the condition persists). Raises `CommandError` on no answer, an authorisation
    refusal, or an answer that fails the daemon's MAC.
    """
    return exchange(session, machine, command, token, args, timeout_s).result


def how_to_check(command: str, machine: str) -> str:
    """Where an operator sees whether `command` ran on `machine` (said with an unknown outcome)."""
    read = {"afc": f"millsense afc status --machine {machine}",
            "limits": f"millsense limits list --machine {machine}"}.get(
        command, f"millsense watch --machine {machine} (its interlock)")
    return (f"check with `{read}` and the daemon's audit log (audit.log in its state directory: "
            f"/var/lib/millsense/{machine}/ under systemd), which records every command granted or refused")


def others_warning(prog: str, machine: str, command: str, others: list[str]) -> str:
    """The CLI's stderr line when other programs answered the proof beside the daemon's signed answer: the
    outcome stands (only the daemon's MAC counts), but something else answers as the machine (docs/zenoh.md)."""
    return (f"{prog}: warning: {len(others)} other program(s) also answered the {command} proof as {machine} "
            f"(Zenoh ids {', '.join(others)}): their answers fail the daemon's MAC and were ignored, the daemon's "
            f"own answer decides; but something else answers on millsense/{machine}/cmd/*: find it "
            "(docs/security.md)")


def exchange(session: Any, machine: str, command: str, token: str | None, args: dict | None = None,
             timeout_s: float = 2.0) -> Outcome:
    """`send_command` with the policy and whether the answer was verified."""
    import zenoh

    args = {} if args is None else args
    canonical_json(args)  # a bad argument is the caller's error, before anything is sent
    key = f"millsense/{machine}/cmd/{command}"
    deadline = time.monotonic() + timeout_s
    # Every queryable on the key is asked and every answer kept apart: with Zenoh's default (the best-matching
    # queryable, answers consolidated to the latest) a second program answering as the daemon went unseen, and its
    # answer could stand in for the daemon's (finding 6 of issue 36).
    querier = session.declare_querier(key, target=zenoh.QueryTarget.ALL,
                                      consolidation=zenoh.ConsolidationMode.NONE, timeout=max(0.1, timeout_s))
    try:
        # A fresh session learns remote queryables a moment after it opens.
        while not querier.matching_status.matching:
            if time.monotonic() >= deadline:
                raise CommandError(f"no daemon answered on {key} within {timeout_s:g} s", no_answer=True)
            time.sleep(0.01)
        zid = _zid(session)
        cn = secrets.token_hex(NONCE_BYTES)
        challenge = _challenge(querier, key, machine, command, cn, zid, deadline, timeout_s)
        policy, sn = challenge["policy"], challenge["server_nonce"]
        if policy == "token" and not token:
            raise CommandError(f"{machine} requires a reset token for {command} and none was given")
        if policy == "open" and token:
            raise CommandError(f'{machine} says its commands are open to anyone (reset = "open"), but a token was '
                               "given: either its config changed or this is not the real daemon; nothing was sent. "
                               "Without a token the command is sent, unverified")
        if challenge.get("paused_s"):
            raise CommandError(f"{machine} refuses commands over the network for {challenge['paused_s']:g} s more "
                               f"(too many failed proofs); {LOCAL_HINT}")
        prove: dict[str, Any] = {"step": "prove", "client_nonce": cn, "server_nonce": sn, "args": args}
        if zid:
            prove["client_zid"] = zid
        if policy == "token":
            prove["mac"] = mac_hex(token or "", command_message(command, machine, sn, cn, args))
        # The same proof again while nothing answers (a flood may have pushed it out of the daemon's
        # queue): it runs at most once, since its server nonce is single-use.
        tries = 0
        while True:
            tries += 1
            replies = _get(querier, prove)
            if replies or time.monotonic() + 0.05 >= deadline:
                break
            time.sleep(0.05)
        unsure = (f"no answer from {machine} to the {command} proof: the outcome is unknown (the command may or "
                  f"may not have run); {how_to_check(command, machine)}")
        if not replies:
            raise CommandError(unsure, no_answer=True, unknown=True)
        try:
            return _verified(replies, machine, command, policy, sn, cn, token)
        except CommandError as exc:
            if tries > 1 and exc.result is not None and "server_nonce" in str(exc.result.get("error")):
                # an earlier try ran, its answer was lost
                raise CommandError(unsure, no_answer=True, unknown=True) from None
            raise
    finally:
        try:
            querier.undeclare()
        except Exception:  # noqa: BLE001 - the session may be closing
            pass


def _programs(replies: list[tuple[bool, Any, str | None]]) -> list[str]:
    """Who answered, one entry per program: its Zenoh id, or "(unknown)" per answer that names none."""
    ids = sorted({r for _, _, r in replies if r is not None})
    return ids + ["(unknown)"] * sum(1 for _, _, r in replies if r is None)


def _challenge(querier: Any, key: str, machine: str, command: str, cn: str, zid: str | None, deadline: float,
               timeout_s: float) -> dict:
    """The daemon's challenge; retried while nobody answers (a flood may have pushed ours out of its queue)."""
    request: dict[str, Any] = {"step": "challenge", "client_nonce": cn}
    if zid:
        request["client_zid"] = zid
    while True:
        replies = _get(querier, request)
        programs = _programs(replies)
        if len(programs) > 1:
            raise CommandError(f"{len(programs)} programs answer on {key} (Zenoh ids {', '.join(programs)}): "
                               f"something else answers as {machine}; nothing was sent")
        answers = [(ok, body) for ok, body, _ in replies]
        for ok, body in answers:
            if not ok:
                reason = body.get("error") if isinstance(body, dict) else body
                raise CommandError(f"{machine} refused {command}: {reason}",
                                   result=body if isinstance(body, dict) else None)
        good = [b for ok, b in answers if isinstance(b, dict) and b.get("step") == "challenge"
                and b.get("machine") == machine and b.get("command") == command and b.get("policy") in POLICIES
                and isinstance(b.get("server_nonce"), str) and SERVER_NONCE_RE.match(b["server_nonce"])]
        if answers and len(good) != len(answers):
            raise CommandError(f"the answer on {key} is not a millsense challenge (docs/zenoh.md): "
                               "not a millsense daemon, or one too old to authorise commands; nothing was sent")
        if len({b["server_nonce"] for b in good}) > 1:
            raise CommandError(f"{len(good)} programs answer on {key}: something else answers as {machine}; "
                               "nothing was sent")
        if good:
            return good[0]
        if time.monotonic() + 0.05 >= deadline:
            raise CommandError(f"no daemon answered on {key} within {timeout_s:g} s", no_answer=True)
        time.sleep(0.05)


def _verified(replies: list[tuple[bool, Any, str | None]], machine: str, command: str, policy: str, sn: str, cn: str,
              token: str | None) -> Outcome:
    """The outcome the answers to the proof prove. With "token", only an answer carrying the daemon's MAC counts:
    any other answer (a forged success, a forged or unverifiable refusal) leaves the outcome unknown."""
    proven: list[tuple[bool, dict]] = []
    provers: list[int] = []   # the index in `replies` of each proven answer
    claims: list[str] = []   # what unverifiable answers say, for the message
    for i, (ok, body, _replier) in enumerate(replies):
        if not (isinstance(body, dict) and isinstance(body.get("result"), str)):
            if isinstance(body, dict) and isinstance(body.get("error"), str):
                claims.append(f"refused: {body['error']}")   # refused before any MAC was possible
            else:
                claims.append("an answer that is not a millsense command reply (docs/zenoh.md)")
            continue
        text = body["result"]
        result = _object(text)
        if policy == "token":
            given = body.get("server_mac")
            expected = mac_hex(token or "", reply_message(command, machine, sn, cn, text))
            if not (isinstance(given, str) and hmac.compare_digest(given, expected)):
                if result is not None and result.get("ok") is False:
                    claims.append(f"{machine} refused {command}: {result.get('error')}")
                else:
                    claims.append("success" if result is not None and result.get("ok") else "an answer")
                continue
        if result is None:
            claims.append("an answer whose result is not a JSON object")
            continue
        proven.append((ok, result))
        provers.append(i)
    if policy != "token" and len(_programs(replies)) > 1:
        # "open": nothing is verifiable, and more than one program answered the proof
        raise CommandError(f"{len(_programs(replies))} programs answered the {command} proof on {machine}: the "
                           f"outcome is unknown; {how_to_check(command, machine)}", unknown=True)
    if proven:
        ok, result = proven[0]
        daemon = replies[provers[0]][2]
        others = [] if policy != "token" else _programs(
            [r for i, r in enumerate(replies) if i != provers[0] and (daemon is None or r[2] != daemon)])
        if not ok:
            also = f" ({len(others)} other program(s) also answered, ignored: {', '.join(others)})" if others else ""
            raise CommandError(f"{machine} refused {command}: {result.get('error', result)}{also}", result=result)
        return Outcome(result, policy, policy == "token", others)
    said = "; ".join(dict.fromkeys(claims)) or "nothing usable"
    if policy != "token":
        raise CommandError(f"{machine}: {said}")
    raise CommandError(
        f"the answer to the {command} proof fails the daemon's MAC for this token (it says: {said}): the outcome "
        f"is unknown. Either the token is wrong (then the daemon ran nothing) or the answer is not the daemon's "
        f"(then the command may have run); {how_to_check(command, machine)}", unknown=True)


def _object(text: str) -> dict | None:
    try:
        value = json.loads(text)
    except ValueError:
        return None
    return value if isinstance(value, dict) else None


def _get(querier: Any, request: dict) -> list[tuple[bool, Any, str | None]]:
    """Every answer to `request`: (a normal reply?, its JSON (or text), the replier's Zenoh id when known)."""
    import zenoh

    out: list[tuple[bool, Any, str | None]] = []
    for reply in querier.get(payload=_dumps(request), encoding=zenoh.Encoding.APPLICATION_JSON):
        sample = reply.ok if reply.ok is not None else reply.err
        data = sample.payload.to_bytes()
        try:
            body: Any = json.loads(data)
        except (UnicodeDecodeError, ValueError):
            body = data.decode("utf-8", "replace")
        replier = getattr(getattr(reply, "replier_id", None), "zid", None)
        out.append((reply.ok is not None, body, str(replier) if replier is not None else None))
    return out


def _zid(session: Any) -> str | None:
    try:
        return str(session.zid())
    except Exception:  # noqa: BLE001
        return None
