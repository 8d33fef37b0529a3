"""A callback that must not stop its caller: the stores' fault callbacks (`call_quietly`) and the live
daemon's handlers on its fault and status paths (`safe`).

Below `history/`, the latch store, `runtime/` and `afc/`, so that each calls the one version.
"""

from __future__ import annotations

from typing import Any, Callable

import structlog

# The logger the latch store lent it before it moved here: a failed callback logs under the same name as before.
log = structlog.get_logger("millsense.latch")
# and the runner's, for `safe`: the live daemon's handlers log under the name they always had
runner_log = structlog.get_logger("millsense.runner")


def call_quietly(fn: Callable[..., Any] | None, event: str, *args: Any) -> None:
    """A store's fault callback (the runner's fault path): one that raises is logged as `event`, never
    stops the writer that called it. Shared by the latch store and the history."""
    if fn is None:
        return
    try:
        fn(*args)
    except Exception as exc:  # noqa: BLE001
        log.error(event, error=f"{type(exc).__name__}: {exc}")


def safe(fn: Callable[..., Any], *args: Any) -> None:
    """A handler on a fault or status path: one that raises is logged, never stops its caller."""
    try:
        fn(*args)
    except Exception as exc:  # noqa: BLE001
        try:
            runner_log.error("fault_handler_failed", handler=getattr(fn, "__name__", "?"),
                             error=f"{type(exc).__name__}: {exc}")
        except Exception:  # noqa: BLE001
            pass
