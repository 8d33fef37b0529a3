"""Acknowledge and Confirm of the alarm conditions (issue 42): the server object of `millsense opcua`
listening on loopback, its machine fed the daemon's payloads, asyncua's client calling the methods.

Only an operator (a certificate in the operators' folder) may; the EventId must be the condition's last;
each is one more event with the comment, and audited; nothing else changes (the held feed stays held).
"""

from __future__ import annotations

import asyncio
import shutil

import pytest

pytest.importorskip("asyncua", reason="the opcua extra (asyncua) is not installed")
import structlog  # noqa: E402
from asyncua import ua  # noqa: E402

from millsense.daemon.opcua.server import Feeder, build_server  # noqa: E402
from tests.opcua.rig import MS_NS, SLOW_S, connect, in_process_options, make_pki, wait_async  # noqa: E402

ACKNOWLEDGE = ua.NodeId(ua.ObjectIds.AcknowledgeableConditionType_Acknowledge)
CONFIRM = ua.NodeId(ua.ObjectIds.AcknowledgeableConditionType_Confirm)
OVERLOAD = {"t": 1.7e9, "seq": 1, "run_id": "r1", "level": "overload", "quantity": "torque_nm", "value": 31.7,
            "limit": 30.0, "interlock": "feed_hold", "rev": 9}


def test_only_an_operator_acknowledges_and_confirms_and_nothing_else_changes(tmp_path):
    pki = make_pki(tmp_path / "pki")
    shutil.copyfile(pki.stranger_cert, pki.trust_dir / "stranger.der")  # trusted, but no operator
    port, options = in_process_options(tmp_path, pki, operators=True)

    async def scenario():
        server, ns, root = await build_server(options)
        await server.start()
        operator = stranger = None
        try:
            operator = await connect(port, pki.client_cert, pki.client_key)
            stranger = await connect(port, pki.stranger_cert, pki.stranger_key)
            ms = await operator.get_namespace_index(MS_NS)
            alarm_type = [operator.get_node(ns.alarm_type.nodeid), operator.get_node(ns.discrete_type.nodeid)]
            events = []

            class Handler:
                def event_notification(self, event):
                    events.append(event)

            subscription = await operator.create_subscription(20, Handler())
            await subscription.subscribe_events(ua.ObjectIds.Server, alarm_type)
            machine = await Feeder(server, ns, root).machine("m1")
            await machine.apply("alarm", OVERLOAD)

            async def fired(name, **fields):
                return next((e for e in events if e.ConditionName == name
                             and all(getattr(e, k) == v for k, v in fields.items())), None)
            first = await wait_async(lambda: fired("torque_nm"), SLOW_S, "the overload's event")
            assert getattr(first, "AckedState/Id") is False and getattr(first, "ConfirmedState/Id") is False
            event_id = first.EventId
            # The condition is a node at its ConditionId (before issue 42: BadNodeIdUnknown), of the event's type,
            # named by HasCondition from its source, its state that of the event.
            condition = operator.get_node(ua.NodeId("m1/Notification/Messages/torque_nm", ms))
            assert await condition.read_type_definition() == ns.alarm_type.nodeid
            source = operator.get_node(ua.NodeId("m1/Notification/Messages", ms))
            named = await source.get_referenced_nodes(refs=ua.ObjectIds.HasCondition, direction=ua.BrowseDirection.Forward)
            assert condition.nodeid in [n.nodeid for n in named]
            assert await (await condition.get_child(["0:ActiveState", "0:Id"])).read_value() is True
            assert await (await condition.get_child(["0:Retain"])).read_value() is True
            assert await (await condition.get_child(["0:Severity"])).read_value() == 800
            assert "overload torque_nm 31.7" in (await (await condition.get_child(["0:Message"])).read_value()).Text
            assert await (await condition.get_child(["0:EventId"])).read_value() == event_id
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
                assert await (await condition.get_child(["0:AckedState", "0:Id"])).read_value() is False
                # An EventId that is not the condition's last: refused.
                wrong = (ua.Variant(b"not-an-event", ua.VariantType.ByteString), args[1])
                assert await call(operator, ACKNOWLEDGE, *wrong) == ua.StatusCodes.BadEventIdUnknown
                # Confirm before Acknowledge: refused.
                assert await call(operator, CONFIRM, *args) == ua.StatusCodes.BadInvalidState
                assert await call(operator, ACKNOWLEDGE, *args) == ua.StatusCodes.Good
                acked = await wait_async(lambda: fired("torque_nm", **{"AckedState/Id": True}), SLOW_S, "the ack event")
                assert acked.Comment.Text == "seen, chip jam cleared" and acked.ClientUserId == "client.der"
                assert getattr(acked, "ActiveState/Id") is True  # acknowledged is not cleared
                assert await call(operator, ACKNOWLEDGE, *args) == ua.StatusCodes.BadConditionBranchAlreadyAcked
                args = (ua.Variant(acked.EventId, ua.VariantType.ByteString), args[1])
                assert await call(operator, CONFIRM, *args) == ua.StatusCodes.Good
                await wait_async(lambda: fired("torque_nm", **{"ConfirmedState/Id": True}), SLOW_S, "the confirm event")
                assert await (await condition.get_child(["0:ConfirmedState", "0:Id"])).read_value() is True
                # The instance's own copy of Acknowledge answers like the type's (a refusal here: done already).
                own = await condition.get_child(["0:Acknowledge"])
                assert await call(operator, own.nodeid, *args) == ua.StatusCodes.BadConditionBranchAlreadyAcked
                # The held feed acknowledged stays held.
                held = await wait_async(lambda: fired("FeedHeld"), SLOW_S, "FeedHeld's event")
                feed = operator.get_node(ua.NodeId("m1/Notification/Messages/FeedHeld", ms))
                held_args = (ua.Variant(held.EventId, ua.VariantType.ByteString), args[1])
                assert await call(operator, ACKNOWLEDGE, *held_args, on=feed) == ua.StatusCodes.Good
                assert await (await feed.get_child(["0:ActiveState", "0:Id"])).read_value() is True
                assert await (await feed.get_child(["0:Retain"])).read_value() is True
            # The daemon clears it: inactive, no longer retained, acknowledged and confirmed as it was.
            await machine.apply("alarm", {**OVERLOAD, "seq": 2, "t": 1.7e9 + 0.2, "level": "clear", "value": 10.0,
                                          "interlock": None})
            assert await (await condition.get_child(["0:ActiveState", "0:Id"])).read_value() is False
            assert await (await condition.get_child(["0:Retain"])).read_value() is False
            assert await (await condition.get_child(["0:AckedState", "0:Id"])).read_value() is True
            assert await (await condition.get_child(["0:LastSeverity"])).read_value() == 800
            audit = [e for e in logs if e["event"] == "opcua.audit"]
            assert [(e["action"], e["comment"], e["user"]) for e in audit] == [
                ("acknowledge", "seen, chip jam cleared", "client.der"), ("confirm", "seen, chip jam cleared", "client.der"),
                ("acknowledge", "seen, chip jam cleared", "client.der")], audit
            assert any(e["event"] == "opcua.audit_refused" and e["user"] == "stranger.der" for e in logs), logs
        finally:
            for client in (operator, stranger):
                if client is not None:
                    await client.disconnect()
            await server.stop()

    asyncio.run(scenario())
