"""Learned limits as stored rows of a real history database: whatever a row holds, the daemon's restore
(`HistoryStore.load_limits` → `ProcessMonitor`) never raises; a key that fails its check is set aside and
learns afresh, shown in status, `limits list` and `limits show`; a good key comes back as it was saved.

Issue 36, finding 1: a row holding JSON null where a number belongs (an overflowed width) made every
`millsense run` exit 1 (`float(None)` in the envelope's restore). The rows here are written with sqlite3
directly, as a torn write, an older release or a hand edit would leave them.
"""

from __future__ import annotations

import copy
import json
import math
import sqlite3

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from millsense.daemon.history import records
from millsense.daemon.history.store import HistoryStore
from millsense.daemon.learning.monitor import ProcessMonitor
from tests.learning.synth import Shape, Shop, ctx, learning

ACTIVE, LEARNING = "1001/12/1", "1001/12/2"


def _good_rows() -> dict[str, dict]:
    """The exports of a monitor with one active key (adjusted, with a last alarm) and one still learning."""
    s = Shop(ProcessMonitor(learning()), rng=np.random.default_rng(5), noise_pct=2.0)
    s.learn(5)
    s.learn(2, context=ctx(operation=2))
    s.monitor.command({"action": "widen", "key": ACTIVE, "pct": 20})
    s.process(Shape(scale=1.5))                      # envelope_high: its last alarm is kept for false_alarm
    s.monitor.command({"action": "low_off", "key": ACTIVE})
    return json.loads(records.payload_json({k: s.monitor.export_limits(k) for k in s.monitor.keys}))


GOOD = _good_rows()
BAD_LEAVES = [None, math.nan, math.inf, -math.inf, "4.2", [], {}, True, 10**400, -1.0e12]


def _paths(value, path=()):
    """Every place in a JSON value: dict members and list items."""
    yield path
    if isinstance(value, dict):
        for k, v in value.items():
            yield from _paths(v, path + (k,))
    elif isinstance(value, list):
        for i, v in enumerate(value[:3]):
            yield from _paths(v, path + (i,))


PATHS = {key: [p for p in _paths(row) if p] for key, row in GOOD.items()}


@st.composite
def damaged_row(draw):
    """A good row with one place replaced by a bad value, or removed."""
    key = draw(st.sampled_from(sorted(GOOD)))
    row = copy.deepcopy(GOOD[key])
    path = draw(st.sampled_from(PATHS[key]))
    parent = row
    for step in path[:-1]:
        parent = parent[step]
    if isinstance(parent, dict) and draw(st.booleans()):
        del parent[path[-1]]
    else:
        parent[path[-1]] = draw(st.sampled_from(BAD_LEAVES))
    return key, json.dumps(row)                      # NaN, Infinity as Python writes them (not JSON)


json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=8),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6), inner, max_size=4),
    max_leaves=20)
any_row = st.one_of(
    damaged_row(),
    st.tuples(st.sampled_from(sorted(GOOD)), json_values.map(json.dumps)),        # any JSON at all
    st.tuples(st.sampled_from(sorted(GOOD)), st.text(max_size=40)),               # not JSON
    st.tuples(st.sampled_from(["12/x", "0012/3/4", "1/2/3/4", ""]), st.sampled_from(list(map(json.dumps, GOOD.values())))),
    st.tuples(st.just(ACTIVE), st.sampled_from(["null", "1e999", '{"state": "active", "envelope": null}', "[]"])),
)


@pytest.fixture(scope="module")
def db(tmp_path_factory):
    path = tmp_path_factory.mktemp("stored") / "history.sqlite3"
    store = HistoryStore(path, machine="m1")
    store.start()
    assert store.flush(10.0)
    store.close()
    return path


def _write(path, rows: list[tuple[str, str]]) -> None:
    with sqlite3.connect(path) as conn:
        conn.execute("DELETE FROM limits")
        conn.executemany("INSERT OR REPLACE INTO limits (key, t, payload) VALUES (?, 0, ?)", rows)


def _finite(value) -> bool:
    if isinstance(value, float):
        return math.isfinite(value)
    if isinstance(value, dict):
        return all(_finite(v) for v in value.values())
    if isinstance(value, list):
        return all(_finite(v) for v in value)
    return True


def _restore(path) -> ProcessMonitor:
    return ProcessMonitor(learning(), limits=HistoryStore(path, machine="m1").load_limits())


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(rows=st.lists(any_row, min_size=1, max_size=3))
def test_no_stored_row_stops_the_restore_and_a_bad_one_is_set_aside(db, rows):
    _write(db, rows)
    stored = dict(rows)
    m = _restore(db)                                  # never raises
    status = m.learned_limits_status()
    aside = {a["key"]: a["reason"] for a in status["set_aside"]}
    for key, text in stored.items():
        if key not in m.keys:                         # no process key: left as it is, shown
            assert key in aside and key in m.unusable
            continue
        ks = m.keys[key]
        if ks.set_aside is not None:
            assert aside[key] == ks.set_aside and ks.state == "learning" and ks.envelope is None
            assert "\n" not in ks.set_aside and 0 < len(ks.set_aside) <= 200
        else:                                         # restored (a removed field may take its default)
            assert key not in aside
            if text == json.dumps(GOOD[key]):
                assert json.loads(records.payload_json(m.export_limits(key))) == GOOD[key]
    # whatever was read, every answer is strict JSON with finite numbers, and commands work
    answers = [status, m.limits_summary()] + [m.show(k) for k in m.keys] + [m.export_limits(k) for k in m.keys]
    for answer in answers:
        assert _finite(answer)
        json.dumps(answer, allow_nan=False)
    for key in m.keys:
        m.command({"action": "widen", "key": key, "pct": 50})
        assert _finite(m.show(key))
    # a set-aside key's process learns afresh (the fixed limits apply meanwhile: no learned check)
    shop = Shop(m, rng=np.random.default_rng(1))
    for key, ks in list(m.keys.items()):
        if ks.set_aside is not None:
            program, tool, operation = (int(p) for p in key.split("/"))
            shop.process(Shape(), ctx(program=program, tool=tool, operation=operation))
            assert shop.processes()[-1]["verdict"] == "learning" and shop.processes()[-1]["learned"] == 1
            assert m.keys[key].set_aside is not None      # shown until it is learned again
    # what the daemon then saves restores without being set aside again (the set-aside row kept inside)
    _write(db, [(k, records.payload_json(m.export_limits(k))) for k in m.keys])
    again = _restore(db)
    assert again.unusable == {}
    assert {k: ks.set_aside for k, ks in again.keys.items()} == {k: ks.set_aside for k, ks in m.keys.items()}
    for k, ks in m.keys.items():
        if ks.set_aside is not None and k in stored:   # the row set aside is kept, as it was read
            assert again.keys[k].set_aside_row == ks.set_aside_row
            assert ks.set_aside_row is not None or stored[k] == "null"


def test_the_overflowed_row_of_finding_1_is_set_aside_and_learned_again(db):
    """The row a widen storm left: the widths null (inf through strict JSON)."""
    row = copy.deepcopy(GOOD[ACTIVE])
    row["envelope"]["entry"]["margin"] = None
    row["envelope"]["energy"]["h_j"] = None
    row["envelope"]["torque"]["h_high"] = [None] * len(row["envelope"]["torque"]["h_high"])
    _write(db, [(ACTIVE, json.dumps(row, allow_nan=False)), (LEARNING, json.dumps(GOOD[LEARNING]))])
    m = _restore(db)
    assert m.learned_limits_status() == {
        "set_aside": [{"key": ACTIVE, "reason": "envelope.torque.h_high: not a finite number >= 0 where the mean is known"}],
        "low_off": []}
    assert m.keys[LEARNING].state == "learning" and len(m.keys[LEARNING].taught) == 2
    listed = {e["key"]: e for e in m.limits_summary()["limits"]}
    assert listed[ACTIVE]["state"] == "learning" and listed[ACTIVE]["set_aside"].startswith("envelope.torque.h_high")
    assert m.show(ACTIVE)["set_aside"] == listed[ACTIVE]["set_aside"]
    assert m.keys[ACTIVE].set_aside_row == row     # nothing lost: saved with the key's next state
    assert m.take_changes()[0] == {ACTIVE}
    # taught again by five good processes: active, the warning gone
    s = Shop(m, rng=np.random.default_rng(3))
    s.learn(5)
    assert m.keys[ACTIVE].state == "active" and m.learned_limits_status()["set_aside"] == []


@pytest.mark.parametrize("field", ["h_high", "h_low", "std", "floor_low"])
def test_a_stored_negative_width_is_set_aside(db, field):
    """Finite but negative: a band whose low side sits above its mean (h_low < 0) would raise envelope_low on
    every good cut, one whose high side sits below it envelope_high; neither is a learned value."""
    row = copy.deepcopy(GOOD[ACTIVE])
    values = row["envelope"]["torque"][field]
    row["envelope"]["torque"][field] = [None if v is None else -abs(v) - 0.1 for v in values]
    _write(db, [(ACTIVE, json.dumps(row, allow_nan=False))])
    m = _restore(db)
    assert m.learned_limits_status()["set_aside"] == [
        {"key": ACTIVE, "reason": f"envelope.torque.{field}: not a finite number >= 0 where the mean is known"}]
    assert m.keys[ACTIVE].state == "learning" and m.keys[ACTIVE].envelope is None


def test_a_row_that_is_not_json_is_read_as_unreadable_with_its_text(db):
    _write(db, [(ACTIVE, "{torn"), (LEARNING, "NaN")])
    loaded = HistoryStore(db, machine="m1").load_limits()
    assert isinstance(loaded[ACTIVE], records.UnreadableRow) and loaded[ACTIVE].text == "{torn"
    assert isinstance(loaded[LEARNING], records.UnreadableRow) and "NaN is not a JSON number" in str(loaded[LEARNING])
    m = ProcessMonitor(learning(), limits=loaded)
    assert m.keys[ACTIVE].set_aside.startswith("not JSON") and m.keys[ACTIVE].set_aside_row == "{torn"


def test_a_bad_tool_row_starts_that_tool_afresh(db):
    m = ProcessMonitor(learning(), tools={"12": {"processes": 4, "ratios": [1.01, None], "warned": False},
                                          "13": {"processes": 9, "ratios": [1.02], "warned": True}, "x": {}})
    assert sorted(m.tools) == [13] and m.tools[13].processes == 9
    notes = m.take_restore_notes()
    assert [n[1]["tool"] for n in notes] == ["12", "x"]
    assert ProcessMonitor(learning(), tools=records.UnreadableRow("not JSON", "{")).tools == {}


def test_the_export_of_limits_reads_any_stored_row(db, tmp_path):
    """`millsense history --what limits` shows a row that is not JSON as what it is, never a traceback."""
    import subprocess
    import sys

    _write(db, [(ACTIVE, "{torn"), (LEARNING, json.dumps(GOOD[LEARNING]))])
    p = subprocess.run([sys.executable, "-m", "millsense.daemon", "history", "--db", str(db), "--what", "limits",
                        "--format", "jsonl"], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0 and "Traceback" not in p.stderr, p.stderr
    rows = {r["key"]: r["payload"] for r in map(json.loads, p.stdout.splitlines())}
    assert rows[ACTIVE] == {"unreadable": "not JSON: Expecting property name enclosed in double quotes: line 1 column 2 "
                                          "(char 1)", "text": "{torn"}
    assert rows[LEARNING] == GOOD[LEARNING]
