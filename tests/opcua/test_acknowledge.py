"""Acknowledge and Confirm of the alarm conditions (issue 42): the server object of `millsense opcua`
listening on loopback, its machine fed the daemon's payloads, asyncua's client calling the methods.

Only an operator (a certificate in the operators' folder) may; the EventId must be the condition's last;
each is one more event with the comment, and audited; nothing else changes (the held feed stays held).
"""

from __future__ import annotations

import asyncio

import pytest

pytest.importorskip("asyncua", reason="the opcua extra (asyncua) is not installed")
import structlog  # noqa: E402
from asyncua import ua  # noqa: E402

from tests.opcua.rig import ACKNOWLEDGE, CONFIRM, opcua_rig, value  # noqa: E402

OVERLOAD = {"t": 1.7e9, "seq": 1, "run_id": "r1", "level": "overload", "quantity": "torque_nm", "value": 31.7,
            "limit": 30.0, "interlock": "feed_hold", "rev": 9}


def test_only_an_operator_acknowledges_and_confirms_and_nothing_else_changes(tmp_path):
    async def scenario():
        # the stranger's certificate trusted, but no operator's
        async with opcua_rig(tmp_path, operators=True, trust_stranger=True, subscribe=["alarm", "discrete"]) as rig:
            operator = rig.client
            stranger = await rig.connect(rig.pki.stranger_cert, rig.pki.stranger_key)
            machine = await rig.machine()
            await machine.apply("alarm", OVERLOAD)

            first = await rig.first("torque_nm")
            assert getattr(first, "AckedState/Id") is False and getattr(first, "ConfirmedState/Id") is False
            event_id = first.EventId
            # The condition is a node at its ConditionId (before issue 42: BadNodeIdUnknown), of the event's type,
            # named by HasCondition from its source, its state that of the event.
            condition = rig.condition("torque_nm")
            assert await condition.read_type_definition() == rig.ns.alarm_type.nodeid
            source = operator.get_node(ua.NodeId("m1/Notification/Messages", rig.ms))
            named = await source.get_referenced_nodes(refs=ua.ObjectIds.HasCondition, direction=ua.BrowseDirection.Forward)
            assert condition.nodeid in [n.nodeid for n in named]
            assert await value(condition, "0:ActiveState", "0:Id") is True
            assert await value(condition, "0:Retain") is True
            assert await value(condition, "0:Severity") == 800
            assert "overload torque_nm 31.7" in (await value(condition, "0:Message")).Text
            assert await value(condition, "0:EventId") == event_id
            args = (ua.Variant(event_id, ua.VariantType.ByteString),
                    ua.Variant(ua.LocalizedText("seen, chip jam cleared"), ua.VariantType.LocalizedText))

            async def call(client, method, *arguments, on=condition):
                try:
                    await client.get_node(on.nodeid).call_method(method, *arguments)
                except ua.UaStatusCodeError as exc:
                    return exc.code
                return ua.StatusCodes.Good

            with structlog.testing.capture_logs() as logs:
                # A trusted client that is no operator: refused, and the refusal logged.
                assert await call(stranger, ACKNOWLEDGE, *args) == ua.StatusCodes.BadUserAccessDenied
                assert await value(condition, "0:AckedState", "0:Id") is False
                # An EventId that is not the condition's last: refused.
                wrong = (ua.Variant(b"not-an-event", ua.VariantType.ByteString), args[1])
                assert await call(operator, ACKNOWLEDGE, *wrong) == ua.StatusCodes.BadEventIdUnknown
                # Confirm before Acknowledge: refused.
                assert await call(operator, CONFIRM, *args) == ua.StatusCodes.BadInvalidState
                assert await call(operator, ACKNOWLEDGE, *args) == ua.StatusCodes.Good
                acked = await rig.first("torque_nm", **{"AckedState/Id": True})
                assert acked.Comment.Text == "seen, chip jam cleared" and acked.ClientUserId == "client.der"
                assert getattr(acked, "ActiveState/Id") is True  # acknowledged is not cleared
                assert await call(operator, ACKNOWLEDGE, *args) == ua.StatusCodes.BadConditionBranchAlreadyAcked
                args = (ua.Variant(acked.EventId, ua.VariantType.ByteString), args[1])
                assert await call(operator, CONFIRM, *args) == ua.StatusCodes.Good
                await rig.first("torque_nm", **{"ConfirmedState/Id": True})
                assert await value(condition, "0:ConfirmedState", "0:Id") is True
                # The instance's own copy of Acknowledge answers like the type's (a refusal here: done already).
                own = await condition.get_child(["0:Acknowledge"])
                assert await call(operator, own.nodeid, *args) == ua.StatusCodes.BadConditionBranchAlreadyAcked
                # The held feed acknowledged stays held.
                held = await rig.first("FeedHeld")
                feed = rig.condition("FeedHeld")
                held_args = (ua.Variant(held.EventId, ua.VariantType.ByteString), args[1])
                assert await call(operator, ACKNOWLEDGE, *held_args, on=feed) == ua.StatusCodes.Good
                assert await value(feed, "0:ActiveState", "0:Id") is True
                assert await value(feed, "0:Retain") is True
            # The daemon clears it: inactive, no longer retained, acknowledged and confirmed as it was.
            await machine.apply("alarm", {**OVERLOAD, "seq": 2, "t": 1.7e9 + 0.2, "level": "clear", "value": 10.0,
                                          "interlock": None})
            assert await value(condition, "0:ActiveState", "0:Id") is False
            assert await value(condition, "0:Retain") is False
            assert await value(condition, "0:AckedState", "0:Id") is True
            assert await value(condition, "0:LastSeverity") == 800
            audit = [e for e in logs if e["event"] == "opcua.audit"]
            assert [(e["action"], e["comment"], e["user"]) for e in audit] == [
                ("acknowledge", "seen, chip jam cleared", "client.der"), ("confirm", "seen, chip jam cleared", "client.der"),
                ("acknowledge", "seen, chip jam cleared", "client.der")], audit
            assert any(e["event"] == "opcua.audit_refused" and e["user"] == "stranger.der" for e in logs), logs

    asyncio.run(scenario())
