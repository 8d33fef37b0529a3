"""A wiring check on the running estimates: a turning motor draws power.

A running induction motor takes positive real power from its supply: its
losses alone (copper, iron, friction) are hundreds of watts. If the input
power of many revolutions in a row comes out negative while the spindle turns
at a steady speed, the current channels are turned round (a current sensor
mounted the wrong way, a negative `scale`) or they are not in the voltages'
phase order, and every torque and force the daemon publishes is wrong. The
interlock cannot protect a machine it cannot measure, so the daemon says so:
fault `signals` (status `degraded`, the log says what to check) until the
power has been positive for as many revolutions again.

Revolutions that say nothing about the wiring are left out: damaged ones, a
spindle speeding up (`accelerating`) and one slowing down, which may be
braking and feeding power back (regeneration).

While this (or another stream check) holds the fault, every revolution is
published invalid (`invalid: "wiring"`, runner.py `_set_stream_problem`), its
quantities null: the estimator hands this check the whole revolution's input
power and speed beside it (`wiring_p_in_w`, `wiring_rpm`, never published), so
that the fault still clears once the wiring is right.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from millsense.daemon.pipeline.verdict import InARow

REVOLUTIONS = 20          # in a row: 2 s at 600 rpm; no braking lasts that long at a steady speed
MARGIN_W = 50.0           # below −MARGIN_W is negative; sensor noise averages far below this per revolution
SLOWING_PCT = 0.5         # a revolution this much slower than the one before may be braking


class PowerSignCheck:
    """Counts steady revolutions with negative input power; says when to raise and to clear the fault."""

    def __init__(self, revolutions: int = REVOLUTIONS):
        self.revolutions = revolutions
        self._verdict = InARow(revolutions)   # qualifying revolutions in a row flip it
        self._prev_rpm: float | None = None

    @property
    def faulted(self) -> bool:
        return self._verdict.faulted

    def update(self, est: Mapping[str, Any]) -> str | None:
        """One estimate. Returns the verdict (verdict.py): the reason when raised, "" when cleared, else None."""
        if est.get("valid", True):
            rpm, p_in = est.get("spindle_rpm"), est.get("p_in_w")
        else:   # invalid for the stream's fault only: whole, judged on what the estimator kept for this check
            rpm, p_in = est.get("wiring_rpm"), est.get("wiring_p_in_w")
        prev, self._prev_rpm = self._prev_rpm, rpm
        if est.get("accelerating") or rpm is None or p_in is None:
            return None
        if prev is not None and rpm < prev * (1.0 - SLOWING_PCT / 100.0):
            return None
        wrong = p_in < -MARGIN_W
        if not self._verdict.observe(wrong):
            return None
        if not wrong:
            return ""
        return (
            f"input power negative for {self.revolutions} revolutions at a steady {rpm:.0f} rpm "
            f"(p_in_w {p_in:.0f}): a current sensor turned round (mounted the wrong way, or a negative scale "
            f"in [channels]), or the current channels not in the phase order of the voltages; "
            f"torque and force are wrong until this is fixed"
        )
