"""First-part programs (issue 41): operations with their cutting parameters, cut by a plant with every effect.

Each program is a ``PartProgram`` of one part (every operation is a first one), so the CNC's context gives the
daemon keys "PROGRAM/TOOL/OPERATION", and each operation carries its *programmed* cut (ae, ap, the feed as
mm/min or per tooth, the mode, constant or varying engagement). ``operations_config(program)`` turns them into
the daemon's ``[operations."P/T/O"]`` tables. The plant cuts them with ``CutEffects()`` (cut_effects.py: the
size effect at the instantaneous chip, edge forces, 5 µm runout, tool deflection, wear) and, through
``PartProgram.material_offset_pct`` or ``millsense sim --material-offset-pct``, a material batch off the
config's; ``--axial-scale OP:K`` / ``--radial-scale OP:K`` make it cut another depth than programmed.

| program | number | gear | operations |
| --- | --- | --- | --- |
| first-part-slot | 4101 | high | 10 slots, 1000-3000 rpm, ap 2-4 mm, fz 0.04-0.15 mm |
| first-part-down | 4102 | low | 10 down-milling cuts, 450-900 rpm, ae 1-8 mm, ap 3-10 mm, fz 0.04-0.2 mm |
| first-part-up | 4103 | high | 10 up-milling cuts, 1000-3000 rpm, ae 1.5-10 mm, ap 3-10 mm, fz 0.04-0.12 mm |
| first-part-pocket | 4104 | high | a pocket side with two corners, a slot ramped in (engagement "varying") |
| first-part-worn | 4105 | high | a slot, a down and an up cut with tools at 80 % of their life |

Every cut is short (about 15 steady revolutions after the cutter's entry) so that a test's stream stays short;
``PartProgram.only(op, ...)`` (``millsense sim --only-operation OP``) plays a few operations alone.

Nothing here imports ``millsense.daemon``: this is the machine, not the model.
"""

from __future__ import annotations

import math

from millsense.sim.cut_effects import CutEffects
from millsense.sim.machine import MATERIALS, TOOL_D, TOOL_F, TOOL_P, Tool
from millsense.sim.program import PROGRAMS, Operation, PartProgram

TOOL_M = Tool(12.0, 3, 35.0, "phi12 3-flute carbide end mill")
# the magazine of every first-part program, by the CNC's tool number
MAGAZINE = {1: TOOL_P, 2: TOOL_D, 3: TOOL_F, 5: TOOL_M}
WRONG = Tool(10.0, 2, 30.0, "phi10 2-flute end mill (the wrong pocket)")
STEADY_REVS = 16  # revolutions of cut at full engagement after the entry (truth's steady: two fewer)
LIFE_USED = 0.8  # first-part-worn's tools


def _op(number: int, tool_number: int, rpm: float, fz_mm: float, ap_mm: float, mode: str = "slot",
        ae_mm: float | None = None, feed_kind: str = "vf", **kw) -> Operation:
    """One constant cut: the cutter enters from the side face, cuts STEADY_REVS revolutions at ap, stops."""
    tool = MAGAZINE[tool_number]
    feed = fz_mm * tool.flutes * rpm
    steady = STEADY_REVS * fz_mm * tool.flutes  # mm of path
    return Operation(number, tool_number, tool, float(rpm), feed, (ap_mm, ap_mm), (steady / 2, steady / 2), WRONG,
                     mode=mode, radial_mm=ae_mm, feed_kind=feed_kind, **kw)


def _programs() -> dict[str, PartProgram]:
    ss41 = MATERIALS["SS41"]
    effects = CutEffects()
    slot = (
        _op(10, 1, 1200, 0.10, 3.0),  # the "1200 rpm in a 3 mm slot"
        _op(20, 1, 1500, 0.15, 2.0, feed_kind="fz"),
        _op(30, 1, 2000, 0.08, 4.0),
        _op(40, 2, 1000, 0.05, 3.0, feed_kind="fz"),
        _op(50, 2, 1400, 0.08, 2.0),
        _op(60, 2, 1800, 0.06, 4.0, feed_kind="fz"),
        _op(70, 3, 2500, 0.04, 2.0),
        _op(80, 3, 3000, 0.05, 3.0, feed_kind="fz"),
        _op(90, 5, 2200, 0.07, 2.5),
        _op(100, 5, 1600, 0.10, 3.5, feed_kind="fz"),
    )
    down = (
        _op(10, 2, 600, 0.10, 6.0, "down", 2.0),
        _op(20, 2, 800, 0.08, 10.0, "down", 4.0, feed_kind="fz"),
        _op(30, 2, 450, 0.15, 8.0, "down", 1.5),
        _op(40, 1, 700, 0.12, 5.0, "down", 5.0, feed_kind="fz"),
        _op(50, 1, 900, 0.20, 3.0, "down", 8.0),
        _op(60, 1, 500, 0.10, 8.0, "down", 3.0, feed_kind="fz"),
        _op(70, 5, 850, 0.06, 6.0, "down", 3.0),
        _op(80, 5, 600, 0.09, 4.0, "down", 6.0, feed_kind="fz"),
        _op(90, 3, 900, 0.05, 8.0, "down", 1.0),
        _op(100, 3, 750, 0.04, 5.0, "down", 2.0, feed_kind="fz"),
    )
    up = (
        _op(10, 1, 1100, 0.12, 4.0, "up", 3.0),
        _op(20, 1, 1800, 0.08, 6.0, "up", 6.0, feed_kind="fz"),
        _op(30, 1, 2400, 0.10, 3.0, "up", 10.0),
        _op(40, 2, 1300, 0.06, 8.0, "up", 2.0, feed_kind="fz"),
        _op(50, 2, 2000, 0.05, 5.0, "up", 5.0),
        _op(60, 2, 1000, 0.10, 10.0, "up", 1.5, feed_kind="fz"),
        _op(70, 5, 2600, 0.05, 6.0, "up", 4.0),
        _op(80, 5, 1500, 0.08, 9.0, "up", 2.0, feed_kind="fz"),
        _op(90, 3, 3000, 0.04, 6.0, "up", 1.5),
        _op(100, 3, 2000, 0.06, 4.0, "up", 3.0, feed_kind="fz"),
    )
    # a pocket's side wall in down milling (ae 4 mm) with two inner corners: there the cutter wraps round
    # the corner, its engagement rising to ae + R over one radius and falling back; and a slot ramped in,
    # its depth rising from 0.5 to 3 mm over 20 mm and then steady
    r = TOOL_D.radius_mm
    corner = 4.0 + r
    wall = ((0.0, 4.0), (12.0, 4.0), (12.0 + r, corner), (12.0 + 2 * r, 4.0), (30.0, 4.0),
            (30.0 + r, corner), (30.0 + 2 * r, 4.0), (60.0, 4.0))
    pocket_wall = _op(10, 2, 1200, 0.06, 5.0, "down", 4.0, engagement="varying", radial_points=wall)
    pocket_wall = _with_length(pocket_wall, 30.0 + 2 * r + 4.0)
    ramp_len = 20.0
    ramp = ((0.0, 0.5), (ramp_len, 3.0), (200.0, 3.0))
    pocket_ramp = _with_length(_op(20, 1, 1500, 0.08, 3.0, engagement="varying", axial_points=ramp),
                               ramp_len + TOOL_P.radius_mm + 4.0)
    worn = (
        _op(10, 1, 1200, 0.10, 3.0, life_used=LIFE_USED),
        _op(20, 2, 1300, 0.06, 8.0, "down", 2.0, feed_kind="fz", life_used=LIFE_USED),
        _op(30, 5, 1500, 0.08, 6.0, "up", 3.0, life_used=LIFE_USED),
    )
    specs = (
        ("first-part-slot", 4101, slot, "10 slots, SS41, 1000-3000 rpm, ap 2-4 mm, fz 0.04-0.15 mm"),
        ("first-part-down", 4102, down, "10 down-milling cuts, SS41, 450-900 rpm (low gear), ae 1-8 mm, ap 3-10 mm"),
        ("first-part-up", 4103, up, "10 up-milling cuts, SS41, 1000-3000 rpm, ae 1.5-10 mm, ap 3-10 mm"),
        ("first-part-pocket", 4104, (pocket_wall, pocket_ramp),
         "a pocket wall with two corners (down, ae 4 -> 12 mm) and a slot ramped in (ap 0.5 -> 3 mm), varying"),
        ("first-part-worn", 4105, worn, "a slot, a down and an up cut, tools at 80 % of their life"),
    )
    out = {}
    for name, number, ops, text in specs:
        prog = PartProgram(name, f"program {number}, first part (issue 41): {text}; the plant with every "
                           "cutting effect (sim/cut_effects.py)", number, ss41, ops, parts=1, effects=effects)
        if len({prog.machine.gear_for_rpm(op.rpm).name for op in ops}) != 1:
            raise ValueError(f"{name}: the operations' speeds span gears; one gear per program")
        out[name] = prog
    return out


def _with_length(op: Operation, end_mm: float) -> Operation:
    """The operation cut up to ``end_mm`` of cutter-centre path (a varying profile's own length)."""
    from dataclasses import replace

    half = (end_mm - op.tool.radius_mm) / 2
    return replace(op, steady_mm=(half, half))


FIRST_PART_PROGRAMS: dict[str, PartProgram] = _programs()
PROGRAMS.update(FIRST_PART_PROGRAMS)  # the emulator, write_capture and ProgramPlant find them by name


def programmed_cut(program: PartProgram, op: Operation) -> dict:
    """One operation's ``[operations."P/T/O"]`` table: what the program says it cuts, never what the plant
    cuts (``--axial-scale``, ``--radial-scale``, the material batch leave it as it is)."""
    mode = op.mode or program.mode
    out: dict = {"ae_mm": round(op.max_radial_mm, 6), "ap_mm": round(op.max_axial_mm, 6)}
    if op.feed_kind == "fz":
        out["fz_mm"] = round(op.feed_per_tooth_mm, 6)
    elif op.feed_kind == "vf":
        out["vf_mm_min"] = round(op.feed_mm_min, 6)
    else:
        raise ValueError(f"operation {op.number}: feed_kind {op.feed_kind!r} (vf or fz)")
    out["mode"] = mode
    out["engagement"] = op.engagement
    if math.isclose(out["ae_mm"], op.tool.diameter_mm) and mode != "slot":
        raise ValueError(f"operation {op.number}: a {mode} cut as wide as the cutter is a slot")
    return out


def operations_config(program: PartProgram | str) -> dict[str, dict]:
    """The daemon's ``[operations]`` tables of a program, keyed "PROGRAM/TOOL/OPERATION" (TOML-ready)."""
    if isinstance(program, str):
        program = PROGRAMS[program]
    return {f"{program.number}/{op.tool_number}/{op.number}": programmed_cut(program, op)
            for op in program.operations}
