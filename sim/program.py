"""The part-program scenario: a CNC making the same part again and again with three tools.

Where ``scenarios.py`` plays one cut, this plays a shop's day in miniature.
Program 1001 makes a block with three slots, one per tool of the magazine,
part after part; between operations the spindle stops for a tool change and
restarts, between parts the cycle is off while the finished part is swapped
for the next.  The CNC tells the DAQ what it is doing (protocol 2's CONTEXT,
daq-protocol.md): program, tool, operation and the cycle and monitoring flags.

One part, per operation (tool T, operation number O)::

    change     spindle stopped, drive off, T into the spindle      context (1001, T, O, cycle)
    spin-up    the drive ramps to the operation's speed, settles   (1001, T, O, cycle)
    feed       approach in air, the slot with a depth step, exit   (1001, T, O, cycle|monitor[|afc])
    retract    the cutter lifts out, still turning                 (1001, T, O, cycle|monitor[|afc])
    spin-down  the drive ramps to a stop                           (1001, T, O, cycle)

and before each part ``load`` (cycle off, operation 0, the last tool still in
the spindle).  A process, in the daemon's words, is one feed + retract: the
samples while cycle and monitor are set.  Feed is programmed by position, so a
feed hold stops the part where it is; the program's timers stop with it (the
CNC's cycle is suspended), and the part resumes when the hold is released.
The feed is the programmed one times the CNC's feed override, so a feed above
programmed (adaptive feed control) shortens the cut and the cycle. ``afc`` is
CONTEXT flag bit 2, set in the cuts of operations with ``afc_allowed`` (10 and 20;
operation 30, the finishing slot, never).

Faults (``ProgramFaults``), each confined to what it names:

- wear: tool T's cutting coefficient K_s grows p % per part, *compounding*:
  part n cuts with K_s·(1 + p/100)^(n−1) (part 1 with a sharp tool). The
  factor follows the part number, whatever happened in earlier parts.
- broken flute (part, T): flute 1 of T breaks when the cutter centre passes
  ``BREAK_AT`` of the slot's length (in the deeper step); the next flute takes
  its chip too (``cutting.tooth_chip_factors``). The part after is made with a
  sound cutter again (the operator replaced it; its wear factor is the part's).
- missing part: no material in that part; every cut is in air.
- wrong tool (part, T): the CNC reports T, the spindle holds the operation's
  ``wrong_cutter`` (another diameter and flute count), sharp (factor 1).

and, in every part, the plant cutting something other than programmed (issue 41's first parts,
``first_part.py``; the operation's programmed cut, hence the daemon's config, stays):

- axial / radial scale (operation, K): the operation cuts K times its programmed axial
  (radial) depth; a slot scaled radially becomes a down-milling cut K·D wide.
- life used (T, fraction): with the program's cutting effects, T cuts with the forces of a
  tool that has used that fraction of its life (``cut_effects.CutEffects.life_used``).

A program's ``effects`` (``cut_effects.CutEffects``; None in program 1001, set in the first-part
programs) make the plant cut what [D]'s average model approximates, and its
``material_offset_pct`` makes the plant's material that many % off ``material`` (the config's).

``program_plant.ProgramPlant`` runs a program; this module only describes it.
Nothing here imports ``millsense.daemon``: this is the machine, not the model.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

from millsense.sim.cut_effects import CutEffects
from millsense.sim.machine import MATERIALS, MCH10, TOOL_D, TOOL_F, TOOL_P, Machine, Material, Tool
from millsense.sim.scenarios import Scenario, _steps

GAP_MM = 2.0  # air between the programmed cutter's edge and the part when the feed starts
PART_GAP_S = 0.4  # cycle off between parts: the finished part out, the next one clamped
TOOL_CHANGE_S = 0.3  # spindle stopped and oriented, the changer swaps the cutter
SETTLE_S = 0.4  # after the drive's ramp, before the CNC feeds (speed arrival)
RETRACT_S = 0.1  # the cutter lifts out of the slot, still turning
STOP_S = 0.1  # after the drive's ramp down, before the spindle counts as stopped
TAIL_S = 1.0  # cycle off after the last part
BREAK_AT = 0.4  # a flute breaks this fraction of the way along the deeper floor's steady stretch
BROKEN_FLUTE = 1  # which flute breaks (0 is the first)


@dataclass(frozen=True)
class Operation:
    """One cut of the program: a closed slot from the part's side face, its floor stepping down once.

    The cutter enters the part at x = 0 at depth ``depths_mm[0]``; the floor steps to
    ``depths_mm[1]`` at ``step_mm``; the feed stops at ``end_mm`` and the cutter lifts out.
    ``steady_mm`` are the lengths of path on which the whole cutting edge (x = s … s + R for
    a slot) is at one depth: before the step (the cutter meets it over its radius) and after.
    """

    number: int  # the operation number the program sets before the cut (CONTEXT operation)
    tool_number: int  # the CNC's T number (CONTEXT tool)
    tool: Tool
    rpm: float
    feed_mm_min: float
    depths_mm: tuple[float, float]
    steady_mm: tuple[float, float]
    wrong_cutter: Tool  # in the spindle instead of ``tool`` under the wrong-tool fault
    # the CNC sets CONTEXT flag bit 2 (adaptive feed allowed) during this cut; a tapping, thread-milling
    # or finishing operation never does (its feed is tied to the spindle, or its finish to the feed)
    afc_allowed: bool = False
    # first-part operations (sim/first_part.py): the cut as programmed, beside the depths above
    mode: str | None = None  # slot, down or up; None: the program's
    radial_mm: float | None = None  # ae of a side-milling cut; None: the cutter's diameter (a slot)
    axial_points: tuple[tuple[float, float], ...] | None = None  # (x mm, d_a mm): a ramp, instead of the step
    radial_points: tuple[tuple[float, float], ...] | None = None  # (x mm, ae mm): a pocket's corners
    feed_kind: str = "vf"  # how the CNC programs the feed: "vf" (mm/min, G94) or "fz" (mm per tooth, G95)
    engagement: str = "constant"  # "varying" where the radial or axial engagement changes along the cut
    life_used: float = 0.0  # the fraction of its life the tool has cut (the plant's wear, cut_effects.py)

    @property
    def step_mm(self) -> float:
        return self.tool.radius_mm + self.steady_mm[0]

    @property
    def end_mm(self) -> float:
        return self.step_mm + self.steady_mm[1]

    @property
    def break_mm(self) -> float:
        """Where a flute breaks under the broken-flute fault: early on the deeper floor."""
        return self.step_mm + BREAK_AT * self.steady_mm[1]

    @property
    def axial_profile(self) -> tuple[tuple[float, float], ...]:
        """(x mm, d_a mm): the slot's floor; the block goes on past the slot's end (a closed slot)."""
        if self.axial_points is not None:
            return self.axial_points
        return _steps([0.0, self.step_mm, self.end_mm + self.tool.diameter_mm], list(self.depths_mm))

    @property
    def radial_profile(self) -> tuple[tuple[float, float], ...]:
        """(x mm, ae mm) at the tool centre: constant ``radial_mm`` unless ``radial_points`` vary it."""
        if self.radial_points is not None:
            return self.radial_points
        ae = self.tool.diameter_mm if self.radial_mm is None else self.radial_mm
        return ((0.0, ae), (1.0, ae))

    @property
    def max_axial_mm(self) -> float:
        return max(d for _, d in self.axial_profile)

    @property
    def max_radial_mm(self) -> float:
        return max(ae for _, ae in self.radial_profile)

    @property
    def feed_per_tooth_mm(self) -> float:
        """The programmed feed per tooth at the programmed speed: vf/(n·N)."""
        return self.feed_mm_min / (self.rpm * self.tool.flutes)


@dataclass(frozen=True)
class PartProgram:
    name: str
    description: str
    number: int  # the CNC's program number (CONTEXT program)
    material: Material
    operations: tuple[Operation, ...]
    parts: int = 30  # default number of parts
    mode: str = "slot"
    machine: Machine = field(default=MCH10)
    filter_cutoff_hz: float = 200.0
    # the CNC's feed rate into the DAQ: a closed slot's end stops the feed, and without it the drop of
    # torque there looks like a tool that snapped (pipeline/alarms.py BreakageTrack needs the feed)
    extra_channels: tuple[str, ...] = ("fx_rate",)
    # the plant's cut: None, [D]'s average model (every program before issue 41); else what it approximates
    effects: CutEffects | None = None
    # the plant's material off from ``material`` (what the daemon's config says, the handbook's) by this
    # percentage: K_s and the edge forces of this batch are (1 + pct/100) times the handbook's
    material_offset_pct: float = 0.0

    def only(self, *numbers: int) -> PartProgram:
        """The program with only the operations numbered (a test's short stream), in the program's order."""
        unknown = sorted(set(numbers) - {op.number for op in self.operations})
        if unknown or not numbers:
            raise ValueError(f"operation {unknown[0] if unknown else '(none)'} is not in program {self.number} "
                             f"(its operations: {', '.join(str(op.number) for op in self.operations)})")
        return replace(self, operations=tuple(op for op in self.operations if op.number in numbers))

    @property
    def tools(self) -> dict[int, Tool]:
        return {op.tool_number: op.tool for op in self.operations}

    def ramp_s(self, rpm: float) -> float:
        """The drive's speed ramp from standstill to rpm (or back)."""
        gear = self.machine.gear_for_rpm(rpm)
        return abs(rpm) * gear.ratio / self.machine.drive.ramp_motor_rpm_s

    def feed_travel_mm(self, op: Operation) -> tuple[float, float]:
        """Start and end of the feed, cutter centre on the path: from GAP_MM of air to the slot's end."""
        return -(op.tool.radius_mm + GAP_MM), op.end_mm

    def part_s(self) -> float:
        """Nominal length of one part in seconds (no feed hold; the feed's few-ms accelerations left out)."""
        total = PART_GAP_S
        for op in self.operations:
            start, end = self.feed_travel_mm(op)
            total += TOOL_CHANGE_S + self.ramp_s(op.rpm) + SETTLE_S
            total += (end - start) / (op.feed_mm_min / 60.0) + RETRACT_S + self.ramp_s(op.rpm) + STOP_S
        return total

    def duration_s(self, parts: int) -> float:
        return round(parts * self.part_s() + TAIL_S, 1)

    def scenario(self, parts: int) -> Scenario:
        """The plant's view of the program: machine, sensors, material, the first tool; the NC is ProgramPlant's."""
        op = self.operations[0]
        return Scenario(self.name, self.description, self.duration_s(parts), op.tool, self.material,
                        op.mode or self.mode,
                        tuple((0.0, o.rpm) for o in self.operations), ((-math.inf, op.feed_mm_min),),
                        op.axial_profile, () if (op.mode or self.mode) == "slot" else op.radial_profile,
                        self.feed_travel_mm(op)[0], extra_channels=self.extra_channels,
                        filter_cutoff_hz=self.filter_cutoff_hz, machine=self.machine)


@dataclass(frozen=True)
class ProgramFaults:
    """What goes wrong during the run (parts from 1; tools by the CNC's number)."""

    wear_pct: tuple[tuple[int, float], ...] = ()  # (tool, % per part, compounding)
    broken_flute: tuple[tuple[int, int], ...] = ()  # (part, tool)
    missing_part: tuple[int, ...] = ()
    wrong_tool: tuple[tuple[int, int], ...] = ()  # (part, tool)
    # the plant cuts another depth than programmed, in every part (the config, from the program, stays):
    axial_scale: tuple[tuple[int, float], ...] = ()  # (operation, real ap / programmed ap)
    radial_scale: tuple[tuple[int, float], ...] = ()  # (operation, real ae / programmed ae; a slot: half-slot)
    life_used: tuple[tuple[int, float], ...] = ()  # (tool, fraction of its life used): cut_effects' wear

    def check(self, program: PartProgram, parts: int) -> None:
        """ValueError naming the option when a fault names no tool or part of this run."""
        tools = program.tools
        known = ", ".join(str(t) for t in tools)

        def tool_ok(option: str, tool: int) -> None:
            if tool not in tools:
                raise ValueError(f"{option}: tool {tool} is not in program {program.number} (its tools: {known})")

        def part_ok(option: str, part: int) -> None:
            if not 1 <= part <= parts:
                raise ValueError(f"{option}: part {part} is not one of the run's parts 1..{parts}")

        for tool, pct in self.wear_pct:
            tool_ok("--wear", tool)
            if not 0.0 < pct <= 100.0:
                raise ValueError(f"--wear: {pct:g} % per part for tool {tool}: expected 0 < PCT <= 100")
        if len({t for t, _ in self.wear_pct}) != len(self.wear_pct):
            raise ValueError("--wear: a tool is named twice")
        for option, pairs in (("--broken-flute", self.broken_flute), ("--wrong-tool", self.wrong_tool)):
            for part, tool in pairs:
                part_ok(option, part)
                tool_ok(option, tool)
        for part in self.missing_part:
            part_ok("--missing-part", part)
        numbers = {op.number for op in program.operations}
        for option, pairs in (("--axial-scale", self.axial_scale), ("--radial-scale", self.radial_scale)):
            for op_number, k in pairs:
                if op_number not in numbers:
                    raise ValueError(f"{option}: operation {op_number} is not in program {program.number} "
                                     f"(its operations: {', '.join(str(n) for n in sorted(numbers))})")
                if not 0.0 < k <= 3.0:
                    raise ValueError(f"{option}: {k:g} for operation {op_number}: expected 0 < K <= 3")
            if len({o for o, _ in pairs}) != len(pairs):
                raise ValueError(f"{option}: an operation is named twice")
        for tool, fraction in self.life_used:
            tool_ok("--life-used", tool)
            if not 0.0 <= fraction <= 1.0:
                raise ValueError(f"--life-used: {fraction:g} for tool {tool}: expected a fraction within 0..1")
            if program.effects is None:
                raise ValueError(f"--life-used: program {program.name} has no cutting effects to wear "
                                 "(a first-part program has)")
        both = set(self.broken_flute) & set(self.wrong_tool)
        if both:
            part, tool = sorted(both)[0]
            raise ValueError(f"--broken-flute and --wrong-tool both name part {part}, tool {tool}: "
                             "one fault per process")
        for option, pairs in (("--broken-flute", self.broken_flute), ("--wrong-tool", self.wrong_tool)):
            clash = sorted(p for p, _ in pairs if p in self.missing_part)
            if clash:
                raise ValueError(f"{option} names part {clash[0]}, which --missing-part leaves without material")

    def wear_factor(self, tool: int, part: int) -> float:
        """K_s multiplier of tool in part: (1 + p/100)^(part − 1), compounding."""
        pct = dict(self.wear_pct).get(tool, 0.0)
        return (1.0 + pct / 100.0) ** (part - 1)

    def depth_scales(self, operation: int) -> tuple[float, float]:
        """(axial, radial): the real depths over the programmed ones of an operation."""
        return dict(self.axial_scale).get(operation, 1.0), dict(self.radial_scale).get(operation, 1.0)

    def fault_of(self, part: int, tool: int) -> str | None:
        if part in self.missing_part:
            return "missing_part"
        if (part, tool) in self.broken_flute:
            return "broken_flute"
        if (part, tool) in self.wrong_tool:
            return "wrong_tool"
        return None


def _build() -> dict[str, PartProgram]:
    ss41 = MATERIALS["SS41"]
    # three closed slots in one block, each floor stepping down once; feeds per tooth 0.2, 0.12, 0.1 mm;
    # the two roughing slots allow adaptive feed, the phi8 finishing slot never does
    ops = (
        Operation(10, 11, TOOL_P, 1500.0, 600.0, (3.0, 5.0), (3.0, 5.0),
                  Tool(12.0, 2, 30.0, "phi12 2-flute end mill (the wrong pocket)"), afc_allowed=True),
        Operation(20, 4, TOOL_D, 1200.0, 576.0, (4.0, 6.0), (3.0, 5.0),
                  Tool(10.0, 2, 30.0, "phi10 2-flute end mill (the wrong pocket)"), afc_allowed=True),
        Operation(30, 27, TOOL_F, 2000.0, 600.0, (3.0, 4.0), (3.0, 5.0),
                  Tool(10.0, 4, 35.0, "phi10 4-flute end mill (the wrong pocket)"), afc_allowed=False),
    )
    prog = PartProgram(
        "part-program",
        "program 1001, SS41, high-speed gear: T11 [P] phi20 2-fl 1500 rpm, T4 [D] phi16 4-fl 1200 rpm, "
        "T27 phi8 3-fl 2000 rpm, a slot each with a depth step; tool changes, 30 parts, CONTEXT (protocol 2)",
        1001, ss41, ops)
    _ = prog.machine.gear_for_rpm(max(op.rpm for op in ops))
    if len({prog.machine.gear_for_rpm(op.rpm).name for op in ops}) != 1:
        raise ValueError(f"{prog.name}: the operations' speeds span gears; one gear per program")
    return {prog.name: prog}


PROGRAMS: dict[str, PartProgram] = _build()
# the first-part programs (first_part.py) add themselves here; the package (sim/__init__.py) imports them


def list_programs() -> list[str]:
    return list(PROGRAMS)
