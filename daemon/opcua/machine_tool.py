"""One machine as an OPC 40501 MachineToolType object under Objects/Machines (OPC 40001-1), issue 42.

Only with the companion specifications loaded (nodesets.py) and only for a machine whose
Identification the configuration gives (`[opcua]` manufacturer, serial_number, product_instance_uri:
mandatory in 40001-1, unknowable to millsense). Instantiated with the type's mandatory nodes only; of
its optional nodes, only those millsense fills are added. A mandatory node millsense cannot know (the
CNC's operation mode, the program's state machine, a tool's lock) reads BadNoData: never a made-up
value with a Good status. docs/opcua.md has the table of what is mapped, what is left empty and why.

    Objects/Machines/<machine>                      MachineToolType (MachineTool namespace, i=13)
      Identification/ Manufacturer SerialNumber ProductInstanceUri
      Monitoring/MachineTool/FeedOverride           the override the CNC applied (estimate feed_override_pct)
      Monitoring/Spindle/ Name IsRotating            SpindleMonitoringType: an estimate's spindle_rpm > 0; false
                                                    from a status when no revolution closed since the last one
      Production/ActiveProgram/Name                 the context's program number
      Equipment/Tools/T<n>/ ControlIdentifier1, ToolLife/ProcessCount, ToolLife/Wear   one per [tools.N]
                                                    and per tool number a process summary names
      millsense                                     Organizes → Objects/millsense/<machine>: every millsense value
"""

from __future__ import annotations

import datetime as dt
from typing import Any

import structlog
from asyncua import Node, Server, ua
from asyncua.common.instantiate_util import instantiate

from millsense.daemon.opcua import fields as F
from millsense.daemon.opcua.machine_nodes import percent_unit
from millsense.daemon.opcua.nodesets import DI_NS, MACHINE_TOOL_NS, MACHINERY_NS
from millsense.daemon.opcua.settings import Identification

log = structlog.get_logger("millsense.opcua")

# OPC 40501 NodeIds (its NodeIds.csv), in the MachineTool namespace
MACHINE_TOOL_TYPE = 13
SPINDLE_MONITORING_TYPE = 22
TOOL_LIST_TYPE = 44
TOOL_TYPE = 50
TOOL_LIFE_TYPE = 61
MACHINES_FOLDER = 1001        # Machinery's Objects/Machines (OPC 40001-1)
ANALOG_UNIT_RANGE_TYPE = 17570  # Part 8: FeedOverride's variable type
TOOL_MANAGEMENT_NUMBER_BASED = 0
INDICATION_NUMBER_OF_USAGES, INDICATION_OTHER = 2, 7
MAX_TOOLS = 256

_NO_DATA = ua.StatusCode(ua.StatusCodes.BadNoData)


def _source_time(payload: dict[str, Any]) -> dt.datetime | None:
    t = payload.get("t")
    if isinstance(t, (int, float)) and not isinstance(t, bool) and 0 < t < 1e11:
        return dt.datetime.fromtimestamp(t, dt.timezone.utc)
    return None


async def _unknown(node: Node) -> None:
    """A mandatory variable millsense cannot know, and the variables below it (a state's Id, a lock's reason):
    BadNoData, never an empty value with a Good status."""
    current = await node.read_data_value(raise_on_bad_status=False)
    await node.write_value(ua.DataValue(current.Value, StatusCode=_NO_DATA))
    for child in await node.get_children(nodeclassmask=ua.NodeClass.Variable):
        await _unknown(child)


class MachineToolInstance:
    """The MachineToolType object of one machine; `apply` writes the payloads that fit 40501 into it."""

    def __init__(self, server: Server, machine: str, ms: int) -> None:
        self.server, self.machine, self.ms = server, machine, ms
        self.mt = self.machinery = 0
        self.obj: Node | None = None
        self.nodes: dict[str, Node] = {}
        self.tools: dict[int, tuple[Node, Node]] = {}
        self.last: dict[str, Any] = {}
        self._tools_full_logged = False
        self._status_revolutions: int | None = None

    def _id(self, *path: str) -> ua.NodeId:
        return ua.NodeId("/".join((self.machine, "MachineTool") + path), self.ms)

    async def create(self, identification: Identification, tool_numbers: list[int], own: Node) -> MachineToolInstance:
        self.mt = await self.server.get_namespace_index(MACHINE_TOOL_NS)
        self.machinery = await self.server.get_namespace_index(MACHINERY_NS)
        mt = self.mt
        machines = self.server.get_node(ua.NodeId(MACHINES_FOLDER, self.machinery))
        (self.obj, *_) = await instantiate(machines, self.server.get_node(ua.NodeId(MACHINE_TOOL_TYPE, mt)),
                                           nodeid=self._id(), bname=ua.QualifiedName(self.machine, self.ms),
                                           dname=ua.LocalizedText(self.machine), instantiate_optional=False)
        di = await self.server.get_namespace_index(DI_NS)
        ident = await self.obj.get_child([f"{di}:Identification"])  # DI's browse name, as 40001-1 has it
        await (await ident.get_child([f"{di}:Manufacturer"])).write_value(
            ua.LocalizedText(identification.manufacturer))
        await (await ident.get_child([f"{di}:SerialNumber"])).write_value(identification.serial_number)
        await (await ident.get_child([f"{di}:ProductInstanceUri"])).write_value(identification.product_instance_uri)

        monitoring = await self.obj.get_child([f"{mt}:Monitoring"])
        machine_tool = await monitoring.get_child([f"{mt}:MachineTool"])
        await _unknown(await machine_tool.get_child([f"{mt}:OperationMode"]))
        (feed,) = [n for n in await instantiate(
            machine_tool, self.server.get_node(ua.NodeId(ANALOG_UNIT_RANGE_TYPE)), nodeid=self._id("FeedOverride"),
            bname=ua.QualifiedName("FeedOverride", mt), instantiate_optional=False) if n.nodeid == self._id("FeedOverride")]
        await feed.write_attribute(ua.AttributeIds.DataType, ua.DataValue(ua.Variant(ua.NodeId(ua.ObjectIds.Double))))
        await (await feed.get_child(["0:EngineeringUnits"])).write_value(
            ua.Variant(percent_unit(), ua.VariantType.ExtensionObject))
        await _unknown(await feed.get_child(["0:EURange"]))  # the CNC's override range: not known here
        await feed.write_value(ua.DataValue(ua.Variant(0.0, ua.VariantType.Double),
                                            StatusCode=ua.StatusCode(ua.StatusCodes.BadWaitingForInitialData)))
        self.nodes["FeedOverride"] = feed
        (spindle, *_) = await instantiate(monitoring, self.server.get_node(ua.NodeId(SPINDLE_MONITORING_TYPE, mt)),
                                          nodeid=self._id("Spindle"), bname=ua.QualifiedName("Spindle", self.ms),
                                          instantiate_optional=False)
        await (await spindle.get_child([f"{mt}:Name"])).write_value("Spindle")
        self.nodes["IsRotating"] = await spindle.get_child([f"{mt}:IsRotating"])
        await self.nodes["IsRotating"].write_value(ua.DataValue(ua.Variant(False, ua.VariantType.Boolean),
                                                   StatusCode=ua.StatusCode(ua.StatusCodes.BadWaitingForInitialData)))

        program = await self.obj.get_child([f"{mt}:Production", f"{mt}:ActiveProgram"])
        self.nodes["ProgramName"] = await program.get_child([f"{mt}:Name"])
        await self.nodes["ProgramName"].write_value(ua.DataValue(ua.Variant("", ua.VariantType.String),
                                                    StatusCode=ua.StatusCode(ua.StatusCodes.BadWaitingForInitialData)))
        await _unknown(await program.get_child(["0:NumberInList"]))
        await _unknown(await program.get_child([f"{mt}:State", "0:CurrentState"]))

        equipment = await self.obj.get_child([f"{mt}:Equipment"])
        (self.tools_folder, *_) = await instantiate(
            equipment, self.server.get_node(ua.NodeId(TOOL_LIST_TYPE, mt)), nodeid=self._id("Equipment", "Tools"),
            bname=ua.QualifiedName("Tools", mt), instantiate_optional=False)
        for number in tool_numbers[:MAX_TOOLS]:
            await self._tool(number)
        # millsense's own values, in its namespace, one reference away
        await self.obj.add_reference(own.nodeid, ua.ObjectIds.Organizes)
        log.info("opcua.machine_tool_added", machine=self.machine, product_instance_uri=identification.product_instance_uri,
                 tools=len(self.tools))
        return self

    async def apply(self, kind: str, payload: dict[str, Any]) -> None:
        when = _source_time(payload)
        if kind == "estimate":
            rpm = F.convert(payload.get("spindle_rpm"), F.DOUBLE) if "spindle_rpm" in payload else F.ABSENT
            if rpm is not F.ABSENT:
                await self._write("IsRotating", None if rpm is None else rpm > 0.0, ua.VariantType.Boolean, when)
            if "feed_override_pct" in payload:
                await self._write("FeedOverride", F.convert(payload.get("feed_override_pct"), F.DOUBLE),
                                  ua.VariantType.Double, when)
            if "program" in payload:
                program = F.convert(payload.get("program"), F.INT64)
                await self._write("ProgramName", None if program is None else str(program), ua.VariantType.String, when)
        elif kind == "status":
            await self._rotation_from_status(payload, when)
        elif kind == "process":
            await self._tool_life(payload, when)

    async def _rotation_from_status(self, status: dict[str, Any], when: dt.datetime | None) -> None:
        """A stopped spindle closes no revolution, so no estimate says it stopped: the status (once a second)
        does. No revolution since the last status: not rotating. The DAQ's link down: not known."""
        revolutions = F.convert(status.get("revolutions"), F.INT64)
        previous, self._status_revolutions = self._status_revolutions, revolutions
        if status.get("daq_link") == "down":
            await self._write("IsRotating", None, ua.VariantType.Boolean, when)
        elif revolutions is not None and revolutions == previous:
            await self._write("IsRotating", False, ua.VariantType.Boolean, when)

    async def gone(self) -> None:
        """The daemon's liveliness token went: nothing it said holds any more."""
        self._status_revolutions = None
        await self._write("IsRotating", None, ua.VariantType.Boolean, None)

    async def _write(self, name: str, value: Any, vt: ua.VariantType, when: dt.datetime | None) -> None:
        if name in self.last and self.last[name] == value:
            return  # unchanged: no write, no data-change notification
        previous = self.last.get(name)
        self.last[name] = value
        if value is None:  # not known this revolution (no context, an invalid revolution): say so
            kept = previous if previous is not None else (False if vt == ua.VariantType.Boolean else
                                                         0.0 if vt == ua.VariantType.Double else "")
            dv = ua.DataValue(ua.Variant(kept, vt), StatusCode=_NO_DATA, SourceTimestamp=when)
        else:
            dv = ua.DataValue(ua.Variant(value, vt), SourceTimestamp=when)
        await self.nodes[name].write_value(dv)

    async def _tool_life(self, payload: dict[str, Any], when: dt.datetime | None) -> None:
        tool = F.convert(payload.get("tool"), F.INT64)
        if tool is None or tool < 0:
            return
        nodes = await self._tool(tool)
        if nodes is None:
            return
        count = F.convert(payload.get("tool_processes"), F.INT64)
        wear = F.convert(payload.get("tool_wear_pct"), F.DOUBLE)
        if count is not None:
            await nodes[0].write_value(ua.DataValue(ua.Variant(count, ua.VariantType.Int64), SourceTimestamp=when))
        if wear is not None:
            await nodes[1].write_value(ua.DataValue(ua.Variant(wear, ua.VariantType.Double), SourceTimestamp=when))

    async def _tool(self, number: int) -> tuple[Node, Node] | None:
        if number in self.tools:
            return self.tools[number]
        if len(self.tools) >= MAX_TOOLS:
            if not self._tools_full_logged:
                self._tools_full_logged = True
                log.warning("opcua.tools_full", machine=self.machine, max_tools=MAX_TOOLS)
            return None
        mt, name = self.mt, f"T{number}"
        (tool, *_) = await instantiate(self.tools_folder, self.server.get_node(ua.NodeId(TOOL_TYPE, mt)),
                                       nodeid=self._id("Equipment", "Tools", name), bname=ua.QualifiedName(name, self.ms),
                                       instantiate_optional=False)
        await (await tool.get_child([f"{mt}:ControlIdentifier1"])).write_value(ua.Variant(number, ua.VariantType.UInt32))
        interpretation = await tool.get_child([f"{mt}:ControlIdentifierInterpretation"])
        await interpretation.write_value(ua.Variant(TOOL_MANAGEMENT_NUMBER_BASED, ua.VariantType.Int32))
        await _unknown(await tool.get_child([f"{mt}:Locked"]))  # the CNC's tool management knows it, not millsense
        life = await tool.add_object(self._id("Equipment", "Tools", name, "ToolLife"), ua.QualifiedName("ToolLife", mt))
        count = await self._life_entry(life, name, "ProcessCount", ua.VariantType.Int64, INDICATION_NUMBER_OF_USAGES, None)
        wear = await self._life_entry(life, name, "Wear", ua.VariantType.Double, INDICATION_OTHER, percent_unit())
        self.tools[number] = (count, wear)
        return count, wear

    async def _life_entry(self, life: Node, tool: str, entry: str, vt: ua.VariantType, indication: int,
                          unit: ua.EUInformation | None) -> Node:
        mt = self.mt
        nodeid = self._id("Equipment", "Tools", tool, "ToolLife", entry)
        (node, *_) = await instantiate(life, self.server.get_node(ua.NodeId(TOOL_LIFE_TYPE, mt)), nodeid=nodeid,
                                       bname=ua.QualifiedName(entry, self.ms), instantiate_optional=False)
        await node.write_value(ua.DataValue(ua.Variant(0 if vt == ua.VariantType.Int64 else 0.0, vt),
                                            StatusCode=ua.StatusCode(ua.StatusCodes.BadWaitingForInitialData)))
        await (await node.get_child([f"{mt}:Indication"])).write_value(ua.Variant(indication, ua.VariantType.Int32))
        await (await node.get_child([f"{mt}:IsCountingUp"])).write_value(True)
        units = await node.get_child([f"{mt}:EngineeringUnits"])
        if unit is not None:
            await units.write_value(ua.Variant(unit, ua.VariantType.ExtensionObject))
        else:
            await _unknown(units)  # a count has no unit; the mandatory property says so rather than a made-up one
        return node
