"""Issue 14's acceptance: 30 simulated parts, 3 tools, learned limits, faults caught, wear warned.

The real simulator makes the parts (drivers/sim, written apart from the
estimator) and the real `millsense replay` watches them with
config/part-program.toml; tests/e2e/learning_run.py pairs the daemon's
output with the simulator's truth.
"""

from __future__ import annotations

import pytest

from tests.e2e import learning_run as lr

pytestmark = pytest.mark.slow  # over about 10 s each: handed out first (tests/parallel.py)


@pytest.fixture(scope="module")
def outcome(tmp_path_factory):
    run = lr.simulate_and_replay(tmp_path_factory.mktemp("program"))
    assert len({p["part"] for p in run.truth}) == lr.PARTS >= 30
    assert len({p["tool"] for p in run.truth}) >= 3
    return run, lr.outcome(run)


def test_limits_are_learned_after_five_parts(outcome):
    run, out = outcome
    keys = {p["key"] for p in run.truth}
    assert out.learned_after_parts == {key: 5 for key in keys}


def test_no_false_alarm_on_good_parts(outcome):
    _, out = outcome
    assert out.false_alarms == []


def test_a_broken_flute_is_caught_within_three_revolutions(outcome):
    _, out = outcome
    assert out.flute_alarm is not None
    assert out.flute_revolutions is not None and out.flute_revolutions <= 3, out.flute_alarm
    # the learned envelope alone catches it too, without the fixed breakage check
    assert out.flute_envelope_revolutions is not None and out.flute_envelope_revolutions <= 3


def test_a_missing_part_is_caught_in_each_of_its_processes(outcome):
    _, out = outcome
    assert out.missing_caught and all(alarm is not None for alarm in out.missing_caught.values()), out.missing_caught
    assert all(alarm["level"] == "envelope_low" for alarm in out.missing_caught.values())


def test_a_wrong_tool_is_caught_in_its_first_process(outcome):
    _, out = outcome
    assert out.wrong_tool_alarm is not None
    assert out.wrong_tool_alarm["level"] in ("envelope_high", "envelope_low")
    assert out.wrong_tool_alarm["tool"] == lr.WRONG_TOOL[1]


def test_wear_is_warned_within_three_parts_of_the_true_rise(outcome):
    _, out = outcome
    assert out.wear_cross_part is not None, "the simulated wear never passed the rise: make it wear faster"
    assert out.wear_warn_part is not None
    assert 0 <= out.wear_warn_part - out.wear_cross_part <= 3, (out.wear_cross_part, out.wear_warn_part)
    assert out.wear_warnings_other_tools == []
    assert out.envelope_high_on_wearing_tool_before_warning == []


def test_every_estimate_and_process_says_what_the_machine_did(outcome):
    run, _ = outcome
    cutting = [e for e in run.estimates if e.get("cutting") and e.get("process_rev") is not None]
    assert cutting and all(e["tool"] in {p["tool"] for p in run.truth} for e in cutting)
    truth_keys = [p["key"] for p in run.truth]
    assert [p["key"] for p in run.processes] == truth_keys
