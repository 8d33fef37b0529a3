"""The condition instances behind the alarm events: a node at each event's ConditionId, with its
acknowledgement (issue 42).

Every alarm event names its condition (`ConditionId`, the event's `NodeId` field:
`<machine>/Notification/Messages/<quantity>`, or `.../FeedHeld`). A standard alarms-and-conditions
client reads that node and browses HasCondition from the source; before this it got BadNodeIdUnknown.
Each condition is an object of its event type (`MillsenseAlarmType`, an ExclusiveLevelAlarmType with the
alarm's HighLimit/LowLimit, or `MillsenseOffNormalAlarmType` for FeedHeld and the DAQ link) at that NodeId,
made at its first event, with HasCondition from the machine's Messages, and its state variables
written from each event it fires: ActiveState, AckedState, ConfirmedState (each with its Id), Retain,
Severity, LastSeverity, Message, Time, EventId, Comment, ClientUserId, ConditionName, ConditionClass,
Source, EnabledState (always enabled).

Acknowledge and Confirm (acknowledge.py, operators only): a condition that goes active is
unacknowledged and unconfirmed; Acknowledge of its last event's EventId makes it acknowledged,
Confirm then confirmed; each is one more event of the condition with the operator's comment. Nothing
else changes: an acknowledged alarm stays active until the daemon clears it, a held feed stays held
until the reset.
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Awaitable, Callable
from typing import Any

from asyncua import Node, ua
from asyncua.common.instantiate_util import instantiate

MAX_CONDITIONS = 64  # per machine: one per judged quantity and FeedHeld; bounded whatever a payload says

_STATES = ("ActiveState", "AckedState", "ConfirmedState")


class Condition:
    """One condition: its nodes and its state."""

    def __init__(self, nodes: dict[str, Node]) -> None:
        self.nodes = nodes
        self.active = False
        self.acked = True       # nothing to acknowledge before its first activation
        self.confirmed = True
        self.event_ids: list[bytes] = []  # of its last event (fired twice: Messages and Server)
        self.values: dict[str, Any] = {}
        self.when: dt.datetime | None = None


class ConditionNodes:
    """One machine's condition instances, by ConditionId."""

    def __init__(self, server: Any, alarm_type: Node | tuple[Node, Node], source: Node,
                 fire: Callable[[dict[str, Any], dt.datetime | None], Awaitable[list[bytes]]],
                 registry: dict[ua.NodeId, Any] | None = None, methods: dict[str, Any] | None = None, *,
                 is_discrete: Callable[[dict[str, Any]], bool] | None = None) -> None:
        """`alarm_type`: the limit alarms' type, or (it, the discrete alarms' type) chosen by `is_discrete`."""
        types = alarm_type if isinstance(alarm_type, tuple) else (alarm_type, alarm_type)
        self.server, self.alarm_type, self.discrete_type = server, types[0], types[1]
        self.source, self.fire = source, fire
        self.is_discrete = is_discrete or (lambda values: False)
        self.conditions: dict[ua.NodeId, Condition] = {}
        self.registry = registry if registry is not None else {}  # the server's ConditionId -> ConditionNodes
        self.methods = methods if methods is not None else {}    # Acknowledge, Confirm (acknowledge.bind)

    def state_fields(self, values: dict[str, Any], reactivated: bool = False) -> dict[str, Any]:
        """The event's values with the condition's acknowledgement states after it (a condition that goes
        active is unacknowledged and unconfirmed) and its Retain: active or unacknowledged."""
        condition = self.conditions.get(values.get("NodeId"))  # type: ignore[arg-type]
        active = bool(values.get("ActiveState/Id"))
        was_active = condition.active if condition is not None else False
        acked = condition.acked if condition is not None else True
        confirmed = condition.confirmed if condition is not None else True
        if active and (not was_active or reactivated):
            acked = confirmed = False
        # Part 9: retained (what ConditionRefresh replays, what an alarm list keeps) while active OR not yet
        # acknowledged: an overload that cleared in 0.2 s stays in the operator's list until someone acknowledges it.
        return {**values, **_state("AckedState", acked, "Acknowledged", "Unacknowledged"),
                **_state("ConfirmedState", confirmed, "Confirmed", "Unconfirmed"), "Retain": active or not acked}

    async def update(self, values: dict[str, Any], event_ids: list[bytes], when: dt.datetime | None) -> None:
        """Write one fired event's fields into its condition instance (made at its first event)."""
        condition_id = values.get("NodeId")
        if not isinstance(condition_id, ua.NodeId):
            return
        condition = self.conditions.get(condition_id)
        if condition is None:
            if len(self.conditions) >= MAX_CONDITIONS:
                return
            condition = await self._create(condition_id, str(values.get("ConditionName", "")),
                                           self.discrete_type if self.is_discrete(values) else self.alarm_type,
                                           limits=not self.is_discrete(values))
        previous = condition.values.get("Severity")
        condition.active = bool(values["ActiveState/Id"])
        condition.acked = bool(values["AckedState/Id"])
        condition.confirmed = bool(values["ConfirmedState/Id"])
        condition.event_ids, condition.values, condition.when = list(event_ids), dict(values), when
        severity = int(values.get("Severity", 0))
        writes: list[tuple[str, Any, ua.VariantType]] = [
            (f"{s}{suffix}", values[f"{s}{suffix}"], vt) for s in _STATES
            for suffix, vt in (("", ua.VariantType.LocalizedText), ("/Id", ua.VariantType.Boolean))]
        writes += [
            ("Retain", bool(values["Retain"]), ua.VariantType.Boolean),
            ("LastSeverity", int(previous if previous is not None else severity), ua.VariantType.UInt16),
            ("Severity", severity, ua.VariantType.UInt16),
            ("Message", values["Message"], ua.VariantType.LocalizedText),
            ("ConditionClassId", values["ConditionClassId"], ua.VariantType.NodeId),
            ("ConditionClassName", values["ConditionClassName"], ua.VariantType.LocalizedText),
            ("SourceNode", values["SourceNode"], ua.VariantType.NodeId),
            ("SourceName", values["SourceName"], ua.VariantType.String),
            ("Time", when or dt.datetime.now(dt.timezone.utc), ua.VariantType.DateTime),
            ("Comment", values.get("Comment") or ua.LocalizedText(""), ua.VariantType.LocalizedText),
            ("ClientUserId", values.get("ClientUserId") or "", ua.VariantType.String),
        ]
        if event_ids:
            writes.append(("EventId", event_ids[-1], ua.VariantType.ByteString))
        writes += [(name, float(values[name]), ua.VariantType.Double) for name in ("HighLimit", "LowLimit")
                   if values.get(name) is not None and name in condition.nodes]
        for name, value, vt in writes:
            await condition.nodes[name].write_value(ua.DataValue(ua.Variant(value, vt), SourceTimestamp=when))

    async def acknowledge(self, condition_id: ua.NodeId, event_id: bytes, comment: ua.LocalizedText, who: str, *,
                          confirm: bool) -> ua.StatusCode:
        """Acknowledge (or confirm) the condition's last event; one more event says so. Part 9's status codes."""
        condition = self.conditions.get(condition_id)
        if condition is None:
            return ua.StatusCode(ua.StatusCodes.BadNodeIdUnknown)
        if confirm and condition.confirmed:
            return ua.StatusCode(ua.StatusCodes.BadConditionBranchAlreadyConfirmed)
        if confirm and not condition.acked:
            return ua.StatusCode(ua.StatusCodes.BadInvalidState)  # acknowledged first, then confirmed
        if not confirm and condition.acked:
            return ua.StatusCode(ua.StatusCodes.BadConditionBranchAlreadyAcked)
        if event_id not in condition.event_ids:  # only the condition's last event: the client saw its state
            return ua.StatusCode(ua.StatusCodes.BadEventIdUnknown)
        if confirm:
            condition.confirmed = True
        else:
            condition.acked = True
        # the event says the new state (state_fields reads it from the condition) and who, with what comment
        values = {**condition.values, "Comment": comment, "ClientUserId": who}
        await self.fire(values, dt.datetime.now(dt.timezone.utc))
        return ua.StatusCode(ua.StatusCodes.Good)

    async def _create(self, condition_id: ua.NodeId, name: str, alarm_type: Node, *, limits: bool) -> Condition:
        (obj, *_) = await instantiate(self.source, alarm_type, nodeid=condition_id,
                                      bname=ua.QualifiedName(name, condition_id.NamespaceIndex),
                                      instantiate_optional=False)
        # Part 9: the source names its conditions by HasCondition (asyncua linked it by HasComponent too)
        await self.source.add_reference(obj.nodeid, ua.ObjectIds.HasCondition)
        # ConfirmedState is optional in AcknowledgeableConditionType: added, since Confirm is offered
        await _optional_state(obj, "ConfirmedState")
        nodes: dict[str, Node] = {}
        for path in ("ActiveState", "ActiveState/Id", "AckedState", "AckedState/Id", "ConfirmedState",
                     "ConfirmedState/Id", "EnabledState", "EnabledState/Id", "Retain", "Severity", "LastSeverity",
                     "Message", "ConditionClassId", "ConditionClassName", "ConditionName", "SourceNode", "SourceName",
                     "Time", "EventId", "Comment", "ClientUserId"):
            nodes[path] = await obj.get_child([f"0:{p}" for p in path.split("/")])
        await nodes["ConditionName"].write_value(ua.Variant(name, ua.VariantType.String))
        await nodes["EnabledState"].write_value(ua.Variant(ua.LocalizedText("Enabled"), ua.VariantType.LocalizedText))
        await nodes["EnabledState/Id"].write_value(ua.Variant(True, ua.VariantType.Boolean))
        if limits:  # LimitAlarmType's optional HighLimit and LowLimit: the alarm's limit, on its side
            for limit in ("HighLimit", "LowLimit"):
                nodes[limit] = await obj.add_property(ua.NodeId(f"{condition_id.Identifier}.{limit}",
                                                                condition_id.NamespaceIndex),
                                                      ua.QualifiedName(limit, 0), float("nan"), ua.VariantType.Double)
        callbacks = self.methods
        for method in await obj.get_children(refs=ua.ObjectIds.HasComponent, nodeclassmask=ua.NodeClass.Method):
            name = (await method.read_browse_name()).Name
            if name in callbacks:  # a client may call the instance's copy of Acknowledge instead of the type's
                self.server.link_method(method, callbacks[name])
        condition = Condition(nodes)
        self.conditions[condition_id] = condition
        self.registry[condition_id] = self
        return condition


def _state(name: str, value: bool, true_text: str, false_text: str) -> dict[str, Any]:
    return {name: ua.LocalizedText(true_text if value else false_text), f"{name}/Id": value}


async def _optional_state(obj: Node, name: str) -> None:
    """An optional TwoStateVariable of the condition's type, added to the instance (its Id below it)."""
    await instantiate(obj, Node(obj.session, ua.NodeId(ua.ObjectIds.TwoStateVariableType)),
                      nodeid=ua.NodeId(f"{obj.nodeid.Identifier}.{name}", obj.nodeid.NamespaceIndex),
                      bname=ua.QualifiedName(name, 0), instantiate_optional=False)
