"""What the front doors ask of the running daemon: the `Controls` protocol.

Declared here, below both `publish/` (the Zenoh queryables, publish/sink.py) and `runtime/` (the local
control socket, runtime/local_control.py), so that neither imports the other. The live daemon has one
implementation, `runtime.controls.OperatorControls`, which names this protocol; tests/runtime/test_controls.py
holds the two together (every member here exists there, with the same signature).

The Zenoh sink also takes a smaller object (a test's fake, a replay): it asks `getattr` for what is optional
(`test_trip`, `limits`, `limits_command`, `afc_command`, `on_context_payload`, `settings`, `audit`) and
declares only the queryables and subscribers that object can serve.
"""

from __future__ import annotations

from typing import Any, Protocol

from millsense.daemon.audit import AuditLog

TEST_TRIP_WAIT_S = 2.0  # longest wait for each confirmation of a test-trip (the daemon's and `commission`'s)


class Controls(Protocol):
    """What the queryables and the local socket ask of the running daemon (docs/architecture.md)."""

    settings: Any        # `settings.interlock`: reset policy and token; `settings.context.source`
    audit: AuditLog      # every command that changes the machine is recorded here

    def status(self) -> dict[str, Any]: ...
    def config(self) -> dict[str, Any]: ...
    def reset(self, requester: str = "") -> dict[str, Any]: ...
    def test_trip(self, requester: str = "", wait_s: float = TEST_TRIP_WAIT_S) -> dict[str, Any]: ...
    def limits(self) -> dict[str, Any]: ...
    def limits_command(self, args: dict, requester: str = "") -> dict[str, Any]: ...
    def afc_command(self, args: dict, requester: str = "") -> dict[str, Any]: ...
    def on_context_payload(self, payload: dict, source: str = "") -> None: ...
