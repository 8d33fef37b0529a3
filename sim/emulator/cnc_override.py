"""The CNC's answer to a commanded feed override: a first-order lag, then a rate limit.

A CNC does not jump to a new override: its interpolator takes the new value over a
few interpolation cycles (tens of milliseconds, modelled as a first-order lag with
time constant ``lag_ms``) and its acceleration control bounds how fast the feed may
change (modelled as a rate limit on the override, ``rate_pct_s`` percent per second).
Both are stepped once per DAQ sample, so the plant's feed sees the override the CNC
really applies at each sample, and the DAQ reports the one applied now.
"""

from __future__ import annotations

import math

import numpy as np

NEUTRAL_PCT = 100.0
SNAP_PCT = 1e-4  # closer than this to the command: the command itself (the feed settles, as a CNC's does)


class CncOverride:
    """The applied override (percent) of a CNC, sample by sample; both states start at 100 %."""

    def __init__(self, lag_ms: float = 40.0, rate_pct_s: float = 1000.0, *, sample_rate_hz: float = 1000.0) -> None:
        if not (math.isfinite(lag_ms) and lag_ms >= 0):
            raise ValueError(f"override lag {lag_ms!r} ms: expected a number >= 0")
        if not (math.isfinite(rate_pct_s) and rate_pct_s >= 0):
            raise ValueError(f"override rate {rate_pct_s!r} %/s: expected a number >= 0 (0 = no limit)")
        if not sample_rate_hz > 0:
            raise ValueError(f"sample rate {sample_rate_hz!r} Hz: expected a number > 0")
        self.lag_ms = float(lag_ms)
        self.rate_pct_s = float(rate_pct_s)
        dt_s = 1.0 / float(sample_rate_hz)
        # exact discretisation of a first-order lag over one sample (zero-order hold on the command)
        self._alpha = 1.0 if lag_ms == 0 else 1.0 - math.exp(-dt_s / (lag_ms / 1000.0))
        self._step_pct = math.inf if rate_pct_s == 0 else rate_pct_s * dt_s
        self._lagged_pct = NEUTRAL_PCT  # the lag's state
        self.applied_pct = NEUTRAL_PCT  # after the rate limit: what the CNC applies now

    def run(self, commanded_pct: float, n: int) -> np.ndarray:
        """The applied override for each of the next ``n`` samples, the command held throughout."""
        cmd = float(commanded_pct)
        if self._lagged_pct == cmd and self.applied_pct == cmd:
            return np.full(n, cmd)  # settled: nothing to step
        out = np.empty(n)
        x, y = self._lagged_pct, self.applied_pct
        a, step = self._alpha, self._step_pct
        for i in range(n):
            x += (cmd - x) * a
            if abs(cmd - x) < SNAP_PCT:
                x = cmd
            y += min(max(x - y, -step), step)
            out[i] = y
        self._lagged_pct, self.applied_pct = x, y
        return out
