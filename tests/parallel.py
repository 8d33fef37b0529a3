"""How the suite runs in parallel processes (pytest-xdist), loaded by tests/conftest.py.

The suite mostly waits on real processes, so pyproject runs it in several workers
(`-n`, `--dist loadgroup`). Three rules keep that honest (docs/testing.md):

- **Sharing.** The tests of a module that uses a module-scoped fixture form one xdist
  group, so that the fixture is built once, not once per worker.
- **Order.** Tests marked `slow` are handed out first, so that the longest ones do not
  start last and leave one worker running alone at the end. `serial` tests come last.
- **The serial phase.** A test marked `serial` asserts a latency or a period (crash →
  hold, the watchdog, heartbeats, reset at standstill): it runs with no other test
  running. All of them form one xdist group, so one worker runs them back to back;
  that worker holds a lock the others need to start any test, from the first serial
  test to the last (a readers–writer lock on files, with writers first: a waiting
  serial test stops new tests from starting, then waits for those running to end).
  The kernel drops a dead worker's lock, so a crash cannot wedge the others.
- **Shares of the box.** `--cpu-shares N`: a running test holds shares of the box, a `slow` test one (it
  streams at 1× real time and mostly waits: about 0.3 of a core), any other test two (it mostly computes);
  N in all. pyproject runs 6 workers with 8 shares: at most 4 computing tests at once, as with 4 workers,
  and while slow tests stream the workers they leave beside them run computing tests in the idle core.
- **CPU, not only time.** `--cpu-report N` prints the N tests that used most CPU
  (the worker process and the children it waited for): on a 2-core box the suite's
  time is bounded by CPU, and a test can be quick and still eat the others' share.
"""

from __future__ import annotations

import fcntl
import json
import os
import resource
import tempfile
import time
import uuid
from pathlib import Path

import pytest

SERIAL_GROUP = "serial"
# What a running test holds of `--cpu-shares`: a slow test streams at 1x real time and mostly waits (the slow
# tests of stop 33's CI: 310 CPU s in 1 002 s of a worker's time, 0.3 of a core each), any other mostly computes
# (0.45 of a core on average, an estimator test a whole core)
SLOW_SHARES = 1
OTHER_SHARES = 2
_holding_serial = False
_locks: dict[str, int] = {}


def pytest_addoption(parser):
    parser.addoption("--cpu-report", type=int, default=0, metavar="N",
                     help="print the N tests that used the most CPU seconds (worker and waited-for children)")
    parser.addoption("--cpu-shares", type=int, default=None, metavar="N",
                     help=f"shares of the box the running tests hold, N in all: a slow test {SLOW_SHARES}, any "
                          f"other {OTHER_SHARES} (0: no limit but the workers'; default: the ini's cpu_shares; "
                          f"docs/testing.md)")
    # an ini key, not an addopt: a pytest run under pyproject's options without this plugin (bench/mutants.py's
    # own test of its options) would refuse an unknown command-line option
    parser.addini("cpu_shares", default="0", help="the default of --cpu-shares")
    parser.addoption("--timeline", default=None, metavar="FILE",
                     help="append one JSON line per test to FILE: worker, start and end (Unix time), CPU s, serial; "
                          "says where a run's cores sat idle (docs/testing.md)")


def _is(item, name: str) -> bool:
    return item is not None and item.get_closest_marker(name) is not None


@pytest.hookimpl(tryfirst=True)  # before xdist reads the xdist_group markers
def pytest_collection_modifyitems(config, items):
    for item in items:
        if _is(item, "serial"):
            item.add_marker(pytest.mark.xdist_group(SERIAL_GROUP))
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

    return GroupScheduling(config, log)


def _tell_the_controller_the_groups(items) -> None:
    """xdist 3.8's loadgroup tags a grouped test's node id (`id@group`), which pytest 9 no longer lets it change:
    its groups are silently ignored. Each worker writes the groups of its collection (the same in every worker)
    to the run's folder instead, and the controller's scheduler (`GroupScheduling`) reads them."""
    if not items or not _is_worker(items[0].config):
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


def _is_worker(config) -> bool:
    """An xdist worker of this run, not a pytest a test started inside one (tests/dashboard/test_ci_browser.py runs
    `pytest -n 0` on another file): that one inherits the worker's environment, PYTEST_XDIST_WORKER included, and
    taking the run's locks and shares beside its parent, which holds its own, would wedge the run."""
    return hasattr(config, "workerinput")


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


def _fd(name: str) -> int:
    if name not in _locks:
        _locks[name] = os.open(_lock_path(name), os.O_RDWR | os.O_CREAT, 0o600)
    return _locks[name]


def _enter(serial: bool) -> None:
    global _holding_serial
    if serial:
        if not _holding_serial:
            fcntl.flock(_fd("gate"), fcntl.LOCK_EX)   # no new test starts from here ...
            fcntl.flock(_fd("run"), fcntl.LOCK_EX)    # ... and the running ones have ended
            _holding_serial = True
        return
    fcntl.flock(_fd("gate"), fcntl.LOCK_EX)
    fcntl.flock(_fd("run"), fcntl.LOCK_SH)
    fcntl.flock(_fd("gate"), fcntl.LOCK_UN)


def _leave(serial: bool, next_serial: bool) -> None:
    global _holding_serial
    if serial and next_serial:
        return                                        # the serial phase goes on
    fcntl.flock(_fd("run"), fcntl.LOCK_UN)
    if _holding_serial:
        fcntl.flock(_fd("gate"), fcntl.LOCK_UN)
        _holding_serial = False


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    parallel = _is_worker(item.config)
    serial = _is(item, "serial")
    if parallel:
        _enter(serial)
    shares = _take_shares(item) if parallel and not serial else []
    if parallel:
        _enter(serial)
    item.stash[_CPU_START] = _cpu_s()
    started = time.time()
    try:
        yield
    finally:
        ended = time.time()   # inside the lock, like the start: a serial test's span and another's never overlap
        if parallel:
            _leave(serial, _is(nextitem, "serial"))
        _give_back(shares)
        _timeline(item, started, ended, serial)


def _take_shares(item) -> list[int]:
    """Hold this test's shares of `--cpu-shares` (one lock file each) until it ends; wait while they are taken.
    One worker at a time picks (the `shares` lock): it takes what is free and looks again every 10 ms for the
    rest. Not a blocking wait on one taken share: the lowest are the slow tests' (handed out first), and a wait
    on one of those held every worker behind it for a minute while other shares came free. No deadlock: a holder
    gives its shares back when its test ends and needs no lock to do it; a serial test takes none (it runs
    alone anyway)."""
    total = item.config.getoption("--cpu-shares")
    if total is None:
        total = int(item.config.getini("cpu_shares") or 0)
    if total <= 0:
        return []
    need = min(total, SLOW_SHARES if _is(item, "slow") else OTHER_SHARES)
    held: list[int] = []
    fcntl.flock(_fd("shares"), fcntl.LOCK_EX)
    try:
        while len(held) < need:
            for i in range(total):
                if len(held) < need and i not in held and _try_lock(_fd(f"share.{i}")):
                    held.append(i)
            if len(held) < need:   # every share taken: a running test's end gives one back
                time.sleep(0.01)
    finally:
        fcntl.flock(_fd("shares"), fcntl.LOCK_UN)
    return held


def _try_lock(fd: int) -> bool:
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return False
    return True


def _give_back(shares: list[int]) -> None:
    for i in shares:
        fcntl.flock(_fd(f"share.{i}"), fcntl.LOCK_UN)


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
        out.append("every serial test ran alone" if not overlapped else
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
