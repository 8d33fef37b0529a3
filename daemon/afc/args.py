"""The arguments of the AFC command, the same at both front doors: Zenoh's `cmd/afc` (publish/sink.py) and
the local socket's `afc` (runtime/local_control.py): exactly {"action": on | off | status}.

Checked before the daemon sees them; the reply names the action asked.
"""

from __future__ import annotations

from typing import Any

AFC_ACTIONS = ("on", "off", "status")


def check_afc_args(args: Any) -> dict[str, str]:
    """The args of `cmd/afc` and the local `afc`: exactly {"action": on | off | status}; ValueError otherwise."""
    if not isinstance(args, dict):
        raise ValueError("afc: args must be an object {\"action\": \"on\" | \"off\" | \"status\"}")
    extra = sorted(set(args) - {"action"})
    if extra:
        raise ValueError(f"afc takes only \"action\" (got {', '.join(extra)})")
    action = args.get("action")
    if action not in AFC_ACTIONS:
        raise ValueError(f"afc: action must be one of {', '.join(AFC_ACTIONS)}, not {action!r}")
    return {"action": action}


def afc_reply(checked: dict[str, str], result: Any) -> dict:
    """The daemon's answer with the action asked; a refusal's `reason` also as `error`, which the
    command clients print (`afc_command` says `reason`, every other command `error`)."""
    if not isinstance(result, dict):
        return {"ok": False, "error": f"the daemon returned {type(result).__name__}, expected an object", **checked}
    out = {**checked, **result}
    if out.get("ok") is False and "error" not in out:
        out["error"] = str(out.get("reason") or "refused")
    return out
