"""`millsense limits` arguments (issue 36): no non-finite percentage gets past the command line, and the new
`low-off` / `low-on` go through the one argument check (publish/limits_args.py) like every other action."""

from __future__ import annotations

import subprocess
import sys

import pytest

from millsense.daemon.commands.limits import request_args

pytestmark = pytest.mark.quick

KEY = "1234/12/3"


@pytest.mark.parametrize("pct", ["inf", "nan", "-inf", "1e999", "Infinity", "12.5"])
def test_a_non_finite_or_fractional_pct_is_a_usage_error_and_nothing_is_sent(pct):
    p = subprocess.run([sys.executable, "-m", "millsense.daemon", "limits", "widen", KEY, f"--pct={pct}",
                        "--machine", "nobody-here", "--no-scouting", "--connect", "tcp/127.0.0.1:9", "--timeout", "1"],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 2, p.stdout + p.stderr
    assert f"argument --pct: invalid int value: '{pct}'" in p.stderr and "Traceback" not in p.stderr
    assert "no daemon" not in p.stderr      # refused before any session: nothing was sent


def test_low_off_and_low_on_take_a_key_and_nothing_else():
    assert request_args("low-off", KEY, None) == {"action": "low_off", "key": KEY}
    assert request_args("low-on", "0001/12/3", None) == {"action": "low_on", "key": "1/12/3"}
    with pytest.raises(ValueError, match="low-off needs a KEY"):
        request_args("low-off", None, None)
    with pytest.raises(ValueError, match="--pct is for widen and narrow, not low-off"):
        request_args("low-off", KEY, 10)
