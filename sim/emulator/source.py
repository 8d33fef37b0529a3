"""Which plant the emulator wraps: the ramp, or a scenario of ``millsense.sim``."""

from __future__ import annotations

from millsense.sim.emulator.ramp import RampPlant


class SourceError(Exception):
    """The scenario cannot be built; the message says why."""


def list_sources() -> list[tuple[str, str]]:
    """(name, description) of every scenario the emulator can serve."""
    names = [("ramp", RampPlant.description)]
    try:
        from millsense import sim

        for name in sim.list_scenarios():
            scen = sim.SCENARIOS.get(name) if hasattr(sim, "SCENARIOS") else None
            desc = getattr(scen, "description", "") if scen is not None else ""
            names.append((name, desc))
        from millsense.sim.program import PROGRAMS

        names += [(name, prog.description) for name, prog in PROGRAMS.items()]
    except (ImportError, AttributeError):
        pass
    return names


def is_program(scenario: str) -> bool:
    """Whether ``scenario`` is a part program (sim/program.py): its own CNC, faults, parts."""
    try:
        from millsense.sim.program import PROGRAMS
    except ImportError:
        return False
    return scenario in PROGRAMS


def make_source(
    scenario: str,
    *,
    seed: int = 0,
    loop: bool = False,
    start_index: int = 0,
    filter_cutoff_hz: float | None = None,
    noise_scale: float | None = None,
    program: dict | None = None,
    material_offset_pct: float | None = None,
):
    """Build the plant for ``scenario``; only options given are passed on.

    ``program``: for a part program, ``parts``, ``faults`` (a ``ProgramFaults``), ``program_number`` and
    ``only`` (operation numbers to play alone). ``material_offset_pct``: the plant's material that many %
    off the scenario's (sim/cut_effects.py ``material_batch``)."""
    if scenario == "ramp":
        if material_offset_pct is not None:
            raise SourceError("--material-offset-pct: the ramp cuts nothing; choose a scenario of the plant")
        return RampPlant(start_index=start_index)
    if is_program(scenario):
        from dataclasses import replace

        from millsense.sim.program import PROGRAMS
        from millsense.sim.program_plant import ProgramPlant

        options = {k: v for k, v in (program or {}).items() if v is not None}
        only = options.pop("only", ())
        if noise_scale is not None:
            options["noise_scale"] = noise_scale
        try:
            part_program = PROGRAMS[scenario].only(*only) if only else PROGRAMS[scenario]
            if material_offset_pct is not None:
                part_program = replace(part_program, material_offset_pct=material_offset_pct)
            return ProgramPlant(part_program, seed=seed, loop=loop, filter_cutoff_hz=filter_cutoff_hz, **options)
        except ValueError as exc:
            raise SourceError(str(exc)) from exc
    try:
        from millsense.sim import SCENARIOS, Plant
    except ImportError as exc:
        raise SourceError(
            f"cannot serve scenario {scenario!r}: the plant simulator is not available ({exc}); only 'ramp' can be"
        ) from exc
    if scenario not in SCENARIOS:
        known = ", ".join(name for name, _ in list_sources())
        raise SourceError(f"unknown scenario {scenario!r} (known: {known})")
    kwargs: dict = {"seed": seed}
    if loop:
        kwargs["loop"] = True
    if filter_cutoff_hz is not None:
        kwargs["filter_cutoff_hz"] = filter_cutoff_hz
    if noise_scale is not None:
        kwargs["noise_scale"] = noise_scale
    plant_scenario = scenario
    if material_offset_pct is not None:
        from dataclasses import replace

        plant_scenario = replace(SCENARIOS[scenario], material_offset_pct=material_offset_pct)
    try:
        return Plant(plant_scenario, **kwargs)
    except TypeError as exc:
        raise SourceError(f"the plant simulator does not take these options: {exc}") from exc
    except ValueError as exc:
        raise SourceError(str(exc)) from exc
