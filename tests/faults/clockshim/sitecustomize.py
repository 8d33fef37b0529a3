"""Test shim: steps the wall clock of this Python process, as NTP (or an operator) would.

Put this folder on PYTHONPATH and set MILLSENSE_TEST_CLOCK_STEPS_FILE to a path. Once
that file exists it is read (once) as lines of `MONO DELTA`: from the moment
CLOCK_MONOTONIC (system-wide on Linux, so the test reads the same clock) reaches MONO
seconds, `time.time()` and `time.time_ns()` read DELTA seconds more (negative:
backwards); steps add up. `time.monotonic()` is untouched, as a step of the system clock
leaves CLOCK_MONOTONIC untouched. Only Python's `time.time`/`time.time_ns` are stepped
(not `datetime.now()`, nor native code such as Zenoh's).
"""

import os
import time

_path = os.environ.get("MILLSENSE_TEST_CLOCK_STEPS_FILE", "")
if _path:
    _real_time, _real_time_ns, _mono = time.time, time.time_ns, time.monotonic
    _state = {"steps": None, "next_look": 0.0}

    def _offset() -> float:
        now = _mono()
        steps = _state["steps"]
        if steps is None:
            if now < _state["next_look"]:
                return 0.0
            _state["next_look"] = now + 0.02  # look for the file at most 50 times a second
            try:
                with open(_path) as fh:
                    text = fh.read()
            except OSError:
                return 0.0
            if not text.endswith("\n"):
                return 0.0  # being written
            steps = _state["steps"] = [tuple(map(float, line.split())) for line in text.splitlines() if line.strip()]
        return sum(delta for at, delta in steps if now >= at)

    def _stepped_time() -> float:
        return _real_time() + _offset()

    def _stepped_time_ns() -> int:
        return _real_time_ns() + int(_offset() * 1e9)

    time.time = _stepped_time
    time.time_ns = _stepped_time_ns
