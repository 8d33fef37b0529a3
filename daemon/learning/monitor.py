"""`ProcessMonitor`: processes cut from the revolutions, envelopes learned and checked, wear. Pure.

The runner (and replay) call it revolution by revolution on the estimator
thread, like `AlarmEngine`: `on_revolution(est, ctx)` with the context that
held at the revolution's last sample, `on_context` after the revolutions up to
that sample were given, `on_link_lost`, `note_alarm` for each fixed-limit alarm.
Each call returns a `MonitorStep`: the alarm events to publish (and trip on,
`AlarmEvent.trips`), the finished processes' summaries, one-time notes to log,
and the keys and tools whose state changed (to persist).

The rules (docs/learning.md):
- A process is the revolutions of one key while `cycle` and `monitor` are set;
  it ends when the key changes, the cycle ends, monitor clears, the context goes
  away (incomplete) or the link is lost (incomplete; what follows of the same
  key with monitor still set is incomplete too). A process that cuts from its
  first revolution began before it was seen: incomplete. A key's cycle that
  never set `monitor` is reported at its end as "unmonitored".
- Complete processes with an entry, no alarm and at most 10 % invalid
  revolutions teach their key until `processes` have; then the envelope is
  learned, active at once or (`confirm`) pending until `accept`.
- With an active envelope, every valid revolution of a process is checked: above the band `high_revolutions` in a row → `envelope_high`, below it
  (where the band expects cutting) `low_revolutions` in a row → `envelope_low`;
  no entry by the learned entry + margin → `envelope_low` on "entry"; a process
  that ran its course with its energy below the band → `envelope_low` on
  "cutting_energy_j". At most one of each per process. One that holds the feed
  latches until `reset()`; one that does not clears when its process ends.
- Each good checked process adds its energy ratio to its tool's wear
  (`wear.py`); a wear warning never holds the feed.
- While the feed moves (the CNC's override), everything above is in terms of
  the programmed feed (`process.py`): loads normalised by (ovr/100)^gain,
  `process_rev` by progress along the path, energy of the same cut at the
  programmed feed. The estimate's `envelope_*_nm` and an alarm's value and limit
  are in the revolution's own terms (the band times its scale), so they read
  against its torque. At 100 % nothing differs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from millsense.daemon.events import AlarmEvent, finite
from millsense.daemon.learning.actions import ACTIONS, run_command
from millsense.daemon.learning.context import Ctx
from millsense.daemon.learning.envelope import Envelope, Taught, Widths, learn, setting
from millsense.daemon.learning.expected import KEPT_WARNING_PROCESSES, ExpectedBand
from millsense.daemon.learning.expected import LEVELS as EXPECTED_LEVELS
from millsense.daemon.learning.keys import KEY_RE, UINT16_MAX, UINT32_MAX, KeyState, key_show, key_summary, seen_outside
from millsense.daemon.learning.process import ProcessRun
from millsense.daemon.learning.wear import ToolWear
from millsense.daemon.physics.milling import load_scale

# Levels of the fixed limits that keep a process from teaching (`note_alarm`).
_FIXED_LEVELS = frozenset({"warning", "overload", "crash", "tool_breakage", "daq_lost"})
# The most process keys and tools one machine keeps. A real machine's are hundreds; a CNC adapter (or a peer
# on an open network) putting a new context every revolution would otherwise grow them without end, and
# every `status` and `limits` answer with them (a probe of stop 26: 8,000 keys in 10 minutes, then queries that
# starved the estimator thread until the DAQ's watchdog held the feed). At the cap a new key or tool is not
# learned (said once in the log, `learning.full`); those learned so far keep theirs.
MAX_KEYS = 2000
MAX_TOOLS = 1000
NO_CONTEXT = ("no context from the CNC (the DAQ's CONTEXT frames or millsense/<machine>/context): "
              "no processes, no learned limits; the fixed [alarms] limits stay armed")


@dataclass
class MonitorStep:
    """What one call produced."""

    events: list[AlarmEvent] = field(default_factory=list)
    processes: list[dict[str, Any]] = field(default_factory=list)   # `process` payloads without machine, t
    notes: list[tuple[str, dict[str, Any]]] = field(default_factory=list)   # (log event, its fields), each once
    changed_keys: set[str] = field(default_factory=set)
    tools_changed: set[int] = field(default_factory=set)


class ProcessMonitor:
    """All learning state of one machine. Not thread-safe: one owner (the estimator thread)."""

    def __init__(self, learning: Any, limits: dict[str, Any] | None = None, tools: Any = None,
                 first_process: int = 1, gain: float = 1.0, alarms: Any = None, expected: Any = None):
        self.learning = learning
        # the physics' expected band of the configured [operations] (expected.py); None: none declared
        self.expected: ExpectedBand | None = expected
        self.gain = float(gain)   # load ~ feed^gain (override_track.load_gain): the programmed-feed normalisation
        self.enabled = bool(setting(learning, "enabled", True))
        self.target = int(setting(learning, "processes", 5))
        self.confirm = bool(setting(learning, "confirm", False))
        self.high_revolutions = max(1, int(setting(learning, "high_revolutions", 3)))
        self.low_revolutions = max(1, int(setting(learning, "low_revolutions", 3)))
        self.hold_high = bool(setting(learning, "hold_high", True))
        self.hold_low = bool(setting(learning, "hold_low", True))
        self.wear_rise_pct = float(setting(learning, "wear_rise_pct", 15.0))
        self.wear_window = int(setting(learning, "wear_window", 3))
        self.widths = Widths.of(learning)
        # the fixed [alarms] limits a band's high side never passes (envelope.py, "bounded")
        self.ceilings = (setting(alarms, "torque_limit_nm", None), setting(alarms, "force_limit_n", None))
        self.keys: dict[str, KeyState] = {}
        self.unusable: dict[str, str] = {}       # stored rows whose key is no process key: left as they are
        self.restore_notes: list[tuple[str, dict[str, Any]]] = []   # what the restore set aside, to log once
        self._changed_keys: set[str] = set()     # by commands (and the restore), handed out with the next step
        self._changed_tools: set[int] = set()
        for key, data in (limits or {}).items():
            self._restore_key(key, data)
        self.tools = self._restore_tools(tools)
        self.proc: ProcessRun | None = None
        self.next_process = int(first_process)   # the runner may seed it from the history (ids go on)
        self._resume_key: str | None = None      # a link loss cut this key's process: the rest is incomplete
        self._run_key: str | None = None         # the key whose cycle runs now (None: no cycle)
        self._run_monitored = False              # that run had its monitored process
        self._latched: list[AlarmEvent] = []
        self._noted_no_context = False
        self.refused_keys = 0                    # new keys not learned at MAX_KEYS (tools: MAX_TOOLS)
        self.refused_tools = 0

    # -- restore (what the history kept): a stored row that fails its check never stops the daemon --------
    def _restore_key(self, key: Any, data: Any) -> None:
        """One stored key: restored, bounded and under today's fixed limits; or set aside (its process learns
        afresh, the fixed limits apply meanwhile, the row is kept in the key's state so nothing is lost).

        `data` is the stored JSON value, or the exception that says why the row could not be read."""
        key = str(key)
        try:
            if isinstance(data, BaseException):
                raise ValueError(str(data))
            ks = KeyState.from_dict(data, self.widths)
            if ks.envelope is not None:
                ks.envelope.set_ceilings(*self.ceilings)
        except Exception as exc:  # noqa: BLE001 - whatever is stored, the daemon starts (ValueError when checked)
            reason = _one_line(f"{exc}" if isinstance(exc, ValueError) else f"{type(exc).__name__}: {exc}")
            self._set_aside(key, reason, getattr(data, "text", data))
            return
        if not _is_key(key):
            self._set_aside(key, "not a process key program/tool/operation", data)
            return
        self.keys[key] = ks

    def _set_aside(self, key: str, reason: str, row: Any) -> None:
        self.restore_notes.append(("learning.set_aside", {"key": key, "reason": reason}))
        if not _is_key(key):
            self.unusable[key] = reason   # no process has this key: shown, never learned
            return
        self.keys[key] = KeyState(set_aside=reason, set_aside_row=_jsonable(row))
        self._changed_keys.add(key)       # saved with the next step: the row now says it was set aside

    def _restore_tools(self, tools: Any) -> dict[int, ToolWear]:
        """The stored tool table; a tool whose entry fails its check starts its life and wear afresh (logged)."""
        out: dict[int, ToolWear] = {}
        if tools is None:
            return out
        if not isinstance(tools, dict):
            self.restore_notes.append(("learning.tools_set_aside", {"reason": _one_line(f"not an object: {tools}")}))
            return out
        for number, data in tools.items():
            try:
                tool = int(str(number))
                if not 0 <= tool <= UINT32_MAX:
                    raise ValueError(f"{number!r} is not a tool number")
                out[tool] = ToolWear.from_dict(data)
            except Exception as exc:  # noqa: BLE001 - whatever is stored, the daemon starts
                self.restore_notes.append(("learning.tools_set_aside",
                                           {"tool": str(number), "reason": _one_line(str(exc))}))
        return out

    def on_revolution(self, est: dict[str, Any], ctx: Ctx | None) -> MonitorStep:
        """One estimate; annotated in place with program, tool, operation, process_rev, envelope_*_nm."""
        step = self._step()
        est["program"] = None if ctx is None else ctx.program
        est["tool"] = None if ctx is None else ctx.tool
        est["operation"] = None if ctx is None else ctx.operation
        est["process_rev"] = None
        est["envelope_low_nm"] = None
        est["envelope_high_nm"] = None
        if ctx is None:
            self._context_gone(step)
            if self.enabled and not self._noted_no_context:
                self._noted_no_context = True
                step.notes.append(("learning.no_context", {"reason": NO_CONTEXT}))
            return step
        self._noted_no_context = False   # said again if the context goes away again
        if not self.enabled:
            return step
        self._boundaries(step, ctx)
        if self._run_key is None:
            return step   # no cycle: no process
        proc = self.proc
        if proc is None:
            if ctx.monitor:
                resumed = self._resume_key == ctx.key
                self._resume_key = None
                proc = self.proc = ProcessRun(self.next_process, ctx, monitored=True, resumed=resumed, gain=self.gain)
                self.next_process += 1
                self._run_monitored = True
            elif self._run_monitored:
                return step   # after its monitored process: the retract, the spindle stopping
            else:
                proc = self.proc = ProcessRun(0, ctx, monitored=False, gain=self.gain)   # numbered if reported
        k = proc.add(est)
        if proc.monitored:
            est["process_rev"] = k
            self._check(step, proc, est, k)
            if self.expected is not None:
                self._physics(step, proc, est, k)
        return step

    def on_context(self, ctx: Ctx | None, seq: int | None = None) -> MonitorStep:
        """The context now (after the revolutions up to `seq`): a process it ends closes without a revolution."""
        step = self._step()
        if ctx is None:
            self._context_gone(step)
        elif self.enabled:
            self._boundaries(step, ctx)
        return step

    def _boundaries(self, step: MonitorStep, ctx: Ctx) -> None:
        """Close what `ctx` ends: a new key or no cycle ends the key's run, monitor off ends its process.

        A key's run is its revolutions while the cycle is set. Its process is the
        part of it with `monitor` set (the CNC clears it for the spindle coming up
        and the retract). A run that never set `monitor` is reported once, at its
        end, as "unmonitored" (it still used its tool).
        """
        run_key = ctx.key if ctx.cycle else None
        if run_key != self._run_key:
            if self.proc is not None:
                self._close(step)
            if run_key != self._resume_key:
                self._resume_key = None
            self._run_key, self._run_monitored = run_key, False
            return
        proc = self.proc
        if proc is not None and proc.monitored != ctx.monitor:
            if proc.monitored:
                self._close(step)
            else:
                self.proc = None   # the lead-in of a monitored process is not a process of its own
        if not ctx.monitor:
            self._resume_key = None   # monitor off seen: the next process is seen from its start

    def _context_gone(self, step: MonitorStep) -> None:
        if self.proc is not None:
            self._close(step, incomplete=True)
        self._run_key, self._run_monitored = None, False

    def on_link_lost(self) -> MonitorStep:
        """The DAQ link went down: the current process is incomplete, and so is the rest of it."""
        step = self._step()
        proc = self.proc
        if proc is not None and proc.monitored:
            self._resume_key = proc.key
            self._close(step, incomplete=True)
        else:
            self.proc = None   # an unmonitored run cut short: nothing to report
        return step

    def take_restore_notes(self) -> list[tuple[str, dict[str, Any]]]:
        """What the restore set aside (log event, fields), once: the caller logs it at start."""
        notes, self.restore_notes = self.restore_notes, []
        return notes

    def note_alarm(self, ev: AlarmEvent) -> None:
        """A fixed-limit alarm: the process it happened in does not teach."""
        if self.proc is not None and ev.level in _FIXED_LEVELS:
            self.proc.fixed_alarm = True

    def reset(self) -> list[AlarmEvent]:
        """Operator reset: the latched envelope alarms clear."""
        events = [AlarmEvent("clear", ev.quantity, None, ev.limit, detail=ev.detail) for ev in self._latched]
        self._latched = []
        return events

    # -- the checks -----------------------------------------------------------
    def _active_envelope(self, proc: ProcessRun) -> Envelope | None:
        ks = self.keys.get(proc.key)
        if ks is None or ks.state != "active" or not proc.monitored or proc.resumed:
            return None
        return ks.envelope

    def _low_check(self, proc: ProcessRun) -> bool:
        """envelope_low is checked for the process's key (`limits low-off` turns it off, audited)."""
        ks = self.keys.get(proc.key)
        return ks is None or ks.low_check

    def _check(self, step: MonitorStep, proc: ProcessRun, est: dict[str, Any], k: int | None) -> None:
        env = self._active_envelope(proc)
        if env is None:
            return
        if k is None:
            # revolutions before entry counted as progress along the path (the plain count at 100 %); an
            # entry being confirmed began in its first revolution
            if self._low_check(proc):
                self._check_entry(step, proc, env)
            return
        if k >= env.length:
            return  # longer than learned: nothing to compare with
        # the band is at the programmed feed; published, and alarms, in this revolution's terms
        scale = load_scale(est.get("feed_override_pct"), self.gain)
        low_check = self._low_check(proc)
        low, high = env.torque.bounds(k)
        est["envelope_low_nm"] = None if low is None or not low_check else round(low * scale, 4)
        est["envelope_high_nm"] = None if high is None else round(high * scale, 4)
        if not est.get("valid", True):
            return  # a damaged revolution neither counts nor breaks a run
        for quantity, band in (("torque_nm", env.torque), ("force_n", env.force)):
            value = finite(est.get(quantity))
            norm = None if value is None else value / scale
            low, high = (None, None) if band is None else band.bounds(k)
            self._judge(step, proc, "envelope_high", quantity, value, norm, high, scale,
                        norm is not None and high is not None and norm > high, k)
            # low only where the band expects cutting, and while envelope_low is on for the key
            self._judge(step, proc, "envelope_low", quantity, value, norm, low, scale,
                        low_check and norm is not None and low is not None and low > 0 and norm < low, k)

    def _physics(self, step: MonitorStep, proc: ProcessRun, est: dict[str, Any], k: int | None) -> None:
        """The expected band of the key's operation (expected.py), every part; its alarms latch like the envelope's."""
        ks = self.keys.get(proc.key)
        judged = self.expected.judge(proc, est, k, None if ks is None else ks.expected_widening, self._low_check(proc))
        step.notes.extend(judged.notes)
        for ev, _observed in judged.events:
            proc.raised[ev.level] = ev
            if ev.hold:
                self._latched.append(ev)
            step.events.append(ev)

    def _judge(self, step: MonitorStep, proc: ProcessRun, level: str, quantity: str, value: float | None,
               norm: float | None, limit: float | None, scale: float, outside: bool, k: int) -> None:
        """`norm`, `limit`: at the programmed feed; `value` as cut (`scale` = (ovr/100)^gain between them)."""
        run_key = (level, quantity)
        proc.runs[run_key] = proc.runs.get(run_key, 0) + 1 if outside else 0
        if outside:   # what `false-alarm` widens the band by: at the programmed feed, like the band
            proc.outside.setdefault(f"{level}:{quantity}", {})[k] = norm
        need = self.high_revolutions if level == "envelope_high" else self.low_revolutions
        if outside and proc.runs[run_key] >= need:
            self._raise(step, proc, level, quantity, value, None if limit is None else limit * scale, k, None)

    def _raise(self, step: MonitorStep, proc: ProcessRun, level: str, quantity: str, value: float | None,
               limit: float | None, k: int | None, observed: dict[int, float] | None) -> None:
        if level in proc.raised:
            return  # at most one of each per process
        hold = self.hold_high if level == "envelope_high" else self.hold_low
        ev = AlarmEvent(level, quantity, value, limit, proc.last_rev, proc.last_seq, hold=hold,
                        detail=proc.detail(k))
        proc.raised[level] = ev
        if observed is not None:
            proc.outside[f"{level}:{quantity}"] = observed
        if hold:
            self._latched.append(ev)
        step.events.append(ev)

    # -- the end of a process -------------------------------------------------
    def _close(self, step: MonitorStep, incomplete: bool = False) -> None:
        proc, self.proc = self.proc, None
        if not proc.monitored:
            if incomplete:
                return   # an unmonitored run cut short: nothing to report
            proc.pid = self.next_process
            self.next_process += 1
        incomplete = incomplete or (proc.monitored and proc.resumed)
        ks = self.keys.get(proc.key)
        env = None if incomplete else self._active_envelope(proc)
        if env is not None and "envelope_low" not in proc.raised and not proc.too_damaged and self._low_check(proc):
            self._end_checks(step, proc, env)
        verdict = self._verdict(proc, ks, incomplete)
        if verdict in EXPECTED_LEVELS and proc.teaches and not proc.fixed_alarm:
            ks = self._keep_from_teaching(step, proc, ks)
        elif verdict == "learning" and ks is not None:
            ks.kept = 0
        if verdict == "learning" and ks is None and proc.teaches:   # a key for a process that teaches, no other
            ks = self._new_key(step, proc.key)
        if verdict == "learning" and ks is not None and ks.state == "learning":
            self._teach(step, proc, ks)
        if proc.raised:
            ks = self.keys.get(proc.key) or self._new_key(step, proc.key)
            if ks is not None:
                ks.last_alarms = seen_outside(proc)
                step.changed_keys.add(proc.key)
        for ev in proc.raised.values():
            if not ev.hold:
                step.events.append(AlarmEvent("clear", ev.quantity, None, ev.limit, proc.last_rev, proc.last_seq,
                                              detail=ev.detail))
        ratio = None
        if not incomplete and ks is not None and ks.envelope is not None and ks.envelope.energy_mean_j > 0:
            ratio = proc.energy_j / ks.envelope.energy_mean_j
        wear = self._wear(step, proc, verdict, ratio)
        summary = proc.summary(verdict)
        if proc.monitored and self.has_operation(proc.key):
            summary.update(self.expected.summary(proc))   # was the physics' band armed in it (expected.py)
        summary.update({
            "learned": 0 if ks is None else (ks.envelope.n if ks.envelope is not None else len(ks.taught)),
            "learn_target": self.target, "envelope": "learning" if ks is None else ks.state,
            "energy_ratio": None if ratio is None else round(ratio, 4),
            "tool_processes": None if wear is None else wear.processes,
            "tool_wear_pct": None if wear is None or wear.wear_pct is None else round(wear.wear_pct, 2),
        })
        step.processes.append(summary)

    def _check_entry(self, step: MonitorStep, proc: ProcessRun, env: Envelope) -> None:
        """No entry by the learned deadline: the part or the tool is missing."""
        without = proc.progress_without_entry
        if without >= env.entry_deadline:
            self._raise(step, proc, "envelope_low", "entry", round(without, 2), float(env.entry_deadline), None,
                        {0: round(without, 2)})

    def _end_checks(self, step: MonitorStep, proc: ProcessRun, env: Envelope) -> None:
        """No entry at all, or too little energy, in a process that ran its course."""
        if proc.entry_rev is None:
            self._check_entry(step, proc, env)
            return
        if len(proc.torque_nm) >= env.cut_length and proc.energy_j < env.energy_low_j:
            self._raise(step, proc, "envelope_low", "cutting_energy_j", round(proc.energy_j, 3),
                        round(env.energy_low_j, 3), None, {0: proc.energy_j})

    @staticmethod
    def _verdict(proc: ProcessRun, ks: KeyState | None, incomplete: bool) -> str:
        if incomplete:
            return "incomplete"
        if not proc.monitored:
            return "unmonitored"
        for level in ("envelope_high", "envelope_low") + EXPECTED_LEVELS:
            if level in proc.raised:
                return level
        if proc.fixed_alarm:
            return "alarm"
        if ks is None or ks.state != "active":
            return "learning"
        return "good"

    def _new_key(self, step: MonitorStep, key: str) -> KeyState | None:
        """A new key's state, None at MAX_KEYS (refused, said)."""
        if len(self.keys) >= MAX_KEYS:
            self.refused_keys += 1
            self._say_full(step)
            return None
        ks = self.keys[key] = KeyState()
        return ks

    def _say_full(self, step: MonitorStep) -> None:
        if self.refused_keys + self.refused_tools == 1:   # a note is said once a run
            step.notes.append(("learning.full", {
                "keys": len(self.keys), "max_keys": MAX_KEYS, "tools": len(self.tools), "max_tools": MAX_TOOLS,
                "refused_keys": self.refused_keys, "refused_tools": self.refused_tools,
                "detail": "new process keys or tools are not learned: is a CNC adapter putting a new program, tool "
                          "or operation number every cycle? The keys learned so far keep their limits"}))

    def _keep_from_teaching(self, step: MonitorStep, proc: ProcessRun, ks: KeyState | None) -> KeyState | None:
        """A process outside its expected band does not teach: kept back (accept / false-alarm teach it);
        KEPT_WARNING_PROCESSES in a row are warned once (`learning.kept_from_teaching`)."""
        ks = ks if ks is not None else self._new_key(step, proc.key)
        if ks is None or ks.state != "learning":
            return ks
        torque, force = proc.arrays()
        ks.held_back = Taught(torque, force, proc.entry_progress, proc.energy_j)
        ks.kept += 1
        step.changed_keys.add(proc.key)
        if ks.kept == KEPT_WARNING_PROCESSES:
            step.notes.append(("learning.kept_from_teaching", {
                "key": proc.key, "processes": ks.kept,
                "detail": "processes in a row outside the physics' expected band do not teach: check the "
                          "operation's [operations] entry (depths, feed, material) and the tool; `limits accept "
                          "KEY` or `limits false-alarm KEY` teaches the last one"}))
        return ks

    def teach_held_back(self, key: str) -> bool:
        """The operator accepted the process kept from teaching (or marked its alarm false): it teaches now."""
        ks = self.keys.get(key)
        if ks is None or ks.held_back is None or ks.state != "learning":
            return False
        taught, ks.held_back, ks.kept = ks.held_back, None, 0
        self._add_taught(ks, taught)
        self.changed_by_command(keys={key})
        return True

    def _teach(self, step: MonitorStep, proc: ProcessRun, ks: KeyState) -> None:
        if not proc.teaches:
            return  # nothing cut, or too little seen: it would teach a wrong footprint
        torque, force = proc.arrays()
        self._add_taught(ks, Taught(torque, force, proc.entry_progress, proc.energy_j))
        step.changed_keys.add(proc.key)

    def _add_taught(self, ks: KeyState, taught: Taught) -> None:
        ks.taught.append(taught)
        ks.held_back = None
        if len(ks.taught) >= self.target:
            ks.envelope = learn(ks.taught, self.learning)
            ks.envelope.set_ceilings(*self.ceilings)
            ks.taught = []   # the envelope holds what matters; the arrays would only cost memory
            ks.state = "pending" if self.confirm else "active"
            ks.set_aside = None   # taught again: no longer a warning (the row set aside stays in its state)

    def _wear(self, step: MonitorStep, proc: ProcessRun, verdict: str, ratio: float | None) -> ToolWear | None:
        tool = proc.ctx.tool
        wear = self.tools.get(tool)
        if proc.entry_rev is None:
            return wear   # it never cut: no life used
        if wear is None:
            if len(self.tools) >= MAX_TOOLS:
                self.refused_tools += 1
                self._say_full(step)
                return None
            wear = self.tools[tool] = ToolWear()
        wear.count_process()
        step.tools_changed.add(tool)
        if verdict == "good" and ratio is not None and wear.add_ratio(ratio, self.wear_window, self.wear_rise_pct):
            step.events.append(AlarmEvent("wear", "cutting_energy_pct", round(wear.wear_pct, 2), self.wear_rise_pct,
                                          proc.last_rev, proc.last_seq, hold=False, detail=proc.detail(None)))
        return wear

    # -- state for status, the limits queryable and the CLI ------------------
    def active(self) -> dict[str, str]:
        """Active learned-limit states by name, for status."""
        out: dict[str, str] = {}
        for ev in self._latched:
            out[ev.level] = ev.level
        if self.proc is not None:
            for ev in self.proc.raised.values():
                out[ev.level] = ev.level
        for tool, wear in sorted(self.tools.items()):
            if wear.warned:
                out[f"wear_T{tool}"] = "wear"
        return out

    def state_counts(self) -> dict[str, int]:
        """How many keys are learning, pending, active (for status, every second: no summaries built)."""
        counts = {"learning": 0, "pending": 0, "active": 0}
        for ks in self.keys.values():
            counts[ks.state] = counts.get(ks.state, 0) + 1
        return counts

    def learned_limits_status(self) -> dict[str, list]:
        """For `status` (`learned_limits`): keys whose stored state was set aside, keys with envelope_low off."""
        aside = [{"key": k, "reason": ks.set_aside} for k, ks in sorted(self.keys.items()) if ks.set_aside]
        aside += [{"key": k, "reason": r} for k, r in sorted(self.unusable.items())]
        return {"set_aside": aside, "low_off": sorted(k for k, ks in self.keys.items() if not ks.low_check)}

    def limits_summary(self) -> dict[str, Any]:
        """The `limits` queryable's body without machine."""
        return {
            "set_aside": self.learned_limits_status()["set_aside"],
            "limits": [key_summary(k, self.keys[k], self.target) for k in sorted(self.keys)],
            "tools": {str(t): {"processes": w.processes,
                               "wear_pct": None if w.wear_pct is None else round(w.wear_pct, 2),
                               "warned": w.warned} for t, w in sorted(self.tools.items())},
        }

    def learned_mean(self, key: str, quantity: str) -> float | None:
        """The mean over the cut of `key`'s learned band mean (`torque_nm` or `force_n`), at the programmed feed.

        "Over the cut": the process_rev where the torque band expects cutting (its low side above 0), so
        neither the entry nor the exit's partial revolutions pull it down. None until an envelope is active
        (a pending one is not trusted yet), for a quantity without a band, or when no revolution cuts.
        """
        ks = self.keys.get(str(key))
        if ks is None or ks.state != "active" or ks.envelope is None:
            return None
        env = ks.envelope
        band = env.force if quantity == "force_n" else env.torque if quantity == "torque_nm" else None
        if band is None:
            return None
        cut = [float(band.mean[k]) for k, low in enumerate(env.torque.low_nan)
               if low > 0 and k < len(band.mean) and math.isfinite(band.mean[k])]   # NaN > 0 is False
        return sum(cut) / len(cut) if cut else None

    def show(self, key: str) -> dict[str, Any]:
        """One key's summary and its band along process_rev (None where there is none); for a key with an
        operation also its expected load beside the learned mean, and their ratio (expected.py)."""
        ks = self.keys.get(key)
        op = None if self.expected is None else self.expected.cut(key)
        if ks is None and op is None:
            raise KeyError(key)
        out = key_show(key, ks if ks is not None else KeyState(), self.target)
        if op is not None:
            learned = {q: self.learned_mean(key, q) for q in ("torque_nm", "force_n")}
            out.update(self.expected.show(key, learned, None if ks is None else ks.expected_widening) or {})
        return out

    def has_operation(self, key: str) -> bool:
        return self.expected is not None and self.expected.cut(key) is not None

    def export_limits(self, key: str) -> dict[str, Any]:
        """One key's whole state, JSON-safe (the `limits` argument takes it back)."""
        return self.keys[key].to_dict()

    def bounds(self, key: Any) -> dict[str, Any] | None:
        """One key's limits in a few numbers, for `limits/change`'s before and after (docs/zenoh.md); None: no
        such key. The band's extremes, not its arrays: a change is told, the band itself is `limits show`'s."""
        ks = self.keys.get(key) if isinstance(key, str) else None
        if ks is None:
            return None
        env = ks.envelope
        out: dict[str, Any] = {"state": ks.state, "learned": env.n if env is not None else len(ks.taught),
                               "low_check": ks.low_check, "widening": None, "torque_high_max_nm": None,
                               "torque_low_min_nm": None, "force_high_max_n": None, "expected_widening": None}
        if env is not None:
            out["widening"] = round(env.widening(), 6)
            highs = [v for v in env.torque.high if v is not None]
            lows = [v for v in env.torque.low if v is not None]
            out["torque_high_max_nm"] = round(max(highs), 6) if highs else None
            out["torque_low_min_nm"] = round(min(lows), 6) if lows else None
            if env.force is not None:
                fh = [v for v in env.force.high if v is not None]
                out["force_high_max_n"] = round(max(fh), 6) if fh else None
        if ks.expected_widening is not None:
            out["expected_widening"] = {"high": round(ks.expected_widening.high, 6),
                                        "low": round(ks.expected_widening.low, 6)}
        return out

    def export_tools(self) -> dict[str, Any]:
        return {str(t): w.to_dict() for t, w in sorted(self.tools.items())}

    def take_changes(self) -> tuple[set[str], set[int]]:
        """Keys and tools changed by commands not yet handed out (`command` hands out its own)."""
        keys, tools = self._changed_keys, self._changed_tools
        self._changed_keys, self._changed_tools = set(), set()
        return keys, tools

    def _step(self) -> MonitorStep:
        keys, tools = self.take_changes()
        return MonitorStep(changed_keys=keys, tools_changed=tools)

    def changed_by_command(self, keys: set[str] = frozenset(), tools: set[int] = frozenset()) -> None:
        self._changed_keys |= set(keys)
        self._changed_tools |= set(tools)

    # -- the operator's actions (actions.py) ------------------------------------
    def command(self, args: Any) -> dict[str, Any]:
        """`cmd/limits` and `millsense limits`: {"action", "key"?, "pct"?, "tool"?} → {"ok", "error"?, ...}.

        The reply also carries `changed_keys` and `tools_changed` (lists, empty when
        nothing changed): what the caller persists, and pops before answering.
        """
        reply = run_command(self, args)
        keys, tools = self.take_changes()
        reply["changed_keys"], reply["tools_changed"] = sorted(keys), sorted(tools)
        return reply


def _is_key(key: str) -> bool:
    m = KEY_RE.match(key)
    return (m is not None and str(int(m[1])) == m[1] and str(int(m[2])) == m[2] and str(int(m[3])) == m[3]
            and int(m[1]) <= UINT32_MAX and int(m[2]) <= UINT32_MAX and int(m[3]) <= UINT16_MAX)


def _one_line(text: str, limit: int = 200) -> str:
    line = " ".join(str(text).split())
    return line if len(line) <= limit else line[: limit - 1] + "…"


def _jsonable(value: Any, depth: int = 0) -> Any:
    """A stored value kept as it was read, JSON-safe (non-finite numbers as null, bounded depth)."""
    if depth > 64:
        return None
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if value is None or isinstance(value, (bool, int, str)):
        return value
    if isinstance(value, dict):
        return {str(k): _jsonable(v, depth + 1) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v, depth + 1) for v in value]
    return str(value)


__all__ = ["ACTIONS", "KeyState", "MonitorStep", "ProcessMonitor"]
