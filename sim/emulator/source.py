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
):
    """Build the plant for ``scenario``; only options given are passed on.

    ``program``: for a part program, ``parts``, ``faults`` (a ``ProgramFaults``) and ``program_number``."""
    if scenario == "ramp":
        return RampPlant(start_index=start_index)
    if is_program(scenario):
        from millsense.sim.program_plant import ProgramPlant

        options = {k: v for k, v in (program or {}).items() if v is not None}
        if noise_scale is not None:
            options["noise_scale"] = noise_scale
        try:
            return ProgramPlant(scenario, seed=seed, loop=loop, filter_cutoff_hz=filter_cutoff_hz, **options)
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
    try:
        return Plant(scenario, **kwargs)
    except TypeError as exc:
        raise SourceError(f"the plant simulator does not take these options: {exc}") from exc
