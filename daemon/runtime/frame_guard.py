"""The reader thread's crash check, frame by frame, where a frame lands (issue 13).

`FrameGuard.on_frame` is the driver's `sample_hook`: before a frame is even queued, the sample-level
crash power and current (`pipeline/safety_check.FrameCheck`, a few vector operations). A crash holds
the feed from there at once, through the Runner's one trip path (`trip`), and is kept until the
estimator thread publishes it with the block that holds it (`take_events`). While the check is
latched (the feed held) it judges nothing: such a frame goes on unchecked, and the estimator judges
it; a reset re-arms it (`rearm`).

The guard also tells the reader when to wake the estimator: a crash, a current over the stall
limit, or a frame reaching the sample at which the next revolution may close (`wake_at_seq`, set by
the estimator thread).
"""

from __future__ import annotations

import threading
import time
import traceback
from typing import Any, Callable

import structlog

from millsense.daemon.events import AlarmEvent
from millsense.daemon.pipeline.safety_check import FrameCheck
from millsense.daemon.runtime.interlock import trip_reason

log = structlog.get_logger("millsense.runner")  # the runner's logger, as before it was carved out of it


class FrameGuard:
    """The per-frame crash check of one live daemon, on the driver's reader thread."""

    def __init__(self, settings: Any, driver: Any, core: Any,
                 trip: Callable[..., str | None]):
        self._settings = settings
        self._driver = driver
        self._core = core   # its estimator's last gain scales the frame's power
        self._trip = trip   # trip(reason, last_seq, started=...): the Runner's one trip path
        self._lock = threading.Lock()  # the check and the crashes it found
        self.frame_check: FrameCheck | None = None
        self._desc: Any = None
        self._events: list[AlarmEvent] = []  # tripped on the reader thread, not yet published
        self._error_said = False
        self.wake_at_seq: int | None = None  # a frame reaching this sample may close a revolution

    def on_frame(self, seq: int, counts: Any, lost: int, disc: bool) -> tuple[bool, bool]:
        """The driver's sample_hook: the crash check on one frame, where it lands. (checked, wake now).

        A crash holds the feed from here, before the frame is even queued; the estimator thread
        publishes it with the frame (`take_events`). While the check is latched (the feed held) it
        judges nothing: such a frame goes on unchecked, and the estimator judges it. A reset may come
        before the estimator has taken it, and then nobody else would.
        """
        t0 = time.monotonic()
        try:
            with self._lock:
                fc = self.check_for(self._driver.descriptor)
                if fc is None:
                    return False, True  # no check fits the DAQ: the estimator thread checks every block
                est = self._core.estimator
                gain = float(getattr(getattr(est, "physics", None), "last_gain", 1.0) or 1.0)
                judged = not fc.latched
                crash, current_high = fc.check(seq, counts, lost, disc, gain)
                if crash is not None:
                    self._events.append(crash)
        except Exception as exc:  # noqa: BLE001 - the estimator thread checks the block instead
            if not self._error_said:
                self._error_said = True
                log.error("frame_check_failed", error=f"{type(exc).__name__}: {exc}", traceback=traceback.format_exc())
            return False, True
        last = seq + len(counts) - 1
        if crash is not None:
            self._trip(trip_reason(crash), last, started=t0)   # frame decoded → output written
            return True, True
        wake_at = self.wake_at_seq
        return judged, current_high or (wake_at is not None and last >= wake_at)

    def predict_close(self, step: Any, spindle_stopped: bool) -> None:
        """The sample at which the next revolution may close, for the reader's wake-up (None: stopped).
        The estimator thread's, after each block (`step`: what the block made)."""
        if spindle_stopped:
            self.wake_at_seq = None
            return
        for kind, item in reversed(step.items):
            if kind == "estimate" and item.get("seq_end") is not None:
                period = int(item.get("samples") or 0) + int(item.get("lost_samples") or 0)
                if period > 0:
                    # the first sample past the next boundary closes it, at this speed: woken earlier, the
                    # estimator found no revolution to close about half the time (a wake-up for nothing);
                    # one that speeds up closes sooner and waits at most for the next frame
                    self.wake_at_seq = int(item["seq_end"]) + period + 1
                return

    def check_for(self, desc: Any) -> FrameCheck | None:
        """The check for the DAQ's descriptor, made again when it changes (None: no check fits it)."""
        if desc is not self._desc:
            self._desc = desc
            try:
                self.frame_check = FrameCheck(self._settings, desc) if desc is not None else None
            except Exception:  # noqa: BLE001 - ConfigError: the estimator thread raises the fault
                self.frame_check = None
        return self.frame_check

    def take_events(self, last_seq: int) -> list[AlarmEvent]:
        """The reader's crashes up to `last_seq`: they are published with the block that holds them."""
        if not self._events:
            return []
        with self._lock:
            taken = [ev for ev in self._events if ev.seq is None or ev.seq <= last_seq]
            self._events = [ev for ev in self._events if not (ev.seq is None or ev.seq <= last_seq)]
        return taken

    def rearm(self) -> None:
        """A granted reset: the check judges frames again."""
        with self._lock:
            if self.frame_check is not None:
                self.frame_check.rearm()
