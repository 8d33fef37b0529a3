"""Retain (OPC UA Part 9): a condition is retained while it is active OR unacknowledged (issue 42).

An overload's condition is active for about 0.2 s: the hold takes the load off and the alarm clears. Before,
its Retain went false with the clear, so an operator's alarm list (built from ConditionRefresh) lost an overload
nobody had acknowledged. The server object of `millsense opcua` on loopback, its machine fed the daemon's
payloads, asyncua's client subscribed to the Server object and calling ConditionRefresh and Acknowledge.
"""

from __future__ import annotations

import asyncio

import pytest

pytest.importorskip("asyncua", reason="the opcua extra (asyncua) is not installed")
from asyncua import ua  # noqa: E402

from millsense.daemon.opcua.server import Feeder, build_server  # noqa: E402
from tests.opcua.rig import MS_NS, SLOW_S, connect, in_process_options, make_pki, wait_async  # noqa: E402

ACKNOWLEDGE = ua.NodeId(ua.ObjectIds.AcknowledgeableConditionType_Acknowledge)
OVERLOAD = {"t": 1.7e9, "seq": 1, "run_id": "r1", "level": "overload", "quantity": "torque_nm", "value": 31.7,
            "limit": 30.0, "interlock": None, "rev": 9}
CLEAR = {**OVERLOAD, "seq": 2, "t": 1.7e9 + 0.2, "level": "clear", "value": 10.0}


def test_a_condition_is_retained_while_active_or_unacknowledged(tmp_path):
    pki = make_pki(tmp_path / "pki")
    port, options = in_process_options(tmp_path, pki, operators=True)

    async def scenario():
        server, ns, root = await build_server(options)
        await server.start()
        client = None
        try:
            client = await connect(port, pki.client_cert, pki.client_key)
            ms = await client.get_namespace_index(MS_NS)
            alarm_type = client.get_node(ns.alarm_type.nodeid)
            events = []

            class Handler:
                def event_notification(self, event):
                    events.append(event)

            subscription = await client.create_subscription(20, Handler())
            await subscription.subscribe_events(ua.ObjectIds.Server, [alarm_type, client.get_node(
                ua.ObjectIds.RefreshEndEventType)])
            machine = await Feeder(server, ns, root).machine("m1")
            condition = client.get_node(ua.NodeId("m1/Notification/Messages/torque_nm", ms))

            async def torque(n):
                got = [e for e in events if e.ConditionName == "torque_nm"]
                return got if len(got) >= n else None

            async def retain():
                return await (await condition.get_child(["0:Retain"])).read_value()

            async def refreshed():
                """The torque_nm events ConditionRefresh replays to a fresh subscription."""
                mark = len(events)
                await client.get_node(ua.ObjectIds.ConditionType).call_method(
                    ua.NodeId(ua.ObjectIds.ConditionType_ConditionRefresh),
                    ua.Variant(subscription.subscription_id, ua.VariantType.UInt32))
                # RefreshEnd (no ConditionName) closes the replay
                await wait_async(lambda: _after(events, mark, lambda e: e.EventType == ua.NodeId(
                    ua.ObjectIds.RefreshEndEventType)), SLOW_S, "RefreshEnd")
                return [e for e in events[mark:] if getattr(e, "ConditionName", None) == "torque_nm"]

            # Active, unacknowledged: retained.
            await machine.apply("alarm", OVERLOAD)
            (active,) = await wait_async(lambda: torque(1), SLOW_S, "the overload's event")
            assert active.Retain is True and await retain() is True
            # Cleared, still unacknowledged: still retained, and ConditionRefresh still replays it.
            await machine.apply("alarm", CLEAR)
            cleared = (await wait_async(lambda: torque(2), SLOW_S, "the clear's event"))[1]
            assert getattr(cleared, "ActiveState/Id") is False and getattr(cleared, "AckedState/Id") is False
            assert cleared.Retain is True and await retain() is True
            (replayed,) = await refreshed()
            assert getattr(replayed, "ActiveState/Id") is False and replayed.Retain is True
            # Acknowledged while inactive: no longer retained, and no longer replayed.
            await client.get_node(condition.nodeid).call_method(
                ACKNOWLEDGE, ua.Variant(cleared.EventId, ua.VariantType.ByteString),
                ua.Variant(ua.LocalizedText("seen"), ua.VariantType.LocalizedText))
            acked = (await wait_async(lambda: torque(4), SLOW_S, "the acknowledgement's event"))[3]
            assert getattr(acked, "AckedState/Id") is True and acked.Retain is False and await retain() is False
            assert await refreshed() == []
            # Active again: unacknowledged, retained; acknowledged while active: retained until it clears.
            await machine.apply("alarm", {**OVERLOAD, "seq": 3, "t": 1.7e9 + 5})
            again = (await wait_async(lambda: torque(5), SLOW_S, "the second overload"))[4]
            assert again.Retain is True and getattr(again, "AckedState/Id") is False
            await client.get_node(condition.nodeid).call_method(
                ACKNOWLEDGE, ua.Variant(again.EventId, ua.VariantType.ByteString),
                ua.Variant(ua.LocalizedText("seen"), ua.VariantType.LocalizedText))
            acked_active = (await wait_async(lambda: torque(6), SLOW_S, "the second acknowledgement"))[5]
            assert getattr(acked_active, "ActiveState/Id") is True and acked_active.Retain is True
            await machine.apply("alarm", {**CLEAR, "seq": 4, "t": 1.7e9 + 5.2})
            last = (await wait_async(lambda: torque(7), SLOW_S, "the second clear"))[6]
            assert getattr(last, "ActiveState/Id") is False and last.Retain is False and await retain() is False
        finally:
            if client is not None:
                await client.disconnect()
            await server.stop()

    asyncio.run(scenario())


async def _after(events, mark, predicate):
    return any(predicate(e) for e in events[mark:])
