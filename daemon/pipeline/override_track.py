"""The CNC's applied feed override as a step function of the sample number. Pure.

The DAQ reports the override the CNC applies now (STATUS, protocol version 2:
tenths of a percent; Modbus input register 6). It lags what the daemon
commanded, and it is what the cut ran at, so feed per tooth, depths and the
learned limits use it. A STATUS names no sample: the value holds from the next
sample the daemon processes (like a Zenoh context), which shifts a change by a
block at most (tens of ms; a revolution at 600 rpm is 100 ms).

Per revolution the override is its time-weighted mean over the revolution's
samples: a revolution cut half at 100 % and half at 120 % removed the chip of a
110 % feed. One short loop per revolution over the few steps inside it, nothing
per sample. Without a reporting DAQ there are no steps and every revolution
reads `DEFAULT_PCT` (the programmed feed).
"""

from __future__ import annotations

import threading
from bisect import bisect_left, bisect_right

DEFAULT_PCT = 100.0
MAX_STEPS = 4096   # a bound whatever happens: steps older than every open revolution are dropped anyway


class OverrideTrack:
    """Steps (first sample, percent), in sample order; the value before the first step is `DEFAULT_PCT`.

    Copy on write: `note` (the thread that reads STATUS) builds new lists and swaps them in with one
    assignment, so the estimator thread reading `mean` always sees a consistent pair. Notes are rare
    (a STATUS comes when the applied override changed), revolutions are many. The two writers (`note`,
    `forget_before`) share a lock so that neither loses the other's change.
    """

    def __init__(self) -> None:
        self._steps: tuple[list[int], list[float]] = ([], [])
        self._write = threading.Lock()

    @property
    def reported(self) -> bool:
        """Has the DAQ ever reported an override?"""
        return bool(self._steps[0])

    def note(self, seq: int, pct: float) -> None:
        """The override is `pct` from sample `seq` on (a note at or before an earlier step replaces it)."""
        seq, pct = int(seq), float(pct)
        with self._write:
            seqs, pcts = self._steps
            if pcts and pcts[-1] == pct:
                return   # the DAQ repeats an unchanged value: no step
            keep = bisect_left(seqs, seq)
            seqs, pcts = seqs[:keep] + [seq], pcts[:keep] + [pct]
            self._steps = (seqs[-MAX_STEPS:], pcts[-MAX_STEPS:])

    def at(self, seq: int) -> float:
        """The override at sample `seq`."""
        seqs, pcts = self._steps
        i = bisect_right(seqs, int(seq)) - 1
        return pcts[i] if i >= 0 else DEFAULT_PCT

    def mean(self, first: int, last: int) -> float:
        """Time-weighted mean over samples first … last (inclusive)."""
        return _mean(*self._steps, first, last)

    def means(self, firsts: list[int], lasts: list[int]) -> list[float]:
        """`mean` of each span firsts[k] … lasts[k] (in sample order), all from one snapshot of the steps:
        one value for all when no step falls after the first span starts (the usual batch of revolutions)."""
        seqs, pcts = self._steps
        if not firsts:
            return []
        if not seqs or seqs[-1] <= firsts[0]:
            return [pcts[-1] if seqs else DEFAULT_PCT] * len(firsts)
        return [_mean(seqs, pcts, a, b) for a, b in zip(firsts, lasts)]

    def forget_before(self, seq: int) -> None:
        """Drop steps no revolution from `seq` on can need (the one in force at `seq` stays)."""
        seqs = self._steps[0]
        if len(seqs) < 2 or seqs[1] > seq:
            return   # nothing to drop: the usual case, no lock taken
        with self._write:
            seqs, pcts = self._steps
            i = bisect_right(seqs, int(seq)) - 1
            if i > 0:
                self._steps = (seqs[i:], pcts[i:])


# --- the load at the programmed feed --------------------------------------------------------------
# Torque and force follow the feed per tooth as t^(1+p) (K_s·t^p·t, [D] eq. 8; p = [material] ks_exp,
# negative): the same static gain the controller assumes (`[afc] process_gain`, 0 = 1 + ks_exp).
DEFAULT_KS_EXP = -0.4362   # [D] Table 2, as config.models' default


def load_gain(settings) -> float:
    """d ln(load) / d ln(feed) of the configuration: `[afc] process_gain`, or 1 + `[material] ks_exp`."""
    afc = getattr(settings, "afc", None)
    gain = float(getattr(afc, "process_gain", 0.0) or 0.0)
    if gain > 0.0:
        return gain
    material = getattr(settings, "material", None)
    ks_exp = getattr(material, "ks_exp", None)
    return 1.0 + float(DEFAULT_KS_EXP if ks_exp is None else ks_exp)


def _mean(seqs: list[int], pcts: list[float], first: int, last: int) -> float:
    """Time-weighted mean over samples first … last (inclusive) of the steps (seqs, pcts)."""
    i = bisect_right(seqs, int(first)) - 1
    value = pcts[i] if i >= 0 else DEFAULT_PCT
    if last <= first or i + 1 >= len(seqs) or seqs[i + 1] > last:
        return value   # no step inside: the usual revolution
    total, start = 0.0, int(first)
    for s, p in zip(seqs[i + 1:], pcts[i + 1:]):
        if s > last:
            break
        total += value * (s - start)
        start, value = s, p
    total += value * (int(last) + 1 - start)
    return total / (int(last) + 1 - int(first))
