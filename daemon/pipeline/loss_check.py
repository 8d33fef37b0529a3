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
(`daq_link`, `daq_stalled`) and the revolutions' `lost_samples` report it, and the
window starts again after it. So does the gap before the first block after the link
came back (the driver marks that block `after_link_up`: a link cut for 0.3 s is fault
`daq_link`, each time), and a discontinuity (the DAQ restarted).
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
        self._blocks: deque[tuple[int, int, int]] = deque()   # (seq of the block's last sample, received, lost)
        self._received = 0
        self._lost = 0
        self._gaps = 0

    def update(self, seq0: int, n: int, lost_before: int = 0, discontinuity: bool = False,
               after_link_up: bool = False) -> str | None:
        """One block of `n` samples from sample `seq0`, after `lost_before` lost ones. Returns the verdict
        (verdict.py): the reason when raised, "" when cleared, else None. `after_link_up`: the first block
        since the link came back (`SampleBlock.after_link_up`): the gap before it is the outage's."""
        if n <= 0:
            return None
        lost = int(lost_before)
        if discontinuity or lost >= self.link_gap or after_link_up:
            self._restart()
            lost = 0
        last = seq0 + n - 1
        self._blocks.append((last, n, lost))
        self._received += n
        self._lost += lost
        self._gaps += lost > 0
        start = last - self.window + 1
        while self._blocks and self._blocks[0][0] < start:
            _, rec, gone = self._blocks.popleft()
            self._received -= rec
            self._lost -= gone
            self._gaps -= gone > 0
        span = self._received + self._lost
        if span < self.window // 2:   # too little of the stream yet to judge a share
            return None
        share = self._lost / span
        if not self.faulted and share > RAISE_SHARE:
            self.faulted = True
            return (f"{100.0 * share:.0f} % of the DAQ's samples over the last {self.window / self.rate:g} s lost "
                    f"({self._gaps} gaps: corrupt or dropped frames): the crash and overload checks do not see "
                    f"them, and almost no revolution is whole; check the DAQ's cable, its grounding and the baud "
                    f"rate (`bad_frames` and `lost_samples` in status)")
        if self.faulted and share <= CLEAR_SHARE:
            self.faulted = False
            return ""
        return None

    def _restart(self) -> None:
        self._blocks.clear()
        self._received = self._lost = self._gaps = 0
