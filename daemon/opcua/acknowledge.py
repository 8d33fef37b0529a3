"""Acknowledge and Confirm of the alarm conditions: the server's only writes, for operators only (issue 42).

asyncua has the methods' nodes (AcknowledgeableConditionType's Acknowledge i=9111 and Confirm i=9113)
but no implementation. Clients call them with the condition's NodeId (its ConditionId) as the object, the
EventId of the event they acknowledge and a comment; `conditions.py` keeps the state.

Who may: a session whose certificate is in the operators' folder (`--operators-dir`, `[opcua]
operators_dir`; each also in the trust list). Nobody by default. asyncua hands a method's callback no
session, so the permission ruleset, which asyncua asks about every request with its session's user,
records that user in a context variable: each connection's requests run one after the other in its
own task, so the callback of a Call reads the user of that Call. Every acknowledgement and
confirmation is logged (`opcua.audit`, with the comment and the certificate's file and thumbprint);
none of them changes anything but the condition's AckedState or ConfirmedState: a held feed stays
held until `millsense reset`.
"""

from __future__ import annotations

import contextvars
from dataclasses import dataclass
from typing import Any

import structlog
from asyncua import ua
from asyncua.crypto.permission_rules import SimpleRoleRuleset, User

log = structlog.get_logger("millsense.opcua")

ACKNOWLEDGE = ua.ObjectIds.AcknowledgeableConditionType_Acknowledge
CONFIRM = ua.ObjectIds.AcknowledgeableConditionType_Confirm
MAX_COMMENT_CHARS = 512

CALLER: contextvars.ContextVar[Any] = contextvars.ContextVar("millsense_opcua_caller", default=None)


@dataclass
class SessionUser(User):
    """asyncua's user, with what millsense needs: may it acknowledge, and which certificate it is."""

    operator: bool = False
    sha256: str = ""


class CallerRuleset(SimpleRoleRuleset):
    """asyncua's role ruleset, unchanged, that also notes the user of the request being served."""

    def check_validity(self, user: Any, action_type_id: Any, body: Any) -> bool:
        CALLER.set(user)
        return super().check_validity(user, action_type_id, body)


def bind(server: Any, registry: dict[ua.NodeId, Any], methods: dict[str, Any]) -> None:
    """Link Acknowledge and Confirm to `registry`: ConditionId -> its ConditionNodes (conditions.py); `methods`
    gets the callbacks by name, for the condition instances' own copies of the methods."""

    async def acknowledge(object_id: ua.NodeId, event_id: Any = None, comment: Any = None) -> Any:
        return await _call("acknowledge", registry, object_id, event_id, comment)

    async def confirm(object_id: ua.NodeId, event_id: Any = None, comment: Any = None) -> Any:
        return await _call("confirm", registry, object_id, event_id, comment)

    server.link_method(server.get_node(ua.NodeId(ACKNOWLEDGE)), acknowledge)
    server.link_method(server.get_node(ua.NodeId(CONFIRM)), confirm)
    # a condition instance's own Acknowledge method node (its copy of the type's) answers the same
    methods.update(Acknowledge=acknowledge, Confirm=confirm)


async def _call(action: str, registry: dict[ua.NodeId, Any], object_id: ua.NodeId, event_id: Any,
                comment: Any) -> ua.StatusCode:
    user = CALLER.get()
    who = getattr(user, "name", None) or "?"
    if not getattr(user, "operator", False):
        log.warning("opcua.audit_refused", action=action, condition=object_id.to_string(), user=who,
                    reason="not an operator (its certificate is not in the operators' folder)")
        return ua.StatusCode(ua.StatusCodes.BadUserAccessDenied)
    condition = registry.get(object_id)
    if condition is None:
        return ua.StatusCode(ua.StatusCodes.BadNodeIdUnknown)
    event = event_id.Value if isinstance(event_id, ua.Variant) else event_id
    text = comment.Value if isinstance(comment, ua.Variant) else comment
    text = text if isinstance(text, ua.LocalizedText) else ua.LocalizedText(str(text or ""))
    if len(text.Text or "") > MAX_COMMENT_CHARS:
        return ua.StatusCode(ua.StatusCodes.BadInvalidArgument)
    if not isinstance(event, bytes):
        return ua.StatusCode(ua.StatusCodes.BadEventIdUnknown)
    status = await condition.acknowledge(object_id, event, text, who, confirm=action == "confirm")
    if status.is_good():
        log.info("opcua.audit", action=action, condition=object_id.to_string(), comment=text.Text or "", user=who,
                 sha256=getattr(user, "sha256", ""))
    return status
