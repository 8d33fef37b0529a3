"""How a long-running command stops on a signal: the handler only sets an event its loop waits on.

SIGTERM (systemd's stop) and SIGINT (Ctrl-C) always; SIGHUP too for a service
(`run`, `router`), where a hang-up means stop rather than die mid-write. Outside
the main thread (a command embedded in a test or another program) Python
refuses handlers: the caller's own stop event is then the only way.
"""

from __future__ import annotations

import signal
import threading
from typing import Any


def stop_on_signals(stop: threading.Event, *, hangup: bool = False) -> None:
    def handler(_signum: int, _frame: Any) -> None:
        stop.set()

    signals = (signal.SIGTERM, signal.SIGINT) + ((signal.SIGHUP,) if hangup else ())
    for sig in signals:
        try:
            signal.signal(sig, handler)
        except (ValueError, OSError):  # not the main thread
            pass
