"""A check on the stream itself: how many of the DAQ's samples never reach the daemon.

Each revolution that lost a sample is published invalid, and the crash check sees
only the frames that arrive. A link that loses a few frames now and then costs a
revolution here and there. One that loses a large share of them (a bad cable or
ground, a baud rate at its limit, a DAQ that overruns its ring, the daemon's own
queue overflowing) leaves almost no revolution judged: every overload passes
unseen, while the link, the heartbeat and every channel look healthy. That is
blind, so the daemon says so: fault `signals` (source `data_loss`) with the share
lost, and under `[interlock] on_blind = "hold"` the feed held while the spindle
turns, until the share over the window is back to a few percent.

The share is counted over the last `WINDOW_S` of sample numbers: the samples the
blocks carried and the gaps before them (`lost_before`). A gap of `LINK_GAP_S` or
longer after an outage of the link is an interruption, not a lossy stream: the link's
own faults (`daq_link`, `daq_stalled`) and the revolutions' `lost_samples` report it,
the DAQ's watchdog holds the feed by itself (its heartbeats went with the link), and
the windows start again after it. So does a discontinuity (the DAQ restarted).

A gap that long with the link up is the reader falling behind the DAQ: a Modbus reader
a ring behind skips half a second or more (`overruns`), and one that cannot keep up
(a slow gateway, a loaded box) does so again and again, the link up all along (stop
29's finding A: 60 % lost, status `running`). One such gap in a 2-s window would be a
third of it, so they are judged over `LONG_WINDOW_S` with every other loss: one now
and then is lost samples, counted; a reader that keeps overrunning is blind. A shorter outage of
the link (the driver marks the first block after it `after_link_up`) counts as lost:
a link that keeps dropping for a few tenths of a second, under the watchdog, leaves the
daemon as blind as a lossy cable does (a probe in stop 28: 43 % of the stream lost over
20 s of a link up 0.35 s, down 0.25 s, with status `running` most of the time).
"""

from __future__ import annotations

from collections import deque

WINDOW_S = 2.0       # the share is judged over this much of the stream (2000 samples at 1 kHz)
RAISE_SHARE = 0.20   # over this share lost: blind (10-sample frames at 600 rpm: about 1 revolution in 10 whole)
CLEAR_SHARE = 0.05   # at or under this share again: seeing (6 revolutions in 10 whole)
LINK_GAP_S = 0.5     # one gap this long after an outage is an interruption of the link, not a lossy stream
LONG_WINDOW_S = 10.0  # gaps that long with the link up (a reader a ring behind) are judged over this much


class _Share:
    """The samples received and lost over the last `window` sample numbers, block by block."""

    def __init__(self, window: int):
        self.window = window
        self._blocks: deque[tuple[int, int, int, bool, bool]] = deque()   # (last seq, received, lost, outage, long)
        self.received = self.lost = self.gaps = self.outages = self.long_gaps = 0

    def add(self, last: int, n: int, lost: int, outage: bool, long: bool) -> float | None:
        """One block; the share lost, or None while too little of the stream is in the window to judge."""
        self._blocks.append((last, n, lost, outage, long))
        self._count(n, lost, outage, long, +1)
        start = last - self.window + 1
        while self._blocks and self._blocks[0][0] < start:
            _, rec, gone, was_outage, was_long = self._blocks.popleft()
            self._count(rec, gone, was_outage, was_long, -1)
        span = self.received + self.lost
        return None if span < self.window // 2 else self.lost / span

    def _count(self, n: int, lost: int, outage: bool, long: bool, sign: int) -> None:
        self.received += sign * n
        self.lost += sign * lost
        self.gaps += sign * (lost > 0)
        self.outages += sign * outage
        self.long_gaps += sign * long

    def restart(self) -> None:
        self._blocks.clear()
        self.received = self.lost = self.gaps = self.outages = self.long_gaps = 0


class LossCheck:
    """The share of samples lost over the last `WINDOW_S` (and `LONG_WINDOW_S`, with the gaps of a reader that
    falls a ring behind); says when to raise and to clear the fault."""

    def __init__(self, sample_rate_hz: float, window_s: float = WINDOW_S, faulted: bool = False):
        """`faulted`: the verdict of the check this one replaces (replay, at another descriptor's rate)."""
        self.rate = float(sample_rate_hz)
        self.window = max(1, int(round(window_s * self.rate)))
        self.link_gap = max(1, int(round(LINK_GAP_S * self.rate)))
        self.faulted = bool(faulted)
        self._short = _Share(self.window)
        self._long = _Share(max(self.window, int(round(LONG_WINDOW_S * self.rate))))

    def update(self, seq0: int, n: int, lost_before: int = 0, discontinuity: bool = False,
               after_link_up: bool = False) -> str | None:
        """One block of `n` samples from sample `seq0`, after `lost_before` lost ones. Returns the verdict
        (verdict.py): the reason when raised, "" when cleared, else None. `after_link_up`: the first block
        since the link came back (`SampleBlock.after_link_up`): the gap before it is the outage's."""
        if n <= 0:
            return None
        lost = int(lost_before)
        last = seq0 + n - 1
        if discontinuity or (after_link_up and lost >= self.link_gap):   # an interruption: both start again
            self._short.restart()
            self._long.restart()
            lost = 0
        long_gap = lost >= self.link_gap           # the link up: a reader a ring behind
        outage = bool(after_link_up and lost)
        if long_gap:
            self._short.restart()                  # judged over the long window only
            short = self._short.add(last, n, 0, False, False)
        else:
            short = self._short.add(last, n, lost, outage, False)
        long = self._long.add(last, n, lost, outage, long_gap)
        if not self.faulted:
            if short is not None and short > RAISE_SHARE:
                self.faulted = True
                return self._reason(self._short, short)
            if long is not None and long > RAISE_SHARE and self._long.long_gaps:
                self.faulted = True
                return self._reason(self._long, long)
            return None
        if (short is None or short <= CLEAR_SHARE) and (long is None or long <= CLEAR_SHARE
                                                        or not self._long.long_gaps):
            self.faulted = False
            return ""
        return None

    def _reason(self, w: _Share, share: float) -> str:
        if w.long_gaps:
            why = (f"{w.gaps} gaps, {w.long_gaps} of them {LINK_GAP_S:g} s or longer with the link up: the reader "
                   f"falls behind the DAQ and skips what it overwrote (a Modbus ring overrun, `overruns` in status: "
                   f"a slow gateway or a loaded box)")
        elif w.outages:
            why = (f"{w.gaps} gaps, {w.outages} of them the link going down and coming back: a link that "
                   f"keeps dropping; check the DAQ's cable, its connectors and the network or converter between")
        else:
            why = (f"{w.gaps} gaps: corrupt or dropped frames; check the DAQ's cable, its grounding and the "
                   f"baud rate")
        return (f"{100.0 * share:.0f} % of the DAQ's samples over the last {w.window / self.rate:g} s lost "
                f"({why}): the crash and overload checks do not see them, and almost no revolution is whole "
                f"(`bad_frames`, `lost_samples` and `daq.link_changes` in status)")
