"""The status payload of the live daemon (`StatusReport`, what `status` answers and the status thread
publishes) and its small pure helpers: live time of a sample, latency percentiles, bad frames.

The helpers are kept apart from the threads so that each can be tested with a fake clock; the text
renderings of a status (the live line, sd_notify's STATUS=, the hold) are daemon/status_text.py's.
"""

from __future__ import annotations

import collections
import threading
import time
from array import array
from typing import Any

STATES = ("starting", "running", "degraded", "stopping")


class SeqClock:
    """Unix time of a sample from its unwrapped index (seq).

    Why not simply "now": a revolution's estimate is computed after its last
    sample arrived, and the DAQ sends samples in frames (TCP) or is polled
    (Modbus every `poll_ms`), so arrival time is late by a variable transport
    delay. Each block gives one observation `offset = arrival − seq_last/rate`
    (the arrival time belongs to the block's last sample); every observation is
    late by its own delay, never early, so the smallest offset of the last
    `window_s` seconds is the best estimate of when samples were taken:
    `t(seq) = offset_min + seq/rate`. The window lets the estimate follow the
    drift between the DAQ's crystal and the host clock (≈ 50 ppm: 0.5 ms per
    10 s). A discontinuity (device restart, lost samples) starts a new window.
    So live `t` is late only by the *smallest* transport delay (≈ 1 ms on TCP).
    The runner feeds it only blocks that did not wait in the driver's queue
    behind others (their hand-over time is not their arrival time).

    Wall-clock steps (NTP, an operator setting the date): the offsets and the
    window are kept on the monotonic clock (`mono_s`, the arrival time on
    `time.monotonic()`), and turned into Unix time with the latest
    `wall_s − mono_s`. So a step of the wall clock moves `t` by exactly the step
    at the next block, instead of leaving `t` on the old clock until the
    window has forgotten every block from before the step (up to `window_s`
    for a forward step smaller than the window). Without `mono_s` the wall
    time serves as both. The two readings are not taken at the same instant, so
    `wall_s − mono_s` jitters by microseconds: it is taken up only when it moved
    by more than `STEP_S` (a step), so that times stay consistent between blocks.
    """

    STEP_S = 0.001

    def __init__(self, sample_rate_hz: float, window_s: float = 10.0):
        self.rate = float(sample_rate_hz)
        self.window_s = window_s
        self._mins: collections.deque[tuple[float, float]] = collections.deque()  # (mono, offset), offsets increasing
        self._wall_minus_mono = 0.0

    def note_block(self, seq_first: int, n: int, wall_s: float, restart: bool = False, mono_s: float | None = None) -> None:
        mono = wall_s if mono_s is None else mono_s
        if not self._mins or abs(wall_s - mono - self._wall_minus_mono) > self.STEP_S:
            self._wall_minus_mono = wall_s - mono
        offset = mono - (seq_first + n - 1) / self.rate
        q = self._mins
        if restart:
            q.clear()
        while q and q[-1][1] >= offset:
            q.pop()
        q.append((mono, offset))
        while q[0][0] < mono - self.window_s and len(q) > 1:
            q.popleft()

    @property
    def empty(self) -> bool:
        return not self._mins

    def time_of(self, seq: int) -> float | None:
        if not self._mins:
            return None
        return self._mins[0][1] + seq / self.rate + self._wall_minus_mono


class LatencyStats:
    """Processing latencies of the last `size` revolutions (seconds in, ms out). Thread-safe."""

    def __init__(self, size: int = 4096):
        # a ring of machine floats: a deque of 4096 Python floats held 130 KB, this one 32 KB
        self._values = array("d", bytes(8 * size))
        self._count = 0
        self._next = 0
        self._lock = threading.Lock()

    def add(self, seconds: float) -> None:
        with self._lock:
            self._values[self._next] = seconds
            self._next = (self._next + 1) % len(self._values)
            self._count = min(self._count + 1, len(self._values))

    def percentiles_ms(self) -> dict[str, float | None]:
        with self._lock:
            values = sorted(self._values[:self._count])
        if not values:
            return {"p50": None, "p99": None, "max": None, "n": 0}
        p50, p99 = (percentile(values, q) * 1e3 for q in (50.0, 99.0))
        return {"p50": round(p50, 3), "p99": round(p99, 3), "max": round(values[-1] * 1e3, 3), "n": len(values)}


def percentile(ordered: list[float], q: float) -> float:
    """The q-th percentile of sorted values, interpolated linearly between the two nearest ranks (numpy's
    default method). Not `np.percentile`: it imports numpy.ma on its first call, 1.3 MB of the daemon's
    memory for two numbers a second."""
    rank = q / 100.0 * (len(ordered) - 1)
    lo = int(rank)
    hi = min(lo + 1, len(ordered) - 1)
    return ordered[lo] + (ordered[hi] - ordered[lo]) * (rank - lo)


BAD_FRAME_KEYS = ("bad_crc", "unknown_type", "bad_length", "descriptor_mismatch")


def bad_frames(driver_stats: dict[str, Any]) -> int:
    """Frames the DAQ link refused (bad CRC, unknown type, impossible length, wrong channel count).

    Stream drivers report their decoder's counters as `decoder_<name>`.
    """
    return sum(int(driver_stats.get(k, 0) or 0) + int(driver_stats.get(f"decoder_{k}", 0) or 0) for k in BAD_FRAME_KEYS)


def interlock_detail(interlock: Any, driver: Any) -> dict[str, Any]:
    """The status's `interlock_detail`: the interlock's own state, and `daq_feed_hold`, what the DAQ's
    last STATUS says of its feed-hold output (None before one came).

    The interlock takes a reset's write as done; a display keeps the machine held until the DAQ
    itself says the feed is released (issue 36, finding 7)."""
    detail = dict(interlock.state_dict())
    last = getattr(driver, "last_status", None)
    detail["daq_feed_hold"] = None if last is None else bool(getattr(last, "feed_hold", False))
    return detail


class LiveState:
    """What the estimator thread counted and last saw, read by the status payload, the fault board and the
    controls. Written by the estimator thread only (and `last_trip_ms` by the trip, `last_test_trip` by a
    test-trip); a reader takes each value as it is."""

    def __init__(self, now_mono: float):
        self.started_mono = now_mono
        self.samples_received = 0
        self.revolutions = 0
        self.alarms_sent = 0
        self.processes = 0
        self.last_estimate: dict | None = None
        self.last_alarm: dict | None = None
        self.last_process: dict | None = None
        self.last_trip_ms: float | None = None
        self.last_test_trip: dict[str, Any] | None = None
        self.last_seq: int | None = None   # the last sample the estimator took: a hold that begins now is newer
        self.spindle_stopped = False
        self.latency = LatencyStats()  # per revolution: its frame handed to the estimator thread → sink
        self.delay = LatencyStats()    # per revolution: its frame decoded by the reader → sink (queue wait too)


class StatusReport:
    """The `status` payload (docs/zenoh.md): what the status thread publishes each second and `status` answers."""

    def __init__(self, machine: str, version: str, driver: Any, core: Any, interlock: Any, live: LiveState, *,
                 board: Any, afc: Any, active_alarms: Any, alarm_lock: threading.Lock,
                 history: Any = None, sink: Any = None):
        self.machine = machine
        self.version = version
        self._driver = driver
        self._core = core
        self._interlock = interlock
        self._live = live
        self._board = board
        self._afc = afc
        self._active_alarms = active_alarms
        self._alarm_lock = alarm_lock
        self.history = history
        self.sink = sink   # set by the Runner's start

    def payload(self) -> dict[str, Any]:
        live, core = self._live, self._core
        stats: dict[str, Any] = {}
        try:
            stats = dict(self._driver.stats())
        except Exception:  # noqa: BLE001
            pass
        with self._alarm_lock:
            alarms = core.active()
            alarm = core.summary()
            ctx = core.context.at(live.last_seq) if live.last_seq is not None else None
            learning = None if core.monitor is None else core.monitor.state_counts()
            learned = {} if core.monitor is None else {"learned_limits": core.monitor.learned_limits_status()}
        return {
            "machine": self.machine,
            "t": time.time(),
            "state": self._board.state,
            "daq_link": "up" if self._driver.link_up else "down",
            "samples_received": live.samples_received,
            "bad_frames": bad_frames(stats),
            "lost_samples": core.lost_samples_total,
            "revolutions": live.revolutions,
            "latency_ms": live.latency.percentiles_ms(),
            "rev_delay_ms": live.delay.percentiles_ms(),
            "interlock": self._interlock.state,
            "interlock_detail": interlock_detail(self._interlock, self._driver),
            "heartbeating": self._interlock.heartbeating,
            "last_trip_ms": live.last_trip_ms,
            "last_test_trip": live.last_test_trip,
            "alarm": alarm,
            "alarms": alarms,
            **self._active_alarms.snapshot(),
            "faults": dict(self._board.faults),
            "context": None if ctx is None else {"program": ctx.program, "tool": ctx.tool,
                                                 "operation": ctx.operation, "source": ctx.source,
                                                 "authority": ctx.authority},
            "context_auth": core.context.auth.status() if core.context.auth is not None else None,
            "processes": live.processes,
            "learning": learning,   # how many process keys are learning, pending, active (None: learning off)
            **learned,
            "afc": self._afc.status(),
            "history": self._history_stats(),
            "daq": stats,
            "sink": self._sink_stats(),
            "uptime_s": round(time.monotonic() - live.started_mono, 1),
            "version": self.version,
        }

    def _history_stats(self) -> dict | None:
        try:
            return self.history.stats() if self.history is not None else None
        except Exception:  # noqa: BLE001
            return None

    def _sink_stats(self) -> dict | None:
        try:
            return self.sink.stats() if self.sink is not None and hasattr(self.sink, "stats") else None
        except Exception:  # noqa: BLE001
            return None
