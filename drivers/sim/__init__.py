"""The plant simulator: the machine the daemon measures, written apart from the daemon's physics.

Public API (docs/architecture.md, "drivers.sim"): ``SCENARIOS``, ``list_scenarios``,
``Plant``, ``write_capture``, ``channel_scales``, ``machine_config``; the part program:
``PROGRAMS``, ``ProgramFaults`` (``program.py``), ``ProgramPlant`` (``program_plant.py``).
"""

from millsense.drivers.sim.capture import write_capture
from millsense.drivers.sim.config_view import machine_config
from millsense.drivers.sim.plant import Plant
from millsense.drivers.sim.program import PROGRAMS, ProgramFaults
from millsense.drivers.sim.program_plant import ProgramPlant
from millsense.drivers.sim.scenarios import SCENARIOS, Scenario, list_scenarios
from millsense.drivers.sim.sensors import channel_scales

__all__ = ["PROGRAMS", "SCENARIOS", "Plant", "ProgramFaults", "ProgramPlant", "Scenario", "channel_scales",
           "list_scenarios", "machine_config", "write_capture"]
