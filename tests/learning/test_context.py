"""ContextTrack: which source counts, what a Zenoh context must look like, from which sample a context holds."""

from __future__ import annotations

import pytest

from millsense.daemon.learning.context import KEEP_PASSED, MAX_HELD, ContextTrack
from millsense.drivers.protocol import Context

pytestmark = pytest.mark.quick

CYCLE, MONITOR, AFC, HELD = 0x01, 0x02, 0x04, 0x08


def daq(program=1001, tool=12, operation=3, flags=CYCLE | MONITOR, index=0) -> Context:
    return Context(index, program, tool, operation, flags)


def zen(**over):
    payload = {"program": 1234, "tool": 12, "operation": 3, "cycle": True, "monitor": True, "afc_allowed": False}
    payload.update(over)
    return payload


def test_auto_takes_the_daq_when_its_descriptor_reports_context():
    track = ContextTrack("auto")
    track.on_descriptor(0x03)   # feed override + context
    assert track.source_in_use == "daq"
    assert track.on_daq(daq(tool=7, flags=CYCLE | AFC | HELD), 500) is None
    reason = track.on_zenoh(zen(), None)
    assert reason is not None and "DAQ reports context" in reason
    assert track.at(499) is None
    got = track.at(500)
    assert (got.program, got.tool, got.operation, got.source) == (1001, 7, 3, "daq")
    assert (got.cycle, got.monitor, got.afc_allowed, got.feed_held) == (True, False, True, True)
    assert got.key == "1001/7/3"


def test_auto_takes_zenoh_when_the_daq_does_not_report_context():
    track = ContextTrack("auto")
    track.on_descriptor(0x01)   # feed override only
    assert track.source_in_use == "zenoh"
    reason = track.on_daq(daq(), 0)
    assert reason is not None and "does not report context" in reason
    assert track.on_zenoh(zen(), 10) is None
    assert track.at(10).source == "zenoh"


def test_a_descriptor_that_switches_the_source_forgets_the_other_sources_contexts():
    track = ContextTrack("auto")
    assert track.on_zenoh(zen(), 0) is None
    assert track.at(5) is not None
    track.on_descriptor(0x02)
    assert track.at(6) is None      # the Zenoh context no longer holds; the DAQ has said nothing yet


@pytest.mark.parametrize("source, taken, ignored", [("daq", "daq", "zenoh"), ("zenoh", "zenoh", "daq")])
def test_a_fixed_source_ignores_the_other_whatever_the_descriptor_says(source, taken, ignored):
    track = ContextTrack(source)
    track.on_descriptor(0x00 if source == "daq" else 0x02)
    assert track.source_in_use == taken
    feed = {"daq": lambda: track.on_daq(daq(), 0), "zenoh": lambda: track.on_zenoh(zen(), 0)}
    assert feed[taken]() is None
    assert f'source = "{source}"' in feed[ignored]()


def test_off_has_no_context_at_all():
    track = ContextTrack("off")
    track.on_descriptor(0x02)
    assert track.source_in_use is None
    assert "off" in track.on_daq(daq(), 0)
    assert "off" in track.on_zenoh(zen(), 0)
    assert track.at(10) is None


def test_an_unknown_source_is_refused():
    with pytest.raises(ValueError, match="auto, daq, zenoh, off"):
        ContextTrack("cnc")


def test_zenoh_flags_default_as_documented():
    track = ContextTrack("zenoh")
    assert track.on_zenoh({"program": 1, "tool": 2, "operation": 3}, 0) is None
    got = track.at(0)
    assert (got.cycle, got.monitor, got.afc_allowed, got.feed_held) == (True, True, False, False)
    # machine and t, which adapters add to every payload, are not refused
    assert track.on_zenoh({"program": 1, "tool": 2, "operation": 4, "machine": "m", "t": 1.0}, 1) is None


@pytest.mark.parametrize("payload, words", [
    ([1, 2, 3], "JSON object"),
    (zen(program=None), "program is missing"),
    ({"tool": 1, "operation": 1}, "program is missing"),
    (zen(program=True), "program must be a whole number"),
    (zen(program=-1), "program must be a whole number"),
    (zen(tool=2**32), "tool must be a whole number 0 … 4294967295"),
    (zen(tool=12.0), "tool must be a whole number"),
    (zen(operation=65536), "operation must be a whole number 0 … 65535"),
    (zen(operation="3"), "operation must be a whole number"),
    (zen(cycle=1), "cycle must be true or false"),
    (zen(monitor="yes"), "monitor must be true or false"),
    (zen(moniter=False), "unknown field 'moniter'"),
])
def test_a_bad_zenoh_context_is_refused_with_its_reason_and_changes_nothing(payload, words):
    track = ContextTrack("zenoh")
    assert track.on_zenoh(zen(tool=5), 0) is None
    reason = track.on_zenoh(payload, 10)
    assert reason is not None and words in reason and "\n" not in reason
    assert track.at(20).tool == 5


def test_a_context_without_seq_holds_from_the_next_sample_processed():
    track = ContextTrack("zenoh")
    track.on_zenoh(zen(operation=1), 0)
    track.mark_processed(99)
    track.on_zenoh(zen(operation=2), None)
    track.mark_processed(199)          # samples 100 … 199 were processed before the news
    assert track.at(150).operation == 1
    assert track.at(199).operation == 1
    assert track.at(200).operation == 2


def test_without_mark_processed_the_next_query_fixes_where_it_holds():
    track = ContextTrack("zenoh")
    track.on_zenoh(zen(operation=1), 0)
    track.on_zenoh(zen(operation=2), None)
    assert track.at(300).operation == 2
    assert track.at(301).operation == 2


def test_a_daq_context_holds_from_its_index_and_old_ones_are_dropped_once_passed():
    track = ContextTrack("daq")
    track.on_daq(daq(operation=1), 0)
    track.on_daq(daq(operation=2), 1000)
    track.on_daq(daq(operation=3), 2000)
    assert track.at(999).operation == 1
    assert track.at(1000).operation == 2
    assert track.at(2500).operation == 3
    for op in range(4, 40):
        track.on_daq(daq(operation=op), op * 1000)
    assert track.at(39_500).operation == 39
    assert len(track._held) == KEEP_PASSED + 1     # the rest will never hold again


def test_a_query_may_step_back_within_a_block():
    """The estimator asks for the tool of each revolution of a block, then the monitor asks again,
    revolution by revolution: a context that stopped holding in the block must still answer."""
    track = ContextTrack("daq")
    track.on_daq(daq(tool=11), 0)
    track.on_daq(daq(tool=4), 1000)
    assert [track.at(s).tool for s in (900, 1100)] == [11, 4]     # the estimator's pass
    assert [track.at(s).tool for s in (900, 1100)] == [11, 4]     # the monitor's pass


def test_the_daq_repeating_its_context_every_second_keeps_one_entry():
    track = ContextTrack("daq")
    for second in range(100):
        track.on_daq(daq(operation=1), second * 1000)
    assert len(track._held) == 1
    assert track.at(0).operation == 1   # it holds from its first announcement


def test_a_restatement_for_an_earlier_sample_replaces_what_was_said_after_it():
    track = ContextTrack("daq")
    track.on_daq(daq(operation=1), 0)
    track.on_daq(daq(operation=2), 1000)
    track.on_daq(daq(operation=3), 500)     # the device restarted its story at 500
    assert track.at(700).operation == 3
    assert track.at(1200).operation == 3


def test_a_flood_of_contexts_never_queried_stays_bounded():
    track = ContextTrack("daq")
    for i in range(10 * MAX_HELD):
        track.on_daq(daq(operation=i % 60000), i)
    assert len(track._held) <= MAX_HELD
    assert track.at(10 * MAX_HELD).operation == (10 * MAX_HELD - 1) % 60000
