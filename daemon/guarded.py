"""A callback that must not stop its caller: the stores' fault callbacks (the runner's fault path).

Below `history/` and the latch store both, so that `history/` needs nothing of
the runtime to call it.
"""

from __future__ import annotations

from typing import Any, Callable

import structlog

# The logger the latch store lent it before it moved here: a failed callback logs under the same name as before.
log = structlog.get_logger("millsense.latch")


def call_quietly(fn: Callable[..., Any] | None, event: str, *args: Any) -> None:
    """A store's fault callback (the runner's fault path): one that raises is logged as `event`, never
    stops the writer that called it. Shared by the latch store and the history."""
    if fn is None:
        return
    try:
        fn(*args)
    except Exception as exc:  # noqa: BLE001
        log.error(event, error=f"{type(exc).__name__}: {exc}")
