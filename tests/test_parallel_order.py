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
    assert "every serial test ran alone" in said and "serial: 1 tests from 30 s to 40 s (10 s)" in said, said
    assert "of which slow: 1 tests" in said, said
    path.write_text("".join(json.dumps(r) + "\n" for r in [*alone, row("c::beside", 35, 36, worker="gw2")]))
    said = summarise(str(path))
    assert "SERIAL TESTS THAT DID NOT RUN ALONE (1): b::timed" in said, said


SHARED = '''
import os
import time
from pathlib import Path

import pytest

RUN = Path(os.environ["SHARES_DIR"])


def _meet(name):
    """Say this test started, then wait (at most 3 s) for the two others to start too: a test the shares
    let run beside this one starts now, one they hold back does not."""
    (RUN / name).touch()
    deadline = time.monotonic() + 3.0
    while len(list(RUN.iterdir())) < 3 and time.monotonic() < deadline:
        time.sleep(0.02)


@pytest.mark.slow
def test_streams():
    _meet("streams")


def test_computes_a():
    _meet("a")


def test_computes_b():
    _meet("b")
'''


def test_cpu_shares_hold_back_a_second_computing_test_but_not_a_slow_one_beside_it(tmp_path):
    """`--cpu-shares 3` in 3 workers: a slow test takes one share, any other two, so the slow test and one
    computing test run at once and the second computing test waits for the first to end. Each test waits for
    the others to start: without the shares all three run at once (watched: `--cpu-shares 0`)."""
    import json
    import os

    (tmp_path / "test_shares.py").write_text(textwrap.dedent(SHARED))
    (tmp_path / "pytest.ini").write_text("[pytest]\nmarkers =\n    slow: s\n    serial: s\n")

    def run(shares: int) -> dict[str, dict]:
        meet = tmp_path / f"met-{shares}"
        meet.mkdir()
        timeline = tmp_path / f"timeline-{shares}.jsonl"
        done = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-p", "tests.parallel",
                               "-n", "3", "--dist", "loadgroup", "--no-loadscope-reorder", f"--cpu-shares={shares}",
                               f"--timeline={timeline}", "test_shares.py"],
                              cwd=tmp_path, capture_output=True, text=True, timeout=120,
                              env={"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin", "SHARES_DIR": str(meet),
                                   "TMPDIR": os.environ.get("TMPDIR", "/tmp")})
        assert done.returncode == 0, done.stdout + done.stderr
        rows = [json.loads(line) for line in timeline.read_text().splitlines()]
        return {r["test"].split("::")[1]: r for r in rows}

    def overlap(x: dict, y: dict) -> bool:
        return x["start"] < y["end"] and y["start"] < x["end"]

    held = run(3)
    a, b, streams = held["test_computes_a"], held["test_computes_b"], held["test_streams"]
    assert len({a["worker"], b["worker"], streams["worker"]}) == 3, held
    assert not overlap(a, b), held
    assert overlap(streams, a) or overlap(streams, b), held
    free = run(0)
    assert overlap(free["test_computes_a"], free["test_computes_b"]), free


OUTER = '''
import os
import subprocess
import sys


def test_runs_a_pytest_of_its_own():
    """As tests/dashboard/test_ci_browser.py does: a pytest inside a worker, in the worker's environment."""
    done = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-p", "tests.parallel",
                           "-n", "0", "nested/test_inner.py"], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stdout + done.stderr


def test_another():
    pass
'''


def test_a_pytest_started_by_a_test_takes_none_of_the_runs_shares(tmp_path):
    """A pytest that a test runs inside a worker inherits PYTEST_XDIST_WORKER. Taken for a worker, it waited for
    shares its own parent held until the parent's test ended: the whole run wedged (stop 34, found by the first
    whole-suite run with shares: tests/dashboard/test_ci_browser.py). Watched timing out with the environment
    taken for the worker's test."""
    (tmp_path / "test_outer.py").write_text(textwrap.dedent(OUTER))
    (tmp_path / "nested").mkdir()
    (tmp_path / "nested" / "test_inner.py").write_text("def test_inner():\n    pass\n")
    (tmp_path / "pytest.ini").write_text("[pytest]\ncpu_shares = 2\nmarkers =\n    slow: s\n    serial: s\n")
    done = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-p", "tests.parallel",
                           "-n", "2", "--dist", "loadgroup", "--no-loadscope-reorder", "test_outer.py"],
                          cwd=tmp_path, capture_output=True, text=True, timeout=120,
                          env={"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin"})
    assert done.returncode == 0 and "2 passed" in done.stdout, done.stdout[-3000:] + done.stderr[-2000:]



def test_a_test_waiting_for_shares_takes_the_first_that_comes_free(tmp_path):
    """`--cpu-shares 3` in 2 workers, share 0 held all along (by this test, as a long slow test would): the two
    computing tests need two shares each, so one waits for the other and must start when the other ends. A
    blocking wait on one taken share (the first version: the lowest, a slow test's) held it, and every worker
    behind it, until that share came free (watched failing so)."""
    import fcntl
    import os

    (tmp_path / "test_two.py").write_text("def test_a():\n    pass\n\n\ndef test_b():\n    pass\n")
    (tmp_path / "pytest.ini").write_text("[pytest]\nmarkers =\n    slow: s\n    serial: s\n")
    run = tmp_path / "millsense-pytest-held"
    run.mkdir()
    fd = os.open(run / "share.0", os.O_RDWR | os.O_CREAT, 0o600)
    fcntl.flock(fd, fcntl.LOCK_EX)
    try:
        inner = subprocess.Popen([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-p", "tests.parallel",
                                  "-n", "2", "--dist", "loadgroup", "--no-loadscope-reorder", "--cpu-shares=3",
                                  "--testrunuid=held", "test_two.py"],
                                 cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                 env={"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin", "TMPDIR": str(tmp_path)})
        try:
            out, _ = inner.communicate(timeout=120)   # a stall lasts until share 0 comes free: forever here
            stalled = False
        except subprocess.TimeoutExpired:
            stalled = True
    finally:
        fcntl.flock(fd, fcntl.LOCK_UN)
        os.close(fd)
    if stalled:
        out, _ = inner.communicate(timeout=60)
    assert not stalled, "the waiting test started only once share 0 came free: " + out[-2000:]
    assert inner.returncode == 0 and "2 passed" in out, out[-2000:]
