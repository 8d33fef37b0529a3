"""Which context (program, tool, operation, flags) holds at a sample. Pure: no I/O, no clock.

Two sources (spec/daq-protocol.md "Version 2", spec/interfaces.md `context`):
the DAQ's CONTEXT frame, which names the sample index it holds from, and a CNC
adapter's Zenoh put, which holds from the next sample the daemon processes
(the adapter cannot know sample numbers). `[context] source` picks one; "auto"
takes the DAQ's when its descriptor says it reports context (capabilities bit 1),
else Zenoh. Only one source is ever in use: two sources that disagree would cut
processes in pieces.

Each context carries who vouches for it (`Ctx.authority`, issue 36): the DAQ's
frames are trusted; a Zenoh put is trusted only when signed with the adapter key
or under `[context] trust = "acl"` (`context_auth.py`). Any put may label the
cut; only a trusted context may let adaptive feed control raise the feed.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from millsense.daemon.learning.context_auth import AUTH_FIELDS, ContextAuth

SOURCES = ("auto", "daq", "zenoh", "off")
CAP_CONTEXT = 0x02              # descriptor capabilities bit 1: the DAQ reports context
MAX_HELD = 64                   # contexts kept at most (a flood cannot grow memory)
KEEP_PASSED = 8                 # contexts kept after they stopped holding: queries may step back a little
_UINT32 = 0xFFFFFFFF
_UINT16 = 0xFFFF
# Fields a Zenoh context may carry; `machine` and `t` are what an adapter adds to every payload.
_FLAG_DEFAULTS = {"cycle": True, "monitor": True, "afc_allowed": False, "feed_held": False}
_IGNORED_FIELDS = frozenset({"machine", "t"})
_AUTH_FIELDS = frozenset(AUTH_FIELDS)   # a signed context's run_id, seq and mac (context_auth.py)


@dataclass(frozen=True)
class Ctx:
    """What the CNC says it is doing."""

    program: int
    tool: int
    operation: int
    cycle: bool
    monitor: bool
    afc_allowed: bool
    feed_held: bool
    source: str  # "daq" | "zenoh"
    # Who vouches for it (issue 36, context_auth.py): "daq" (the DAQ's own frame), "mac" (the adapter key),
    # "acl" (`[context] trust = "acl"`), "none" (an unauthenticated put: it labels, AFC never follows it)
    authority: str = "none"

    @property
    def trusted(self) -> bool:
        """May adaptive feed control follow it: the DAQ's own context, or a Zenoh one vouched for."""
        return self.source == "daq" or self.authority in ("mac", "acl")

    @property
    def key(self) -> str:
        """The process key "program/tool/operation" (CLI, Zenoh, history)."""
        return f"{self.program}/{self.tool}/{self.operation}"


def ctx_from_daq(ctx: Any) -> Ctx:
    """A `drivers.protocol.Context` as a `Ctx`."""
    return Ctx(int(ctx.program), int(ctx.tool), int(ctx.operation), bool(ctx.cycle), bool(ctx.monitor),
               bool(ctx.afc_allowed), bool(ctx.feed_held), "daq", "daq")


def ctx_from_payload(payload: Any, auth: ContextAuth | None = None, *, take: bool = False) -> Ctx | str:
    """The Zenoh `context` JSON as a `Ctx`, or a one-line reason it is refused.

    `auth` says who vouches for it (no `auth`: nobody, "none"); `take` spends a signed put's sequence number."""
    if not isinstance(payload, dict):
        return f"context refused: a JSON object is expected, not {type(payload).__name__}"
    unknown = sorted(str(k) for k in payload if k not in _FLAG_DEFAULTS and k not in _IGNORED_FIELDS
                     and k not in _AUTH_FIELDS and k not in ("program", "tool", "operation"))
    if unknown:
        # a misspelt flag ("moniter") must not silently take its default
        return f"context refused: unknown field {unknown[0]!r}"
    numbers = {}
    for name, top in (("program", _UINT32), ("tool", _UINT32), ("operation", _UINT16)):
        value = payload.get(name)
        if value is None:
            return f"context refused: {name} is missing"
        if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= top:
            return f"context refused: {name} must be a whole number 0 … {top}, not {value!r}"
        numbers[name] = value
    flags = {}
    for name, default in _FLAG_DEFAULTS.items():
        value = payload.get(name, default)
        if not isinstance(value, bool):
            return f"context refused: {name} must be true or false, not {value!r}"
        flags[name] = value
    authority = "none"  # without a judge (replay, tests) nobody vouches, signed or not
    if auth is not None:
        authority, refusal = (auth.take if take else auth.judge)(payload, {**numbers, **flags})
        if refusal is not None:
            return refusal
    return Ctx(numbers["program"], numbers["tool"], numbers["operation"], source="zenoh", authority=authority,
               **flags)


class ContextTrack:
    """The contexts announced, each from the sample it holds from; `at(seq)` answers per revolution.

    Not thread-safe: the Zenoh subscriber and the estimator thread share it
    under the caller's lock. Sample numbers are the driver's unwrapped `seq`.
    """

    def __init__(self, source: str = "auto"):
        if source not in SOURCES:
            raise ValueError(f"context source {source!r} is not one of {', '.join(SOURCES)}")
        self.source = source
        self.auth: ContextAuth | None = None  # who vouches for a Zenoh context (the runner sets it; None: nobody)
        self._daq_reports: bool | None = None  # None: no descriptor seen yet
        self._held: list[tuple[int | None, Ctx]] = []  # (from seq or None = the next sample processed, ctx)

    # -- which source ----------------------------------------------------
    @property
    def source_in_use(self) -> str | None:
        """"daq", "zenoh" or None (off)."""
        if self.source == "off":
            return None
        if self.source == "auto":
            return "daq" if self._daq_reports else "zenoh"
        return self.source

    def on_descriptor(self, capabilities: int) -> None:
        """A DAQ descriptor: bit 1 of its capabilities says it reports context."""
        before = self.source_in_use
        self._daq_reports = bool(int(capabilities) & CAP_CONTEXT)
        if self.source_in_use != before:
            self._held.clear()  # what the other source said no longer counts

    # -- inputs ------------------------------------------------------------
    def on_daq(self, ctx: Any, seq: int | None) -> str | None:
        """A CONTEXT frame (`drivers.protocol.Context`), `seq` = its index unwrapped. None: taken."""
        if self.source_in_use != "daq":
            return self._ignored("the DAQ's CONTEXT")
        self._add(seq, ctx_from_daq(ctx))
        return None

    def judge_zenoh(self, payload: Any) -> Ctx | str:
        """A Zenoh `context` payload (parsed JSON) judged, not taken: its context, or why it is refused or ignored.
        Read-only: the Zenoh thread asks it too, so that the sink counts a refusal as one (`context_refused`)."""
        if self.source_in_use != "zenoh":
            return self._ignored("the Zenoh context")
        return ctx_from_payload(payload, self.auth)

    def on_zenoh(self, payload: Any, seq: int | None) -> str | None:
        """A Zenoh `context` payload (parsed JSON). None: taken; else why it was refused or ignored.
        A signed one's sequence number is spent here: the same put is never taken twice."""
        if self.source_in_use != "zenoh":
            return self._ignored("the Zenoh context")
        ctx = ctx_from_payload(payload, self.auth, take=True)
        if isinstance(ctx, str):
            return ctx
        self._add(seq, ctx)
        return None

    def _ignored(self, what: str) -> str:
        if self.source == "off":
            return f"{what} ignored: [context] source = \"off\""
        if self.source == "auto":
            why = "the DAQ reports context" if self._daq_reports else "the DAQ does not report context"
            return f"{what} ignored: {why} ([context] source = \"auto\")"
        return f"{what} ignored: [context] source = \"{self.source}\""

    def _add(self, seq: int | None, ctx: Ctx) -> None:
        if seq is not None:
            # a statement about sample `seq` replaces what was said about samples from there on
            self._held = [(s, c) for s, c in self._held if s is not None and s < seq]
        elif self._held and self._held[-1][0] is None:
            self._held.pop()  # two contexts for "the next sample": the later one is the news
        if self._held and self._held[-1][1] == ctx:
            return  # the DAQ repeats its context once a second: nothing new
        self._held.append((seq, ctx))
        if len(self._held) > MAX_HELD:
            del self._held[0]

    # -- queries -----------------------------------------------------------
    def mark_processed(self, seq: int) -> None:
        """Samples up to `seq` were processed: a context "from the next sample" holds from seq + 1."""
        self._held = [(seq + 1 if s is None else s, c) for s, c in self._held]

    def at(self, seq: int) -> Ctx | None:
        """The context holding at sample `seq`.

        Queries come roughly in sample order but may step back within a block
        (the estimator asks for each revolution's tool, then the monitor asks for
        each revolution in turn), so the last `KEEP_PASSED` contexts that stopped
        holding are kept; older ones are dropped.
        """
        if self.source_in_use is None:
            return None
        self._held = [(seq if s is None else s, c) for s, c in self._held]
        current = None
        for i, (s, _) in enumerate(self._held):
            if s <= seq:
                current = i
        if current is None:
            return None
        ctx = self._held[current][1]
        if current > KEEP_PASSED:
            del self._held[: current - KEEP_PASSED]
        return ctx
