"""How the wiring and stream checks answer, and the debounce two of them share.

Each check (`power_check.py`, `phase_check.py`, `loss_check.py`) is fed one
observation at a time and answers with a verdict on fault `signals`: the
fault's reason (in words, naming what to check) when it is raised, "" when it
clears, None when nothing changed. The live daemon (`FaultBoard.verdict`) and replay
(`_note_fault_change`) read the verdicts the same way.

`InARow` is the debounce of the power and phase checks: the verdict flips
only after `needed` observations in a row on its other side, so one odd
revolution or window neither raises nor clears the fault. (The loss check
debounces by two shares instead: raise above one, clear at or under a lower.)
"""

from __future__ import annotations


class InARow:
    """A wrong/right verdict that flips after `needed` observations in a row on its other side."""

    def __init__(self, needed: int):
        self.needed = int(needed)
        self.faulted = False
        self._run = 0   # observations in a row on the other side of `faulted`

    def observe(self, wrong: bool) -> bool:
        """One observation. True when it flipped the verdict (`faulted` says which way)."""
        self._run = self._run + 1 if wrong != self.faulted else 0
        if self._run < self.needed:
            return False
        self._run = 0
        self.faulted = wrong
        return True
