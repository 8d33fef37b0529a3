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
from millsense.daemon.opcua.server import Feeder, build_server  # noqa: E402
from tests.opcua.rig import MS_NS, SLOW_S, connect, in_process_options, make_pki, wait_async  # noqa: E402

FLOOD = 40  # transitions of one condition, at one instant of the limiter's clock
OVERLOAD = {"t": 1.7e9, "run_id": "r1", "level": "overload", "quantity": "torque_nm", "value": 31.7, "limit": 30.0,
            "interlock": None, "rev": 9}


def _flood(i):
    level = "overload" if i % 2 == 0 else "clear"
    return {**OVERLOAD, "seq": i + 1, "t": 1.7e9 + i * 0.01, "level": level,
            "value": 31.7 if level != "clear" else 10.0}


def test_a_flapping_condition_fires_a_few_events_counts_the_rest_and_ends_in_its_newest_state(tmp_path):
    pki = make_pki(tmp_path / "pki")
    port, options = in_process_options(tmp_path, pki)
    now = [1000.0]

    async def scenario():
        server, ns, root = await build_server(options)
        await server.start()
        client = None
        try:
            client = await connect(port, pki.client_cert, pki.client_key)
            ms = await client.get_namespace_index(MS_NS)
            events = []

            class Handler:
                def event_notification(self, event):
                    events.append(event)

            subscription = await client.create_subscription(20, Handler())
            await subscription.subscribe_events(ua.ObjectIds.Server, client.get_node(ns.alarm_type.nodeid))
            feeder = Feeder(server, ns, root)
            machine = await feeder.machine("m1")
            machine.limiter = EventLimiter(clock=lambda: now[0])

            async def named(name, n):
                got = [e for e in events if e.ConditionName == name]
                return got if len(got) >= n else None

            with structlog.testing.capture_logs() as logs:
                for i in range(FLOOD):
                    await machine.apply("alarm", _flood(i))
                # Another condition of the same machine is not held back by the flapping one.
                await machine.apply("alarm", {**OVERLOAD, "seq": 999, "quantity": "force_n", "value": 900.0,
                                              "limit": 800.0})
                await wait_async(lambda: named("force_n", 1), SLOW_S, "force_n's event")
                fired = await wait_async(lambda: named("torque_nm", BURST), SLOW_S, "the burst")
                # the burst, in order; the rest held back and counted
                assert [getattr(e, "ActiveState/Id") for e in fired] == [i % 2 == 0 for i in range(BURST)]
                held = client.get_node(ua.NodeId("m1/events_held", ms))
                assert await held.read_value() == FLOOD - BURST
                # Nothing more while the clock stands still ...
                await feeder.flush()
                # ... then, as soon as the rate allows one more, the newest state: the last clear.
                now[0] += 1.0 / EVENTS_PER_S
                await feeder.flush()
                last = (await wait_async(lambda: named("torque_nm", BURST + 1), SLOW_S, "the newest state"))[BURST]
                assert getattr(last, "ActiveState/Id") is False and last.Level == "clear" and last.Revolution == 9
                assert last.Time.timestamp() == pytest.approx(_flood(FLOOD - 1)["t"])
                condition = client.get_node(ua.NodeId("m1/Notification/Messages/torque_nm", ms))
                assert await (await condition.get_child(["0:ActiveState", "0:Id"])).read_value() is False
                # A flush with nothing held fires nothing: the force_n event and BURST + 1 torque events, no more.
                now[0] += 10.0
                await feeder.flush()
                await machine.apply("alarm", {**OVERLOAD, "seq": 1000, "quantity": "force_n", "level": "clear",
                                              "value": 10.0, "limit": 800.0})
                await wait_async(lambda: named("force_n", 2), SLOW_S, "force_n's clear")
                assert len(await named("torque_nm", 1)) == BURST + 1
            said = [e for e in logs if e["event"] == "opcua.events_held"]
            assert len(said) == 1 and said[0]["condition"] == "torque_nm", said
        finally:
            if client is not None:
                await client.disconnect()
            await server.stop()

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
    pki = make_pki(tmp_path / "pki")
    port, options = in_process_options(tmp_path, pki, operators=True)
    now = [1000.0]

    async def scenario():
        server, ns, root = await build_server(options)
        await server.start()
        client = None
        try:
            client = await connect(port, pki.client_cert, pki.client_key)
            ms = await client.get_namespace_index(MS_NS)
            events = []

            class Handler:
                def event_notification(self, event):
                    events.append(event)

            subscription = await client.create_subscription(20, Handler())
            await subscription.subscribe_events(ua.ObjectIds.Server, client.get_node(ns.alarm_type.nodeid))
            feeder = Feeder(server, ns, root)
            machine = await feeder.machine("m1")
            machine.limiter = EventLimiter(per_s=2.0, burst=1, clock=lambda: now[0])

            async def torque(n):
                got = [e for e in events if e.ConditionName == "torque_nm"]
                return got if len(got) >= n else None

            await machine.apply("alarm", _flood(0))  # overload: the bucket's one token
            (raised,) = await wait_async(lambda: torque(1), SLOW_S, "the overload")
            condition = client.get_node(ua.NodeId("m1/Notification/Messages/torque_nm", ms))
            await condition.call_method(ua.NodeId(ua.ObjectIds.AcknowledgeableConditionType_Acknowledge),
                                        ua.Variant(raised.EventId, ua.VariantType.ByteString),
                                        ua.Variant(ua.LocalizedText("seen"), ua.VariantType.LocalizedText))
            acked = (await wait_async(lambda: torque(2), SLOW_S, "the acknowledgement"))[1]
            assert getattr(acked, "AckedState/Id") is True
            await machine.apply("alarm", _flood(1))  # its clear: held back
            await machine.apply("alarm", _flood(2))  # raised again: held back, replacing the clear
            now[0] += 1.0
            await feeder.flush()
            again = (await wait_async(lambda: torque(3), SLOW_S, "the newest state"))[2]
            assert getattr(again, "ActiveState/Id") is True and getattr(again, "AckedState/Id") is False
            assert again.Retain is True
            assert await (await condition.get_child(["0:AckedState", "0:Id"])).read_value() is False
        finally:
            if client is not None:
                await client.disconnect()
            await server.stop()

    asyncio.run(scenario())
