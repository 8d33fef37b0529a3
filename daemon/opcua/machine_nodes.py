"""One machine in the OPC UA address space: its variables, its tool life, its alarm events.

Under `Objects/millsense/<machine>` (namespace `urn:millsense:opcua`):

    <machine>            object; an event notifier (alarm events of this machine)
      alive              Boolean: its liveliness token is present
      Spindle/ Safety/ Process/ Afc/   the variables of `fields.FIELDS`
      Notification/Messages            (OPC 40501 browse names) the source of the alarm events
      Equipment/Tools/<tool>/ToolLife/ (OPC 40501 browse names) ProcessCount and Wear per tool number

Alarm changes are fired as events of `MillsenseAlarmType`, a subtype of ExclusiveLevelAlarmType (the
alarm's limit its HighLimit or LowLimit), or for the discrete conditions (FeedHeld, the DAQ link) of
`MillsenseOffNormalAlarmType` (OffNormalAlarmType), one condition per judged quantity
(`ConditionName` = `torque_nm`, `force_n`, `daq`, ...):
`ActiveState/Id` true from the alarm until its `clear`. Alarm changes this server missed (it
connected late, or its link dropped) are fired from the next `status` (publish/alarm_state.py).
The held feed is one more condition of the machine, `FeedHeld` (feed_held.py): active from the trip
until the daemon says the feed is released, whatever its alarms do meanwhile.
docs/opcua.md says what is and is not implemented of the condition model.
"""

from __future__ import annotations

import copy
import datetime as dt
from typing import Any

import structlog
from asyncua import Node, Server, ua

from millsense.daemon.opcua import fields as F
from millsense.daemon.opcua.conditions import ConditionNodes
from millsense.daemon.opcua.feed_held import NAME as FEED_HELD
from millsense.daemon.opcua.feed_held import Change, FeedHeldTrack
from millsense.daemon.opcua.flapping import EventLimiter, Held
from millsense.daemon.publish.alarm_state import ShownAlarms, catch_up, caught_up

log = structlog.get_logger("millsense.opcua")

MILLSENSE_NS = "urn:millsense:opcua"
MACHINE_TOOL_NS = "http://opcfoundation.org/UA/MachineTool/"
# OPC 40501 NodeIds (its NodeIds.csv) used as condition classes; the spec's nodeset is not loaded (docs/opcua.md).
MT_TOOL_BREAKAGE_CLASS = 57      # ToolBreakageConditionClassType
MT_PROCESS_IRREGULARITY_CLASS = 55  # ProcessIrregularityConditionClassType
MAX_TOOLS = 256  # tool numbers shown per machine; memory stays bounded whatever a payload says

SEVERITY = {"crash": 1000, "tool_breakage": 900, "overload": 800, "daq_lost": 700, "envelope_high": 600,
            "envelope_low": 600, "expected_high": 600, "expected_low": 600, "warning": 400, "wear": 300, "clear": 100}

ALARM_FIELDS = [("Level", ua.VariantType.String), ("Quantity", ua.VariantType.String),
                ("Value", ua.VariantType.Double), ("Limit", ua.VariantType.Double),
                ("Interlock", ua.VariantType.String), ("Revolution", ua.VariantType.Int64),
                ("ProcessKey", ua.VariantType.String)]

_DEFAULTS = {F.DOUBLE: 0.0, F.INT64: 0, F.BOOL: False, F.STRING: ""}


def _vt(ua_type: str) -> ua.VariantType:
    return getattr(ua.VariantType, ua_type)


def _source_time(payload: dict[str, Any]) -> dt.datetime | None:
    t = payload.get("t")
    if isinstance(t, (int, float)) and not isinstance(t, bool) and 0 < t < 1e11:
        return dt.datetime.fromtimestamp(t, dt.timezone.utc)
    return None


def percent_unit() -> ua.EUInformation:
    """Percent as OPC UA's EUInformation: UNECE code P1, its UnitId by Part 8's rule (the code's bytes)."""
    unit_id = int.from_bytes(b"P1", "big")
    return ua.EUInformation(NamespaceUri="http://www.opcfoundation.org/UA/units/un/cefact", UnitId=unit_id,
                            DisplayName=ua.LocalizedText("%"), Description=ua.LocalizedText("percent"))


class Namespaces:
    def __init__(self, ms: int, mt: int, alarm_type: Any, server_events: Any, discrete_type: Any = None,
                 discrete_events: Any = None) -> None:
        self.ms, self.mt, self.alarm_type, self.discrete_type = ms, mt, alarm_type, discrete_type
        self.server_events = server_events  # one generator on the Server object, shared by every machine
        self.server_template = copy.deepcopy(server_events.event)
        self.discrete_events = discrete_events  # the same for the discrete alarms' type
        self.discrete_template = copy.deepcopy(discrete_events.event) if discrete_events is not None else None
        self.conditions: dict[ua.NodeId, Any] = {}  # every machine's ConditionId -> its ConditionNodes (Acknowledge)
        self.ack_methods: dict[str, Any] = {}  # Acknowledge, Confirm callbacks (acknowledge.bind)

    @classmethod
    async def register(cls, server: Server) -> Namespaces:
        ms = await server.register_namespace(MILLSENSE_NS)
        mt = await server.register_namespace(MACHINE_TOOL_NS)
        # Part 9's types (issue 42): a judged quantity's condition is a limit alarm, its levels the exclusive
        # states of ExclusiveLevelAlarmType; the held feed and the DAQ link are discrete, OffNormalAlarmType.
        alarm_type = await server.create_custom_event_type(ms, "MillsenseAlarmType",
                                                           ua.ObjectIds.ExclusiveLevelAlarmType, ALARM_FIELDS)
        discrete_type = await server.create_custom_event_type(ms, "MillsenseOffNormalAlarmType",
                                                              ua.ObjectIds.OffNormalAlarmType, ALARM_FIELDS)
        return cls(ms, mt, alarm_type, await server.get_event_generator(alarm_type, ua.ObjectIds.Server),
                   discrete_type, await server.get_event_generator(discrete_type, ua.ObjectIds.Server))


DISCRETE_QUANTITIES = (FEED_HELD, "daq")  # conditions that are on or off, no value beside a limit
LOW_LEVELS = ("envelope_low", "expected_low")  # a value under its limit: LowLimit; every other level: HighLimit


def is_discrete(values: dict[str, Any]) -> bool:
    """Is this condition (by its quantity, fixed for its ConditionId) an OffNormalAlarmType?"""
    return values.get("Quantity") in DISCRETE_QUANTITIES


def condition_class(level: str, quantity: str, mt: int) -> tuple[ua.NodeId, str]:
    """The condition class an alarm level belongs to: 40501's where one fits, else Part 9's."""
    if level == "tool_breakage":
        return ua.NodeId(MT_TOOL_BREAKAGE_CLASS, mt), "ToolBreakageConditionClassType"
    if level in ("envelope_high", "envelope_low", "expected_high", "expected_low"):
        return ua.NodeId(MT_PROCESS_IRREGULARITY_CLASS, mt), "ProcessIrregularityConditionClassType"
    if level == "wear":
        return ua.NodeId(ua.ObjectIds.MaintenanceConditionClassType), "MaintenanceConditionClassType"
    if level == "daq_lost" or quantity == "daq":
        return ua.NodeId(ua.ObjectIds.SystemConditionClassType), "SystemConditionClassType"
    return ua.NodeId(ua.ObjectIds.ProcessConditionClassType), "ProcessConditionClassType"


async def add_notifier_child(parent: Any, nodeid: ua.NodeId, name: ua.QualifiedName) -> Any:
    """An object whose one reference from `parent` is HasNotifier (the event-notifier hierarchy).

    HasNotifier is itself a hierarchical reference, so a client's Browse and browse paths find the object
    through it; asyncua's `add_object` would add a folder's Organizes beside it, and every client then
    listed each machine twice under `Objects/millsense` (issue 39).
    """
    item = ua.AddNodesItem()
    item.RequestedNewNodeId = nodeid
    item.BrowseName = name
    item.ParentNodeId = parent.nodeid
    item.ReferenceTypeId = ua.NodeId(ua.ObjectIds.HasNotifier)
    item.NodeClass = ua.NodeClass.Object
    item.TypeDefinition = ua.NodeId(ua.ObjectIds.BaseObjectType)
    attrs = ua.ObjectAttributes()
    attrs.DisplayName = ua.LocalizedText(name.Name)
    attrs.Description = ua.LocalizedText(name.Name)
    item.NodeAttributes = attrs
    (result,) = await parent.session.add_nodes([item])
    result.StatusCode.check()
    return Node(parent.session, result.AddedNodeId)


class MachineNodes:
    """The nodes of one machine; `apply` writes a payload into them."""

    def __init__(self, server: Server, ns: Namespaces, machine: str) -> None:
        self.server, self.ns, self.machine = server, ns, machine
        self.obj: Any = None
        self.folders: dict[str, Any] = {}
        self.variables: dict[tuple[str, str], Any] = {}  # (folder, name) -> node
        self.last: dict[tuple[str, str], Any] = {}       # last value written, to skip unchanged writes
        self.tools: dict[int, tuple[Any, Any]] = {}      # tool number -> (ProcessCount, Wear)
        self.shown = ShownAlarms()                       # the alarm changes fired (active ones by quantity)
        self.feed_held = FeedHeldTrack(SEVERITY)         # the FeedHeld condition's state (feed_held.py)
        self.alive_node: Any = None
        self.messages: Any = None
        self.tools_folder: Any = None
        self.events: Any = None
        self.event_template: Any = None
        self.conditions: Any = None                      # the condition instances (conditions.py)
        self.limiter = EventLimiter()                    # a flapping condition's events (flapping.py)
        self.pending: dict[Any, Held] = {}               # ConditionId -> its newest event held back
        self.events_held = 0                             # alarm events held back, since the server started
        self.held_node: Any = None
        self._tools_full_logged = False

    def _id(self, *parts: str) -> ua.NodeId:
        return ua.NodeId("/".join((self.machine, *parts)), self.ns.ms)

    async def create(self, parent: Any) -> MachineNodes:
        ms, mt = self.ns.ms, self.ns.mt
        self.obj = await add_notifier_child(parent, self._id(), ua.QualifiedName(self.machine, ms))
        await self.obj.set_event_notifier([ua.EventNotifier.SubscribeToEvents])
        self.alive_node = await self.obj.add_variable(self._id("alive"), ua.QualifiedName("alive", ms), False,
                                                      ua.VariantType.Boolean)
        self.held_node = await self.obj.add_variable(self._id("events_held"), ua.QualifiedName("events_held", ms), 0,
                                                     ua.VariantType.Int64)
        for folder in dict.fromkeys(f.folder for f in F.FIELDS):
            if folder not in F.OPTIONAL_FOLDERS:
                await self._folder(folder)
        notification = await self.obj.add_object(self._id("Notification"), ua.QualifiedName("Notification", mt))
        self.messages = await notification.add_object(self._id("Notification", "Messages"),
                                                      ua.QualifiedName("Messages", mt))
        await self.messages.set_event_notifier([ua.EventNotifier.SubscribeToEvents])
        await self.obj.add_reference(self.messages.nodeid, ua.ObjectIds.HasNotifier)
        equipment = await self.obj.add_object(self._id("Equipment"), ua.QualifiedName("Equipment", mt))
        self.tools_folder = await equipment.add_folder(self._id("Equipment", "Tools"), ua.QualifiedName("Tools", mt))
        self.events = await self.server.get_event_generator(self.ns.alarm_type, self.messages)
        self.event_template = copy.deepcopy(self.events.event)
        self.discrete_events = await self.server.get_event_generator(self.ns.discrete_type, self.messages)
        self.discrete_template = copy.deepcopy(self.discrete_events.event)
        types = (self.ns.alarm_type, self.ns.discrete_type)
        self.conditions = ConditionNodes(self.server, types, self.messages, self._trigger,
                                         self.ns.conditions, self.ns.ack_methods, is_discrete=is_discrete)
        return self

    async def _folder(self, name: str) -> Any:
        if name not in self.folders:
            self.folders[name] = await self.obj.add_folder(self._id(name), ua.QualifiedName(name, self.ns.ms))
            for f in F.FIELDS:
                if f.folder == name:
                    node = await self.folders[name].add_variable(
                        self._id(name, f.name), ua.QualifiedName(f.name, self.ns.ms), _DEFAULTS[f.ua_type], _vt(f.ua_type))
                    # The initial value is a placeholder: nothing received yet.
                    await node.write_value(ua.DataValue(ua.Variant(_DEFAULTS[f.ua_type], _vt(f.ua_type)),
                                                        StatusCode=ua.StatusCode(ua.StatusCodes.BadWaitingForInitialData)))
                    await node.write_attribute(ua.AttributeIds.Description,
                                               ua.DataValue(ua.Variant(ua.LocalizedText(f.description))))
                    self.variables[(name, f.name)] = node
        return self.folders[name]

    async def set_alive(self, alive: bool) -> None:
        await self.alive_node.write_value(ua.DataValue(ua.Variant(alive, ua.VariantType.Boolean)))

    async def apply(self, kind: str, payload: dict[str, Any]) -> None:
        when = _source_time(payload)
        for f in F.fields_of(kind):
            value = F.value_at(payload, f)
            if value is F.ABSENT:
                continue
            if f.folder in F.OPTIONAL_FOLDERS and f.folder not in self.folders:
                if value is None:
                    continue  # an Afc folder only for a daemon that has AFC
                await self._folder(f.folder)
            await self._write(f, value, when)
        if kind == "alarm":
            if self.shown.is_new(payload):
                await self._fire_alarm(payload)
            await self._fire_feed_held(self.feed_held.on_alarm(payload))
        elif kind == "status":
            await self._catch_up(payload)
            await self._fire_feed_held(self.feed_held.on_status(payload))
        elif kind == "process":
            await self._tool_life(payload)

    async def _write(self, f: F.Field, value: Any, when: dt.datetime | None) -> None:
        key = (f.folder, f.name)
        previous = self.last.get(key, F.ABSENT)
        if value == previous and type(value) is type(previous) and f.kind in F.COALESCED_KINDS:
            return  # unchanged: no write, no data-change notification
        self.last[key] = value
        node = self.variables[key]
        if value is None:
            # Null = could not be estimated: say so, rather than leave a stale number looking fresh.
            kept = previous if previous not in (None, F.ABSENT) else _DEFAULTS[f.ua_type]
            dv = ua.DataValue(ua.Variant(kept, _vt(f.ua_type)), StatusCode=ua.StatusCode(ua.StatusCodes.BadNoData),
                              SourceTimestamp=when)
        else:
            dv = ua.DataValue(ua.Variant(value, _vt(f.ua_type)), SourceTimestamp=when)
        await node.write_value(dv)

    async def _catch_up(self, status: dict[str, Any]) -> None:
        """Fire the alarm changes this server missed (it connected late, or its link blinked): the status
        says which alarms are active now (alarm_state.py)."""
        for alarm in catch_up(self.shown, status):
            await self._fire_alarm(alarm)
        caught_up(self.shown, status)

    async def _fire_alarm(self, payload: dict[str, Any]) -> None:
        level = payload.get("level") if isinstance(payload.get("level"), str) else "unknown"
        quantity = payload.get("quantity") if isinstance(payload.get("quantity"), str) else "unknown"
        had = self.shown.active.get(str(payload.get("quantity")))
        was = had.get("level") if had is not None else None
        self.shown.shown(payload)
        active = level != "clear"
        shown = level if active else (was or "clear")
        class_id, class_name = condition_class(shown, quantity, self.ns.mt)
        value = F.convert(payload.get("value"), F.DOUBLE)
        limit = F.convert(payload.get("limit"), F.DOUBLE)
        hold = payload.get("interlock") if isinstance(payload.get("interlock"), str) else ""
        text = f"{self.machine}: {level} {quantity}"
        if active:
            if value is not None:
                text += f" {value:g}" + (f" (limit {limit:g})" if limit is not None else "")
        else:  # a clear says what it ends, not its value beside the limit (issue 36, finding 7)
            said = ([f"was {was}"] if was else []) + ([f"limit {limit:g}"] if limit is not None else [])
            text += f" ({', '.join(said)})" if said else ""
        if hold:
            text += f"; {hold}"
        rev = F.convert(payload.get("rev"), F.INT64)
        limits = {}
        if limit is not None and quantity not in DISCRETE_QUANTITIES:  # LimitAlarmType's HighLimit or LowLimit
            limits = {"LowLimit" if shown in LOW_LEVELS else "HighLimit": limit}
        values = {
            "Message": ua.LocalizedText(text),
            "Severity": SEVERITY.get(level, 500),
            "SourceName": self.machine,
            "SourceNode": self.messages.nodeid,
            # ConditionId: one condition per judged quantity of this machine (no instance node: docs/opcua.md).
            "NodeId": self._id("Notification", "Messages", quantity),
            "ConditionName": quantity,
            "ConditionClassId": class_id,
            "ConditionClassName": ua.LocalizedText(class_name),
            "ActiveState": ua.LocalizedText("Active" if active else "Inactive"),
            "ActiveState/Id": active,
            "Retain": active,
            "Level": level, "Quantity": quantity, "Interlock": hold,
            "Value": value if value is not None else float("nan"),
            "Limit": limit if limit is not None else float("nan"),
            "Revolution": rev if rev is not None else -1,
            "ProcessKey": "/".join(str(payload.get(k)) for k in ("program", "tool", "operation"))
            if payload.get("process") is not None else "",
            **limits,
        }
        await self._limited(values, _source_time(payload))

    async def _limited(self, values: dict[str, Any], when: dt.datetime | None) -> None:
        """Fire an alarm event, or hold it back while its condition flaps (flapping.py): the newest waits."""
        key = values["NodeId"]
        held = self.pending.pop(key, None)
        activated = held.activated if held is not None else False
        if self.limiter.allow(key):
            await self._trigger(values, when, reactivated=activated)
            return
        fired = self.conditions.conditions.get(key)
        before = bool(held.values["ActiveState/Id"]) if held is not None else (fired is not None and fired.active)
        activated = activated or (bool(values["ActiveState/Id"]) and not before)
        self.pending[key] = Held(values, when, activated)
        self.events_held += 1
        await self.held_node.write_value(ua.DataValue(ua.Variant(self.events_held, ua.VariantType.Int64)))
        if held is None:
            log.warning("opcua.events_held", machine=self.machine, condition=str(values.get("ConditionName")),
                        events_held=self.events_held, detail="the condition flaps: its newest state is fired when its "
                        "rate allows, the events between are dropped")

    async def flush(self) -> None:
        """Fire each held-back condition's newest event whose rate allows it now (the server's loop calls this)."""
        for key, held in list(self.pending.items()):
            if self.limiter.allow(key):
                del self.pending[key]
                await self._trigger(held.values, held.when, reactivated=held.activated)

    async def _fire_feed_held(self, change: Change | None) -> None:
        """The FeedHeld condition's event for one transition (None: nothing changed)."""
        if change is None:
            return
        when = _source_time({"t": change.since if change.active else change.t})
        values = {
            "Message": ua.LocalizedText(change.message(self.machine)),
            "Severity": change.severity,
            "SourceName": self.machine,
            "SourceNode": self.messages.nodeid,
            "NodeId": self._id("Notification", "Messages", FEED_HELD),  # its ConditionId: one per machine
            "ConditionName": FEED_HELD,
            "ConditionClassId": ua.NodeId(ua.ObjectIds.ProcessConditionClassType),
            "ConditionClassName": ua.LocalizedText("ProcessConditionClassType"),
            "ActiveState": ua.LocalizedText("Active" if change.active else "Inactive"),
            "ActiveState/Id": change.active,
            "Retain": change.active,
            "Level": "feed_hold" if change.active else "clear", "Quantity": FEED_HELD,
            "Interlock": "feed_hold" if change.active else "",
            "Value": float("nan"), "Limit": float("nan"), "Revolution": -1, "ProcessKey": "",
        }
        log.info("opcua.feed_held", machine=self.machine, active=change.active, reason=change.reason)
        await self._trigger(values, when)

    async def _trigger(self, values: dict[str, Any], when: dt.datetime | None, *, reactivated: bool = False
                       ) -> list[bytes]:
        """Fire one event of a condition; returns its EventIds (one per copy). `reactivated`: a held-back event
        between this one and the last fired made the condition active again (flapping.py)."""
        values = self.conditions.state_fields(values, reactivated)  # AckedState, ConfirmedState, Retain
        event_ids: list[bytes] = []
        # The machine's Messages (OPC 40501's notifier) first, the Server object last: asyncua keeps the last
        # copy of a retained condition for ConditionRefresh, and plant alarm clients subscribe to Server.
        if is_discrete(values):
            copies = ((self.discrete_events, self.discrete_template), (self.ns.discrete_events, self.ns.discrete_template))
        else:
            copies = ((self.events, self.event_template), (self.ns.server_events, self.ns.server_template))
        for generator, template in copies:
            event = copy.deepcopy(template)  # asyncua keeps the object of a retained event: one each
            for name, v in values.items():
                setattr(event, name, v)
            generator.event = event
            await generator.trigger(time_attr=when)
            event_ids.append(event.EventId.Value if isinstance(event.EventId, ua.Variant) else event.EventId)
        # the condition instance at the event's ConditionId; after the events, and never in their way: a node
        # that cannot be written costs a log line, not an event
        try:
            await self.conditions.update(values, event_ids, when)
        except Exception as exc:  # noqa: BLE001
            log.warning("opcua.condition_node_error", machine=self.machine, condition=str(values.get("ConditionName")),
                        error=f"{type(exc).__name__}: {exc}")
        return event_ids

    async def _tool_life(self, payload: dict[str, Any]) -> None:
        tool = F.convert(payload.get("tool"), F.INT64)
        if tool is None or tool < 0:
            return
        count = F.convert(payload.get("tool_processes"), F.INT64)
        wear = F.convert(payload.get("tool_wear_pct"), F.DOUBLE)
        if count is None and wear is None:
            return
        nodes = await self._tool(tool)
        if nodes is None:
            return
        when = _source_time(payload)
        if count is not None:
            await nodes[0].write_value(ua.DataValue(ua.Variant(count, ua.VariantType.Int64), SourceTimestamp=when))
        if wear is not None:
            await nodes[1].write_value(ua.DataValue(ua.Variant(wear, ua.VariantType.Double), SourceTimestamp=when))

    async def _tool(self, tool: int) -> tuple[Any, Any] | None:
        if tool in self.tools:
            return self.tools[tool]
        if len(self.tools) >= MAX_TOOLS:
            if not self._tools_full_logged:
                self._tools_full_logged = True
                log.warning("opcua.tools_full", machine=self.machine, max_tools=MAX_TOOLS)
            return None
        ms, mt = self.ns.ms, self.ns.mt
        name = f"T{tool}"
        obj = await self.tools_folder.add_object(self._id("Equipment", "Tools", name), ua.QualifiedName(name, ms))
        # 40501 BaseToolType: Identifier and Name belong to the CNC's tool management; only the number is ours.
        await obj.add_property(self._id("Equipment", "Tools", name, "ControlIdentifier1"),
                               ua.QualifiedName("ControlIdentifier1", mt), tool, ua.VariantType.UInt32)
        life = await obj.add_folder(self._id("Equipment", "Tools", name, "ToolLife"), ua.QualifiedName("ToolLife", mt))
        count = await self._life_entry(life, name, "ProcessCount", 0, ua.VariantType.Int64, indication=2, unit="")
        wear = await self._life_entry(life, name, "Wear", 0.0, ua.VariantType.Double, indication=7, unit="%")
        self.tools[tool] = (count, wear)
        return count, wear

    async def _life_entry(self, life: Any, tool_name: str, entry: str, initial: Any, vt: ua.VariantType, *,
                          indication: int, unit: str) -> Any:
        """A ToolLifeType-shaped entry: the value, 40501's Indication (an enum index) and IsCountingUp."""
        ms, mt = self.ns.ms, self.ns.mt
        base = ("Equipment", "Tools", tool_name, "ToolLife", entry)
        node = await life.add_variable(self._id(*base), ua.QualifiedName(entry, ms), initial, vt)
        # ToolLifeIndication: 2 = NumberOfUsages, 7 = Other (OPC 40501's enumeration).
        await node.add_property(self._id(*base, "Indication"), ua.QualifiedName("Indication", mt), indication,
                                ua.VariantType.Int32)
        await node.add_property(self._id(*base, "IsCountingUp"), ua.QualifiedName("IsCountingUp", mt), True,
                                ua.VariantType.Boolean)
        if unit == "%":
            await node.add_property(self._id(*base, "EngineeringUnits"), ua.QualifiedName("EngineeringUnits", mt),
                                    percent_unit(), ua.VariantType.ExtensionObject)
        return node
