"""A check on the stream itself: do the samples come as fast as the DAQ says it takes them?

Every time and speed the daemon computes divides a sample count by the sample rate
the DAQ's descriptor states (and `[daq] sample_rate_hz` must agree with it). Set
wrong in both places (a DAQ configured for 2 kHz that samples at 1 kHz, a board
swapped for one with another crystal or divider), everything still looks healthy:
an encoder-only installation closes its revolutions on the encoder's counts, the
currents swing, nothing is lost. But the speed is off by the ratio, the inertia and
friction terms with it, and the torque is wrong (a probe in stop 28: 115 revolutions
of 115 published valid at twice the true speed, some with negative torque). A speed
channel in rpm catches it (the signal check compares it with the encoder and f_e);
without one, only the host's own clock can.

So the arrival of the samples is timed on the monotonic clock. Each observation is a
block's last sample and when it arrived: `offset = arrival − seq / rate`. Transport
delays only ever make an arrival late, so the earliest offsets trace when the samples
were taken. At the stated rate that lower edge is flat (a DAQ crystal drifts
≈ 50 ppm); at a wrong one it climbs or falls by `1 − true/stated` seconds per second.
The check compares the earliest offset in the first `EDGE_S` of the last `WINDOW_S`
of arrivals with the earliest in the last `EDGE_S`: a reader held up for a second (a
loaded host, the DAQ's frames bunched, a Modbus catch-up) makes some arrivals late,
not all of an edge's. Judged once a second; `JUDGEMENTS` in a row over `RAISE_SHARE`
raise fault `signals` (source `sample_rate`: blind, so `on_blind`; every revolution
published invalid with `invalid: "sample_rate"`), as many under it clear it. A
discontinuity (the DAQ restarted) starts the window again.
"""

from __future__ import annotations

from collections import deque

from millsense.daemon.pipeline.verdict import InARow

WINDOW_S = 10.0       # arrivals judged together (the measured rate's error: a few ms over 8 s)
EDGE_S = 2.0          # the window's first and last EDGE_S: the earliest arrival of each is compared
JUDGE_EVERY_S = 1.0
RAISE_SHARE = 0.05    # measured rate this far from the stated one: the stream's timing is wrong
JUDGEMENTS = 3        # in a row, to raise and to clear


class RateCheck:
    """The samples' arrival rate against the stated `sample_rate_hz`; says when to raise and to clear."""

    def __init__(self, sample_rate_hz: float, faulted: bool = False):
        """`faulted`: the verdict of the check this one replaces (a new descriptor)."""
        self.rate = float(sample_rate_hz)
        self._verdict = InARow(JUDGEMENTS)
        self._verdict.faulted = bool(faulted)
        self._arrivals: deque[tuple[float, float]] = deque()   # (arrival, offset), oldest first
        self._judge_at: float | None = None
        self.measured_hz: float | None = None   # the last judgement's rate, for the reason and the log

    @property
    def faulted(self) -> bool:
        return self._verdict.faulted

    def update(self, seq_last: int, arrival_s: float, restart: bool = False) -> str | None:
        """The block ending with sample `seq_last` arrived at `arrival_s` (monotonic). Returns the verdict
        (verdict.py): the reason when raised, "" when cleared, else None."""
        arrivals = self._arrivals
        if restart:
            arrivals.clear()
            self._judge_at = None
        arrivals.append((arrival_s, arrival_s - seq_last / self.rate))
        while arrivals[0][0] < arrival_s - WINDOW_S:
            arrivals.popleft()
        if self._judge_at is None:
            self._judge_at = arrival_s + JUDGE_EVERY_S
        if arrival_s < self._judge_at:
            return None
        self._judge_at = arrival_s + JUDGE_EVERY_S
        first = arrivals[0][0]
        if arrival_s - first < WINDOW_S - JUDGE_EVERY_S:   # too little of the stream yet
            return None
        head = min((a for a in arrivals if a[0] < first + EDGE_S), key=lambda a: a[1])
        tail = min((a for a in arrivals if a[0] > arrival_s - EDGE_S), key=lambda a: a[1])
        if tail[0] - head[0] < WINDOW_S / 2:   # both edges' earliest near the middle: not enough between
            return None
        drift = (tail[1] - head[1]) / (tail[0] - head[0])   # seconds of offset per second: 1 - true/stated
        self.measured_hz = self.rate * (1.0 - drift)
        wrong = abs(drift) > RAISE_SHARE
        if not self._verdict.observe(wrong):
            return None
        if not wrong:
            return ""
        factor = self.rate / self.measured_hz if self.measured_hz > 0 else float("inf")
        return (f"samples arrive at {self.measured_hz:.0f} per second, the DAQ states {self.rate:g} Hz: every "
                f"speed, time and torque would be off by x{factor:.2f}; check the DAQ's "
                "sample rate setting and [daq] sample_rate_hz")
