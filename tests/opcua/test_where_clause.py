"""A client that watches only active conditions gets them (issue 42's last acceptance line).

What such a client puts on the wire (OPC UA Part 4, 7.7): an event filter on the Server object whose where clause
is `OfType(AlarmConditionType) AND ActiveState/Id = true`. asyncua 2.1.0's server matched `OfType` to the event's
exact type (ours are subtypes: MillsenseAlarmType, MillsenseOffNormalAlarmType) and read a field's browse path by
its first name only (`ActiveState`, a LocalizedText, never equal to true), and it filtered ConditionRefresh's
RefreshStart/RefreshEnd too (Part 9 5.5.7: they ignore the filter): such a client got nothing at all.
daemon/opcua/where_clause.py evaluates the clause as Part 4 says.

The server object of `millsense opcua` on loopback, its machine fed the daemon's payloads (an overload that holds
the feed, its clear, the held machine's statuses), asyncua's client subscribed with that filter.
"""

from __future__ import annotations

import asyncio
import logging
from typing import Any

import pytest

pytest.importorskip("asyncua", reason="the opcua extra (asyncua) is not installed")
from asyncua import ua  # noqa: E402
from asyncua.common.events import get_filter_from_event_type  # noqa: E402

from millsense.daemon.opcua import where_clause  # noqa: E402
from tests.opcua.rig import REFRESH_END, opcua_rig  # noqa: E402

OVERLOAD = {"t": 1.7e9, "seq": 1, "run_id": "r1", "level": "overload", "quantity": "torque_nm", "value": 31.7,
            "limit": 30.0, "interlock": "feed_hold", "rev": 9}
CLEAR = {**OVERLOAD, "seq": 2, "t": 1.7e9 + 0.2, "level": "clear", "value": 0.0}
REFRESH_START = ua.NodeId(ua.ObjectIds.RefreshStartEventType)


def _held_status(t):
    """The daemon's status of a held, stopped machine (docs/zenoh.md, `status`)."""
    return {"t": t, "state": "running", "alarm": "ok", "interlock": "feed_hold", "daq_link": "up",
            "interlock_detail": {"interlock": "feed_hold", "reason": "overload torque_nm 31.7 > 30", "since": 1.7e9,
                                 "daq_feed_hold": True}}


def active_only() -> ua.ContentFilter:
    """`OfType(AlarmConditionType) AND ActiveState/Id = true`, as a standard alarm client writes it."""
    active_id = ua.SimpleAttributeOperand(TypeDefinitionId=ua.NodeId(ua.ObjectIds.AlarmConditionType),
                                          BrowsePath=[ua.QualifiedName("ActiveState", 0), ua.QualifiedName("Id", 0)],
                                          AttributeId=ua.AttributeIds.Value)
    return ua.ContentFilter(Elements=[
        ua.ContentFilterElement(FilterOperator=ua.FilterOperator.And,
                                FilterOperands=[ua.ElementOperand(Index=1), ua.ElementOperand(Index=2)]),
        ua.ContentFilterElement(FilterOperator=ua.FilterOperator.OfType, FilterOperands=[
            ua.LiteralOperand(Value=ua.Variant(ua.NodeId(ua.ObjectIds.AlarmConditionType)))]),
        ua.ContentFilterElement(FilterOperator=ua.FilterOperator.Equals, FilterOperands=[
            active_id, ua.LiteralOperand(Value=ua.Variant(True, ua.VariantType.Boolean))]),
    ])


def test_a_client_that_watches_only_active_conditions_gets_the_held_feed_live_and_from_condition_refresh(tmp_path):
    async def scenario():
        async with opcua_rig(tmp_path) as rig:
            evfilter = await get_filter_from_event_type([rig.client.get_node(ua.ObjectIds.AlarmConditionType)],
                                                        where_clause_generation=False)
            evfilter.WhereClause = active_only()
            await rig.subscribe(evfilter=evfilter)
            machine = await rig.machine()

            # Live: the overload and the held feed it caused, both active; the overload's clear is not sent.
            await machine.apply("alarm", OVERLOAD)
            await machine.apply("alarm", CLEAR)
            for t in (1.7e9 + 1.5, 1.7e9 + 2.5):
                await machine.apply("status", _held_status(t))
            await rig.until(lambda events: sorted({getattr(e, "ConditionName", None) for e in events}) == [
                "FeedHeld", "torque_nm"], "both active conditions")
            # the clear's event was fired after both: had it passed the filter, it would be here by RefreshEnd
            live = list(rig.events)
            refresh = await rig.refresh()   # RefreshEnd, whatever the filter
            assert sorted(e.ConditionName for e in live) == ["FeedHeld", "torque_nm"], live
            assert all(getattr(e, "ActiveState/Id") is True for e in live), live

            # ConditionRefresh on the held, stopped machine: RefreshStart, FeedHeld active, RefreshEnd. The cleared
            # overload nobody acknowledged is retained (Part 9) but inactive: not for this client.
            assert [e.EventType for e in refresh][0] == REFRESH_START and refresh[-1].EventType == REFRESH_END
            (held,) = refresh[1:-1]
            assert held.ConditionName == "FeedHeld" and getattr(held, "ActiveState/Id") is True, held
            assert held.EventType == rig.ns.discrete_type.nodeid and held.Severity >= 900, held

    asyncio.run(scenario())


def _aspace_with(*chain: ua.NodeId) -> Any:
    """An asyncua AddressSpace holding one type hierarchy: each NodeId of `chain` a subtype of the next."""
    from asyncua.server.address_space import AddressSpace, NodeData

    aspace = AddressSpace()
    for sub, parent in zip(chain, chain[1:]):
        data = aspace.get(sub) or NodeData(sub)
        data.references.append(ua.ReferenceDescription(ReferenceTypeId=ua.NodeId(ua.ObjectIds.HasSubtype),
                                                       NodeId=parent, IsForward=False))
        aspace[sub] = data
    return aspace


def _event(etype: ua.NodeId, **fields: Any) -> Any:
    from asyncua.common.events import Event

    event = Event()
    event.add_property("EventType", etype, ua.VariantType.NodeId)
    for name, value in fields.items():
        event.add_property(name.replace("__", "/"), value, ua.VariantType.Boolean)
    return event


@pytest.mark.quick
def test_of_type_matches_subtypes_and_a_browse_path_is_read_whole():
    mine, level = ua.NodeId("MillsenseAlarmType", 2), ua.NodeId(ua.ObjectIds.ExclusiveLevelAlarmType)
    alarm, base = ua.NodeId(ua.ObjectIds.AlarmConditionType), ua.NodeId(ua.ObjectIds.BaseEventType)
    aspace = _aspace_with(mine, level, alarm, ua.NodeId(ua.ObjectIds.AcknowledgeableConditionType), base)
    evaluator = where_clause.ConformingEvaluator(logging.getLogger("test"), aspace, active_only())
    assert evaluator.eval(_event(mine, ActiveState__Id=True)) is True
    assert evaluator.eval(_event(mine, ActiveState__Id=False)) is False
    assert evaluator.eval(_event(alarm, ActiveState__Id=True)) is True  # the type itself
    # not an alarm: a supertype, an unrelated type, a type the address space does not know
    assert evaluator.eval(_event(base, ActiveState__Id=True)) is False
    assert evaluator.eval(_event(ua.NodeId(ua.ObjectIds.ProgressEventType), ActiveState__Id=True)) is False
    # an event without the field: NULL (Part 4), not an exception
    assert evaluator.eval(_event(mine)) is False
    # ConditionRefresh's markers ignore every filter (Part 9 5.5.7)
    assert evaluator.eval(_event(ua.NodeId(ua.ObjectIds.RefreshStartEventType))) is True
    assert evaluator.eval(_event(ua.NodeId(ua.ObjectIds.RefreshEndEventType))) is True
    # a type hierarchy with a loop ends
    loop_a, loop_b = ua.NodeId("A", 2), ua.NodeId("B", 2)
    looped = where_clause.ConformingEvaluator(logging.getLogger("test"), _aspace_with(loop_a, loop_b, loop_a),
                                              active_only())
    assert looped.eval(_event(loop_a, ActiveState__Id=True)) is False


@pytest.mark.quick
def test_another_asyncua_version_is_not_patched_and_the_log_says_so():
    from asyncua.server import monitored_item_service
    from structlog.testing import capture_logs

    before = monitored_item_service.WhereClauseEvaluator
    with capture_logs() as logs:
        assert where_clause.install("2.2.0") is False
    assert monitored_item_service.WhereClauseEvaluator is before
    (line,) = [x for x in logs if x["event"] == "opcua.where_clause_unpatched"]
    assert line["asyncua"] == "2.2.0" and line["written_for"] == where_clause.FOR_ASYNCUA == "2.1.0"
    assert where_clause.install() is True  # the installed asyncua is the one it was written for
    assert monitored_item_service.WhereClauseEvaluator is where_clause.ConformingEvaluator
