"""The CNC running a part program on the plant: spindle, feed, tool changes and context, sample by sample.

``ProgramPlant`` is a ``Plant`` whose NC is a state machine over the phases of
``program.py`` (load, change, spin-up, feed, retract, spin-down) instead of one
scenario's feed and speed schedule. Per 1 kHz sample it advances the phase
(program time stops under a feed hold), moves the feed by position, commands
the spindle, and records each change of the CNC's context with the index of
the first sample it holds for. Hooks of ``Plant`` carry the rest:

- a tool change always starts a block (``_nc`` ends the block before it), so
  the cutter, its chip factors and the worn material are swapped between
  blocks, with the spindle at rest;
- the drive stops at standstill: commanded to 0 rpm, once the spindle reaches
  0 the drive is off (no voltage, no current) and the brake holds it;
- ``_account`` integrates the true cutting energy ∫T·ω dt = ∫T dθ over each
  monitored process and writes its truth line when it has ended.

Nothing here imports ``millsense.daemon``: this is the machine, not the model.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from millsense.drivers.protocol import CTX_AFC_ALLOWED, CTX_CYCLE, CTX_MONITOR
from millsense.sim.cut_effects import material_batch
from millsense.sim.cutting import CutGeometry, tooth_chip_factors
from millsense.sim.machine import Tool
from millsense.sim.plant import CUT_PER_SAMPLE, SAMPLE_RATE_HZ, Plant
from millsense.sim.program import (
    BROKEN_FLUTE,
    PART_GAP_S,
    PROGRAMS,
    RETRACT_S,
    SETTLE_S,
    STOP_S,
    TAIL_S,
    TOOL_CHANGE_S,
    Operation,
    PartProgram,
    ProgramFaults,
)

CUTTING_MIN_NM = 1e-4  # a sample is "cutting" when its true mean cutting torque is above this


@dataclass
class _Process:
    """One monitored span of the run: what the truth file lists per process."""

    seq: int
    part: int
    op: Operation
    pass_no: int
    first_index: int
    wear_factor: float
    fault: str | None
    cutter: Tool
    last_index: int | None = None
    energy_j: float = 0.0
    entry_index: int | None = None
    broken_index: int | None = None

    def record(self, program: int) -> dict:
        return {
            "process": self.seq, "pass": self.pass_no, "part": self.part, "program": program,
            "tool": self.op.tool_number, "operation": self.op.number,
            "key": f"{program}/{self.op.tool_number}/{self.op.number}",
            "first_index": self.first_index, "last_index": self.last_index, "entry_index": self.entry_index,
            "energy_j": round(self.energy_j, 4), "wear_factor": round(self.wear_factor, 6), "fault": self.fault,
            "broken_index": self.broken_index,
            "cutter": {"diameter_mm": self.cutter.diameter_mm, "flutes": self.cutter.flutes},
        }


class ProgramPlant(Plant):
    """The plant running a part program: a CNC state machine drives spindle, feed, tool and context."""

    def __init__(self, program: str | PartProgram = "part-program", *, parts: int | None = None,
                 faults: ProgramFaults | None = None, program_number: int | None = None, seed: int = 0,
                 extra_channels=None, filter_cutoff_hz: float | None = None, noise_scale: float = 1.0,
                 loop: bool = False) -> None:
        if isinstance(program, str):
            try:
                program = PROGRAMS[program]
            except KeyError:
                raise ValueError(f"unknown part program {program!r} (known: {', '.join(PROGRAMS)})") from None
        if program_number is not None:
            if not 0 <= int(program_number) < 1 << 32:
                raise ValueError(f"program number {program_number} outside 0..4294967295")
            program = replace(program, number=int(program_number))
        self.program = program
        self.parts = program.parts if parts is None else int(parts)
        if self.parts < 1:
            raise ValueError(f"parts must be at least 1, not {self.parts}")
        self.faults = faults or ProgramFaults()
        self.faults.check(program, self.parts)
        # the CNC, before index 0: cycle off, the last operation's tool still in the spindle
        last = program.operations[-1]
        self._pass, self._part, self._op_i = 1, 1, -1
        self._phase, self._left = "load", round(PART_GAP_S * SAMPLE_RATE_HZ)
        self._ctx = (program.number, last.tool_number, 0, 0)
        self._ctx_changes: list[tuple[int, tuple[int, int, int, int]]] = []
        self._processes: list[_Process] = []  # open, or closed but not yet written (energy of the block)
        self._seq = 0
        self._break_at: float | None = None
        self._drive_mask = np.zeros(0, dtype=bool)
        super().__init__(program.scenario(self.parts), seed=seed, extra_channels=extra_channels,
                         filter_cutoff_hz=filter_cutoff_hz, noise_scale=noise_scale, loop=loop)

    # -- public ---------------------------------------------------------------------
    def context(self) -> tuple[int, int, int, int]:
        """(program, tool, operation, flags) the CNC reports for the next sample (``index``)."""
        return self._ctx

    def drain_context(self) -> list[tuple[int, tuple[int, int, int, int]]]:
        """The context changes since the last call: (sample index at which it holds, context)."""
        out, self._ctx_changes = self._ctx_changes, []
        return out

    def processes(self) -> list[dict]:
        return [r for r in self.truth.records if "process" in r]

    # -- hooks of Plant ---------------------------------------------------------------
    def _sibling(self) -> Plant:
        return ProgramPlant(self.program, parts=self.parts, faults=self.faults, seed=self._seed + 1,
                            extra_channels=self._extras, filter_cutoff_hz=self.filter_cutoff_hz,
                            noise_scale=self._noise_scale, loop=True)

    def _initial_rpm(self) -> float:
        return 0.0  # the spindle stands before the first part

    def _init_state(self) -> None:
        super()._init_state()
        self._v = 0.0  # ... and so does the feed

    def _drive_on(self, n: int) -> np.ndarray:
        return self._drive_mask[:n]

    def _spindle(self, n, dt, w_ref_m, t_cut_spindle):
        """The drive's speed loop, plus its stop: commanded to 0 rpm, once the spindle reaches standstill
        the drive switches off and the spindle brake holds it (no overshoot into reverse)."""
        w, te = super()._spindle(n, dt, w_ref_m, t_cut_spindle)
        stopped = np.flatnonzero((w_ref_m == 0) & (w[1:] <= 0))
        if stopped.size:
            j = int(stopped[0])
            running = np.flatnonzero(w_ref_m[j:] != 0)  # a start later in the block releases the brake
            end = n if not running.size else j + int(running[0])
            w[j + 1 : end + 1] = 0.0
            te[j + 1 : end + 1] = 0.0
            self._drive_mask[j:end] = False
            if end == n:
                self._omega_m = self._ref_m = self._torque_m = self._integ = 0.0
        return w, te

    def _torque_nm(self, theta, s, v, w_sp, dtheta):
        """As Plant's, computed only where the feed moves: with no feed there is no chip (t_c = 0), and
        most of a part (spindle ramps, tool changes, loading) is spent so."""
        moving = np.asarray(v) > 0
        if moving.all():
            return super()._torque_nm(theta, s, v, w_sp, dtheta)
        tool = self.geometry.tool
        tc = np.asarray(v) / (tool.flutes * np.maximum(w_sp, 1e-3) / (2 * math.pi))
        forces = {key: np.zeros(len(theta)) for key in ("fx_n", "fy_n", "fz_n", "ft_n")}
        rows = np.flatnonzero(moving)
        if rows.size:
            dth = dtheta[rows] if np.ndim(dtheta) else dtheta
            _, sub, _ = super()._torque_nm(theta[rows], s[rows], v[rows], w_sp[rows], dth)
            for key, values in forces.items():
                values[rows] = sub[key]
        return forces["ft_n"] * (tool.radius_mm / 1000.0), forces, tc

    def _chip_factors(self, s_mm: np.ndarray) -> np.ndarray:
        if self._break_at is None:
            return self._sound
        return np.where((s_mm >= self._break_at)[:, None], self._broken, self._sound)

    def _nc(self, n, t0, dt, events):
        del t0
        s0, s1, v0, v1, target, rpm = (np.empty(n) for _ in range(6))
        drive = np.empty(n, dtype=bool)
        acc = self.machine.feed.accel_mm_s2 * dt
        held = bool(self.feed_hold)
        scale = self._override_scale(n)
        s, v = self._s, self._v
        m = n
        for i in range(n):
            k = self._k + i
            if k >= 0 and not held:
                stop = False
                while self._phase_over(s):
                    if self._next_is_change() and i > 0:
                        stop = True  # a tool change starts a block: the plant swaps the cutter between blocks
                        break
                    s, v = self._advance(k, s, v, events)
                if stop:
                    m = i
                    break
            op = self._op()
            phase = self._phase
            # the programmed feed times the CNC's override; a hold wins (program time runs by position,
            # so a feed above programmed makes the cut, and the cycle, shorter)
            tgt = op.feed_mm_min / 60.0 * scale[i] if phase == "feed" and not held else 0.0
            v_new = v + min(max(tgt - v, -acc), acc)
            s0[i], v0[i], v1[i], target[i] = s, v, v_new, tgt
            s += 0.5 * (v + v_new) * dt
            s1[i] = s
            v = v_new
            rpm[i] = op.rpm if phase in ("spin_up", "feed", "retract") else 0.0
            drive[i] = phase in ("spin_up", "feed", "retract", "spin_down")
            if k >= 0 and not held and phase != "feed" and self._left > 0:
                self._left -= 1
            if self._break_at is not None and s >= self._break_at and self._processes:
                proc = self._processes[-1]
                if proc.broken_index is None and proc.last_index is None:
                    proc.broken_index = k
                    events.append({"event": "tool_breakage", "index": k, "t_s": round(k * dt, 6),
                                   "tooth": BROKEN_FLUTE, "position_mm": self._break_at, "part": proc.part,
                                   "tool": op.tool_number})
        self._s, self._v = s, v
        self._drive_mask = drive[:m]
        return s0[:m], s1[:m], v0[:m], v1[:m], target[:m], rpm[:m]

    def _account(self, k0: int, n: int, torque_c: np.ndarray, dtheta_c: np.ndarray) -> None:
        """Cutting energy ∫T·ω dt = ∫T dθ per sample, summed over each process's samples."""
        if not self._processes:
            return
        per_sample = (torque_c * dtheta_c).reshape(n, CUT_PER_SAMPLE).sum(axis=1)
        cutting = torque_c.reshape(n, CUT_PER_SAMPLE).max(axis=1) > CUTTING_MIN_NM
        keep = []
        for proc in self._processes:
            lo = max(proc.first_index, k0)
            hi = k0 + n - 1 if proc.last_index is None else min(proc.last_index, k0 + n - 1)
            if hi >= lo:
                proc.energy_j += float(per_sample[lo - k0 : hi - k0 + 1].sum())
                hit = np.flatnonzero(cutting[lo - k0 : hi - k0 + 1])
                if proc.entry_index is None and hit.size:
                    proc.entry_index = lo + int(hit[0])
            if proc.last_index is not None and proc.last_index < k0 + n:
                self.truth.note(proc.record(self.program.number))
            else:
                keep.append(proc)
        self._processes = keep

    # -- the CNC ------------------------------------------------------------------------
    def _op(self) -> Operation:
        ops = self.program.operations
        return ops[self._op_i] if self._op_i >= 0 else ops[-1]

    def _phase_over(self, s: float) -> bool:
        if self._phase == "feed":
            return s >= self.program.feed_travel_mm(self._op())[1]
        if self._phase == "end":
            return self.loop and self._left <= 0
        return self._left <= 0

    def _next_is_change(self) -> bool:
        return self._phase == "load" or (self._phase == "spin_down" and self._op_i < len(self.program.operations) - 1)

    def _advance(self, k: int, s: float, v: float, events: list[dict]) -> tuple[float, float]:
        """Leave the current phase for the next one at sample k; returns the tool position and feed."""
        prog, ops = self.program, self.program.operations
        rate = SAMPLE_RATE_HZ
        op = self._op()
        if self._phase == "load":
            self._op_i = 0
            s, v = self._change(k)
        elif self._phase == "change":
            self._enter("spin_up", k, round((prog.ramp_s(op.rpm) + SETTLE_S) * rate))
        elif self._phase == "spin_up":
            self._enter("feed", k, 0)
            self._open_process(k)
        elif self._phase == "feed":
            self._enter("retract", k, round(RETRACT_S * rate))
        elif self._phase == "retract":
            self._processes[-1].last_index = k - 1
            self._enter("spin_down", k, round((prog.ramp_s(op.rpm) + STOP_S) * rate))
        elif self._phase == "spin_down" and self._op_i < len(ops) - 1:
            self._op_i += 1
            s, v = self._change(k)
        elif self._phase == "spin_down" and self._part < self.parts:
            self._part += 1
            self._op_i = -1
            self._enter("load", k, round(PART_GAP_S * rate))
        elif self._phase == "spin_down":
            self._op_i = -1
            self._enter("end", k, round(TAIL_S * rate))
        else:  # the end of a pass, looping: the program starts over with sharp tools
            self._pass += 1
            self._part, self._op_i = 1, -1
            events.append({"event": "scenario_restart", "index": k, "t_s": round(k / rate, 6), "pass": self._pass})
            self._enter("load", k, round(PART_GAP_S * rate))
        return s, v

    def _enter(self, phase: str, k: int, samples: int) -> None:
        self._phase, self._left = phase, samples
        prog, op = self.program, self._op()
        if phase in ("load", "end"):
            ctx = (prog.number, op.tool_number, 0, 0)
        elif phase in ("feed", "retract"):
            afc = CTX_AFC_ALLOWED if op.afc_allowed else 0
            ctx = (prog.number, op.tool_number, op.number, CTX_CYCLE | CTX_MONITOR | afc)
        else:
            ctx = (prog.number, op.tool_number, op.number, CTX_CYCLE)
        if ctx != self._ctx:
            self._ctx = ctx
            self._ctx_changes.append((k, ctx))

    def _change(self, k: int) -> tuple[float, float]:
        """The tool change at sample k (always a block's first): stopped spindle, the part's cutter."""
        op, part = self._op(), self._part
        fault = self.faults.fault_of(part, op.tool_number)
        cutter = op.wrong_cutter if fault == "wrong_tool" else op.tool
        wear = 1.0 if fault == "wrong_tool" else self.faults.wear_factor(op.tool_number, part)
        material = replace(self.program.material, ks=self.program.material.ks * wear)
        axial_k, radial_k = self.faults.depth_scales(op.number)
        xp = np.array([x for x, _ in op.axial_profile])
        fp = np.zeros(len(xp)) if fault == "missing_part" else np.array([d for _, d in op.axial_profile]) * axial_k
        mode = op.mode or self.program.mode
        rxp = np.array([x for x, _ in op.radial_profile])
        rfp = np.array([ae for _, ae in op.radial_profile]) * radial_k
        if fault == "wrong_tool" and op.radial_mm is None and op.radial_points is None:
            rfp = np.full(len(rxp), cutter.diameter_mm)  # a slot: as wide as the cutter in the spindle
        if mode == "slot" and radial_k != 1.0:
            mode = "down"  # half the slot already gone: the cutter takes ae on one side, in down milling
        # this batch against the handbook's material (the daemon's config keeps the handbook's)
        material, effects = material_batch(material, self._effects(op), self.program.material_offset_pct)
        self.geometry = CutGeometry(cutter, material, mode, xp, fp, rxp, rfp,
                                    max(1.0, op.max_axial_mm * axial_k), effects)
        self._sound = tooth_chip_factors(cutter.flutes)
        self._broken = tooth_chip_factors(cutter.flutes, (BROKEN_FLUTE,))
        self._pending = (part, op, wear, fault, cutter)
        self._break_at = None  # a broken cutter stays in the spindle until this change (the block's start)
        # the spindle is stopped and oriented for the change: the drive starts the next cut from rest
        self._omega_m = self._ref_m = self._torque_m = self._integ = 0.0
        self._enter("change", k, round(TOOL_CHANGE_S * SAMPLE_RATE_HZ))
        start = self.program.feed_travel_mm(op)[0]  # positioned by the programmed tool's radius
        return start, 0.0

    def _effects(self, op: Operation):
        """The program's cutting effects with this operation's tool wear (its ``life_used`` or --life-used)."""
        effects = self.program.effects
        if effects is None:
            return None
        life = dict(self.faults.life_used).get(op.tool_number, op.life_used)
        return replace(effects, life_used=life) if life != effects.life_used else effects

    def _open_process(self, k: int) -> None:
        part, op, wear, fault, cutter = self._pending
        self._seq += 1
        self._processes.append(_Process(self._seq, part, op, self._pass, k, wear, fault, cutter))
        if fault == "broken_flute":
            self._break_at = op.break_mm
