"""The simulated machine as configuration sections, so config examples can be checked against it.

Keys follow the daemon's TOML (`interfaces.md`): ``motor``, ``gears``, ``tool``,
``material``, ``cut``, plus the DAQ filter and the feed drive's calibration.
A part program (``sim/program.py``) adds ``tools`` (its magazine by the
CNC's tool number), ``program`` (its number) and ``channels`` (the extra ones).
"""

from __future__ import annotations

from millsense.sim.scenarios import Scenario, get_scenario


def _constant(profile) -> float | None:
    values = {d for _, d in profile}
    return values.pop() if len(values) == 1 else None


def machine_config(scenario: str | Scenario = "step") -> dict:
    from millsense.sim.program import PROGRAMS, PartProgram

    if isinstance(scenario, PartProgram) or (isinstance(scenario, str) and scenario in PROGRAMS):
        return _program_config(scenario if isinstance(scenario, PartProgram) else PROGRAMS[scenario])
    sc = scenario if isinstance(scenario, Scenario) else get_scenario(scenario)
    m = sc.machine
    cut: dict = {"mode": sc.mode, "feed_mm_min": sc.feed_segments[0][1]}
    axial = _constant(sc.axial_profile) if sc.axial_profile else None
    if axial:
        cut["axial_depth_mm"] = axial
    radial = sc.tool.diameter_mm if sc.mode == "slot" else (_constant(sc.radial_profile) if sc.radial_profile else None)
    if radial and sc.mode != "slot":
        cut["radial_depth_mm"] = radial
    out = {
        "motor": {
            "winding": m.motor.winding,
            "stator_resistance_ohm": m.motor.stator_resistance_ohm,
            "pole_pairs": m.motor.pole_pairs,
        },
        "gears": [
            {"name": g.name, "ratio": g.ratio, "max_spindle_rpm": g.max_spindle_rpm,
             "friction_torque_nm": g.friction_torque_nm, "viscous_nms": g.viscous_nms}
            for g in sorted(m.gears, key=lambda g: g.max_spindle_rpm)
        ],
        "tool": {"diameter_mm": sc.tool.diameter_mm, "flutes": sc.tool.flutes},
        "material": {k: getattr(sc.material, k) for k in ("ks", "ks_exp", "r1", "r1_exp", "r2", "r2_exp")},
        "cut": cut,
        "daq": {"filter_cutoff_hz": sc.filter_cutoff_hz, "filter_order": 2},
    }
    if "ix_feed" in sc.extra_channels:
        out["feed_force"] = {"ix_feed": {"newton_per_amp": m.feed.newton_per_amp, "friction_n": m.feed.friction_n}}
    return out


def _program_config(program) -> dict:
    """The part program's machine: the scenario sections of its first tool, and the whole magazine."""
    out = machine_config(program.scenario(1))
    out["tools"] = {number: {"diameter_mm": tool.diameter_mm, "flutes": tool.flutes, "helix_deg": tool.helix_deg}
                    for number, tool in program.tools.items()}
    out["program"] = program.number
    out["channels"] = list(program.extra_channels)
    return out
