"""A hold's reason shows the alarm's value and limit as a person reads them, not a float's 17 digits."""

from __future__ import annotations

import pytest

from millsense.daemon.events import AlarmEvent
from millsense.daemon.runtime.interlock import trip_reason

pytestmark = pytest.mark.quick


def test_the_value_and_the_limit_to_three_decimals():
    ev = AlarmEvent("overload", "torque_nm", 12.345678901234, 10.0, 42, 4200)
    assert trip_reason(ev) == "overload torque_nm 12.346 > 10.0"
    low = AlarmEvent("expected_low", "torque_nm", 0.49912345, 1.2000000001, 7, 700)
    assert trip_reason(low) == "expected_low torque_nm 0.499 < 1.2"


def test_whole_numbers_and_missing_values_as_they_are():
    assert trip_reason(AlarmEvent("crash", "i_w", 61.2, 55.0, None, 10)) == "crash i_w 61.2 > 55.0"
    assert trip_reason(AlarmEvent("overload", "signals", None, None, None, 10)) == "overload signals None > None"
