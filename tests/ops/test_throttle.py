"""The one rate limit of refusal lines (audit log, refused queries): nothing lost, nothing flooded."""

import pytest

from millsense.daemon.throttle import Throttle

pytestmark = pytest.mark.quick


def test_counts_everything_lets_one_through_a_period_and_keeps_the_rest_for_the_stop():
    now = [100.0]
    t = Throttle(10.0, mono=lambda: now[0])
    assert t.note("a") == (1, "a")          # the first goes out at once
    assert [t.note(x) for x in "bcd"] == [None, None, None]
    now[0] += 9.9
    assert t.note("e") is None
    now[0] += 0.2                            # a period after the last one let through
    assert t.note("f") == (5, "f")           # b, c, d, e and f: counted, the last one shown
    assert t.pending() is None
    t.note("g")
    assert t.pending() == (1, "g") and t.pending() is None
