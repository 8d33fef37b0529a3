"""An event filter's where clause evaluated as OPC UA says, for asyncua 2.1.0's server (issue 42).

A standard alarms client that watches only active conditions subscribes with the where clause
`OfType(AlarmConditionType) AND ActiveState/Id = true`. asyncua 2.1.0's `WhereClauseEvaluator`
(asyncua/server/monitored_item_service.py) gives such a client nothing at all:

- `OfType` matches the event's exact type (Part 4, 7.7.3, Table 119: that type *or a subtype*); every
  millsense alarm is a subtype (MillsenseAlarmType, MillsenseOffNormalAlarmType);
- an operand's browse path is read by its first name only: `ActiveState/Id` reads `ActiveState`, a
  LocalizedText, never equal to true; a field the event lacks raises (and the event is dropped) where
  Part 4 says it is NULL; an operand with no browse path (the ConditionId) reads the event *type's* attribute;
- the where clause filters ConditionRefresh's RefreshStart and RefreshEnd too, which Part 9 (5.5.7) says
  ignore the event filter, so a filtering client cannot tell where a refresh ends.

`ConformingEvaluator` overrides those three, nothing else; the operators asyncua lacks (Like, Cast, ...)
stay as it has them. asyncua makes one evaluator per event monitored item, by the module-level name
`WhereClauseEvaluator` of that module, with no way to pass another: `install()` rebinds that one name,
once per process, and only on the asyncua version this was written and tested for
(`FOR_ASYNCUA`). On any other version it patches nothing, logs `opcua.where_clause_unpatched`, and the
server runs with asyncua's own evaluation (docs/opcua.md says what a client then gets).
"""

from __future__ import annotations

from importlib import metadata
from typing import Any

import structlog
from asyncua import ua
from asyncua.server import monitored_item_service

log = structlog.get_logger("millsense.opcua")

FOR_ASYNCUA = "2.1.0"
# another asyncua may lack the name: then nothing is subclassed for real, and install() refuses anyway
_ORIGINAL: Any = getattr(monitored_item_service, "WhereClauseEvaluator", object)
# Part 9, 5.5.7: "the three special EventTypes ... ignore the Event content filtering ... and will always be provided"
_NEVER_FILTERED = frozenset(ua.NodeId(i) for i in (ua.ObjectIds.RefreshStartEventType, ua.ObjectIds.RefreshEndEventType,
                                                    ua.ObjectIds.RefreshRequiredEventType))
_HAS_SUBTYPE = ua.NodeId(ua.ObjectIds.HasSubtype)
_MAX_TYPE_DEPTH = 64  # a type hierarchy with a loop in it ends here instead of hanging the server's loop


class ConformingEvaluator(_ORIGINAL):  # type: ignore[misc]
    """asyncua's evaluator with Part 4's OfType, full browse paths, and Part 9's unfiltered refresh events."""

    def eval(self, event: Any) -> bool:
        if getattr(event, "EventType", None) in _NEVER_FILTERED:
            return True
        return bool(super().eval(event))

    def _eval_el(self, index: int, event: Any) -> Any:
        el = self.elements[index]
        if el.FilterOperator == ua.FilterOperator.OfType:
            return self._is_of_type(getattr(event, "EventType", None), self._eval_op(el.FilterOperands[0], event))
        return super()._eval_el(index, event)

    def _eval_op(self, op: Any, event: Any) -> Any:
        if isinstance(op, ua.SimpleAttributeOperand):
            return _field(event, [q.Name for q in op.BrowsePath], op.AttributeId)
        if isinstance(op, ua.AttributeOperand):
            elements = op.BrowsePath.Elements if op.BrowsePath else []
            return _field(event, [e.TargetName.Name for e in elements], op.AttributeId)
        return super()._eval_op(op, event)

    def _is_of_type(self, etype: Any, wanted: Any) -> bool:
        """`etype` is `wanted` or one of its subtypes: walk HasSubtype up from `etype` in the address space."""
        if not isinstance(etype, ua.NodeId) or not isinstance(wanted, ua.NodeId):
            return False
        for _ in range(_MAX_TYPE_DEPTH):
            if etype == wanted:
                return True
            node = self._aspace.get(etype)
            if node is None:
                return False
            parent = next((r.NodeId for r in node.references
                           if not r.IsForward and r.ReferenceTypeId == _HAS_SUBTYPE), None)
            if parent is None:
                return False
            etype = parent
        return False


def _field(event: Any, path: list[str], attribute_id: Any) -> Any:
    """The event's field at `path`, as the event carries it ("ActiveState/Id", the key asyncua's own select
    clauses use: Event.browse_path_to_attribute_name); with no path the attribute's name (NodeId: the
    ConditionId). A field the event does not carry is NULL (None), as Part 4 says."""
    if path:
        name = "/".join(path)
    else:
        try:
            name = ua.AttributeIds(attribute_id).name
        except ValueError:
            return None
    if name in getattr(event, "internal_properties", ()):
        return None  # asyncua's own bookkeeping on the event object (data_types, ...), not a field
    return getattr(event, name, None)


def install(version: str | None = None) -> bool:
    """Make asyncua's server evaluate where clauses with `ConformingEvaluator` (idempotent). False, with a log
    line, on an asyncua other than FOR_ASYNCUA: nothing is patched then."""
    found = version if version is not None else metadata.version("asyncua")
    if found != FOR_ASYNCUA:
        log.warning("opcua.where_clause_unpatched", asyncua=found, written_for=FOR_ASYNCUA,
                    detail="this asyncua's own where-clause evaluation serves: OfType matches the exact event type "
                           "only, a browse path is read by its first name; a client that filters on "
                           "OfType(AlarmConditionType) or ActiveState/Id may get nothing (docs/opcua.md)")
        return False
    monitored_item_service.WhereClauseEvaluator = ConformingEvaluator
    return True
