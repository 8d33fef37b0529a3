"""Commands at the machine: a Unix socket in the daemon's state directory, for root and the daemon's user.

Why a local socket beside the Zenoh commands: an operator standing at the
machine must always be able to clear a latched hold, even with
`[interlock] reset = "off"` (that policy is about the network) or with the
network down. Who may ask is decided by the kernel, not by a secret: the
peer's credentials (`SO_PEERCRED`) must be uid 0 or the daemon's own uid.
The socket file is mode 0660 in the state directory.

Protocol: one connection per request; the client sends one JSON line
`{"command": "reset" | "test-trip" | "status" | "limits" | "afc", "args": {...}}` and
gets one JSON line back (daemon/local_socket.py: the protocol and the client; this is the server).
Every request is asked of the daemon's one `Controls` (runtime/controls.py), the same object the
Zenoh queryables ask. `reset` and `test-trip` go through `Controls.reset` /
`Controls.test_trip`, so a reset is still refused while the condition that
latched persists. `limits` takes the args of `cmd/limits` (publish/limits_args.py):
`list` and `show` read (`Controls.limits()`, or the key's detail), the other
actions change the learned limits through `Controls.limits_command`. `afc` takes the
args of `cmd/afc` ({"action": "on" | "off" | "status"}): `status` reads, `on` and
`off` switch adaptive feed control through `Controls.afc_command`. Every command
that changes something is recorded in the audit log, granted or refused, with
the peer's uid and pid.

Requests are served one at a time by one thread (a test-trip takes up to a
few seconds; a second request waits for it). The whole request must arrive within
`READ_DEADLINE_S` of the connection (a client that connects and says nothing, or
dribbles a byte a second, is cut off then), and from a uid that may not command
the daemon within `DENIED_READ_S`: its refusal is audited and it holds the socket
for no longer than that.
"""

from __future__ import annotations

import json
import os
import socket
import threading
from pathlib import Path
from typing import Any, Callable

import structlog

from millsense.daemon.afc.args import afc_reply, check_afc_args
from millsense.daemon.controls import Controls
from millsense.daemon.local_socket import (COMMANDS, DENIED_READ_S, READ_DEADLINE_S, SOCKET_MODE, command_of,
                                           peer_credentials, read_line, socket_path, unix_address)
from millsense.daemon.publish.limits_args import READS, check_args
from millsense.drivers.base import name_os_thread

log = structlog.get_logger("millsense.local_control")


class LocalControl:
    """The server side: one thread accepting on `state_dir/control.sock`."""

    def __init__(self, state_dir: Path, controls: Controls, allowed_uids: tuple[int, ...] | None = None,
                 on_error: Callable[[str, str], Any] | None = None):
        """`controls`: what the requests ask (the daemon's `OperatorControls`, the same as Zenoh's); its
        `audit` records them. `on_error(kind, reason)`: a socket that cannot be made (the fault path)."""
        self.path = socket_path(state_dir)
        self.controls = controls
        self._on_error = on_error
        self.allowed_uids = allowed_uids if allowed_uids is not None else tuple(sorted({0, os.getuid()}))
        self._sock: socket.socket | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.served = 0

    def start(self) -> bool:
        """Bind and serve. False (after logging a fault) if the socket cannot be made: the daemon runs on."""
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True, mode=0o750)
            if self.path.is_socket() or self.path.exists():
                self.path.unlink()  # left by a daemon that died; one daemon per state directory
            sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            # Bound under a name of its own, listening, then renamed into place: `control.sock` appears only
            # when a client can connect (a client that saw it between bind and listen was refused: "no daemon
            # listens", under load in CI).
            aside = self.path.with_name(f".{self.path.name}.{os.getpid()}")
            try:
                aside.unlink(missing_ok=True)
                with unix_address(aside) as address:   # a deep state_dir: through the folder's fd
                    sock.bind(address)
                os.chmod(aside, SOCKET_MODE)
                sock.listen(8)
                sock.settimeout(0.2)  # the accept loop looks at the stop flag
                os.replace(aside, self.path)
            except OSError:
                sock.close()
                aside.unlink(missing_ok=True)
                raise
        except OSError as exc:
            reason = f"cannot open the local control socket {self.path}: {exc}"
            if self._on_error is not None:
                self._on_error("local_control", reason)
            else:
                log.error("local_control.failed", reason=reason)
            return False
        self._sock = sock
        self._stop.clear()   # started again after a close (the socket deleted under the daemon)
        self._thread = threading.Thread(target=self._serve, name="millsense-local-control", daemon=True)
        self._thread.start()
        log.info("local_control.listening", path=str(self.path), uids=list(self.allowed_uids))
        return True

    @property
    def listening(self) -> bool:
        return self._sock is not None

    def close(self, timeout_s: float = 1.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout_s)
            self._thread = None
        if self._sock is not None:
            self._sock.close()
            self._sock = None
            try:
                self.path.unlink()
            except OSError:
                pass

    def _serve(self) -> None:
        name_os_thread("ms-local-ctl")
        while not self._stop.is_set():
            try:
                conn, _ = self._sock.accept()
            except socket.timeout:
                continue
            except OSError as exc:
                if not self._stop.is_set():
                    log.error("local_control.accept_failed", error=str(exc))
                    self._stop.wait(0.2)
                continue
            try:
                self._handle(conn)
            except Exception as exc:  # noqa: BLE001 - one bad client must not end the server
                log.error("local_control.request_failed", error=f"{type(exc).__name__}: {exc}")
            finally:
                conn.close()

    def _handle(self, conn: socket.socket) -> None:
        pid, uid, _gid = peer_credentials(conn)
        requester = f"local uid={uid} pid={pid}"
        audit = self.controls.audit
        allowed = uid in self.allowed_uids
        try:
            line = read_line(conn, READ_DEADLINE_S if allowed else DENIED_READ_S)
        except socket.timeout:
            if allowed:
                audit.record("?", requester, False, reason=f"no complete request within {READ_DEADLINE_S:g} s: cut off")
                return
            line = b""   # refused all the same, below: its command unknown
        except OSError:
            return
        command, args = command_of(line)
        if not allowed:
            reply = {"ok": False, "error": f"uid {uid} may not command this daemon (root or uid {os.getuid()} only)"}
            audit.record(command or "?", requester, False, reason=reply["error"])
        elif command is None:
            reply = {"ok": False, "error": f"bad request: expected one JSON line {{\"command\": one of {list(COMMANDS)}}}"}
        elif command == "status":
            reply = {"ok": True, **self.controls.status()}
        elif command == "limits":
            reply = self._limits(args, requester)
        elif command == "afc":
            reply = self._afc(args, requester)
        else:
            fn = self.controls.reset if command == "reset" else self.controls.test_trip
            reply = fn(requester=requester)
            audit.record(command, requester, bool(reply.get("ok")), reason=reply.get("error"),
                         result={k: v for k, v in reply.items() if k not in ("interlock_detail",)})
        self.served += 1
        conn.settimeout(READ_DEADLINE_S)
        conn.sendall((json.dumps(reply, default=str) + "\n").encode())


    def _limits(self, args: Any, requester: str) -> dict[str, Any]:
        """`limits` at the machine: reads answered as they are, changes audited like a reset."""
        audit = self.controls.audit
        method = getattr(self.controls, "limits_command", None)
        if not callable(method):
            return {"ok": False, "error": "this daemon has no learned limits"}
        try:
            checked = check_args(args if args is not None else {"action": "list"})
        except ValueError as exc:
            audit.record("limits", requester, False, reason=str(exc))
            return {"ok": False, "error": str(exc)}
        if checked["action"] == "list":
            return {"ok": True, **self.controls.limits()}
        try:
            result = method(checked, requester)
        except Exception as exc:  # noqa: BLE001 - ValueError: the daemon's refusal; anything else: said, not hung up
            result = {"ok": False, "error": str(exc) if isinstance(exc, ValueError) else f"{type(exc).__name__}: {exc}"}
        if not isinstance(result, dict):
            result = {"ok": False, "error": f"the daemon returned {type(result).__name__}, expected an object"}
        reply = {**checked, **result}
        if checked["action"] not in READS:
            # Granted as over Zenoh (cmd/limits): the operator was allowed and the daemon asked; whether it
            # could do it is in the result (a refusal line would be rate-limited, and this is no attack).
            audit.record("limits", requester, True, result=reply)
        return reply

    def _afc(self, args: Any, requester: str) -> dict[str, Any]:
        """`afc` at the machine: `status` read as it is, `on` / `off` audited like a reset."""
        audit = self.controls.audit
        method = getattr(self.controls, "afc_command", None)
        if not callable(method):
            return {"ok": False, "error": "this daemon has no adaptive feed control"}
        try:
            checked = check_afc_args(args if args is not None else {"action": "status"})
        except ValueError as exc:
            audit.record("afc", requester, False, reason=str(exc))
            return {"ok": False, "error": str(exc)}
        try:
            reply = afc_reply(checked, method(checked, requester))
        except Exception as exc:  # noqa: BLE001 - said to the operator, not hung up on
            reply = {**checked, "ok": False, "error": f"{type(exc).__name__}: {exc}"}
        if checked["action"] != "status":
            # Granted as over Zenoh (cmd/afc): the operator was allowed and the daemon asked; a refusal
            # of the daemon's own (a protocol-1 DAQ, say) is in the result.
            audit.record("afc", requester, True, result=reply)
        return reply
