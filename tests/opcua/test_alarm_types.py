"""Each alarm condition is an instance of a fitting Part 9 type (issue 42): a judged quantity's (overload,
envelope, expected band, ...) an ExclusiveLevelAlarmType with the alarm's limit as its HighLimit or LowLimit, the
held feed and the DAQ link OffNormalAlarmType. The server object of `millsense opcua` on loopback, its machine
fed the daemon's payloads, asyncua's client reading the types and the conditions as any client would.
"""

from __future__ import annotations

import asyncio
import math

import pytest

pytest.importorskip("asyncua", reason="the opcua extra (asyncua) is not installed")
from asyncua import ua  # noqa: E402

from millsense.daemon.opcua.server import Feeder, build_server  # noqa: E402
from tests.opcua.rig import MS_NS, SLOW_S, alarm_types, connect, in_process_options, make_pki, wait_async  # noqa: E402

BASE = {"t": 1.7e9, "run_id": "r1", "rev": 9}
ALARMS = [
    {**BASE, "seq": 1, "level": "overload", "quantity": "torque_nm", "value": 31.7, "limit": 30.0,
     "interlock": "feed_hold"},
    {**BASE, "seq": 2, "level": "envelope_low", "quantity": "force_n", "value": 80.0, "limit": 120.0,
     "interlock": None, "program": 7, "tool": 3, "operation": "rough", "process": "p1", "process_rev": 4},
    {**BASE, "seq": 3, "level": "daq_lost", "quantity": "daq", "value": None, "limit": None, "interlock": None},
]


async def _supertypes(node):
    """The type's supertypes, nearest first, up to BaseEventType."""
    chain = []
    while True:
        parents = await node.get_referenced_nodes(refs=ua.ObjectIds.HasSubtype, direction=ua.BrowseDirection.Inverse)
        if not parents:
            return chain
        node = parents[0]
        chain.append(node.nodeid)


def test_limit_alarms_are_exclusive_level_alarms_with_their_limit_and_discrete_ones_off_normal(tmp_path):
    pki = make_pki(tmp_path / "pki")
    port, options = in_process_options(tmp_path, pki)

    async def scenario():
        server, ns, root = await build_server(options)
        await server.start()
        client = None
        try:
            client = await connect(port, pki.client_cert, pki.client_key)
            ms = await client.get_namespace_index(MS_NS)
            limit_type, discrete_type = await alarm_types(client)
            assert ua.NodeId(ua.ObjectIds.ExclusiveLevelAlarmType) in await _supertypes(limit_type)
            assert ua.NodeId(ua.ObjectIds.OffNormalAlarmType) in await _supertypes(discrete_type)
            events = []

            class Handler:
                def event_notification(self, event):
                    events.append(event)

            subscription = await client.create_subscription(20, Handler())
            await subscription.subscribe_events(ua.ObjectIds.Server, [limit_type, discrete_type])
            machine = await Feeder(server, ns, root).machine("m1")
            for alarm in ALARMS:
                await machine.apply("alarm", alarm)

            async def named(name):
                return next((e for e in events if e.ConditionName == name), None)
            expected = {"torque_nm": limit_type, "force_n": limit_type, "daq": discrete_type, "FeedHeld": discrete_type}
            for name, etype in expected.items():
                event = await wait_async(lambda n=name: named(n), SLOW_S, f"{name}'s event")
                assert event.EventType == etype.nodeid, (name, event.EventType)
                condition = client.get_node(ua.NodeId(f"m1/Notification/Messages/{name}", ms))
                assert await condition.read_type_definition() == etype.nodeid, name
            # The limit, on its side: an overload's is a high limit, an envelope_low's a low one.
            torque = client.get_node(ua.NodeId("m1/Notification/Messages/torque_nm", ms))
            assert await (await torque.get_child(["0:HighLimit"])).read_value() == 30.0
            assert math.isnan(await (await torque.get_child(["0:LowLimit"])).read_value())
            force = client.get_node(ua.NodeId("m1/Notification/Messages/force_n", ms))
            assert await (await force.get_child(["0:LowLimit"])).read_value() == 120.0
            assert (await named("torque_nm")).HighLimit == 30.0 and (await named("force_n")).LowLimit == 120.0
            # A discrete condition has no limits; it is active or not.
            daq = client.get_node(ua.NodeId("m1/Notification/Messages/daq", ms))
            assert await (await daq.get_child(["0:ActiveState", "0:Id"])).read_value() is True
            with pytest.raises(ua.UaStatusCodeError):
                await daq.get_child(["0:HighLimit"])
        finally:
            if client is not None:
                await client.disconnect()
            await server.stop()

    asyncio.run(scenario())
