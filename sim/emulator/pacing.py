"""Real-time pacing without drift: the sample count due is computed from the start time.

Sleeping a fixed 10 ms per batch would drift by the work done each batch; instead
the number of samples due is ``floor((now - t0) * rate)``, so a late wake-up is
caught up by the next batch and minutes of running stay on the clock.

With a `quantum` (the stream's samples per frame) only whole frames are due, as
a DAQ with its own sample clock sends them: a wake-up 1 ms late at 10-sample
frames sends one 10-sample frame and keeps the 11th for the next, instead of a
10-sample frame and a 1-sample one (which doubled the frames on the wire and
was nothing a real DAQ does). The end of a finite run sends what is left.

`millsense sim --start-on-connect` (a test bench's option) makes sample 0 wait
for the first client: the servers await `first_of(client, stop)`, then
`Pacer.restart(now)`, so a reader that starts late still sees the run from its
first sample, however long its start-up took.
"""

from __future__ import annotations

import math
import time


class Pacer:
    def __init__(self, sample_rate_hz: int, *, realtime: bool = True, batch_s: float = 0.01, clock=time.monotonic,
                 quantum: int = 1, speed: float = 1.0):
        self.rate = sample_rate_hz
        # realtime only: samples due `speed` times as fast as the clock (a test bench playing a part at speed;
        # the samples and their descriptor keep their true rate)
        self.speed = float(speed)
        self.realtime = realtime
        self.quantum = max(1, int(quantum))
        self.batch = max(1, round(sample_rate_hz * batch_s))
        self.clock = clock
        self.t0 = clock()
        self.produced = 0

    def restart(self, now: float) -> None:
        """Sample 0 is due at `now` (nothing produced yet: --start-on-connect)."""
        self.t0, self.produced = now, 0

    def due(self, now: float | None = None, limit: int | None = None) -> int:
        """How many samples to produce now (and count them as produced)."""
        if self.realtime:
            now = self.clock() if now is None else now
            n = math.floor((now - self.t0) * self.rate * self.speed) - self.produced
            if limit is None or self.produced + n < limit:
                n -= n % self.quantum   # whole frames only; the rest waits for the next one
        else:
            n = self.batch * 100
        if limit is not None:
            n = min(n, limit - self.produced)
        n = max(0, n)
        self.produced += n
        return n

    def next_time(self) -> float:
        """Monotonic time when the next batch is due."""
        return self.t0 + (self.produced + max(self.batch * self.speed, self.quantum)) / (self.rate * self.speed)


class CncTimer:
    """Protocol 2: wakes the server when the simulated CNC is due to report a feed-hold change.

    One asyncio timer at a time, at the device's next pending change; `on_change(now)` is
    called when a due change altered the context (the stream server sends a CONTEXT then;
    the Modbus server's registers are read from the device anyway).
    """

    def __init__(self, device, on_change=None):
        self.device = device
        self.on_change = on_change
        self._timer = None

    def arm(self) -> None:
        import asyncio

        due = self.device.next_cnc_time()
        if due is None or (self._timer is not None and self._timer.when() <= due):
            return
        if self._timer is not None:
            self._timer.cancel()
        self._timer = asyncio.get_running_loop().call_at(due, self._fire)

    def _fire(self) -> None:
        self._timer = None
        now = time.monotonic()
        if self.device.update_cnc(now) and self.on_change is not None:
            self.on_change(now)
        self.arm()


async def first_of(*events) -> None:
    """Wait until any of the asyncio `events` is set."""
    import asyncio

    waits = [asyncio.ensure_future(e.wait()) for e in events]
    try:
        await asyncio.wait(waits, return_when=asyncio.FIRST_COMPLETED)
    finally:
        for w in waits:
            w.cancel()
