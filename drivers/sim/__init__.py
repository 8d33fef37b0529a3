"""The plant simulator: the machine the daemon measures, written apart from the daemon's physics.

Public API (docs/architecture.md, "drivers.sim"): ``SCENARIOS``, ``list_scenarios``,
``Plant``, ``write_capture``, ``channel_scales``, ``machine_config``.
"""

from millsense.drivers.sim.capture import write_capture
from millsense.drivers.sim.config_view import machine_config
from millsense.drivers.sim.plant import Plant
from millsense.drivers.sim.scenarios import SCENARIOS, Scenario, list_scenarios
from millsense.drivers.sim.sensors import channel_scales

__all__ = ["SCENARIOS", "Plant", "Scenario", "channel_scales", "list_scenarios", "machine_config", "write_capture"]
