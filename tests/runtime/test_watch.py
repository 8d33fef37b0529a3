"""`_Daemon.serve`'s periodic looks (the state directory, another daemon of this name): when they run, and that
a failing one is logged, never raised."""

from __future__ import annotations

import pytest

from millsense.daemon.commands.run import _Watch

pytestmark = pytest.mark.quick


class _Log:
    def __init__(self):
        self.errors = []

    def error(self, event, **fields):
        self.errors.append((event, fields))


def test_a_watch_looks_first_one_period_after_it_starts_then_every_period_from_its_last_look():
    looks = []
    w = _Watch(lambda: looks.append(1), 2.0, "x.watch_failed")
    first = w.due
    log = _Log()
    w.run_if_due(first - 0.1, log)
    assert looks == []
    late = first + 0.5
    w.run_if_due(late, log)   # the next look is a period after this one, not after `first`
    assert looks == [1] and w.due == late + 2.0
    w.run_if_due(late + 1.9, log)
    assert looks == [1]
    w.run_if_due(late + 2.0, log)
    assert looks == [1, 1] and log.errors == []


def test_a_failing_look_is_logged_and_tried_again_a_period_later():
    def look():
        raise OSError("gone")

    w = _Watch(look, 5.0, "zenoh.name_watch_failed")
    log = _Log()
    now = w.due
    w.run_if_due(now, log)
    assert log.errors == [("zenoh.name_watch_failed", {"error": "OSError: gone"})]
    assert w.due == now + 5.0
