"""Tool life and wear, per CNC tool number. Pure.

A tool wears: its edges round off and the same cut takes more energy. Each
good process of a key with a learned baseline gives one ratio, its cutting
energy over the key's learned energy (`energy_j / energy_mean_j`); a tool used
in several operations collects the ratios of all of them. The wear figure is
the mean of the last `wear_window` ratios, as a rise in %:

    wear_pct = (mean(ratio) − 1) · 100

A mean of several processes, because one process varies (stock, a harder
spot); the warning waits for a full window for the same reason. The warning is
raised once, when wear_pct reaches `wear_rise_pct`, and re-armed by
`new_tool` (the operator changed the tool), which also restarts its life count.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any


@dataclass
class ToolWear:
    """One tool number's life count and recent energy ratios."""

    processes: int = 0                              # processes that cut with it since `new_tool`
    ratios: list[float] = field(default_factory=list)   # the newest `wear_window` energy ratios
    warned: bool = False

    @property
    def wear_pct(self) -> float | None:
        if not self.ratios:
            return None
        return (sum(self.ratios) / len(self.ratios) - 1.0) * 100.0

    def count_process(self) -> None:
        self.processes += 1

    def add_ratio(self, ratio: float, window: int, rise_pct: float) -> bool:
        """One good process's energy ratio. True when this one raises the wear warning."""
        window = max(1, int(window))
        self.ratios.append(float(ratio))
        del self.ratios[:-window]
        wear = self.wear_pct
        if self.warned or len(self.ratios) < window or wear is None or wear < rise_pct:
            return False
        self.warned = True
        return True

    def new_tool(self) -> None:
        """A fresh tool in the holder: life from zero, no ratios, the warning re-armed."""
        self.processes, self.ratios, self.warned = 0, [], False

    def to_dict(self) -> dict[str, Any]:
        return {"processes": self.processes, "ratios": list(self.ratios), "warned": self.warned}

    @classmethod
    def from_dict(cls, d: Any) -> "ToolWear":
        """A stored tool, checked: ValueError naming what is wrong."""
        if not isinstance(d, dict):
            raise ValueError(f"not an object ({type(d).__name__})")
        processes, ratios, warned = d.get("processes", 0), d.get("ratios", []), d.get("warned", False)
        if isinstance(processes, bool) or not isinstance(processes, int) or not 0 <= processes <= 10**12:
            raise ValueError(f"processes: {processes!r} is not a count")
        if not isinstance(ratios, list) or not all(
                not isinstance(r, bool) and isinstance(r, (int, float)) and 0 <= r <= 1e6 and math.isfinite(r)
                for r in ratios):
            raise ValueError("ratios: not a list of finite energy ratios")
        if not isinstance(warned, bool):
            raise ValueError(f"warned: {warned!r} is not true or false")
        return cls(processes, [float(r) for r in ratios], warned)
