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
blocks carried and the gaps before them (`lost_before`). A single gap longer than
`LINK_GAP_S` is an interruption, not a lossy stream: the link's own faults
(`daq_link`, `daq_stalled`) and the revolutions' `lost_samples` report it, the DAQ's
watchdog holds the feed by itself (its heartbeats went with the link), and the window
starts again after it. So does a discontinuity (the DAQ restarted). A shorter outage of
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
LINK_GAP_S = 0.5     # one gap this long is an interruption of the link, not a lossy stream


class LossCheck:
    """The share of samples lost over the last `WINDOW_S`; says when to raise and to clear the fault."""

    def __init__(self, sample_rate_hz: float, window_s: float = WINDOW_S, faulted: bool = False):
        """`faulted`: the verdict of the check this one replaces (replay, at another descriptor's rate)."""
        self.rate = float(sample_rate_hz)
        self.window = max(1, int(round(window_s * self.rate)))
        self.link_gap = max(1, int(round(LINK_GAP_S * self.rate)))
        self.faulted = bool(faulted)
        # (seq of the block's last sample, received, lost before it, that gap the link's outage)
        self._blocks: deque[tuple[int, int, int, bool]] = deque()
        self._received = 0
        self._lost = 0
        self._gaps = 0
        self._outages = 0

    def update(self, seq0: int, n: int, lost_before: int = 0, discontinuity: bool = False,
               after_link_up: bool = False) -> str | None:
        """One block of `n` samples from sample `seq0`, after `lost_before` lost ones. Returns the verdict
        (verdict.py): the reason when raised, "" when cleared, else None. `after_link_up`: the first block
        since the link came back (`SampleBlock.after_link_up`): the gap before it is the outage's."""
        if n <= 0:
            return None
        lost = int(lost_before)
        if discontinuity or lost >= self.link_gap:
            self._restart()
            lost = 0
        outage = bool(after_link_up and lost)
        last = seq0 + n - 1
        self._blocks.append((last, n, lost, outage))
        self._received += n
        self._lost += lost
        self._gaps += lost > 0
        self._outages += outage
        start = last - self.window + 1
        while self._blocks and self._blocks[0][0] < start:
            _, rec, gone, was_outage = self._blocks.popleft()
            self._received -= rec
            self._lost -= gone
            self._gaps -= gone > 0
            self._outages -= was_outage
        span = self._received + self._lost
        if span < self.window // 2:   # too little of the stream yet to judge a share
            return None
        share = self._lost / span
        if not self.faulted and share > RAISE_SHARE:
            self.faulted = True
            if self._outages:
                why = (f"{self._gaps} gaps, {self._outages} of them the link going down and coming back: a link that "
                       f"keeps dropping; check the DAQ's cable, its connectors and the network or converter between")
            else:
                why = (f"{self._gaps} gaps: corrupt or dropped frames; check the DAQ's cable, its grounding and the "
                       f"baud rate")
            return (f"{100.0 * share:.0f} % of the DAQ's samples over the last {self.window / self.rate:g} s lost "
                    f"({why}): the crash and overload checks do not see them, and almost no revolution is whole "
                    f"(`bad_frames`, `lost_samples` and `daq.link_changes` in status)")
        if self.faulted and share <= CLEAR_SHARE:
            self.faulted = False
            return ""
        return None

    def _restart(self) -> None:
        self._blocks.clear()
        self._received = self._lost = self._gaps = self._outages = 0
