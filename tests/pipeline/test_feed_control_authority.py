"""The controller under a context nobody vouches for (issue 36): idle, and at most 100 % from that revolution on.

`untrusted` is what the runner passes when the context in force is an unsigned Zenoh put
(learning/context_auth.py). Whatever the rest says (a target, permission, a light cut that wants more
feed), the override never stays above the programmed feed, and it drops there at once, not at the rate
limit: an unauthenticated put can never keep the feed raised, not even while it ramps down.
"""

from __future__ import annotations

import pytest

from millsense.daemon.learning.context_auth import UNTRUSTED
from tests.pipeline.test_feed_control import controller, est

pytestmark = pytest.mark.quick


def test_an_untrusted_context_idles_the_controller_and_never_raises_the_feed():
    c = controller()
    for k in range(30):
        d = c.on_revolution(est(40.0), target=100.0, allowed=True, now_s=0.1 * k, untrusted=UNTRUSTED)
        assert (d.state, d.reason) == ("idle", UNTRUSTED)
        assert c.commanded_pct <= 100.0
    assert c.status()["reason"] == UNTRUSTED


def test_a_raised_feed_comes_down_to_100_at_once_when_the_context_loses_its_authority():
    c = controller(rate_pct_s=100.0)   # slow ramps: "at once" is not the rate limit
    for k in range(50):
        c.on_revolution(est(40.0), target=100.0, allowed=True, now_s=0.1 * k)
    assert c.commanded_pct == 150.0
    d = c.on_revolution(est(40.0), target=100.0, allowed=True, now_s=5.0, untrusted=UNTRUSTED)
    assert d.override_pct == 100.0 and d.state == "idle"
    # a trusted context again: control resumes from there
    for k in range(51, 80):
        c.on_revolution(est(40.0), target=100.0, allowed=True, now_s=0.1 * k)
    assert c.commanded_pct > 100.0 and c.state in ("armed", "saturated")


def test_an_air_override_above_100_is_not_reached_under_an_untrusted_context():
    c = controller(air_override_pct=120.0)
    for k in range(30):
        c.on_revolution(est(0.0, cutting=False), target=100.0, allowed=True, now_s=0.1 * k, untrusted=UNTRUSTED)
        assert c.commanded_pct <= 100.0


def test_an_air_override_below_100_is_still_approached():
    c = controller(air_override_pct=80.0, rate_pct_s=100.0)
    for k in range(30):
        c.on_revolution(est(40.0), target=100.0, allowed=True, now_s=0.1 * k, untrusted=UNTRUSTED)
    assert c.commanded_pct == 80.0 and c.state == "idle"
