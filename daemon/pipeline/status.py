"""Small pure helpers of the runtime: live time of a sample, latency percentiles, the status line.

Kept apart from the threads so that each can be tested with a fake clock.
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


def _fmt(value: Any, spec: str) -> str:
    if value is None:
        return "–"
    try:
        return format(float(value), spec)
    except (TypeError, ValueError):
        return "–"


# The alarm levels whose alarm, sent with `"interlock": "feed_hold"`, is the trip itself (pipeline/alarms.py,
# TRIP_LEVELS; envelope alarms hold as `[learning]` says): a display may show the hold from it at once.
TRIP_LEVELS = ("overload", "crash", "tool_breakage", "envelope_high", "envelope_low")


def interlock_detail(interlock: Any, driver: Any) -> dict[str, Any]:
    """The status's `interlock_detail`: the interlock's own state, and `daq_feed_hold`, what the DAQ's
    last STATUS says of its feed-hold output (None before one came).

    The interlock takes a reset's write as done; a display keeps the machine held until the DAQ
    itself says the feed is released (issue 36, finding 7)."""
    detail = dict(interlock.state_dict())
    last = getattr(driver, "last_status", None)
    detail["daq_feed_hold"] = None if last is None else bool(getattr(last, "feed_hold", False))
    return detail


def hold_of(status: dict[str, Any]) -> tuple[str, float | None] | None:
    """(reason, since) while a status says the feed is held, else None.

    Held: the interlock latched (`feed_hold`: its reason and the trip's Unix time), the DAQ holds a
    feed this run did not set (`held_by_device`), or the DAQ's last STATUS still shows the hold (a
    release written but not yet confirmed)."""
    if not isinstance(status, dict):
        return None
    detail = status.get("interlock_detail") if isinstance(status.get("interlock_detail"), dict) else {}
    state = status.get("interlock")
    since = detail.get("since")
    since = float(since) if isinstance(since, (int, float)) and not isinstance(since, bool) else None
    if state == "feed_hold":
        reason = detail.get("reason")
        return (reason if isinstance(reason, str) and reason else "latched"), since
    if state == "held_by_device":
        return ("by the DAQ, not set by this run" + (" (its watchdog tripped)" if detail.get("watchdog_tripped")
                                                      else "")), since
    if detail.get("daq_feed_hold") is True:
        return "release not yet confirmed by the DAQ", since
    return None


def held_text(reason: str, since: float | None) -> str:
    """"feed held: <reason>, since HH:MM:SS" (local time), as every display says it."""
    when = f", since {time.strftime('%H:%M:%S', time.localtime(since))}" if since is not None else ""
    return f"feed held: {reason}{when}"


def summary_line(estimate: dict[str, Any] | None, alarm_state: str, status: dict[str, Any]) -> str:
    """The live line: state, interlock and alarm first (and while held, why and since when), then rpm,
    torque, force, depths.

    Fixed widths, so that a line refreshed in place does not jitter; what matters for
    safety comes first, because a terminal narrower than the line cuts its end.
    """
    e = estimate or {}
    hold = hold_of(status)
    return (
        f"{status.get('state', '?'):<8} interlock {status.get('interlock', '?'):<9}  alarm {alarm_state:<8}  "
        + (held_text(*hold) + "  " if hold is not None else "")
        + f"rev {e.get('rev', '–')!s:>6}  "
        f"{_fmt(e.get('spindle_rpm'), '5.0f')} rpm  "
        f"T {_fmt(e.get('torque_nm'), '6.2f')} N·m  "
        f"F {_fmt(e.get('force_n'), '6.0f')} N  "
        f"ae {_fmt(e.get('radial_depth_mm'), '5.2f')} ap {_fmt(e.get('axial_depth_mm'), '5.2f')} mm"
        + ("  (speeding up)" if e.get("accelerating") else "")
    )


def status_line(status: dict[str, Any]) -> str:
    """One-line health for sd_notify STATUS= and the debug stats line."""
    lat = status.get("latency_ms") or {}
    return (
        f"{status.get('state')}; DAQ {status.get('daq_link')}; {status.get('samples_received')} samples, "
        f"{status.get('lost_samples')} lost, {status.get('bad_frames')} bad frames; "
        f"{status.get('revolutions')} revs, p99 {_fmt(lat.get('p99'), '.2f')} ms; "
        f"alarm {status.get('alarm')}; interlock {status.get('interlock')}"
        + _afc_part(status.get("afc"))
        + _zenoh_part(status.get("sink"))
    )


def _afc_part(afc: dict[str, Any] | None) -> str:
    """Only while adaptive feed control is on: its state and the override it commands (issue 15)."""
    if not isinstance(afc, dict) or not afc.get("enabled"):
        return ""
    return f"; AFC {afc.get('state')} override {_fmt(afc.get('override_pct'), '.0f')} %"


def _zenoh_part(sink: dict[str, Any] | None) -> str:
    if not sink or sink.get("zenoh_routers") is None:
        return ""
    return f"; Zenoh {sink['zenoh_routers']} routers, {sink.get('zenoh_peers')} peers"
