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

from dataclasses import dataclass, field
from typing import Any

from millsense.daemon.pipeline.alarms import AlarmEngine, AlarmEvent
from millsense.daemon.pipeline.safety_check import SafetyCheck

# Internal fields of the estimator's dicts that are not part of the `estimate` payload.
_INTERNAL = ("seq_end",)


@dataclass
class Step:
    """What one block produced, in publication order."""

    items: list[tuple[str, Any]] = field(default_factory=list)  # ("estimate", dict) | ("alarm", AlarmEvent)
    trips: list[AlarmEvent] = field(default_factory=list)
    revolutions: int = 0
    # Signal plausibility (signal_check.py): fault kind ("signals") -> what is wrong, naming the
    # channel; `clear_faults`: kinds whose condition this block showed gone.
    faults: dict[str, str] = field(default_factory=dict)
    clear_faults: set[str] = field(default_factory=set)
    # Sample-level values of this block (safety_check.py), for the reset's "condition gone" test:
    # "p_gap_w" (smoothed air-gap power) and "current_a" (smoothed largest line current), block maxima.
    peaks: dict[str, float] = field(default_factory=dict)
    stalled: bool = False            # the stall check holds: no revolution closing while the current is high
    spindle_stopped: bool = False    # the block's last sample turned below the stop speed
    last_seq: int | None = None      # the block's last sample


def estimate_payload(est: dict[str, Any], machine: str, t: float | None) -> dict[str, Any]:
    """interfaces.md `estimate`: machine, rev, t first, then the estimator's fields."""
    out: dict[str, Any] = {"machine": machine, "rev": est.get("rev"), "t": t}
    for key, value in est.items():
        if key not in out and key not in _INTERNAL:
            out[key] = value
    return out


class PipelineCore:
    """Owns the estimator (re-made when the descriptor changes) and the alarm engine."""

    def __init__(self, settings: Any, estimator_factory: Any = None, check_descriptor: Any = None):
        self.settings = settings
        self.alarms = AlarmEngine(getattr(settings, "alarms", None))
        self._factory = estimator_factory
        self._check = check_descriptor
        self.estimator: Any = None
        self.descriptor: Any = None
        self.last_rev: int | None = None
        self.lost_samples_before = 0  # lost samples counted by estimators replaced since, and while none fitted
        self._rev_base = 0  # revolutions numbered by estimators replaced since: `rev` never restarts
        self.safety: SafetyCheck | None = None

    def on_descriptor(self, descriptor: Any) -> bool:
        """A (new) descriptor: check the config against it, make the estimator. True if re-made.

        Raises `ConfigError` when the configuration does not fit the DAQ's channels.
        """
        if descriptor is None or descriptor == self.descriptor:
            return False
        check = self._check
        if check is None:
            from millsense.daemon.config import check_against_descriptor as check
        check(self.settings, descriptor)
        factory = self._factory
        if factory is None:
            from millsense.daemon.pipeline.estimator import Estimator as factory
        self._retire()
        self.estimator = factory(self.settings, descriptor, descriptor.sample_rate_hz)
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
            self.lost_samples_before += int(getattr(est, "lost_samples_total", 0) or 0)
            self._rev_base = int(getattr(est, "rev", self._rev_base) or 0)

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
        fault = getattr(result, "signal_fault", None)
        if fault:
            step.faults["signals"] = fault
        elif fault == "":
            step.clear_faults.add("signals")
        step.spindle_stopped = bool(getattr(result, "spindle_stopped", False))
        n = len(getattr(block, "counts", ()))
        step.last_seq = int(block.seq) + n - 1 if n else None
        for est in result.estimates:
            # publication stays in time order: a crash goes out after the revolutions that ended before it
            while crashes and est.get("seq_end") is not None and int(est["seq_end"]) >= crashes[0].seq:
                step.items.append(("alarm", crashes.pop(0)))
            step.items.append(("estimate", est))
            step.revolutions += 1
            if est.get("rev") is not None:
                self.last_rev = int(est["rev"])
            for ev in self.alarms.on_revolution(est):
                step.items.append(("alarm", ev))
                if ev.trips:
                    step.trips.append(ev)
        step.items.extend(("alarm", ev) for ev in crashes)
        return step


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
    return AlarmEvent(ev.level, ev.quantity, ev.value, ev.limit, rev, ev.seq)
