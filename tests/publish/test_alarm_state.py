"""The alarm state a late subscriber catches up with (daemon/publish/alarm_state.py).

The daemon side numbers its changes and keeps the active ones; the subscriber side, given what
it showed and a status, fires exactly the changes it missed and nothing when the status is older
than what it already showed. A subscriber that follows every publication and every status, in
any interleaving a network can give, ends up showing what the daemon has active.
"""

from __future__ import annotations

import threading

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from millsense.daemon.publish.alarm_state import ActiveAlarms, ShownAlarms, catch_up, caught_up

pytestmark = pytest.mark.quick


def alarm(level: str, quantity: str = "torque_nm", value: float | None = 1.0) -> dict:
    return {"machine": "m", "t": 0.0, "rev": 1, "level": level, "quantity": quantity, "value": value,
            "limit": 0.8, "interlock": None}


def status(table: ActiveAlarms) -> dict:
    return {"machine": "m", "t": 0.0, **table.snapshot()}


class Viewer:
    """A subscriber as daemon/opcua/machine_nodes.py is one: `fired` is every change it showed."""

    def __init__(self) -> None:
        self.shown = ShownAlarms()
        self.fired: list[dict] = []

    def fire(self, payload: dict) -> None:
        self.shown.shown(payload)
        self.fired.append(payload)

    def on_alarm(self, payload: dict) -> None:
        if self.shown.is_new(payload):
            self.fire(payload)

    def on_status(self, payload: dict) -> None:
        for change in catch_up(self.shown, payload):
            self.fire(change)
        caught_up(self.shown, payload)

    def active(self) -> dict[str, str]:
        return {q: a["level"] for q, a in self.shown.active.items()}


def test_changes_are_numbered_and_the_status_lists_the_active_ones():
    table = ActiveAlarms()
    a = table.stamp(alarm("overload"))
    b = table.stamp(alarm("warning", "force_n"))
    assert (a["alarm_seq"], b["alarm_seq"]) == (1, 2) and a["run_id"] == b["run_id"] == table.run_id
    snap = table.snapshot()
    assert snap["alarm_seq"] == 2 and [x["quantity"] for x in snap["active_alarms"]] == ["torque_nm", "force_n"]
    table.stamp(alarm("clear"))
    snap = table.snapshot()
    assert snap["alarm_seq"] == 3 and [x["quantity"] for x in snap["active_alarms"]] == ["force_n"]
    assert ActiveAlarms().run_id != table.run_id  # each start is a new run


def test_a_subscriber_that_joins_late_is_shown_the_active_alarm_once():
    table, viewer = ActiveAlarms(), Viewer()
    raised = table.stamp(alarm("overload"))  # published before the viewer was connected
    viewer.on_status(status(table))
    assert viewer.fired == [raised]
    viewer.on_alarm(raised)  # the publication arrives late after all: not shown twice
    viewer.on_status(status(table))
    assert viewer.fired == [raised]


def test_catching_up_fires_only_what_was_missed():
    table, viewer = ActiveAlarms(), Viewer()
    shown = table.stamp(alarm("overload"))
    viewer.on_alarm(shown)
    missed = table.stamp(alarm("warning", "force_n"))
    viewer.on_status(status(table))
    assert viewer.fired == [shown, missed]


def test_an_alarm_cleared_while_away_is_cleared():
    table, viewer = ActiveAlarms(), Viewer()
    viewer.on_alarm(table.stamp(alarm("overload")))
    table.stamp(alarm("clear"))  # missed
    viewer.on_status(status(table))
    assert viewer.active() == {} and viewer.fired[-1]["level"] == "clear"


def test_a_status_older_than_the_last_alarm_changes_nothing():
    table, viewer = ActiveAlarms(), Viewer()
    old = status(table)  # made before the alarm, delivered after it
    viewer.on_alarm(table.stamp(alarm("overload")))
    viewer.on_status(old)
    assert viewer.active() == {"torque_nm": "overload"} and len(viewer.fired) == 1


def test_a_restarted_daemon_replaces_the_old_runs_alarms():
    first, viewer = ActiveAlarms(), Viewer()
    viewer.on_alarm(first.stamp(alarm("overload")))
    second = ActiveAlarms()
    viewer.on_status(status(second))  # the new run has nothing active, and its alarm_seq 0 is below the old 1
    assert viewer.active() == {}
    viewer.on_alarm(second.stamp(alarm("crash", "p_gap_w")))  # its first alarm is seq 1 again: shown
    assert viewer.active() == {"p_gap_w": "crash"}


def test_a_status_from_a_daemon_without_the_fields_is_ignored():
    viewer = Viewer()
    viewer.on_alarm(alarm("overload"))  # no run_id, no alarm_seq: always shown
    viewer.on_status({"machine": "m", "alarm": "overload"})
    viewer.on_alarm(alarm("clear"))
    assert [a["level"] for a in viewer.fired] == ["overload", "clear"]


EVENTS = st.lists(st.tuples(st.sampled_from(["overload", "warning", "crash", "clear"]),
                            st.sampled_from(["torque_nm", "force_n"])), max_size=12)


@settings(max_examples=300, deadline=None)
@given(changes=EVENTS, data=st.data())
def test_any_interleaving_ends_showing_what_the_daemon_has_active(changes, data):
    """Publications may be lost (not connected) or overtaken by statuses; the last status settles it."""
    table, viewer = ActiveAlarms(), Viewer()
    deliveries: list[tuple[str, dict]] = []
    for level, quantity in changes:
        payload = table.stamp(alarm(level, quantity))
        if data.draw(st.booleans(), label="alarm delivered"):
            deliveries.append(("alarm", payload))
        if data.draw(st.booleans(), label="a status now"):
            deliveries.append(("status", status(table)))
    # Statuses and alarms travel on different keys: a status may overtake the alarms before it.
    order = data.draw(st.permutations(range(len(deliveries))), label="arrival order")
    for i in order:
        kind, payload = deliveries[i]
        (viewer.on_alarm if kind == "alarm" else viewer.on_status)(payload)
    viewer.on_status(status(table))  # the next status, after everything
    assert viewer.active() == {q: a["level"] for q, a in ((a["quantity"], a) for a in table.snapshot()["active_alarms"])}


def test_stamping_from_several_threads_numbers_each_change_once():
    table = ActiveAlarms()
    seqs: list[int] = []
    lock = threading.Lock()

    def raise_many(quantity: str) -> None:
        for _ in range(500):
            seq = table.stamp(alarm("warning", quantity))["alarm_seq"]
            with lock:
                seqs.append(seq)

    threads = [threading.Thread(target=raise_many, args=(f"q{i}",)) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert sorted(seqs) == list(range(1, 2001)) and table.snapshot()["alarm_seq"] == 2000
