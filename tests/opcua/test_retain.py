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

from tests.opcua.rig import acknowledge, opcua_rig, value  # noqa: E402

OVERLOAD = {"t": 1.7e9, "seq": 1, "run_id": "r1", "level": "overload", "quantity": "torque_nm", "value": 31.7,
            "limit": 30.0, "interlock": None, "rev": 9}
CLEAR = {**OVERLOAD, "seq": 2, "t": 1.7e9 + 0.2, "level": "clear", "value": 10.0}


def test_a_condition_is_retained_while_active_or_unacknowledged(tmp_path):
    async def scenario():
        async with opcua_rig(tmp_path, operators=True, subscribe=["alarm", "refresh_end"]) as rig:
            machine = await rig.machine()
            condition = rig.condition("torque_nm")

            async def torque(n):
                return await rig.named("torque_nm", n)

            async def retain():
                return await value(condition, "0:Retain")

            async def refreshed():
                """The torque_nm events ConditionRefresh replays to a fresh subscription."""
                return [e for e in await rig.refresh() if getattr(e, "ConditionName", None) == "torque_nm"]

            # Active, unacknowledged: retained.
            await machine.apply("alarm", OVERLOAD)
            (active,) = await torque(1)
            assert active.Retain is True and await retain() is True
            # Cleared, still unacknowledged: still retained, and ConditionRefresh still replays it.
            await machine.apply("alarm", CLEAR)
            cleared = (await torque(2))[1]
            assert getattr(cleared, "ActiveState/Id") is False and getattr(cleared, "AckedState/Id") is False
            assert cleared.Retain is True and await retain() is True
            (replayed,) = await refreshed()
            assert getattr(replayed, "ActiveState/Id") is False and replayed.Retain is True
            # Acknowledged while inactive: no longer retained, and no longer replayed.
            await acknowledge(condition, cleared.EventId)
            acked = (await torque(4))[3]
            assert getattr(acked, "AckedState/Id") is True and acked.Retain is False and await retain() is False
            assert await refreshed() == []
            # Active again: unacknowledged, retained; acknowledged while active: retained until it clears.
            await machine.apply("alarm", {**OVERLOAD, "seq": 3, "t": 1.7e9 + 5})
            again = (await torque(5))[4]
            assert again.Retain is True and getattr(again, "AckedState/Id") is False
            await acknowledge(condition, again.EventId)
            acked_active = (await torque(6))[5]
            assert getattr(acked_active, "ActiveState/Id") is True and acked_active.Retain is True
            await machine.apply("alarm", {**CLEAR, "seq": 4, "t": 1.7e9 + 5.2})
            last = (await torque(7))[6]
            assert getattr(last, "ActiveState/Id") is False and last.Retain is False and await retain() is False

    asyncio.run(scenario())
