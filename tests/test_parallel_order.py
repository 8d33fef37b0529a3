"""tests/parallel.py's order holds after every other plugin's: `slow` first, `serial` last.

pytest reorders the collection itself to group the tests of a session-scoped parametrised fixture
(tests/firmware's two builds). That ran after tests/parallel.py's sort and pulled four serial tests, and
with them the whole serial group, to the middle of the suite: in a run of stop 33 the serial phase came
with 943 tests still to go. A small suite of its own, collected by a real pytest with the plugin.
"""

from __future__ import annotations

import subprocess
import sys
import textwrap

from tests.conftest import REPO

TESTS = '''
import pytest

@pytest.fixture(scope="session", params=["plain", "san"])
def build(request):
    return request.param

def test_a_plain_one():
    pass

@pytest.mark.serial
def test_a_timed_one(build):
    pass

def test_one_on_each_build(build):
    pass

@pytest.mark.slow
def test_a_long_one():
    pass
'''


def test_slow_first_and_serial_last_even_after_pytests_own_reordering(tmp_path):
    (tmp_path / "test_order.py").write_text(textwrap.dedent(TESTS))
    (tmp_path / "pytest.ini").write_text("[pytest]\nmarkers =\n    slow: s\n    serial: s\n")
    done = subprocess.run([sys.executable, "-m", "pytest", "--collect-only", "-q", "-p", "no:cacheprovider",
                           "-p", "tests.parallel", "-n", "0", "test_order.py"],
                          cwd=tmp_path, capture_output=True, text=True, timeout=120,
                          env={"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin"})
    assert done.returncode == 0, done.stdout + done.stderr
    order = [line.split("::", 1)[1] for line in done.stdout.splitlines() if "::" in line]
    assert order[0] == "test_a_long_one", order
    assert order[-2:] == ["test_a_timed_one[plain]", "test_a_timed_one[san]"], order
    assert sorted(order) == sorted(["test_a_long_one", "test_a_plain_one", "test_a_timed_one[plain]",
                                    "test_a_timed_one[san]", "test_one_on_each_build[plain]",
                                    "test_one_on_each_build[san]"]), order


def test_the_timeline_names_a_serial_test_that_did_not_run_alone(tmp_path):
    """`--timeline`'s summary (what `.ci/run` prints): the phases, and a serial test another test ran beside."""
    import json

    from tests.parallel import summarise

    def row(test, start, end, serial=False, slow=False, worker="gw0"):
        return {"test": test, "worker": worker, "start": 1000.0 + start, "end": 1000.0 + end, "cpu_s": 1.0,
                "serial": serial, "slow": slow}

    alone = [row("a::long", 0, 30, slow=True), row("a::short", 0, 10, worker="gw1"),
             row("b::timed", 30, 40, serial=True, worker="gw1")]
    path = tmp_path / "t.jsonl"
    path.write_text("".join(json.dumps(r) + "\n" for r in alone))
    said = summarise(str(path))
    assert "every serial test ran with no other test but serial ones (1 at most at once)" in said, said
    assert "serial: 1 tests from 30 s to 40 s (10 s)" in said, said
    assert "of which slow: 1 tests" in said, said
    lanes = [*alone, row("d::timed", 32, 38, serial=True, worker="gw2")]   # the other lane's, beside it
    path.write_text("".join(json.dumps(r) + "\n" for r in lanes))
    said = summarise(str(path))
    assert "every serial test ran with no other test but serial ones (2 at most at once)" in said, said
    path.write_text("".join(json.dumps(r) + "\n" for r in [*lanes, row("c::beside", 35, 36, worker="gw3")]))
    said = summarise(str(path))
    assert "SERIAL TESTS THAT DID NOT RUN ALONE (2): b::timed; d::timed" in said, said


def test_the_serial_modules_are_dealt_to_two_lanes_in_turn_each_module_whole():
    from types import SimpleNamespace

    from tests.parallel import SERIAL_LANES, _serial_lanes

    def item(module, serial):
        marker = object() if serial else None
        return SimpleNamespace(module=SimpleNamespace(__name__=module),
                               get_closest_marker=lambda name, m=marker: m if name == "serial" else None)

    items = [item("a", True), item("a", True), item("b", False), item("c", True), item("d", True), item("c", True)]
    assert _serial_lanes(items) == {"a": SERIAL_LANES[0], "c": SERIAL_LANES[1], "d": SERIAL_LANES[0]}
