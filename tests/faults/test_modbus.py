"""Modbus server exceptions and timeouts, between the real pymodbus server of the emulator and the reader.

A Modbus TCP proxy in this process (tests/faults/netfault.py) answers chosen
requests with an exception response (code 4, server device failure) instead
of passing them on, swallows answers so that the client times out, delivers
them late, or holds all traffic for a while. One bad answer is a glitch: the
request is sent again and the link stays up. Three in a row, an answer that
says the register map is wrong, or silence drop the link and reconnect; the
ring (4096 samples, 4 s) lets the reader fetch what it missed, so a short
outage loses nothing and a long one loses exactly the index gap.
A refused *write* is not a link failure but must not pass for a done one: the
feed hold is written again until the DAQ shows it.
"""

from __future__ import annotations

import math
import signal
import time

import numpy as np
import pytest

from millsense.drivers import create_driver
from tests.drivers.emulator_proc import RAMP_CHANNELS, Emulator, ramp
from tests.drivers.test_contract import Collector
from tests.e2e.helpers import read_jsonl, wait_for
from tests.faults.helpers import (assert_clean_exit, assert_no_damaged_estimate_looks_valid, log_events, modbus_proxy_daemon,
                                  outputs, status, wait_status)
from tests.faults.netfault import ModbusProxy

FC_READ_COILS, FC_READ_INPUT, FC_WRITE_REGISTER, FC_WRITE_COILS = 1, 4, 6, 15
RING = 4096
SLOW_S = 60.0  # detects a failure; no budget (CI is a loaded 2-core box)
START_S = 120.0  # the same, for what waits on two processes starting on such a box
DEVICE_WATCHDOG_MS = 5000


def _check_blocks(blocks) -> tuple[int, list]:
    """Right values, no sample twice, seq contiguous but for counted gaps: (samples, gaps)."""
    gaps = []
    for prev, b in zip(blocks, blocks[1:]):
        np.testing.assert_array_equal(b.counts, ramp(b.index, len(b.counts)))
        assert b.seq == prev.seq + len(prev.counts) + b.lost_before, "a sample lost without being counted, or twice"
        assert b.index == b.seq % (1 << 32) and not b.discontinuity
        if b.lost_before:
            gaps.append(b.lost_before)
    return sum(len(b.counts) for b in blocks), gaps


def _nothing_lost_between_driver_and_pipeline(st: dict) -> None:
    """The driver's queue dropped nothing. (Equal counts would need a snapshot with no block in
    flight; on a loaded box the status is often taken with one still queued.)"""
    daq = st["daq"]
    assert daq.get("queue_dropped_samples", 0) == 0 and st["samples_received"] <= daq["samples"], st


def test_exceptions_and_timeouts_lose_nothing_the_ring_holds_and_count_what_it_does_not(tmp_path, port):
    emu = Emulator(tmp_path, "--modbus-tcp", f"127.0.0.1:{port}")
    proxy = driver = None
    try:
        emu.start()
        proxy = ModbusProxy(port)
        driver = create_driver("modbus-tcp", host="127.0.0.1", tcp_port=proxy.port, unit=1, poll_ms=20)
        driver.start()
        assert driver.wait_connected(10.0)
        col = Collector(driver)
        assert col.pump(SLOW_S, until=lambda: len(col.blocks) > 20)

        def outage(inject, what: str) -> None:
            n_down = sum(not e.up for e in col.links)
            inject()
            assert col.pump(SLOW_S, until=lambda: sum(not e.up for e in col.links) > n_down), f"{what}: no link down"
            n = len(col.blocks)
            assert col.pump(SLOW_S, until=lambda: len(col.blocks) > n + 5), f"{what}: no samples after"
            assert col.links[-1].up

        def glitch(inject, what: str, retries: int) -> None:
            n_links, before = len(col.links), driver.stats().get("modbus_retries", 0)
            inject()
            assert col.pump(SLOW_S, until=lambda: driver.stats().get("modbus_retries", 0) >= before + retries), \
                f"{what}: not retried"
            n = len(col.blocks)
            assert col.pump(SLOW_S, until=lambda: len(col.blocks) > n + 5), f"{what}: no samples after"
            assert len(col.links) == n_links, f"{what}: the link went down: {[e.reason for e in col.links[n_links:]]}"
            assert driver.stats()["modbus_retries"] == before + retries, f"{what}: retried more than it failed"

        glitch(lambda: proxy.fail(FC_READ_INPUT, 1), "exception to a ring read", 1)
        glitch(lambda: proxy.fail(FC_READ_COILS, 2), "two exceptions to the status poll", 2)
        glitch(lambda: proxy.swallow(FC_READ_INPUT, 1), "a ring read that times out", 1)
        # its answer comes after the timeout, while the retry waits: taken for the retry's, the
        # registers would be from the wrong address, and _check_blocks would see it
        glitch(lambda: proxy.late(FC_READ_INPUT, 1, 0.3), "an answer that comes late", 1)
        outage(lambda: proxy.fail(FC_READ_INPUT, 3), "three exceptions in a row")
        retries = driver.stats()["modbus_retries"]
        outage(lambda: proxy.fail(FC_READ_INPUT, 1, code=2), "illegal data address: the map is wrong")
        assert driver.stats()["modbus_retries"] == retries, "an illegal-address answer was retried"
        outage(lambda: proxy.hold(1.5), "1.5 s of silence")
        short = [b for _, b in col.blocks]
        n_short, gaps_short = _check_blocks(short)
        assert gaps_short == [], f"the ring held every sample of a short outage, yet {gaps_short} were lost"
        assert proxy.injected_count("exception") == 1 + 2 + 3 + 1
        assert proxy.injected_count("swallowed") == 1 and proxy.injected_count("late") == 1

        # longer than the ring: what the device overwrote is lost, and counted exactly
        outage(lambda: proxy.hold(6.0), "6 s of silence")
        blocks = [b for _, b in col.blocks]
        n_all, gaps = _check_blocks(blocks)
        stats = driver.stats()
        downs = [e for e in col.links if not e.up]
        print(f"{len(downs)} outages, {n_all} samples, gaps {gaps}, reasons: {[e.reason for e in downs]}")
        assert len(gaps) == 1 and gaps[0] >= 6000 - RING - 1000, gaps
        assert stats["reconnect_gaps"] == 1 and stats["lost_samples"] == gaps[0]
        assert stats["samples"] == n_all and stats.get("queue_dropped_samples", 0) == 0  # every sample read was handed over
        assert any("refused a request" in e.reason and "(3 tries)" in e.reason for e in downs), [e.reason for e in downs]
        assert any("no answer from DAQ" in e.reason and "within 200 ms (3 tries)" in e.reason for e in downs), \
            [e.reason for e in downs]
        assert [e.up for e in col.links] == [True, False] * len(downs) + [True]
    finally:
        if driver is not None:
            driver.close()
        if proxy is not None:
            proxy.close()
        emu.stop()


def test_a_device_slower_than_its_samples_hands_over_what_it_reads_and_counts_what_it_cannot(tmp_path, port):
    """A gateway answering every read 40 ms late: 15 samples a request cannot keep up with 1 kHz.

    (A loaded box does the same to a local emulator, only less predictably.) The reader must not
    sit on a growing backlog until it is all read, which held every sample back for seconds and
    made the daemon take the DAQ for stalled: each poll hands over what it read within
    `READ_SLICE_S`, and what the device overwrote before it could be read is lost and counted.
    """
    from millsense.drivers.modbus_driver import MAX_REGS, READ_SLICE_S

    delay_s = 0.04
    emu = Emulator(tmp_path, "--modbus-tcp", f"127.0.0.1:{port}")
    proxy = driver = None
    try:
        emu.start()
        proxy = ModbusProxy(port)
        driver = create_driver("modbus-tcp", host="127.0.0.1", tcp_port=proxy.port, unit=1, poll_ms=20)
        driver.start()
        assert driver.wait_connected(10.0)
        col = Collector(driver)
        assert col.pump(SLOW_S, until=lambda: len(col.blocks) > 5)
        proxy.late(FC_READ_INPUT, 10**9, delay_s)  # in time for the 200 ms timeout, every one
        n_slow = len(col.blocks)
        # behind by more than the ring (4096 samples) some seconds later: the first overrun, then more blocks
        assert col.pump(SLOW_S, until=lambda: driver.stats().get("overruns", 0) >= 1), "never fell a ring behind"
        n = len(col.blocks)
        assert col.pump(SLOW_S, until=lambda: len(col.blocks) > n + 10), "no samples after the overrun"
        blocks = [b for _, b in col.blocks]
        stats = driver.stats()
    finally:
        if driver is not None:
            driver.close()
        if proxy is not None:
            proxy.close()
        emu.stop()
    # a request takes at least delay_s, so a poll reads at most this many chunks before it hands over
    # (a loaded box only makes requests slower: fewer); the old reader handed over the whole backlog
    most = math.ceil(READ_SLICE_S / delay_s) * (MAX_REGS // RAMP_CHANNELS)
    sizes = [len(b.counts) for b in blocks[n_slow + 1:]]
    assert max(sizes) <= most, f"a block of {max(sizes)} samples: the reader sat on its backlog (at most {most})"
    n_all, gaps = _check_blocks(blocks)
    assert gaps and stats["lost_samples"] == sum(gaps), (gaps, stats)
    assert stats["samples"] == n_all and stats.get("queue_dropped_samples", 0) == 0
    assert [e.up for e in col.links] == [True], "a slow device is not a lost one"


@pytest.mark.slow
def test_daemon_over_modbus_refused_writes_and_read_faults(tmp_path):
    """A refused feed-hold write is written again; refused heartbeats are reported; read faults lose nothing."""
    machine = "mb-01"
    with modbus_proxy_daemon(
        tmp_path, machine,
        alarms="torque_limit_nm = 1.2\nrevolutions = 2\nbreakage_drop_pct = 0",  # trips on the first cut
        # a watchdog a loaded box cannot trip by delaying a heartbeat, nor a reconnect: one that acts
        # here means the heartbeats stopped (whether one goes out while a read waits is checked below)
        interlock=f'enabled = true\nheartbeat_ms = 50\nwatchdog_ms = {DEVICE_WATCHDOG_MS}\nreset = "open"',
        before_daemon=lambda proxy: proxy.fail(FC_WRITE_COILS, 1),  # the DAQ refuses the first outputs write: the trip
    ) as (procs, daemon, sub, sim_log, proxy):
        # the first cut trips: on a loaded box that can be before this subscriber is connected, so
        # the daemon's own log of the alarm (the same record) stands in for a publication missed
        def overload():
            published = next((a for a in sub.get("alarm") if a["level"] == "overload"), None)
            logged = next((e for e in log_events(procs.text("daemon", "out")) if e.get("alarm_level") == "overload"), None)
            return published or logged or daemon.poll() is not None

        alarm = wait_for(overload, START_S, "the overload")
        assert daemon.poll() is None, procs.text("daemon", "out")[-3000:]
        # the refused write did not count as a hold; the next heartbeat period wrote it again
        wait_for(lambda: outputs(read_jsonl(sim_log), feed_hold=True, cause="command"), SLOW_S, "feed hold on the DAQ")
        assert proxy.injected_count("exception", FC_WRITE_COILS) == 1
        assert alarm["interlock"] is None, "the alarm claimed a feed hold the DAQ had refused"
        st = wait_status(sub, machine, lambda s: s["interlock_detail"]["device_feed_hold"], SLOW_S, "hold confirmed")
        assert st["interlock"] == "feed_hold" and st["interlock_detail"]["hold_unconfirmed"] is False
        assert st["daq"]["commands_refused"] == 1

        # -- exceptions to reads: retried, the link stays up, the heartbeats go on
        def read_fault(inject, retries: int) -> None:
            before = status(sub, machine)["daq"]
            inject()
            st = wait_status(sub, machine, lambda s: s["daq"].get("modbus_retries", 0) >= before.get("modbus_retries", 0) + retries,
                             SLOW_S, "the read retried")
            assert st["daq"]["link_changes"] == before["link_changes"] and st["daq_link"] == "up", st
            assert st["state"] == "running", st

        read_fault(lambda: proxy.fail(FC_READ_INPUT, 1), 1)
        read_fault(lambda: proxy.fail(FC_READ_COILS, 2), 2)
        # -- three in a row: the link drops and comes back, the ring covers the gap
        changes = status(sub, machine)["daq"]["link_changes"]
        proxy.fail(FC_READ_INPUT, 3)
        wait_status(sub, machine, lambda s: s["daq"]["link_changes"] >= changes + 2 and s["daq_link"] == "up"
                    and s["state"] == "running", SLOW_S, "reconnected after three failed tries")
        time.sleep(1.0)
        after = status(sub, machine)
        assert after["lost_samples"] == 0 and after["daq"]["lost_samples"] == 0, after
        _nothing_lost_between_driver_and_pipeline(after)
        assert not outputs(read_jsonl(sim_log), cause="watchdog"), "an exception reply must not starve the watchdog"

        # -- heartbeats refused by the DAQ: status says so, and the DAQ's watchdog holds the feed
        proxy.fail(FC_WRITE_REGISTER, 10**6)
        refused = wait_status(sub, machine, lambda s: s["heartbeating"] is False, SLOW_S, "heartbeats reported failing")
        wait_for(lambda: outputs(read_jsonl(sim_log), cause="watchdog"), SLOW_S, "the DAQ's watchdog acts")
        # (The Modbus map has no watchdog flag: with the hold already commanded, a trip looks the same
        # as the commanded hold, so status can only say the feed is held, which it is.)
        assert status(sub, machine)["interlock_detail"]["device_feed_hold"] is True
        proxy.fail(FC_WRITE_REGISTER, 0)
        wait_status(sub, machine, lambda s: s["heartbeating"] is True, SLOW_S, "heartbeats resumed")

        # -- a read that times out (200 ms, then tried again): nothing is lost, the link stays up, and
        # the heartbeats do not wait behind it: one goes out while the read waits for its answer (how
        # soon is the box's; that the I/O lock is free while a request waits is the product's)
        read_fault(lambda: proxy.swallow(FC_READ_INPUT, 1), 1)
        time.sleep(1.0)
        after = status(sub, machine)
        # the timed-out read lost nothing; a box so loaded that the reader fell a ring behind loses
        # samples, but as overruns, named and counted
        overrun = after["daq"].get("overruns", 0) + after["daq"].get("overwritten_during_read", 0)
        assert after["lost_samples"] == 0 or overrun > 0, after
        _nothing_lost_between_driver_and_pipeline(after)
        (t_swallowed,) = [t for t, _, kind in proxy.injected if kind == "swallowed"]
        t_retry = next(t for t, fc in list(proxy.arrivals) if fc == FC_READ_INPUT and t > t_swallowed)
        beats_while = [t for t, fc in list(proxy.arrivals) if fc == FC_WRITE_REGISTER and t_swallowed < t < t_retry]
        assert beats_while, "no heartbeat went out while a read waited for its answer: the I/O lock was held"
        assert proxy.injected_count("swallowed") == 1 and proxy.injected_count("exception", FC_READ_INPUT) == 1 + 3
        estimates = sub.get("estimate")
        assert daemon.poll() is None
        daemon.send_signal(signal.SIGTERM)
        assert daemon.wait(10) == 0
    assert refused["state"] == "running"  # a refused heartbeat is the DAQ's call, not a pipeline fault
    assert_no_damaged_estimate_looks_valid(estimates)
    events = log_events(procs.text("daemon", "out"))
    assert any(e["event"] == "interlock.write_failed" and e["feed_hold"] for e in events)
    assert any(e["event"] == "interlock.feed_hold_rewritten" for e in events)
    assert any(e["event"] == "interlock.heartbeat_failed" for e in events)
    assert_clean_exit(procs, "daemon")
