"""A payload → the historian's rows (pure): a `t` that is no clock's is refused (it would make a partition of
year 33658 or overflow the writer), the per-second load closes a second when the next one starts."""

from __future__ import annotations

import json
import math

import pytest

from millsense.daemon.historian import rows

pytestmark = pytest.mark.quick


@pytest.mark.parametrize("t", [None, "1795324800", True, math.nan, math.inf, -1.0, 0.0, 1e20, 1e12])
def test_a_time_that_is_no_clocks_makes_no_row(t):
    payload = {"t": t, "level": "warning", "rev": 3, "valid": True, "torque_nm": 1.0}
    assert rows.alarm_row("m", payload, 1795324800.0) is None
    assert rows.revolution_row("m", payload, 1795324800.0) is None
    assert rows.LoadSeconds().add("m", payload, 1795324800.0) == []


def test_the_load_of_a_second_closes_when_the_next_second_starts():
    load = rows.LoadSeconds()
    t0 = 1795324800.0
    revs = [(0.1, True, 2.0), (0.4, False, None), (0.7, True, 4.0), (0.9, True, 3.0)]
    for dt, valid, torque in revs:
        assert load.add("m", {"t": t0 + dt, "valid": valid, "torque_nm": torque, "force_n": 10.0, "p_in_w": 500.0},
                        t0) == []
    (row,) = load.add("m", {"t": t0 + 1.05, "valid": True, "torque_nm": 9.0}, t0)
    assert row[0] == t0 and row[3:9] == [4, 3, 1, 2.0, 3.0, 4.0]
    assert row[9:] == [10.0, 10.0, 10.0, 500.0, 500.0, 500.0]
    assert load.close_idle(t0 + 0.5) == []                # its last revolution came just now
    (last,) = load.close_all()
    assert last[0] == t0 + 1 and last[3:6] == [1, 1, 0]


def test_a_steady_flood_of_payloads_does_not_hold_back_the_flush(tmp_path):
    """The loop takes payloads until the flush is due, then flushes, however many still come (before: it took
    them until the queue was empty, which a flood faster than it never lets be)."""
    import threading
    import time

    from millsense.daemon.historian import schema
    from millsense.daemon.historian.service import Inbox, Rows, _drain
    from millsense.daemon.historian.spool import Spool
    from millsense.daemon.historian.writer import Writer

    writer = Writer("host=127.0.0.1 port=1", "", Spool(tmp_path / "spool", 10**6), {t: 1.0 for t in schema.TABLES},
                    None)
    inbox, taker = Inbox(), Rows(writer, revolutions_for={"m"})
    on_sample = inbox.callback("estimate")
    stop = threading.Event()

    def flood():
        t, rev = time.time(), 0
        while not stop.is_set():
            for _ in range(200):
                rev += 1
                on_sample(Sample("millsense/m/estimate", {"t": t + rev * 1e-4, "rev": rev, "valid": True,
                                                          "torque_nm": 1.0}))

    producer = threading.Thread(target=flood, daemon=True)
    producer.start()
    try:
        done = threading.Event()
        drainer = threading.Thread(target=lambda: (_drain(inbox, taker, time.monotonic() + 0.3, None), done.set()),
                                   daemon=True)
        drainer.start()
        assert done.wait(20.0), "the drain never gave the flush its turn"
        assert writer.pending.get("revolutions")   # it took some, and left the rest for the next cycle
    finally:
        stop.set()
        producer.join(5.0)


class Sample:
    """What the historian's callback reads of a Zenoh sample: `key_expr`, `payload.to_bytes()`."""

    def __init__(self, key: str, payload: dict | bytes) -> None:
        data = payload if isinstance(payload, bytes) else json.dumps(payload).encode()
        self.key_expr, self.payload = key, type("Bytes", (), {"to_bytes": lambda _: data})()


def _summary(t: float, envelope: str, learned: int, process: int) -> dict:
    return {"machine": "m", "t": t, "key": "1234/12/3", "envelope": envelope, "learned": learned,
            "process": process}


def test_a_published_change_is_one_row_and_the_summaries_after_it_infer_no_second():
    """`accept` published: one row (`accept`), never also `pending->active` from the next summary; a summary older
    than the change (the keys travel apart) is passed over; a change no command made is still inferred."""
    from millsense.daemon.historian.schema import column_names

    names = column_names("limit_changes")
    changes, t0 = rows.LimitChanges(), 1795324800.0
    assert changes.row("m", _summary(t0, "learning", 4, 1), t0) is None        # the first seen: no change
    (learned,) = [r for r in [changes.row("m", _summary(t0 + 10, "pending", 5, 2), t0)] if r is not None]
    assert learned[names.index("change")] == "learning->pending" and learned[names.index("action")] is None
    accept = {"machine": "m", "t": t0 + 20, "key": "1234/12/3", "action": "accept", "pct": None,
              "before": {"state": "pending", "learned": 5}, "after": {"state": "active", "learned": 5},
              "requester": "local uid=0 pid=7", "authority": "local"}
    row = dict(zip(names, changes.published("m", accept, t0 + 20)))
    assert (row["change"], row["action"], row["envelope"], row["learned"], row["requester"], row["authority"]) == \
        ("accept", "accept", "active", 5, "local uid=0 pid=7", "local")
    assert row["before"] == {"state": "pending", "learned": 5} and row["payload"] == accept
    assert changes.row("m", _summary(t0 + 15, "pending", 5, 3), t0) is None    # older than the change: passed over
    assert changes.row("m", _summary(t0 + 30, "active", 5, 4), t0) is None     # the change's own state: no row
    relearn = changes.row("m", _summary(t0 + 40, "active", 2, 5), t0)          # a count that falls: still inferred
    assert relearn is not None and relearn[names.index("change")] == "relearn"


def test_a_number_too_large_for_a_double_is_no_value_and_never_stops_the_loop():
    """JSON's integers have no bound: `1` and 400 zeros is a valid number that no double holds. It is no value
    (null, as NaN is), never an OverflowError out of the loop (before: `math.isfinite` raised it, and the historian
    stopped on one such payload)."""
    from millsense.daemon.historian.schema import column_names

    t0, huge = 1795324800.0, 10 ** 400
    load = rows.LoadSeconds()
    load.add("m", {"t": t0 + 0.1, "valid": True, "torque_nm": huge, "force_n": 10.0, "p_in_w": huge}, t0)
    load.add("m", {"t": t0 + 0.2, "valid": True, "torque_nm": 2.0, "force_n": 12.0, "p_in_w": 400.0}, t0)
    (row,) = load.close_all()
    assert row[3:6] == [2, 2, 0] and row[6:] == [2.0, 2.0, 2.0, 10.0, 11.0, 12.0, 400.0, 400.0, 400.0]
    rev = rows.revolution_row("m", {"t": t0, "rev": 1, "valid": True, "torque_nm": huge, "spindle_rpm": 900}, t0)
    names = column_names("revolutions")
    assert rev[names.index("torque_nm")] is None and rev[names.index("spindle_rpm")] == 900.0
    assert rows.alarm_row("m", {"t": huge, "level": "warning"}, t0) is None


def test_a_payload_nested_past_the_parsers_depth_is_refused_and_the_rest_taken(tmp_path):
    """256 KiB of `[` is JSON nested deeper than Python's parser goes: RecursionError, not ValueError. It is one
    refused payload, never an error out of the loop (which would stop the historian), and the payloads after it
    are taken."""
    from millsense.daemon.historian import schema
    from millsense.daemon.historian.service import Inbox, Rows, _drain_all
    from millsense.daemon.historian.spool import Spool
    from millsense.daemon.historian.writer import Writer

    writer = Writer("host=127.0.0.1 port=1", "", Spool(tmp_path / "spool", 10**6), {t: 1.0 for t in schema.TABLES},
                    None)
    inbox, taker = Inbox(), Rows(writer, revolutions_for={"m"})
    on_sample, t0 = inbox.callback("estimate"), 1795324800.0
    on_sample(Sample("millsense/m/estimate", {"t": t0 + 0.1, "rev": 1, "valid": True, "torque_nm": 1.0}))
    on_sample(Sample("millsense/m/estimate", b"[" * 100_000 + b"]" * 100_000))
    on_sample(Sample("millsense/m/estimate", {"t": t0 + 0.2, "rev": 2, "valid": True, "torque_nm": 2.0}))
    _drain_all(inbox, taker)
    assert inbox.refused == 1 and inbox.received["estimate"] == 2
    assert [row[3] for row in writer.pending["revolutions"]] == [1, 2]
