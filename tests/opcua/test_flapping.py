"""A flapping condition is limited to a few events a second, its held-back events counted (issue 42).

The server object of `millsense opcua` on loopback, its machine fed a flood of the daemon's alarm payloads (an
overload and its clear, over and over), asyncua's client subscribed to the Server object's events. The clock of
the limiter is the test's (a flood's speed on a loaded box must not decide what the test sees); everything else
is real: the server, the events, the client.
"""

from __future__ import annotations

import asyncio

import pytest

pytest.importorskip("asyncua", reason="the opcua extra (asyncua) is not installed")
import structlog  # noqa: E402
from asyncua import ua  # noqa: E402

from millsense.daemon.opcua.flapping import BURST, EVENTS_PER_S, EventLimiter  # noqa: E402
from tests.opcua.rig import acknowledge, opcua_rig, value  # noqa: E402

FLOOD = 40  # transitions of one condition, at one instant of the limiter's clock
OVERLOAD = {"t": 1.7e9, "run_id": "r1", "level": "overload", "quantity": "torque_nm", "value": 31.7, "limit": 30.0,
            "interlock": None, "rev": 9}


def _flood(i):
    level = "overload" if i % 2 == 0 else "clear"
    return {**OVERLOAD, "seq": i + 1, "t": 1.7e9 + i * 0.01, "level": level,
            "value": 31.7 if level != "clear" else 10.0}


def test_a_flapping_condition_fires_a_few_events_counts_the_rest_and_ends_in_its_newest_state(tmp_path):
    now = [1000.0]

    async def scenario():
        async with opcua_rig(tmp_path, subscribe=["alarm"]) as rig:
            machine = await rig.machine()
            machine.limiter = EventLimiter(clock=lambda: now[0])
            with structlog.testing.capture_logs() as logs:
                for i in range(FLOOD):
                    await machine.apply("alarm", _flood(i))
                # Another condition of the same machine is not held back by the flapping one.
                await machine.apply("alarm", {**OVERLOAD, "seq": 999, "quantity": "force_n", "value": 900.0,
                                              "limit": 800.0})
                await rig.named("force_n", 1)
                fired = await rig.named("torque_nm", BURST)
                # the burst, in order; the rest held back and counted
                assert [getattr(e, "ActiveState/Id") for e in fired] == [i % 2 == 0 for i in range(BURST)]
                held = rig.client.get_node(ua.NodeId("m1/events_held", rig.ms))
                assert await held.read_value() == FLOOD - BURST
                # Nothing more while the clock stands still ...
                await rig.feeder.flush()
                # ... then, as soon as the rate allows one more, the newest state: the last clear.
                now[0] += 1.0 / EVENTS_PER_S
                await rig.feeder.flush()
                last = (await rig.named("torque_nm", BURST + 1))[BURST]
                assert getattr(last, "ActiveState/Id") is False and last.Level == "clear" and last.Revolution == 9
                assert last.Time.timestamp() == pytest.approx(_flood(FLOOD - 1)["t"])
                assert await value(rig.condition("torque_nm"), "0:ActiveState", "0:Id") is False
                # A flush with nothing held fires nothing: the force_n event and BURST + 1 torque events, no more.
                now[0] += 10.0
                await rig.feeder.flush()
                await machine.apply("alarm", {**OVERLOAD, "seq": 1000, "quantity": "force_n", "level": "clear",
                                              "value": 10.0, "limit": 800.0})
                await rig.named("force_n", 2)
                assert len(await rig.named("torque_nm", 1)) == BURST + 1
            said = [e for e in logs if e["event"] == "opcua.events_held"]
            assert len(said) == 1 and said[0]["condition"] == "torque_nm", said

    asyncio.run(scenario())


@pytest.mark.quick
def test_the_limiter_refills_at_its_rate_and_keeps_each_condition_apart():
    now = [0.0]
    limiter = EventLimiter(per_s=2.0, burst=3, clock=lambda: now[0])
    assert [limiter.allow("a") for _ in range(4)] == [True, True, True, False]
    assert limiter.allow("b") is True
    now[0] += 0.5
    assert [limiter.allow("a") for _ in range(2)] == [True, False]
    now[0] += 100.0
    assert [limiter.allow("a") for _ in range(4)] == [True, True, True, False]  # never more than the burst


def test_an_alarm_that_came_back_while_held_back_is_unacknowledged_again(tmp_path):
    """Acknowledged, then cleared and raised again within one held-back interval: the event fired for the newest
    state (active, as the last one fired) must say unacknowledged: it is a new occurrence nobody has seen."""
    now = [1000.0]

    async def scenario():
        async with opcua_rig(tmp_path, operators=True, subscribe=["alarm"]) as rig:
            machine = await rig.machine()
            machine.limiter = EventLimiter(per_s=2.0, burst=1, clock=lambda: now[0])
            await machine.apply("alarm", _flood(0))  # overload: the bucket's one token
            (raised,) = await rig.named("torque_nm", 1)
            condition = rig.condition("torque_nm")
            await acknowledge(condition, raised.EventId)
            acked = (await rig.named("torque_nm", 2))[1]
            assert getattr(acked, "AckedState/Id") is True
            await machine.apply("alarm", _flood(1))  # its clear: held back
            await machine.apply("alarm", _flood(2))  # raised again: held back, replacing the clear
            now[0] += 1.0
            await rig.feeder.flush()
            again = (await rig.named("torque_nm", 3))[2]
            assert getattr(again, "ActiveState/Id") is True and getattr(again, "AckedState/Id") is False
            assert again.Retain is True
            assert await value(condition, "0:AckedState", "0:Id") is False

    asyncio.run(scenario())
