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

from tests.opcua.rig import alarm_types, opcua_rig, value  # noqa: E402

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
    async def scenario():
        async with opcua_rig(tmp_path) as rig:
            limit_type, discrete_type = await alarm_types(rig.client)
            assert ua.NodeId(ua.ObjectIds.ExclusiveLevelAlarmType) in await _supertypes(limit_type)
            assert ua.NodeId(ua.ObjectIds.OffNormalAlarmType) in await _supertypes(discrete_type)
            await rig.subscribe([limit_type, discrete_type])
            machine = await rig.machine()
            for alarm in ALARMS:
                await machine.apply("alarm", alarm)

            expected = {"torque_nm": limit_type, "force_n": limit_type, "daq": discrete_type, "FeedHeld": discrete_type}
            for name, etype in expected.items():
                event = (await rig.named(name))[0]
                assert event.EventType == etype.nodeid, (name, event.EventType)
                assert await rig.condition(name).read_type_definition() == etype.nodeid, name
            # The limit, on its side: an overload's is a high limit, an envelope_low's a low one.
            torque = rig.condition("torque_nm")
            assert await value(torque, "0:HighLimit") == 30.0
            assert math.isnan(await value(torque, "0:LowLimit"))
            assert await value(rig.condition("force_n"), "0:LowLimit") == 120.0
            assert (await rig.named("torque_nm"))[0].HighLimit == 30.0
            assert (await rig.named("force_n"))[0].LowLimit == 120.0
            # A discrete condition has no limits; it is active or not.
            daq = rig.condition("daq")
            assert await value(daq, "0:ActiveState", "0:Id") is True
            with pytest.raises(ua.UaStatusCodeError):
                await daq.get_child(["0:HighLimit"])

    asyncio.run(scenario())
