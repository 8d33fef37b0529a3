"""The plant simulator: the machine the daemon measures, written apart from the daemon's physics.

Public API (docs/architecture.md, "sim"): ``SCENARIOS``, ``list_scenarios``,
``Plant``, ``write_capture``, ``channel_scales``, ``machine_config``; the part program:
``PROGRAMS``, ``ProgramFaults`` (``program.py``), ``ProgramPlant`` (``program_plant.py``); the first parts
(issue 41): ``FIRST_PART_PROGRAMS``, ``operations_config`` (``first_part.py``), ``CutEffects``
(``cut_effects.py``).
"""

from millsense.sim.capture import write_capture
from millsense.sim.config_view import machine_config
from millsense.sim.cut_effects import CutEffects
from millsense.sim.first_part import FIRST_PART_PROGRAMS, operations_config
from millsense.sim.plant import Plant
from millsense.sim.program import PROGRAMS, ProgramFaults
from millsense.sim.program_plant import ProgramPlant
from millsense.sim.scenarios import SCENARIOS, Scenario, list_scenarios
from millsense.sim.sensors import channel_scales

__all__ = ["FIRST_PART_PROGRAMS", "PROGRAMS", "SCENARIOS", "CutEffects", "Plant", "ProgramFaults", "ProgramPlant",
           "Scenario", "channel_scales", "list_scenarios", "machine_config", "operations_config", "write_capture"]
