"""Estimator + alarm engine for one machine: the part `run` and `replay` share.

Why one class: replay must give the same estimates and alarms as the live
daemon on the same samples, so both feed blocks through this and differ only
in where time comes from and where results go.

The per-block order matters for the interlock: `Step.trips` lists the events
that ask for feed hold (the sample-level crash on the block's smoothed
air-gap power or line current, a stall — `safety_check.py` — then overloads,
breakage) so that the caller acts on them before it publishes anything.
`Step.items` is in time order: each closed revolution followed by the alarms it caused, a crash after the revolutions that ended
before its sample.

Live, the crash power and current were decided frame by frame in the reader
thread (`safety_check.FrameCheck`), which already held the feed: such a block
comes with `checked` set and the crashes found in it (`frame_events`); they are
latched in the alarm engine and published here like any other (once: the
engine's latch), but not listed in `Step.trips` again.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

from millsense.daemon.events import AlarmEvent
from millsense.daemon.learning.context import ContextTrack
from millsense.daemon.learning.monitor import ProcessMonitor
from millsense.daemon.learning.expected import ExpectedBand
from millsense.daemon.config.operations import operation_cuts
from millsense.daemon.pipeline.alarms import AlarmEngine
from millsense.daemon.pipeline.override_track import OverrideTrack, load_gain
from millsense.daemon.pipeline.per_revolution import OperationEngagement
from millsense.daemon.pipeline.safety_check import SafetyCheck

_BEFORE_ANY = -(1 << 62)   # a STATUS before any sample: it holds from the first one on

# Internal fields of the estimator's dicts that are not part of the `estimate` payload.
_INTERNAL = ("seq_end", "wiring_p_in_w", "wiring_rpm")   # the last two: power_check.py's, on invalid revolutions


@dataclass
class Step:
    """What one block produced, in publication order."""

    # ("estimate", dict) | ("alarm", AlarmEvent) | ("process", dict: a finished process's summary)
    items: list[tuple[str, Any]] = field(default_factory=list)
    trips: list[AlarmEvent] = field(default_factory=list)
    revolutions: int = 0
    # Signal plausibility (signal_check.py): fault kind ("signals") -> what is wrong, naming the
    # channel; `clear_faults`: kinds whose condition this block showed gone.
    # A kind in both was raised and cleared within the block (a large one); `fault_changes` has every change
    # in order: (kind, seq where decided, reason; "" cleared).
    faults: dict[str, str] = field(default_factory=dict)
    clear_faults: set[str] = field(default_factory=set)
    fault_changes: list[tuple[str, int, str]] = field(default_factory=list)
    # Sample-level values of this block (safety_check.py), for the reset's "condition gone" test:
    # "p_gap_w" (smoothed air-gap power) and "current_a" (smoothed largest line current), block maxima.
    peaks: dict[str, float] = field(default_factory=dict)
    stalled: bool = False            # the stall check holds: no revolution closing while the current is high
    spindle_stopped: bool = False    # the block's last sample turned below the stop speed
    last_seq: int | None = None      # the block's last sample
    # Learned limits (daemon/learning): envelopes and tools whose state changed (to persist), and
    # one-time notes to log (event, fields).
    changed_limits: set[str] = field(default_factory=set)
    tools_changed: bool = False
    notes: list[tuple[str, dict]] = field(default_factory=list)

    def merge(self, other: Step) -> None:
        """What a context step decided, after this block's own items (alarms, processes, limits, notes)."""
        self.items.extend(other.items)
        self.trips.extend(other.trips)
        self.changed_limits |= other.changed_limits
        self.tools_changed = self.tools_changed or other.tools_changed
        self.notes.extend(other.notes)

    def take_monitor(self, mon: Any) -> None:
        """What the process monitor decided (`learning.monitor.MonitorStep`), in publication order."""
        for ev in mon.events:
            self.items.append(("alarm", ev))
            if ev.trips:
                self.trips.append(ev)
        self.items.extend(("process", summary) for summary in mon.processes)
        self.changed_limits |= set(mon.changed_keys)
        self.tools_changed = self.tools_changed or bool(mon.tools_changed)
        self.notes.extend(mon.notes)


def estimate_payload(est: dict[str, Any], machine: str, t: float | None, kind: str | None = None) -> dict[str, Any]:
    """interfaces.md `estimate`: machine, rev, t first, then the estimator's fields; `kind`: a leading
    `"type"` (replay's JSON lines), without a second copy of the dict (one per revolution)."""
    out: dict[str, Any] = {} if kind is None else {"type": kind}
    out.update(machine=machine, rev=est.get("rev"), t=t)
    out.update(est)   # a key already there keeps its place: the head stays first
    out["machine"], out["t"] = machine, t   # (the estimator has neither; the head wins, as documented)
    if kind is not None:
        out["type"] = kind
    for key in _INTERNAL:
        out.pop(key, None)
    return out


# A process summary's fields that are the monitor's bookkeeping, not the `process` payload.
_PROCESS_INTERNAL = ("seq_start", "seq_end")


def process_payload(summary: dict[str, Any], machine: str, t: float | None) -> dict[str, Any]:
    """The `process` payload (one finished process): machine, t, then the monitor's summary."""
    out: dict[str, Any] = {"machine": machine, "t": t}
    out.update((k, v) for k, v in summary.items() if k not in out and k not in _PROCESS_INTERNAL)
    return out


def _operation_cuts(settings: Any) -> dict[str, Any]:
    return operation_cuts(settings) if getattr(settings, "operations", None) else {}


def expected_band(settings: Any, cuts: dict[str, Any] | None = None) -> ExpectedBand | None:
    """The physics' expected band of the configured [operations] (`cuts`: already resolved); None without any
    (everything as before)."""
    cuts = _operation_cuts(settings) if cuts is None else cuts
    return ExpectedBand(cuts, getattr(settings, "learning", None), getattr(settings, "alarms", None)) if cuts else None


def operation_engagements(cuts: dict[str, Any]) -> dict[str, OperationEngagement]:
    """key → the engagement of each resolved `[operations]` entry of constant engagement: the force's C_f takes
    the operation's mode and programmed depths where the CNC reports it (a varying one's are only maxima)."""
    return {key: OperationEngagement(op.cut.mode, float(op.cut.radial_depth_mm), float(op.cut.axial_depth_mm))
            for key, op in cuts.items() if op.engagement == "constant"}


class PipelineCore:
    """Owns the estimator (re-made when the descriptor changes) and the alarm engine."""

    def __init__(self, settings: Any, estimator_factory: Any = None, check_descriptor: Any = None,
                 limits: dict | None = None, tools: dict | None = None, first_process: int = 1):
        self.settings = settings
        self.alarms = AlarmEngine(getattr(settings, "alarms", None))
        self.alarms.breakage.gain = load_gain(settings)   # a feed change is not a breakage (BreakageTrack)
        # What the machine is doing (the DAQ's CONTEXT or Zenoh's) and the limits learned per process.
        context = getattr(settings, "context", None)
        self.context = ContextTrack(str(getattr(context, "source", "off") or "off"))
        # The CNC's applied feed override by sample (STATUS): kept here so that a new estimator goes on with it
        self.override = OverrideTrack()
        learning = getattr(settings, "learning", None)
        cuts = _operation_cuts(settings)   # [operations] resolved once: the expected band and the force's engagement
        self.monitor: ProcessMonitor | None = (
            ProcessMonitor(learning, limits=limits, tools=tools, first_process=first_process,
                           gain=load_gain(settings), alarms=getattr(settings, "alarms", None),
                           expected=expected_band(settings, cuts))   # [operations] (issue 41)
            if learning is not None and getattr(learning, "enabled", False) else None)
        self._block_end: tuple[int, int] | None = None  # (seq, device index) one past the last block
        self._engagements = operation_engagements(cuts)
        self._context_change: int | None = None  # a context change the process monitor has not settled yet
        self._last_rev_end: int | None = None  # the last sample of the last revolution closed
        self._factory = estimator_factory
        self._check = check_descriptor
        self.estimator: Any = None
        self.descriptor: Any = None
        self.last_rev: int | None = None
        self.lost_samples_before = 0  # lost samples counted by estimators replaced since, and while none fitted
        self._rev_base = 0  # revolutions numbered by estimators replaced since: `rev` never restarts
        self.safety: SafetyCheck | None = None
        self._signals_faulted = False  # the signal check's fault, carried to the estimator of the next descriptor
        # a fault of the whole stream the estimator cannot see from its samples (the runner's rate check):
        # while set, every revolution is published invalid with it as the reason
        self.stream_problem: str | None = None

    def on_descriptor(self, descriptor: Any) -> bool:
        """A (new) descriptor: check the config against it, make the estimator. True if re-made.

        Raises `ConfigError` when the configuration does not fit the DAQ's channels.
        """
        if descriptor is None or descriptor == self.descriptor:
            return False
        check = self._check
        if check is None:
            from millsense.daemon.config.load import check_against_descriptor as check
        check(self.settings, descriptor)
        factory = self._factory
        if factory is None:
            from millsense.daemon.pipeline.estimator import Estimator as factory
        self._retire()
        self.estimator = factory(self.settings, descriptor, descriptor.sample_rate_hz)
        signals = getattr(self.estimator, "signals", None)
        if signals is not None:
            # the new estimator's signal check goes on from the fault the last one raised: only sound samples
            # clear it (made fresh, nothing would, and the daemon would stay blind until restarted)
            signals.faulted = self._signals_faulted
        self.context.on_descriptor(int(getattr(descriptor, "capabilities", 0) or 0))
        if hasattr(self.estimator, "override"):
            self.estimator.override = self.override  # the feed the cut runs at: configured x applied override
        if hasattr(self.estimator, "tool_at"):
            self.estimator.tool_at = self.tool_at  # force and depth use the tool in the spindle
        if hasattr(self.estimator, "cut_at") and self._engagements:
            self.estimator.cut_at = self.cut_at    # the force: the engagement of the operation being cut
        if hasattr(self.estimator, "rev"):
            self.estimator.rev = self._rev_base  # revolution numbers go on where the last estimator stopped
        self.descriptor = descriptor
        self.safety = SafetyCheck(getattr(self.settings, "alarms", None), float(descriptor.sample_rate_hz))
        return True

    def drop_estimator(self) -> None:
        """The DAQ's channels no longer fit the configuration: no estimator until they do.

        Its counts (lost samples, revolution numbers) are kept.
        """
        self._retire()
        self.estimator = None
        self.descriptor = None

    def skip(self, block: Any) -> None:
        """A block that no estimator can take (no fitting descriptor): its known losses still count."""
        self.lost_samples_before += int(getattr(block, "lost_before", 0) or 0)

    def _retire(self) -> None:
        est = self.estimator
        if est is not None:
            self._signals_faulted = bool(getattr(getattr(est, "signals", None), "faulted", False))
            self.lost_samples_before += int(getattr(est, "lost_samples_total", 0) or 0)
            self._rev_base = int(getattr(est, "rev", self._rev_base) or 0)

    # -- context ----------------------------------------------------------
    def cut_at(self, seq: int) -> OperationEngagement | None:
        """The engagement the operation at sample `seq` declares (`[operations]`, constant), None otherwise."""
        ctx = self.context.at(seq)
        return None if ctx is None else self._engagements.get(ctx.key)

    def tool_at(self, seq: int) -> int | None:
        """The CNC's tool number in the spindle at sample `seq` (None: no context)."""
        ctx = self.context.at(seq)
        return None if ctx is None else ctx.tool

    def seq_of_index(self, index: int) -> int | None:
        """The unwrapped sample number of a device index near the samples processed (None before any)."""
        if self._block_end is None:
            return None
        seq_end, index_end = self._block_end
        delta = (int(index) - index_end) & 0xFFFFFFFF
        if delta >= 1 << 31:
            delta -= 1 << 32
        return seq_end + delta

    def on_status(self, status: Any) -> None:
        """A DAQ STATUS: its applied feed override (version 2; None: not reported) holds from the next sample.

        A STATUS names no sample; the next one processed is the earliest it can describe, and the CNC's
        own lag (tens of ms) dwarfs the block's latency. Every estimate's `feed_override_pct` comes from here.
        """
        tenths = getattr(status, "feed_override", None)
        if tenths is None:
            return
        seq = self._block_end[0] if self._block_end is not None else _BEFORE_ANY
        self.override.note(seq, float(tenths) / 10.0)

    def on_context(self, ctx: Any) -> Step:
        """The DAQ's CONTEXT frame: it holds from its index on (see `_settle_context`)."""
        seq = self.seq_of_index(ctx.index)
        self.context.on_daq(ctx, seq)
        return self._context_changed(seq)

    def on_zenoh_context(self, payload: dict) -> tuple[Step, str | None]:
        """A CNC adapter's context on Zenoh, holding from the next sample processed; (step, refusal)."""
        seq = None if self._block_end is None else self._block_end[0]
        refused = self.context.on_zenoh(payload, seq)
        return (Step() if refused else self._context_changed(seq)), refused

    def _context_changed(self, seq: int | None) -> Step:
        if self.monitor is None:
            return Step()
        self._context_change = seq if seq is not None else (self._block_end[0] if self._block_end else 0)
        return self._settle_context()

    def _settle_context(self) -> Step:
        """Tell the process monitor of a context change once no revolution can still close before it.

        A revolution closing after the change is judged with the new context by the monitor itself
        (`on_revolution`); this is for a change with no revolution after it: the spindle stopped for a
        tool change, or the cycle ended. The revolution under way when the frame came ends before the
        change and still belongs to the old process: it waits for that revolution, for the spindle to
        stop, or for 2 s of samples past the change.
        """
        step = Step()
        change = self._context_change
        if self.monitor is None or change is None:
            return step
        if self._last_rev_end is not None and self._last_rev_end >= change:
            self._context_change = None  # a revolution after the change closed: the monitor has seen it
            return step
        done = self._block_end[0] if self._block_end is not None else None
        rate = float(getattr(self.descriptor, "sample_rate_hz", 1000) or 1000)
        if done is not None and done > change and (self.spindle_stopped or done - change > 2 * rate):
            self._context_change = None
            step.take_monitor(self.monitor.on_context(self.context.at(done - 1), done - 1))
        return step

    def on_link_lost(self) -> Step:
        """The DAQ link went down: the process under way is incomplete (it never teaches)."""
        step = Step()
        if self.monitor is not None:
            step.take_monitor(self.monitor.on_link_lost())
        return step

    def reset(self) -> list[AlarmEvent]:
        """Operator reset: the fixed alarms' latches and the learned limits' latched alarms."""
        events = self.alarms.reset()
        if self.monitor is not None:
            events.extend(self.monitor.reset())
        return events

    def active(self) -> dict[str, str]:
        out = self.alarms.active()
        if self.monitor is not None:
            out.update(self.monitor.active())
        return out

    def summary(self) -> str:
        """The worst active state in one word ("ok" when none)."""
        states = set(self.active().values())
        for level in ("crash", "tool_breakage", "overload", "envelope_high", "envelope_low", "expected_high",
                      "expected_low", "daq_lost", "warning", "wear"):
            if level in states:
                return level
        return "ok"

    @property
    def lost_samples_total(self) -> int:
        return int(getattr(self.estimator, "lost_samples_total", 0) or 0) + self.lost_samples_before

    @property
    def spindle_stopped(self) -> bool:
        return bool(getattr(self.estimator, "spindle_stopped", False))

    def _rev_at(self, seq: int, estimates: list[dict]) -> int | None:
        return _rev_at_seq(seq, self.last_rev, estimates)

    def process(self, block: Any, frame_events: list[AlarmEvent] = ()) -> Step:
        """Run one SampleBlock through estimator and alarms.

        `frame_events`: crashes the per-frame check found in this block's samples (and held the
        feed for); with `block.checked` the sample-level power and current are not decided again.
        """
        step = Step()
        self.estimator.stream_problem = self.stream_problem
        result = self.estimator.process(block)
        crashes: list[AlarmEvent] = []
        if self.safety is None:
            self.safety = SafetyCheck(getattr(self.settings, "alarms", None),
                                      float(getattr(self.estimator, "sample_rate_hz", 1000.0)))
        checked = bool(getattr(block, "checked", False))
        # tripped already, on the reader thread: latched (first, they are the earliest) and published,
        # not tripped again
        held = [_with_rev(e, self._rev_at(e.seq, result.estimates))
                for ev in frame_events for e in self.alarms.latch_crash(ev)]
        p_gap = getattr(result, "p_gap_w", None)
        if p_gap is not None and p_gap.size:  # smoothed per-sample power and current from `seq` on
            safe = self.safety.on_block(result, self.alarms, sample_level=not checked)
            crashes = [_with_rev(ev, self._rev_at(ev.seq, result.estimates)) for ev in safe.events]
            step.peaks, step.stalled = safe.peaks, safe.stalled
        step.trips.extend(crashes)  # the caller trips on these before it publishes anything
        if held:
            crashes = sorted(crashes + held, key=lambda ev: ev.seq if ev.seq is not None else 0)
        changes = getattr(result, "signal_changes", ())
        for seq, reason in changes:
            step.fault_changes.append(("signals", seq, reason))
            if reason:
                step.faults.setdefault("signals", reason)
        if changes and changes[-1][1] == "":
            step.clear_faults.add("signals")
        step.spindle_stopped = bool(getattr(result, "spindle_stopped", False))
        n = len(getattr(block, "counts", ()))
        step.last_seq = int(block.seq) + n - 1 if n else None
        if n:
            self._block_end = (int(block.seq) + n, (int(getattr(block, "index", block.seq)) + n) & 0xFFFFFFFF)
        monitor = self.monitor
        if monitor is not None:
            for ev in held + crashes:  # a process that raised an alarm does not teach
                monitor.note_alarm(ev)
        for est in result.estimates:
            # publication stays in time order: a crash goes out after the revolutions that ended before it
            while crashes and est.get("seq_end") is not None and int(est["seq_end"]) >= crashes[0].seq:
                step.items.append(("alarm", crashes.pop(0)))
            seq_end = est.get("seq_end")
            ctx = self.context.at(int(seq_end)) if seq_end is not None else None
            # every estimate says what the machine was doing (null without context)
            est["program"], est["tool"], est["operation"] = (
                (ctx.program, ctx.tool, ctx.operation) if ctx is not None else (None, None, None))
            mon = None
            if monitor is not None:  # its process, and the envelope it is checked against
                mon = monitor.on_revolution(est, ctx)
            step.items.append(("estimate", est))
            step.revolutions += 1
            if est.get("rev") is not None:
                self.last_rev = int(est["rev"])
            for ev in self.alarms.on_revolution(est):
                if ctx is not None:  # which program, tool and operation it happened in
                    ev = dataclasses.replace(ev, detail=ev.detail + _context_detail(ctx))
                step.items.append(("alarm", ev))
                if ev.trips:
                    step.trips.append(ev)
                if monitor is not None:
                    monitor.note_alarm(ev)
            if mon is not None:
                step.take_monitor(mon)
            if seq_end is not None:
                self._last_rev_end = int(seq_end)
        step.items.extend(("alarm", ev) for ev in crashes)
        if self._context_change is not None:
            step.merge(self._settle_context())
        return step


def _context_detail(ctx: Any) -> tuple[tuple[str, Any], ...]:
    return (("program", ctx.program), ("tool", ctx.tool), ("operation", ctx.operation))


def _rev_at_seq(seq: int, last_rev: int | None, estimates: list[dict]) -> int | None:
    """The revolution in progress at sample `seq`: one after the last that closed before it."""
    rev = last_rev
    for est in estimates:
        end, r = est.get("seq_end"), est.get("rev")
        if end is not None and r is not None and int(end) < seq:
            rev = int(r)
    return None if rev is None else rev + 1


def _with_rev(ev: AlarmEvent, rev: int | None) -> AlarmEvent:
    if ev.rev is not None or rev is None:
        return ev
    return dataclasses.replace(ev, rev=rev)
