"""How the suite runs in parallel processes (pytest-xdist), loaded by tests/conftest.py.

The suite mostly waits on real processes, so pyproject runs it in several workers
(`-n`, `--dist loadgroup`). Three rules keep that honest (docs/testing.md):

- **Sharing.** The tests of a module that uses a module-scoped fixture form one xdist
  group, so that the fixture is built once, not once per worker.
- **Order.** Tests marked `slow` are handed out first, so that the longest ones do not
  start last and leave one worker running alone at the end. `serial` tests come last.
- **The serial phase.** A test marked `serial` asserts a latency or a period (crash →
  hold, the watchdog, heartbeats, reset at standstill): it runs with no test running
  but a serial one. They form two xdist groups, two lanes (their modules dealt
  alternately), handed out last, each to one worker that runs its tests back to back:
  so at most two run at once, each well under a core, which loads the box less than
  one beside three workers' tests. The controller's scheduler writes how many other
  tests have not ended yet (`others_left`); a serial test starts once that is 0. A
  worker holds its last test until it is handed the next (xdist runs a test once it
  knows the one after it), so the count reaches 0 with no help from the lanes: a
  lane's worker runs its own other tests first, the rest run theirs as they are
  shut down. Nothing is locked, so a dead worker cannot wedge the others.
- **CPU, not only time.** `--cpu-report N` prints the N tests that used most CPU
  (the worker process and the children it waited for): on a 2-core box the suite's
  time is bounded by CPU, and a test can be quick and still eat the others' share.
"""

from __future__ import annotations

import json
import os
import resource
import sys
import tempfile
import time
import uuid
from pathlib import Path

import pytest

SERIAL_LANES = ("serial-1", "serial-2")
OTHERS_LEFT = "others_left"
WAIT_STEP_S = 0.05
GIVE_UP_S = 1200.0


def pytest_addoption(parser):
    parser.addoption("--cpu-report", type=int, default=0, metavar="N",
                     help="print the N tests that used the most CPU seconds (worker and waited-for children)")
    parser.addoption("--timeline", default=None, metavar="FILE",
                     help="append one JSON line per test to FILE: worker, start and end (Unix time), CPU s, serial; "
                          "says where a run's cores sat idle (docs/testing.md)")


def _serial_lanes(items) -> dict[str, str]:
    """The serial modules, in the collection's order, dealt to the lanes in turn: a module's serial tests
    stay on one worker (their module fixtures are made once)."""
    modules = list(dict.fromkeys(item.module.__name__ for item in items if _is(item, "serial")))
    return {name: SERIAL_LANES[i % len(SERIAL_LANES)] for i, name in enumerate(modules)}


def _is(item, name: str) -> bool:
    return item is not None and item.get_closest_marker(name) is not None


@pytest.hookimpl(tryfirst=True)  # before xdist reads the xdist_group markers
def pytest_collection_modifyitems(config, items):
    lanes = _serial_lanes(items)
    for item in items:
        if _is(item, "serial"):
            item.add_marker(pytest.mark.xdist_group(lanes[item.module.__name__]))
        elif _shares_a_module_fixture(item) and not _is(item, "xdist_group"):
            item.add_marker(pytest.mark.xdist_group(f"module:{item.module.__name__}"))
    _tell_the_controller_the_groups(items)


@pytest.hookimpl(hookwrapper=True, specname="pytest_collection_modifyitems")
def pytest_collection_modifyitems_last(config, items):
    """After every other plugin's reordering: pytest's own groups the tests of a session-scoped parametrised
    fixture together (tests/firmware's two builds), which pulled four serial tests to the middle of the
    collection, and with them the serial group: it was handed out with half the run still to come."""
    yield
    # a stable sort: slow first, serial last, the collection's order kept within each
    items.sort(key=lambda item: 2 if _is(item, "serial") else 0 if _is(item, "slow") else 1)


@pytest.hookimpl(tryfirst=True)
def pytest_configure(config):
    """The controller names the run (xdist's --testrunuid), so that it finds the folder its workers write to."""
    if not os.environ.get("PYTEST_XDIST_WORKER") and getattr(config.option, "testrunuid", "unset") is None:
        config.option.testrunuid = uuid.uuid4().hex


def pytest_xdist_make_scheduler(config, log):
    from xdist.scheduler import LoadScopeScheduling

    class GroupScheduling(LoadScopeScheduling):
        """loadscope with the scopes the workers wrote: a group's tests go to one worker, back to back; every
        other test is its own scope, handed out in the collection's order (slow first, serial last)."""

        _groups: dict[str, str] | None = None

        def _split_scope(self, nodeid: str) -> str:
            if self._groups is None:
                path = _lock_path("groups.json", config.option.testrunuid)
                self._groups = json.loads(path.read_text()) if path.exists() else {}
            return self._groups.get(nodeid, nodeid)

        def schedule(self) -> None:
            super().schedule()
            self._tell_the_serial_tests()

        def mark_test_complete(self, node, item_index: int, duration: float = 0) -> None:
            super().mark_test_complete(node, item_index, duration)
            self._tell_the_serial_tests()

        def remove_node(self, node):
            crashed = super().remove_node(node)
            self._tell_the_serial_tests()
            return crashed

        def _tell_the_serial_tests(self) -> None:
            """How many other tests have not ended (handed out or not): the serial lanes wait for 0."""
            left = sum(not done for work in self.assigned_work.values() for scope, unit in work.items()
                       if scope not in SERIAL_LANES for done in unit.values())
            left += sum(len(unit) for scope, unit in self.workqueue.items() if scope not in SERIAL_LANES)
            if left != getattr(self, "_told", None):
                path = _lock_path(OTHERS_LEFT, config.option.testrunuid)
                tmp = path.with_name(f"{OTHERS_LEFT}.tmp")
                tmp.write_text(str(left))
                os.replace(tmp, path)
                self._told = left

    return GroupScheduling(config, log)


def _tell_the_controller_the_groups(items) -> None:
    """xdist 3.8's loadgroup tags a grouped test's node id (`id@group`), which pytest 9 no longer lets it change:
    its groups are silently ignored. Each worker writes the groups of its collection (the same in every worker)
    to the run's folder instead, and the controller's scheduler (`GroupScheduling`) reads them."""
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        return
    groups = {}
    for item in items:
        names = sorted({str(m.args[0] if m.args else m.kwargs.get("name", "default"))
                        for m in item.iter_markers("xdist_group")})
        if names:
            groups[item.nodeid] = "_".join(names)
    path = _lock_path("groups.json")
    tmp = path.with_name(f"groups.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(groups))
    os.replace(tmp, path)


def _shares_a_module_fixture(item) -> bool:
    """A module-scoped fixture (a built wheelhouse, a precomputed stream, a shared daemon) is made once per
    worker that runs a test of its module: the module's tests go to one worker, so it is made once."""
    info = getattr(item, "_fixtureinfo", None)
    if info is None:
        return False
    return any(defs and defs[-1].scope == "module" for name, defs in info.name2fixturedefs.items()
               if name in info.names_closure)


def _lock_path(name: str, run: str | None = None) -> Path:
    run = run or os.environ.get("PYTEST_XDIST_TESTRUNUID", "")
    d = Path(tempfile.gettempdir()) / f"millsense-pytest-{run}"
    d.mkdir(exist_ok=True)
    return d / name


def _wait_for_the_others() -> None:
    """A serial test starts once every other test of the run has ended (the controller's count, above).
    A hang guard, not a bound: a worker that crashed at the very end can leave a test queued with no worker
    left to take it; after `GIVE_UP_S` the serial test runs anyway, says so, and the timeline's summary names
    it among those that did not run alone."""
    path = _lock_path(OTHERS_LEFT)
    give_up = time.monotonic() + GIVE_UP_S
    while time.monotonic() < give_up:
        try:
            if int(path.read_text() or "1") == 0:
                return
        except (FileNotFoundError, ValueError):   # not written yet, or caught between write and rename
            pass
        time.sleep(WAIT_STEP_S)
    sys.stderr.write(f"tests/parallel.py: other tests still not ended after {GIVE_UP_S} s: the serial tests run\n")


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    parallel = bool(os.environ.get("PYTEST_XDIST_WORKER"))
    serial = _is(item, "serial")
    if parallel and serial:
        _wait_for_the_others()
    item.stash[_CPU_START] = _cpu_s()
    started = time.time()
    try:
        yield
    finally:
        ended = time.time()
        _timeline(item, started, ended, serial)


def _timeline(item, started: float, ended: float, serial: bool) -> None:
    """One line per test for `--timeline`: appended in one write, so the workers' lines never interleave."""
    path = item.config.getoption("--timeline")
    if not path:
        return
    line = json.dumps({"test": item.nodeid, "worker": os.environ.get("PYTEST_XDIST_WORKER", "main"),
                       "start": round(started, 3), "end": round(ended, 3),
                       "cpu_s": round(_cpu_s() - item.stash.get(_CPU_START, _cpu_s()), 2), "serial": serial,
                       "slow": _is(item, "slow")})
    fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    try:
        os.write(fd, (line + "\n").encode())
    finally:
        os.close(fd)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_teardown(item):
    yield
    # before the teardown's report is made, which carries user_properties to the controller
    item.user_properties.append(("cpu_s", round(_cpu_s() - item.stash.get(_CPU_START, _cpu_s()), 2)))


def _cpu_s() -> float:
    own = resource.getrusage(resource.RUSAGE_SELF)
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


_CPU_START = pytest.StashKey[float]()


def pytest_runtest_logreport(report):
    if report.when != "teardown":
        return
    for key, value in report.user_properties:
        if key == "cpu_s":
            _cpu_by_test[report.nodeid] = value


_cpu_by_test: dict[str, float] = {}


def pytest_terminal_summary(terminalreporter, config):
    timeline = config.getoption("--timeline")
    if timeline and not os.environ.get("PYTEST_XDIST_WORKER") and Path(timeline).exists():
        terminalreporter.section("where the time went (--timeline)")
        for line in summarise(timeline).splitlines():
            terminalreporter.write_line(line)
    n = config.getoption("--cpu-report")
    if not n or not _cpu_by_test:
        return
    total = sum(_cpu_by_test.values())
    terminalreporter.section(f"most CPU: {n} of {len(_cpu_by_test)} tests, {total:.0f} CPU s in all")
    for nodeid, cpu_s in sorted(_cpu_by_test.items(), key=lambda kv: -kv[1])[:n]:
        terminalreporter.write_line(f"{cpu_s:8.2f}s cpu  {nodeid}")
    by_folder: dict[str, float] = {}
    for nodeid, cpu_s in _cpu_by_test.items():
        folder = "/".join(nodeid.split("::")[0].split("/")[:2])
        by_folder[folder] = by_folder.get(folder, 0.0) + cpu_s
    terminalreporter.write_line("by folder: " + ", ".join(
        f"{folder} {cpu_s:.0f} s" for folder, cpu_s in sorted(by_folder.items(), key=lambda kv: -kv[1])))


def pytest_unconfigure(config):
    """The controller removes the run's folder of locks and groups once its workers are gone."""
    run = getattr(config.option, "testrunuid", None)
    if run and not os.environ.get("PYTEST_XDIST_WORKER"):
        import shutil

        shutil.rmtree(Path(tempfile.gettempdir()) / f"millsense-pytest-{run}", ignore_errors=True)


def summarise(path: str) -> str:
    """What a `--timeline` file says about a run: the parallel and the serial phase's wall time, the CPU seconds
    the tests used in each (so how many of the box's cores they kept busy), and the tests running alone at the
    end of the parallel phase. `python -m tests.parallel FILE`."""
    rows = [json.loads(line) for line in Path(path).read_text().splitlines() if line.strip()]
    if not rows:
        return "no tests in the timeline"
    t0 = min(r["start"] for r in rows)
    serial = [r for r in rows if r["serial"]]
    other = [r for r in rows if not r["serial"]]
    out = [f"{len(rows)} tests, {max(r['end'] for r in rows) - t0:.0f} s from the first start to the last end, "
           f"{sum(r['cpu_s'] for r in rows):.0f} CPU s, {len({r['worker'] for r in rows})} workers, "
           f"{os.cpu_count()} cores here"]
    slow = [r for r in other if r.get("slow")]
    for name, part in (("parallel", other), ("  of which slow", slow), ("serial", serial)):
        if part:
            a, b = min(r["start"] for r in part) - t0, max(r["end"] for r in part) - t0
            cpu = sum(r["cpu_s"] for r in part)
            busy = sum(r["end"] - r["start"] for r in part)
            out.append(f"{name}: {len(part)} tests from {a:.0f} s to {b:.0f} s ({b - a:.0f} s), {cpu:.0f} CPU s "
                       f"({cpu / max(b - a, 1e-9):.2f} cores busy on average), {busy / max(b - a, 1e-9):.1f} tests "
                       f"running on average")
    overlapped = sorted({s["test"] for s in serial for r in other if r["start"] < s["end"] and r["end"] > s["start"]})
    if serial:
        lanes = max(sum(1 for r in serial if r["start"] <= s["start"] < r["end"]) for s in serial)  # at a start
        out.append(f"every serial test ran with no other test but serial ones ({lanes} at most at once)"
                   if not overlapped else
                   f"SERIAL TESTS THAT DID NOT RUN ALONE ({len(overlapped)}): " + "; ".join(overlapped[:10]))
    if slow:
        out.append(f"the slow tests: {sum(r['end'] - r['start'] for r in slow):.0f} s of a worker's time, "
                   f"{sum(r['cpu_s'] for r in slow):.0f} CPU s; the other parallel tests: "
                   f"{sum(r['end'] - r['start'] for r in other if not r.get('slow')):.0f} s, "
                   f"{sum(r['cpu_s'] for r in other if not r.get('slow')):.0f} CPU s")
    if other:
        end = max(r["end"] for r in other)
        tail = sorted((r for r in other if r["end"] > end - 60 and r["end"] - r["start"] > 5), key=lambda r: r["start"])
        if tail:
            out.append("over 5 s in the parallel phase's last minute: " + "; ".join(
                f"{r['test']} ({r['start'] - t0:.0f}-{r['end'] - t0:.0f} s)" for r in tail[:10]))
    # the cores' use, 30 s at a time: CPU s of the tests running then (each test's CPU spread over its time)
    span = max(r["end"] for r in rows) - t0
    buckets = [0.0] * (int(span // 30) + 1)
    for r in rows:
        dur = max(r["end"] - r["start"], 1e-3)
        for i in range(len(buckets)):
            lo, hi = t0 + 30 * i, t0 + 30 * (i + 1)
            overlap = min(hi, r["end"]) - max(lo, r["start"])
            if overlap > 0:
                buckets[i] += r["cpu_s"] * overlap / dur
    out.append("cores busy, 30 s at a time: " + " ".join(f"{b / 30:.1f}" for b in buckets))
    return "\n".join(out)


if __name__ == "__main__":
    import sys

    print(summarise(sys.argv[1]))
