"""What the Runner takes from outside, as `Protocol`s: the driver, the sink, the history, the latch store, the
estimator factory and the descriptor check. Structural: the real ones (drivers/, publish/sink.py,
history/, runtime/latch_store.py, pipeline/estimator.py) and the tests' fakes fit without naming them.

Only what the runtime (the Runner and the parts it builds) calls is listed; where it asks with
`getattr`/`hasattr` (a driver's batched queue and reader hook, a sink's `process`), the member is
optional and named in a comment.
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any, Callable, Protocol

from millsense.drivers.protocol import Descriptor


class Driver(Protocol):
    """A DAQ driver (drivers/base.py), already started. Optional: `drain()` and `wake` (a batched queue),
    `sample_hook` (the reader thread's per-frame check), `last_context` (protocol 2)."""

    descriptor: Descriptor | None
    link_up: bool
    last_status: Any
    queued: int

    def get(self, timeout: float | None = None) -> Any: ...
    def stats(self) -> dict[str, Any]: ...
    # the interlock's outputs (runtime/interlock.py) and the feed override's (afc/output.py)
    def set_outputs(self, feed_hold: bool, alarm_lamp: bool = False) -> bool: ...
    def set_watchdog_ms(self, ms: int) -> None: ...
    def heartbeat(self) -> bool: ...


class BatchedDriver(Driver, Protocol):
    """A driver whose reader thread batches: the estimator sleeps on `wake` and takes all with `drain`."""

    wake: threading.Event

    def drain(self) -> list[Any]: ...


class Sink(Protocol):
    """Where the live daemon's output goes (publish/sink.py's ZenohSink). Optional: `process(payload)`,
    `stats()`. Every method returns at once: a slow subscriber never slows the estimator."""

    def estimate(self, payload: dict) -> None: ...
    def alarm(self, payload: dict) -> None: ...
    def status(self, payload: dict) -> None: ...


class History(Protocol):
    """The SQLite history (daemon/history): handed what went out, written by its own thread."""

    on_error: Callable[[str], Any] | None
    on_ok: Callable[[], Any] | None

    def add_revolution(self, estimate: dict) -> None: ...
    def add_alarm(self, alarm: dict) -> None: ...
    def add_process(self, summary: dict) -> None: ...
    def save_limits(self, key: str, data: dict) -> None: ...
    def save_tools(self, data: dict) -> None: ...
    def stats(self) -> dict[str, Any]: ...


class LatchStore(Protocol):
    """The latched interlock on disk (runtime/latch_store.py)."""

    path: Path
    on_error: Callable[[str], Any] | None
    on_ok: Callable[[], Any] | None

    def load(self) -> dict[str, Any] | None: ...
    def start(self) -> None: ...
    def save(self, record: dict[str, Any]) -> None: ...
    def close(self, timeout_s: float = 1.0) -> None: ...


class EstimatorFactory(Protocol):
    """Makes the estimator for a descriptor (pipeline/estimator.py's `Estimator`, or a test's)."""

    def __call__(self, settings: Any, descriptor: Descriptor, sample_rate_hz: float) -> Any: ...


class DescriptorCheck(Protocol):
    """Raises `ConfigError` when the configuration does not fit the DAQ (config/load.py's)."""

    def __call__(self, settings: Any, descriptor: Descriptor) -> Any: ...
