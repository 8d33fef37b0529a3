"""What every fault case checks afterwards, on real processes.

Built on tests/e2e/helpers.py (Procs, Subscriber, write_config, wait_for):
here are the after-the-fault checks the reliability table refers to —
the daemon is alive (or exited with a documented code), no estimate was
published from damaged data, status and logs tell the truth.
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np

from tests.e2e.helpers import Subscriber, wait_for

# One sample of a crash pulse on the simulated DAQ's eight channels, in counts: 300 V line voltages
# (0.02 V/count), line currents 30 A and 60 A (0.002 A/count) summing to zero, every line swinging (none looks
# flat); the spindle's speed and encoder channels at 0: it stands still. bench/crash_latency.py sends it.
PULSE = np.array([15000, 15000, -30000, 15000, 15000, -30000, 0, 0], dtype=np.int16)

# Every physical quantity of an estimate (daemon/pipeline/estimator.py NULL_FIELDS):
# null in an estimate built on damaged data.
PHYSICAL = (
    "spindle_rpm", "gear", "p_in_w", "p_gap_w", "torque_nm", "torque_sigma_nm", "force_n",
    "force_tangential_n", "force_feed_n", "feed_per_tooth_mm", "radial_depth_mm",
    "axial_depth_mm", "depth_status",
)


def status(sub: Subscriber, machine: str, timeout_s: float = 10.0) -> dict:
    """The daemon's `status` queryable, asked until it answers (a query can race a link change)."""
    deadline = time.monotonic() + timeout_s
    while True:
        replies = [r for r in sub.query(f"millsense/{machine}/status", timeout=2.0) if "error" not in r]
        if replies:
            return replies[0]
        if time.monotonic() > deadline:
            raise AssertionError(f"no status from {machine} within {timeout_s} s")
        time.sleep(0.1)


def wait_status(sub: Subscriber, machine: str, predicate, timeout_s: float, what: str) -> dict:
    last: dict = {}

    def check() -> dict | None:
        nonlocal last
        last = status(sub, machine)
        return last if predicate(last) else None

    try:
        return wait_for(check, timeout_s, what, step_s=0.1)
    except AssertionError as exc:
        raise AssertionError(f"{exc}; last status: {json.dumps(last)[:1500]}") from None


def log_events(text: str) -> list[dict]:
    """The daemon's JSON log lines (stdout under a config with format = "json")."""
    out = []
    for line in text.splitlines():
        line = line.strip()
        if line.startswith("{"):
            try:
                out.append(json.loads(line))
            except ValueError:
                pass  # a line being written right now
    return out


def assert_no_damaged_estimate_looks_valid(estimates: list[dict]) -> int:
    """An estimate built on lost samples or across a discontinuity has every quantity null.

    Returns how many such (invalid) estimates there were.
    """
    invalid = 0
    for e in estimates:
        damaged = e.get("lost_samples", 0) > 0 or e.get("valid") is False
        if damaged:
            invalid += 1
            assert e.get("valid") is False, f"damaged estimate published as valid: {e}"
            assert all(e.get(k) is None for k in PHYSICAL), f"a number built on damaged data: {e}"
            assert e.get("cutting") is False
    return invalid


def assert_revs_contiguous(estimates: list[dict]) -> None:
    revs = [e["rev"] for e in estimates]
    assert revs == list(range(revs[0], revs[0] + len(revs))), "a revolution number went missing or repeated"


def assert_clean_exit(procs, name: str) -> None:
    for stream in ("err", "out"):
        assert "Traceback" not in procs.text(name, stream), procs.text(name, stream)[-3000:]


def outputs(events: list[dict], **match: Any) -> list[dict]:
    """The emulator status log's output changes, filtered by field values."""
    return [e for e in events if e.get("event") == "outputs" and all(e.get(k) == v for k, v in match.items())]


@contextmanager
def runner_on_the_sim(settings) -> Iterator[tuple[Any, Any, Any]]:
    """(runner, driver, sink): the real `Runner` on the in-process simulated DAQ (`step`, its device and
    interlock live), its threads not started. The test is its estimator thread: it hands the runner's block
    handler (`_on_block`) blocks cut where it needs them, which live is a matter of timing (a catch-up after
    the thread fell behind, where a hold falls in a block). The sink records what would be published."""
    from millsense.daemon.runtime.runner import Runner
    from millsense.drivers.sim_driver import SimDriver
    from tests.runtime.test_runner import RecordingSink

    drv = SimDriver("step", realtime=True, loop=True)
    drv.start()
    runner = None
    try:
        assert drv.wait_connected(5)
        wait_for(lambda: drv.descriptor is not None, 5, "descriptor")
        runner = Runner(settings, drv)
        runner.sink = sink = RecordingSink(lambda: drv.device)
        runner.core.on_descriptor(drv.descriptor)
        runner.interlock.start()
        yield runner, drv, sink
    finally:
        if runner is not None:
            runner.stop(1.0)
        drv.close()


INTERLOCK_OPEN = 'enabled = true\nheartbeat_ms = 50\nwatchdog_ms = 1000\nreset = "open"'


@contextmanager
def live_daemon(tmp_path, machine: str, sim_args: list[str], *, interlock: str = INTERLOCK_OPEN,
                edit_config=None, watchdog_ms: int = 1000) -> Iterator[tuple[Any, Any, Subscriber, Any]]:
    """The emulator (`millsense sim --scenario step --tcp …`, its status log on, `sim_args` added) and the real
    daemon on it (`millsense run`, Zenoh on loopback); `edit_config(text) -> text` may change the config file
    first. Yields (procs, the daemon's process, a subscriber, the emulator's status log path)."""
    from tests.conftest import free_tcp_port
    from tests.e2e.helpers import Procs, tcp, write_config

    daq_port, z_port = free_tcp_port(), free_tcp_port()
    sim_log = tmp_path / "sim.jsonl"
    cfg = write_config(tmp_path / "d.toml", machine=machine, daq=f'transport = "tcp"\nhost = "127.0.0.1"\ntcp_port = {daq_port}',
                       zenoh_listen=[tcp(z_port)], interlock=interlock)
    if edit_config is not None:
        cfg.write_text(edit_config(cfg.read_text()))
    with Procs(tmp_path) as procs:
        procs.start("sim", ["sim", "--scenario", "step", "--loop", "--tcp", f"127.0.0.1:{daq_port}", "--realtime",
                            "--watchdog-ms", str(watchdog_ms), "--status-log", str(sim_log), *sim_args])
        wait_for(lambda: "serving" in procs.text("sim"), 60.0, "emulator serving")
        daemon = procs.start("daemon", ["run", "--config", str(cfg)])
        sub = Subscriber([tcp(z_port)], machine)
        try:
            yield procs, daemon, sub, sim_log
        finally:
            sub.close()


@contextmanager
def modbus_proxy_daemon(tmp_path, machine: str, *, interlock: str = INTERLOCK_OPEN, alarms: str = "",
                        before_daemon=None) -> Iterator[tuple[Any, Any, Subscriber, Any, Any]]:
    """The emulator's Modbus TCP server (`millsense sim --scenario step --modbus-tcp …`, its status log on), a
    Modbus proxy in this process in front of it (tests/faults/netfault.py: faults by function code), and the real
    daemon reading through the proxy (unit 1, `poll_ms = 20`, Zenoh on loopback). `before_daemon(proxy)` may
    arm faults before the daemon's first request. Yields (procs, the daemon's process, a subscriber, the
    emulator's status log path, the proxy)."""
    from tests.conftest import free_tcp_port
    from tests.e2e.helpers import Procs, tcp, write_config
    from tests.faults.netfault import ModbusProxy

    mb_port, z_port = free_tcp_port(), free_tcp_port()
    sim_log = tmp_path / "sim.jsonl"
    with Procs(tmp_path) as procs:
        procs.start("sim", ["sim", "--scenario", "step", "--loop", "--modbus-tcp", f"127.0.0.1:{mb_port}", "--realtime",
                            "--status-log", str(sim_log)])
        wait_for(lambda: "serving" in procs.text("sim"), 60.0, "emulator serving")
        proxy = ModbusProxy(mb_port)
        sub = None
        try:
            cfg = write_config(tmp_path / "d.toml", machine=machine,
                               daq=f'transport = "modbus-tcp"\nhost = "127.0.0.1"\ntcp_port = {proxy.port}\nunit = 1\n'
                                   "poll_ms = 20",
                               zenoh_listen=[tcp(z_port)], alarms=alarms, interlock=interlock)
            if before_daemon is not None:
                before_daemon(proxy)
            daemon = procs.start("daemon", ["run", "--config", str(cfg)])
            sub = Subscriber([tcp(z_port)], machine)
            yield procs, daemon, sub, sim_log, proxy
        finally:
            if sub is not None:
                sub.close()
            proxy.close()
