"""The scenario book: the cuts of [P] and [D], air cuts for calibration, breakage, a crash.

A scenario is an NC program in miniature: a spindle-speed schedule in time, a
feed rate by position along a straight path, and a workpiece described by its
axial (and, for side milling, radial) depth as a function of position.  Feed is
programmed by position, as a CNC does block by block, so after a feed hold the
program resumes where it stopped.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

from millsense.sim.cut_effects import CutEffects
from millsense.sim.machine import MATERIALS, MCH10, TOOL_D, TOOL_P, Machine, Material, Tool

STEP_EDGE_MM = 1e-6  # width of a vertical wall in a depth profile (np.interp needs increasing x)
APPROACH_MM = 5.0  # air gap between the tool's edge and the part at start and end
D_EXTRAS = ("ix_feed", "fx_rate", "fx", "fy", "fz")


@dataclass(frozen=True)
class Scenario:
    name: str
    description: str
    duration_s: float
    tool: Tool
    material: Material
    mode: str  # down | up | slot
    spindle_schedule: tuple[tuple[float, float], ...]  # (from time s, commanded spindle rpm)
    feed_segments: tuple[tuple[float, float], ...]  # (from position mm, feed mm/min); first from -inf
    axial_profile: tuple[tuple[float, float], ...] = ()  # (x mm, d_a mm), 0 outside
    radial_profile: tuple[tuple[float, float], ...] = ()  # (x mm, d_r mm) for down/up milling
    start_mm: float = 0.0
    path_angle_deg: float = 0.0  # feed direction from the machine X axis
    extra_channels: tuple[str, ...] = ()
    filter_cutoff_hz: float = 200.0
    breakage: tuple[float, int] | None = None  # (path position mm, tooth that breaks)
    crash_power_w: float | None = None  # air-gap power marked as a crash
    machine: Machine = field(default=MCH10)
    # the plant's cut beyond [D]'s average model (sim/cut_effects.py); None in every scenario of this book
    effects: CutEffects | None = None
    # the plant's material this many % off ``material`` (the config's, machine_config): this batch
    material_offset_pct: float = 0.0

    @property
    def gear(self):
        gears = {self.machine.gear_for_rpm(rpm).name for _, rpm in self.spindle_schedule}
        if len(gears) != 1:
            raise ValueError(f"scenario {self.name}: speeds span gears {sorted(gears)}; one gear per scenario")
        return self.machine.gear_for_rpm(self.spindle_schedule[0][1])

    @property
    def max_axial_mm(self) -> float:
        return max([1.0, *(d for _, d in self.axial_profile)])


def _steps(edges: list[float], depths: list[float]) -> tuple[tuple[float, float], ...]:
    """Flat steps: depths[i] between edges[i] and edges[i+1], vertical walls between."""
    pts: list[tuple[float, float]] = []
    for i, d in enumerate(depths):
        x0 = edges[i] + (STEP_EDGE_MM if i else 0.0)
        pts += [(x0, d), (edges[i + 1], d)]
    return tuple(pts)


def _travel_s(start: float, end: float, feed_segments) -> float:
    """Time to move from start to end under the position-based feed program (no accelerations)."""
    bounds = [s for s, _ in feed_segments[1:]] + [math.inf]
    total, x = 0.0, start
    for (_, feed), upper in zip(feed_segments, bounds, strict=True):
        seg_end = min(upper, end)
        if seg_end > x:
            total += (seg_end - x) / (feed / 60.0)
            x = seg_end
    return total


def _cut(name, description, tool, material, rpm, feed_segments, axial, *, part_end, radial=(), mode="slot",
         angle=0.0, extras=(), tail_s=1.0, **kw) -> Scenario:
    start = -(tool.radius_mm + APPROACH_MM)
    end = part_end + tool.radius_mm + APPROACH_MM
    feed_segments = tuple(feed_segments)
    duration = round(_travel_s(start, end, feed_segments) + tail_s, 1)
    return Scenario(name, description, duration, tool, material, mode, ((0.0, rpm),), feed_segments, tuple(axial),
                    tuple(radial), start, angle, tuple(extras), **kw)


def _aircut(name, description, speeds, hold_s) -> Scenario:
    schedule = tuple((i * hold_s, float(rpm)) for i, rpm in enumerate(speeds))
    return Scenario(name, description, hold_s * len(speeds), TOOL_P, MATERIALS["SM45C"], "slot", schedule,
                    ((-math.inf, 0.0),))


# Static sensitivity ([P] eq. 20: torque noise = power noise / spindle speed): one constant slot cut
# at each spindle speed of [P] Table 1's trial grid, with the feed per tooth (hence the cutting
# torque) the same at every speed, so only the speed changes between them.
SWEEP_RPM = (300, 500, 700, 900, 1000, 1500, 2000, 2500)
SWEEP_TC_MM = 0.15
SWEEP_DOC_MM = 2.0
SWEEP_PART_MM = 50.0  # 30 mm of full engagement: ~100 steady revolutions at every speed, <= 60 s at 300 rpm


def _speed_sweep(material) -> list[Scenario]:
    out = []
    for rpm in SWEEP_RPM:
        feed = SWEEP_TC_MM * TOOL_P.flutes * rpm
        out.append(_cut(f"speed-{rpm}", f"[P] Table 1 speed, constant slot: SM45C, {rpm} rpm, t_c {SWEEP_TC_MM} mm "
                        f"({feed:g} mm/min), d.o.c. {SWEEP_DOC_MM:g} mm (static sensitivity, eq. 20)",
                        TOOL_P, material, rpm, ((-math.inf, feed),),
                        ((0.0, SWEEP_DOC_MM), (SWEEP_PART_MM, SWEEP_DOC_MM)), part_end=SWEEP_PART_MM))
    return out


# Adaptive feed control (issue 15): depth steps 2 -> 3 -> 2.5 mm, 25 mm each, the load a controller
# holding a target through the feed override must follow; the programmed feed per tooth is about the
# same at every speed of a material (0.2 mm at 300 rpm keeps the pass under a minute). One gear per
# scenario: 300 and 600 rpm in the low-speed gear, 1500 and 3000 rpm in the high-speed one (top 4500 rpm).
AFC_STEP_MM = (2.0, 3.0, 2.5)
AFC_STEP_LEN_MM = 25.0
AFC_LATE_START_MM = 0.12  # afc-step-1500-late: 0.4 of a revolution's travel at 150 % (0.3 mm)


def _afc(sm45c, ss41) -> list[Scenario]:
    steps = _steps([AFC_STEP_LEN_MM * i for i in range(len(AFC_STEP_MM) + 1)], list(AFC_STEP_MM))
    end = AFC_STEP_LEN_MM * len(AFC_STEP_MM)
    out = []
    for name, material, rpm, feed in (("afc-step-300", sm45c, 300, 120.0), ("afc-step", sm45c, 600, 200.0),
                                      ("afc-step-1500", ss41, 1500, 300.0), ("afc-step-3000", ss41, 3000, 600.0)):
        out.append(_cut(name, f"AFC depth steps: [P] slot, {material.name}, {rpm} rpm, {feed:g} mm/min, "
                        "d.o.c. 2->3->2.5 mm, 25 mm each (adaptive feed control)",
                        TOOL_P, material, rpm, ((-math.inf, feed),), steps, part_end=end))
    # The settle count depends on where in a revolution the tool meets a wall (docs/afc.md); this start puts
    # the 3 mm wall just before a revolution begins under the controller: the late phase
    at_1500 = next(sc for sc in out if sc.name == "afc-step-1500")
    out.append(replace(at_1500, name="afc-step-1500-late", start_mm=at_1500.start_mm + AFC_LATE_START_MM,
                       description=at_1500.description.replace(
                           "(adaptive feed control)",
                           f"(adaptive feed control), the tool starting {AFC_LATE_START_MM:g} mm nearer")))
    out.append(_cut("afc-taper", "AFC taper: [P] slot, SM45C, 600 rpm, 200 mm/min, d.o.c. 1->3 mm over 75 mm "
                    "(cycle time at constant load)", TOOL_P, sm45c, 600, ((-math.inf, 200.0),),
                    ((0.0, 1.0), (75.0, 3.0)), part_end=75))
    return out


def _build() -> dict[str, Scenario]:
    sm45c, ss41, sb40 = MATERIALS["SM45C"], MATERIALS["SS41"], MATERIALS["SB40"]
    step3 = _steps([0, 25, 50, 75], [1.0, 2.0, 3.0])
    taper3 = ((0.0, 0.0), (75.0, 3.0))
    fz = {"feed": ((-math.inf, 200.0),), "f300": ((-math.inf, 300.0),), "f250": ((-math.inf, 250.0),)}
    out = [
        _cut("step", "[P] slot, SM45C, 600 rpm, 200 mm/min, d.o.c. 1->2->3 mm steps (demo default)",
             TOOL_P, sm45c, 600, fz["feed"], step3, part_end=75),
        _cut("taper", "[P] slot, SM45C, 600 rpm, 200 mm/min, d.o.c. taper 0->3 mm",
             TOOL_P, sm45c, 600, fz["feed"], taper3, part_end=75),
        _cut("step-1200", "[P] slot, SS41, 1200 rpm (high-speed gear), 300 mm/min, d.o.c. 1->2->3 mm steps",
             TOOL_P, ss41, 1200, fz["f300"], step3, part_end=75),
        _cut("step-1800", "[P] slot, SS41, 1800 rpm (high-speed gear), 300 mm/min, d.o.c. 1->2->3 mm steps",
             TOOL_P, ss41, 1800, fz["f300"], step3, part_end=75),
        _cut("taper-1200", "[P] slot, SS41, 1200 rpm (high-speed gear), 300 mm/min, d.o.c. taper 0->3 mm",
             TOOL_P, ss41, 1200, fz["f300"], taper3, part_end=75),
        _cut("taper-1800", "[P] slot, SS41, 1800 rpm (high-speed gear), 300 mm/min, d.o.c. taper 0->3 mm",
             TOOL_P, ss41, 1800, fz["f300"], taper3, part_end=75),
        _cut("diagonal-step", "[P] diagonal slot (45 deg), SS41, 600 rpm, 250 mm/min, d.o.c. 1->2->3 mm steps",
             TOOL_P, ss41, 600, fz["f250"], step3, part_end=75, angle=45.0),
        _cut("diagonal-taper", "[P] diagonal slot (45 deg), SS41, 600 rpm, 250 mm/min, d.o.c. taper 0->3 mm",
             TOOL_P, ss41, 600, fz["f250"], taper3, part_end=75, angle=45.0),
        _cut("breakage", "[P] diagonal step cut, SS41, 600 rpm, 250 mm/min; flute 1 breaks at 60 mm (3 mm step)",
             TOOL_P, ss41, 600, fz["f250"], step3, part_end=75, angle=45.0, breakage=(60.0, 1)),
        _cut("crash", "slot 2 mm at 200 mm/min, then a rapid (8000 mm/min) at 12 mm into a 15 mm boss: "
             "air-gap power passes 15 kW", TOOL_P, sm45c, 600, ((-math.inf, 200.0), (12.0, 8000.0)),
             ((0.0, 2.0), (25.0, 2.0), (27.0, 15.0), (60.0, 15.0)), part_end=60, tail_s=2.0,
             crash_power_w=15_000.0),
        _cut("fig5", "[D] Fig. 5: down milling, SB40, 4-flute phi16, 600 rpm, t_c 0.1042 mm, d_a 16 mm, "
             "d_r ramp 1->8 mm", TOOL_D, sb40, 600, ((-math.inf, 0.1042 * 4 * 600),), ((0.0, 16.0), (100.0, 16.0)),
             part_end=100, radial=((0.0, 1.0), (100.0, 8.0)), mode="down", extras=D_EXTRAS),
        _cut("fig6", "[D] Fig. 6: down milling, SB40, 600 rpm, t_c 0.2083 mm, d_r 2 mm, d_a 6/11/16 mm steps",
             TOOL_D, sb40, 600, ((-math.inf, 0.2083 * 4 * 600),), _steps([0, 50, 100, 150], [6.0, 11.0, 16.0]),
             part_end=150, radial=((0.0, 2.0), (150.0, 2.0)), mode="down", extras=D_EXTRAS),
        _cut("fig7", "[D] Fig. 7: down milling, SB40, 600 rpm, d_a 2 mm, d_r ramp 1.5->8 mm, "
             "feed 1000/500/250 mm/min", TOOL_D, sb40, 600, ((-math.inf, 1000.0), (40.0, 500.0), (80.0, 250.0)),
             ((0.0, 2.0), (120.0, 2.0)), part_end=120, radial=((0.0, 1.5), (120.0, 8.0)), mode="down",
             extras=D_EXTRAS),
        _aircut("aircut-low", "air cut, low-speed gear, 300/450/600/750/900 rpm, 4 s each (friction calibration)",
                [300, 450, 600, 750, 900], 4.0),
        _aircut("aircut-high", "air cut, high-speed gear, 1000/1375/1750/2125/2500 rpm, 3 s each "
                "(friction calibration)", [1000, 1375, 1750, 2125, 2500], 3.0),
        *_speed_sweep(sm45c),
        *_afc(sm45c, ss41),
    ]
    for s in out:
        _ = s.gear  # one gear per scenario, checked at import
    return {s.name: s for s in out}


SCENARIOS: dict[str, Scenario] = _build()


def list_scenarios() -> list[str]:
    return list(SCENARIOS)


def get_scenario(name: str) -> Scenario:
    try:
        return SCENARIOS[name]
    except KeyError:
        raise ValueError(f"unknown scenario {name!r} (known: {', '.join(SCENARIOS)})") from None
