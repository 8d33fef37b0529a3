"""The DAQ's own state, independent of any transport: index, ring, outputs, watchdog.

Every server (pty, TCP, Modbus, in-process) drives one ``DeviceModel``; time is
passed in (``now`` from ``time.monotonic()``) so the watchdog logic is testable
with a fake clock.

Protocol version 2 adds a simulated CNC beside the DAQ: its context (program,
tool, operation; cycle and monitoring on) and its "feed held" input, which
follows the DAQ's feed-hold output ``cnc_hold_lag_s`` later, as a real CNC
answers its feed-hold input after its own scan time; and the feed-override
output, which the device returns to 100.0 % when its watchdog trips (a restarted
device starts there too). The CNC answers the commanded override through its
own lag and rate limit (``cnc_override.CncOverride``): per sample, the applied
override goes to the plant (``source.feed_override_pct``) before it makes the
samples, and STATUS / Modbus input register 6 report the applied one, the
holding register 102 the commanded one. A stream carries a STATUS after each
frame at whose last sample the applied override (in 0.1 %) moved, within a
block too (``override_points``): however many samples a block holds (``--fast``
makes a second of them at once), the host learns of a change where it happened,
a frame late at most, as from a real DAQ.
A part program's plant (sim/program_plant.py) is a CNC of its own: it
sets program, tool, operation, cycle and monitor by sample index, and the
device passes each change on with the index of the first sample it holds for.
"""

from __future__ import annotations

import collections
import json
import time
from dataclasses import replace
from typing import IO

import numpy as np

from millsense.sim.emulator.cnc_override import CncOverride
from millsense.drivers.protocol import (
    CAP_CONTEXT,
    CAP_FEED_OVERRIDE,
    CMD_HEARTBEAT,
    CMD_SET_FEED_OVERRIDE,
    CMD_SET_OUTPUTS,
    CTX_AFC_ALLOWED,
    CTX_CYCLE,
    CTX_FEED_HELD,
    CTX_MONITOR,
    FEED_OVERRIDE_MAX,
    FEED_OVERRIDE_NEUTRAL,
    FLAG_WATCHDOG,
    INDEX_MOD,
    OUT_FEED_HOLD,
    Command,
    Context,
    Samples,
    Status,
)

PROTOCOLS = (1, 2)


class StatusLog:
    """JSON lines of what the device did, with monotonic and wall time (for tests)."""

    def __init__(self, path: str | None) -> None:
        self._fh: IO[str] | None = open(path, "a", buffering=1) if path else None  # noqa: SIM115

    def write(self, event: str, now: float | None = None, **fields) -> None:
        if self._fh is None:
            return
        rec = {"event": event, "mono": time.monotonic() if now is None else now, "wall": time.time(), **fields}
        self._fh.write(json.dumps(rec) + "\n")

    def close(self) -> None:
        if self._fh is not None:
            self._fh.close()
            self._fh = None


class DeviceModel:
    """Samples from a plant, numbered with a wrapping 32-bit index and kept in a ring."""

    def __init__(
        self,
        source,
        *,
        start_index: int = 0,
        ring_depth: int = 4096,
        watchdog_ms: int = 0,
        status_log: StatusLog | None = None,
        protocol: int = 1,
        program: int = 0,
        tool: int = 0,
        operation: int = 0,
        cnc_hold_lag_ms: float = 30.0,
        cnc_override_lag_ms: float = 40.0,
        cnc_override_rate_pct_s: float = 1000.0,
        afc_allowed: bool = False,
    ) -> None:
        if protocol not in PROTOCOLS:
            raise ValueError(f"protocol version {protocol} not one of {PROTOCOLS}")
        self.source = source
        self.protocol = protocol
        self.capabilities = CAP_FEED_OVERRIDE | CAP_CONTEXT if protocol >= 2 else 0
        self.descriptor = source.descriptor
        if protocol >= 2:
            self.descriptor = replace(source.descriptor, protocol_version=protocol, capabilities=self.capabilities)
        self.channel_count = self.descriptor.channel_count
        self.sample_rate_hz = self.descriptor.sample_rate_hz
        self.ring_depth = ring_depth
        self.ring = np.zeros((ring_depth, self.channel_count), dtype=np.int16)
        self.head = start_index % INDEX_MOD  # index the next sample will get
        history = getattr(source, "history", None)
        if history is not None and start_index >= ring_depth:
            # started mid-count (--start-index): behave like a device that has been
            # sampling all along, with a full ring, as the Modbus reader assumes
            first = start_index - ring_depth
            self.ring[(first + np.arange(ring_depth)) % INDEX_MOD % ring_depth] = history(first, ring_depth)
        self.outputs = 0  # what the outputs are (commanded, or feed hold forced by the watchdog)
        self.commanded = 0  # what the last set-outputs command asked for (Modbus coils read this)
        self.flags = 0
        self.last_heartbeat = 0
        self.watchdog_ms = watchdog_ms
        self.watchdog_broken = False   # `sim --watchdog-broken`: a DAQ whose watchdog never holds the feed
        self._armed = False
        self._last_heartbeat_time = 0.0
        self._heard_heartbeat = False
        self.log = status_log or StatusLog(None)
        # version 2: the feed override and the simulated CNC's context
        # a restart starts at 100.0 %, commanded and applied alike
        self.feed_override = FEED_OVERRIDE_NEUTRAL  # applied, in 0.1 % (what STATUS reports)
        self.feed_override_commanded = FEED_OVERRIDE_NEUTRAL  # what the host last commanded (or the watchdog)
        self.cnc_override = CncOverride(cnc_override_lag_ms, cnc_override_rate_pct_s,
                                        sample_rate_hz=getattr(source, "sample_rate_hz", self.sample_rate_hz))
        self.program = program
        self.tool = tool
        self.operation = operation
        self.cnc_flags = CTX_CYCLE | CTX_MONITOR | (CTX_AFC_ALLOWED if afc_allowed else 0)
        self.context_index = self.head  # the first sample index at which the context holds
        # a part program (sim/program.py) is a CNC of its own: it sets program, tool, operation,
        # cycle and monitor sample by sample; the device adds only "feed held"
        self._program_source = callable(getattr(source, "drain_context", None))
        if self._program_source:
            self.program, self.tool, self.operation, self.cnc_flags = source.context()
        self.context_changes: list[tuple[int, Context]] = []  # of the last produce: (offset in it, CONTEXT)
        # of the last produce: the applied override per sample (0.1 %), and what it was before the block
        self._override_trace: np.ndarray | None = None
        self._override_before = self.feed_override
        self._before_first_block = True
        self.cnc_hold_lag_s = max(0.0, cnc_hold_lag_ms) / 1000.0
        self._cnc_pending: collections.deque[tuple[float, bool]] = collections.deque()
        self._cnc_target = False  # what the CNC will report once the pending changes are through

    # -- samples --------------------------------------------------------------

    def produce(self, n: int) -> tuple[int, np.ndarray]:
        """The next ``n`` samples: (first index, (n, C) int16), also written to the ring.

        A part program's context changes within them are in ``context_changes`` afterwards, as
        (offset of the first sample it holds for, its CONTEXT), so a stream puts each CONTEXT
        just before that sample (version 2; version 1 sends none, the context is kept all the same)."""
        first = self.head
        source_first = self.source.index if self._program_source else 0
        if self.protocol >= 2:
            self._apply_override(n)
        counts = np.asarray(self.source.step(n), dtype=np.int16)
        keep = min(n, self.ring_depth)  # only the newest D samples survive
        pos = (first + n - keep + np.arange(keep, dtype=np.int64)) % INDEX_MOD % self.ring_depth
        self.ring[pos] = counts[n - keep :]
        self.head = (first + n) % INDEX_MOD
        self.context_changes = []
        if self._program_source:
            changes = self.source.drain_context()
            if self._before_first_block:  # the context at the very first sample leads the stream
                self._before_first_block = False
                ctx = self.context()
                if ctx is not None and not (changes and changes[0][0] == source_first):
                    self.context_changes.append((0, ctx))
            for index, (program, tool, operation, flags) in changes:
                offset = index - source_first
                self.program, self.tool, self.operation = program, tool, operation
                self.cnc_flags = flags | (self.cnc_flags & CTX_FEED_HELD)
                self.context_index = (first + offset) % INDEX_MOD
                ctx = self.context()
                if ctx is not None:
                    self.context_changes.append((offset, ctx))
        return first, counts

    def _apply_override(self, n: int) -> None:
        """The CNC steps its override through the next n samples; the plant feeds with it."""
        applied_pct = self.cnc_override.run(self.feed_override_commanded / 10.0, n)
        self.source.feed_override_pct = applied_pct  # a source without feed (the ramp) ignores it
        self._override_before = self.feed_override
        self._override_trace = np.clip(np.rint(np.asarray(applied_pct, dtype=float) * 10.0), 0,
                                       FEED_OVERRIDE_MAX).astype(np.int64)
        tenths = int(self._override_trace[-1]) if n else None
        if tenths is not None and tenths != self.feed_override:
            self.feed_override = tenths
            self.log.write("feed_override_applied", value=tenths, index=(self.head + n - 1) % INDEX_MOD)

    def override_points(self, frame: int) -> list[tuple[int, int]]:
        """Where STATUS frames go in the last produced block (version 2): after each run of ``frame``
        samples at whose last sample the applied override differs from the one before; (offset of the
        sample after it, the override in 0.1 %)."""
        trace = self._override_trace
        if self.protocol < 2 or trace is None or not len(trace):
            return []
        n = len(trace)
        ends = np.minimum(np.arange(frame, n + frame, frame), n)
        out, last = [], self._override_before
        for end, tenths in zip(ends.tolist(), trace[ends - 1].tolist()):
            if tenths != last:
                out.append((end, tenths))
                last = tenths
        return out

    def status_with(self, feed_override: int) -> Status:
        """STATUS as it was when the applied override was `feed_override` (0.1 %) within the last block."""
        return replace(self.status(), feed_override=feed_override)

    def stream_items(self, first: int, counts: np.ndarray, frame: int = 10) -> list:
        """The block of the last ``produce`` as the stream carries it: ``Samples``, with each CONTEXT
        of ``context_changes`` just before the sample it holds for, and a STATUS after every ``frame``
        samples in which the applied override moved (the in-process driver's frames)."""
        marks = sorted([(offset, 0, self.status_with(tenths)) for offset, tenths in self.override_points(frame)]
                       + [(offset, 1, ctx) for offset, ctx in self.context_changes], key=lambda m: m[:2])
        items: list = []
        done = 0
        for offset, _, item in marks:
            if offset > done:
                items.append(Samples((first + done) % INDEX_MOD, counts[done:offset]))
                done = offset
            items.append(item)
        if done < len(counts) or not items:
            items.append(Samples((first + done) % INDEX_MOD, counts[done:]))
        return items

    def ring_registers(self, offset: int, count: int) -> list[int]:
        """Registers 1000 + offset .. + count - 1 of the Modbus ring, as uint16."""
        flat = self.ring.reshape(-1).view(np.uint16)
        return flat[offset : offset + count].tolist()

    # -- outputs and watchdog -------------------------------------------------

    def status(self) -> Status:
        if self.protocol >= 2:
            return Status(self.outputs, self.flags, self.last_heartbeat, self.feed_override)
        return Status(self.outputs, self.flags, self.last_heartbeat)

    # -- version 2: feed override and the CNC ----------------------------------

    def context(self) -> Context | None:
        if self.protocol < 2:
            return None
        return Context(self.context_index, self.program, self.tool, self.operation, self.cnc_flags)

    @property
    def cnc_feed_held(self) -> bool:
        return bool(self.cnc_flags & CTX_FEED_HELD)

    def set_feed_override(self, tenths: int, now: float, cause: str = "command") -> bool:
        """Command the override (0.1 % steps); False if out of 0..2000 (refused) or no such output.

        The CNC applies it through its lag (``produce``); ``feed_override`` follows."""
        if self.protocol < 2:
            return False
        if cause == "command":  # every command the host sends, even one that changes nothing
            self.log.write("feed_override_command", now, value=tenths)
        if not 0 <= tenths <= FEED_OVERRIDE_MAX:
            self.log.write("feed_override_refused", now, value=tenths, cause=cause)
            return False
        if tenths != self.feed_override_commanded:
            self.feed_override_commanded = tenths
            self.log.write("feed_override", now, feed_override=tenths, cause=cause)
        return True

    def _feed_hold_changed(self, now: float) -> None:
        """The feed-hold output may have changed: the CNC follows it after its lag."""
        held = self.feed_hold
        if self.protocol >= 2 and held != self._cnc_target:
            self._cnc_target = held
            self._cnc_pending.append((now + self.cnc_hold_lag_s, held))

    def next_cnc_time(self) -> float | None:
        """When the CNC's next pending change is due (monotonic), or None."""
        return self._cnc_pending[0][0] if self._cnc_pending else None

    def update_cnc(self, now: float) -> bool:
        """Apply the CNC changes that are due; True if the context changed."""
        changed = False
        while self._cnc_pending and self._cnc_pending[0][0] <= now:
            due, held = self._cnc_pending.popleft()
            flags = (self.cnc_flags | CTX_FEED_HELD) if held else (self.cnc_flags & ~CTX_FEED_HELD)
            if flags != self.cnc_flags:
                self.cnc_flags = flags
                self.context_index = self.head
                changed = True
                self.log.write("cnc_feed_held", now, feed_held=held, due_mono=due, index=self.head)
        return changed

    @property
    def feed_hold(self) -> bool:
        return bool(self.outputs & OUT_FEED_HOLD)

    def set_outputs(self, bits: int, now: float, cause: str = "command") -> bool:
        """An explicit set-outputs command: clears a watchdog trip too. True if anything changed."""
        bits &= 0x03
        changed = bits != self.outputs or (self.flags & FLAG_WATCHDOG)
        self.outputs = bits
        self.commanded = bits
        self.flags &= ~FLAG_WATCHDOG
        self.source.feed_hold = bool(bits & OUT_FEED_HOLD)
        if changed:
            self._log_outputs(now, cause)
        self._feed_hold_changed(now)
        return bool(changed)

    def heartbeat(self, counter: int, now: float) -> None:
        """A heartbeat counts only if the value changed (the host writes a changing counter)."""
        counter &= 0xFFFF
        # A device's watchdog runs on its own: a heartbeat that arrives after the deadline comes to a
        # watchdog that has already tripped, even when nothing polled it in between (the in-process DAQ
        # is polled by the daemon's reader thread, which a stopped or starved daemon does not run).
        self.check_watchdog(now)
        if self._heard_heartbeat and counter == self.last_heartbeat:
            return
        self._heard_heartbeat = True
        self.last_heartbeat = counter
        self._last_heartbeat_time = now
        self._armed = True
        self.log.write("heartbeat", now, counter=counter)

    def set_watchdog_ms(self, ms: int, now: float) -> None:
        if ms != self.watchdog_ms:
            self.watchdog_ms = ms
            self.log.write("watchdog_period", now, watchdog_ms=ms)
            if self._heard_heartbeat:
                self._last_heartbeat_time = max(self._last_heartbeat_time, now)

    def watchdog_deadline(self) -> float | None:
        """Monotonic time at which the watchdog trips unless a heartbeat comes, or None."""
        if not self._armed or self.watchdog_ms <= 0 or self.flags & FLAG_WATCHDOG:
            return None
        return self._last_heartbeat_time + self.watchdog_ms / 1000.0

    def check_watchdog(self, now: float) -> bool:
        """Trip if the deadline passed: assert feed hold, raise the flag. True if it tripped now."""
        deadline = self.watchdog_deadline()
        if deadline is None or now < deadline or self.watchdog_broken:
            return False
        self.outputs |= OUT_FEED_HOLD
        self.flags |= FLAG_WATCHDOG
        self.source.feed_hold = True
        self._log_outputs(now, "watchdog", last_heartbeat_mono=self._last_heartbeat_time)
        self._feed_hold_changed(now)
        # a silent host must not leave the machine at a feed it chose
        self.set_feed_override(FEED_OVERRIDE_NEUTRAL, now, cause="watchdog")
        return True

    def apply_command(self, cmd: Command, now: float) -> bool:
        """Apply a COMMAND frame; True if the outputs changed."""
        if cmd.command == CMD_SET_OUTPUTS:
            return self.set_outputs(cmd.argument or 0, now)
        if cmd.command == CMD_HEARTBEAT:
            self.heartbeat(cmd.argument or 0, now)
        elif cmd.command == CMD_SET_FEED_OVERRIDE:
            self.set_feed_override(cmd.argument or 0, now)
        return False

    def _log_outputs(self, now: float, cause: str, **extra) -> None:
        self.log.write(
            "outputs",
            now,
            outputs=self.outputs,
            feed_hold=bool(self.outputs & 1),
            alarm_lamp=bool(self.outputs & 2),
            watchdog=bool(self.flags & FLAG_WATCHDOG),
            cause=cause,
            **extra,
        )
