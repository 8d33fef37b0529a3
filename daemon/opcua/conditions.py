"""The condition instances behind the alarm events: a node at each event's ConditionId (issue 42, first part).

Every alarm event names its condition (`ConditionId`, the event's `NodeId` field:
`<machine>/Notification/Messages/<quantity>`, or `.../FeedHeld`). A standard alarms-and-conditions
client reads that node and browses HasCondition from the source; before this it got BadNodeIdUnknown.
Each condition is now an object of `MillsenseAlarmType` (an AlarmConditionType subtype) at that NodeId,
made at its first event, with HasCondition from the machine's Messages, and its state variables
written from each event it fires: ActiveState (and Id), Retain, Severity, LastSeverity, Message, Time,
EventId, ConditionName, ConditionClass, Source, EnabledState (always enabled).

Read only, like everything here. Acknowledge and Confirm are not implemented yet (docs/opcua.md):
AckedState reads BadNoData rather than a state nobody can change, and the instance's Acknowledge,
Enable, Disable and AddComment methods answer BadNothingToDo.
"""

from __future__ import annotations

import datetime as dt
from typing import Any

from asyncua import Node, ua
from asyncua.common.instantiate_util import instantiate

MAX_CONDITIONS = 64  # per machine: one per judged quantity and FeedHeld; bounded whatever a payload says

_NO_DATA = ua.StatusCode(ua.StatusCodes.BadNoData)


class ConditionNodes:
    """One machine's condition instances, by ConditionId."""

    def __init__(self, server: Any, alarm_type: Node, source: Node) -> None:
        self.server, self.alarm_type, self.source = server, alarm_type, source
        self.nodes: dict[ua.NodeId, dict[str, Node]] = {}

    async def update(self, values: dict[str, Any], event_id: Any, when: dt.datetime | None) -> None:
        """Write one fired event's fields into its condition instance (made at its first event)."""
        condition_id = values.get("NodeId")
        if not isinstance(condition_id, ua.NodeId):
            return
        nodes = self.nodes.get(condition_id)
        if nodes is None:
            if len(self.nodes) >= MAX_CONDITIONS:
                return
            nodes = await self._create(condition_id, str(values.get("ConditionName", "")))
        severity = int(values.get("Severity", 0))
        previous = await nodes["Severity"].read_value()
        writes: list[tuple[str, Any, ua.VariantType]] = [
            ("ActiveState", values["ActiveState"], ua.VariantType.LocalizedText),
            ("ActiveState/Id", bool(values["ActiveState/Id"]), ua.VariantType.Boolean),
            ("Retain", bool(values["Retain"]), ua.VariantType.Boolean),
            ("LastSeverity", int(previous or severity), ua.VariantType.UInt16),
            ("Severity", severity, ua.VariantType.UInt16),
            ("Message", values["Message"], ua.VariantType.LocalizedText),
            ("ConditionClassId", values["ConditionClassId"], ua.VariantType.NodeId),
            ("ConditionClassName", values["ConditionClassName"], ua.VariantType.LocalizedText),
            ("SourceNode", values["SourceNode"], ua.VariantType.NodeId),
            ("SourceName", values["SourceName"], ua.VariantType.String),
            ("Time", when or dt.datetime.now(dt.timezone.utc), ua.VariantType.DateTime),
        ]
        if isinstance(event_id, (bytes, ua.Variant)):
            writes.append(("EventId", event_id.Value if isinstance(event_id, ua.Variant) else event_id,
                           ua.VariantType.ByteString))
        for name, value, vt in writes:
            await nodes[name].write_value(ua.DataValue(ua.Variant(value, vt), SourceTimestamp=when))

    async def _create(self, condition_id: ua.NodeId, name: str) -> dict[str, Node]:
        (obj, *_) = await instantiate(self.source, self.alarm_type, nodeid=condition_id,
                                      bname=ua.QualifiedName(name, condition_id.NamespaceIndex),
                                      instantiate_optional=False)
        # Part 9: the source names its conditions by HasCondition (asyncua linked it by HasComponent too)
        await self.source.add_reference(obj.nodeid, ua.ObjectIds.HasCondition)
        nodes: dict[str, Node] = {}
        for path in ("ActiveState", "ActiveState/Id", "AckedState", "AckedState/Id", "EnabledState",
                     "EnabledState/Id", "Retain", "Severity", "LastSeverity", "Message", "ConditionClassId",
                     "ConditionClassName", "ConditionName", "SourceNode", "SourceName", "Time", "EventId"):
            nodes[path] = await obj.get_child([f"0:{p}" for p in path.split("/")])
        await nodes["ConditionName"].write_value(ua.Variant(name, ua.VariantType.String))
        await nodes["EnabledState"].write_value(ua.Variant(ua.LocalizedText("Enabled"), ua.VariantType.LocalizedText))
        await nodes["EnabledState/Id"].write_value(ua.Variant(True, ua.VariantType.Boolean))
        for acked in ("AckedState", "AckedState/Id"):  # not implemented yet: say so, not "unacknowledged"
            current = await nodes[acked].read_data_value(raise_on_bad_status=False)
            await nodes[acked].write_value(ua.DataValue(current.Value, StatusCode=_NO_DATA))
        self.nodes[condition_id] = nodes
        return nodes
