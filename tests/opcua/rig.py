"""What the OPC UA tests run: `millsense opcua` as a subprocess, and a real asyncua client.

The server connects over loopback Zenoh (scouting off) to daemons that run the simulator; the
client speaks Basic256Sha256 Sign & Encrypt with throw-away certificates (tests/opcua/pki.py).
"""

from __future__ import annotations

import asyncio
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from asyncua import Client, ua
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256

from tests.e2e.helpers import Procs, tcp, wait_for
from tests.opcua.pki import make_app_cert

MS_NS = "urn:millsense:opcua"
MT_NS = "http://opcfoundation.org/UA/MachineTool/"
CLIENT_URI = "urn:millsense:test:client"
SLOW_S = 60.0  # detects a failure; no budget (a loaded 2-core box)


@dataclass
class Pki:
    server_cert: Path
    server_key: Path
    client_cert: Path    # in the trust list
    client_key: Path
    stranger_cert: Path  # not in the trust list
    stranger_key: Path
    trust_dir: Path


def make_pki(folder: Path) -> Pki:
    folder.mkdir(parents=True, exist_ok=True)
    trust = folder / "trusted"
    trust.mkdir()
    server_cert, server_key = make_app_cert(folder, "server", "urn:millsense:test:server", server=True)
    client_cert, client_key = make_app_cert(folder, "client", CLIENT_URI, server=False)
    stranger_cert, stranger_key = make_app_cert(folder, "stranger", CLIENT_URI, server=False)
    (trust / "client.der").write_bytes(client_cert.read_bytes())
    return Pki(server_cert, server_key, client_cert, client_key, stranger_cert, stranger_key, trust)


def start_opcua(procs: Procs, name: str, pki: Pki, ua_port: int, z_port: int, *extra: str) -> Any:
    p = procs.start(name, ["opcua", "--endpoint", f"opc.tcp://127.0.0.1:{ua_port}", "--cert", str(pki.server_cert),
                           "--key", str(pki.server_key), "--trust-dir", str(pki.trust_dir),
                           "--connect", tcp(z_port), "--no-scouting", "--log-format", "json", *extra])
    wait_for(lambda: "opcua.listening" in procs.text(name) or p.poll() is not None, SLOW_S, f"{name} listening")
    assert p.poll() is None, procs.text(name)
    return p


async def connect(port: int, cert: Path | None, key: Path | None, *, user_cert: bool = True,
                  policy: Any = SecurityPolicyBasic256Sha256) -> Client:
    """A connected client: the channel signed and encrypted with `cert` under `policy` (none: no security at all),
    and the session's user that certificate (`user_cert`) or anonymous."""
    client = Client(f"opc.tcp://127.0.0.1:{port}", timeout=10)
    client.application_uri = CLIENT_URI
    if cert is not None:
        await client.set_security(policy, str(cert), str(key),
                                  mode=ua.MessageSecurityMode.SignAndEncrypt)
        if user_cert:
            await client.load_client_certificate(str(cert))
            await client.load_private_key(key)
    await client.connect()
    return client


async def unsecured_session(port: int) -> str:
    """What a client that ignores the endpoint list gets: a channel with no security (open for discovery),
    then CreateSession and an anonymous ActivateSession on it. Returns how it ended."""
    from asyncua.common.utils import create_nonce

    client = Client(f"opc.tcp://127.0.0.1:{port}", timeout=10)
    await client.connect_socket()
    try:
        await client.send_hello()
        await client.open_secure_channel()
        params = ua.CreateSessionParameters()
        params.ClientNonce = create_nonce(32)
        params.ClientDescription = ua.ApplicationDescription(ApplicationUri=CLIENT_URI,
                                                             ApplicationType=ua.ApplicationType.Client)
        params.EndpointUrl = f"opc.tcp://127.0.0.1:{port}"
        params.SessionName = "unsecured"
        params.RequestedSessionTimeout = 60000
        try:
            await client.uaclient.create_session(params)
        except ua.UaStatusCodeError as exc:
            return f"CreateSession refused: {type(exc).__name__}"
        activate = ua.ActivateSessionParameters(LocaleIds=["en"], UserIdentityToken=ua.AnonymousIdentityToken(
            PolicyId="anonymous"))
        try:
            await client.uaclient.activate_session(activate)
        except ua.UaStatusCodeError as exc:
            return f"ActivateSession refused: {type(exc).__name__}"
        try:
            return f"read: {(await client.nodes.server.read_browse_name()).Name}"
        except ua.UaStatusCodeError as exc:
            return f"read refused: {type(exc).__name__}"
    finally:
        client.disconnect_socket()


async def wait_async(predicate: Any, timeout_s: float, what: str, step_s: float = 0.05) -> Any:
    deadline = time.monotonic() + timeout_s
    while True:
        value = await predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s} s: {what}")
        await asyncio.sleep(step_s)


async def child(node: Any, *names: str) -> Any:
    """The node at a browse path under `node`, or None while it does not exist yet."""
    try:
        return await node.get_child(list(names))
    except ua.UaStatusCodeError:
        return None


_ALARM_CONDITION = ["0:Types", "0:EventTypes", "0:BaseEventType", "0:ConditionType", "0:AcknowledgeableConditionType",
                    "0:AlarmConditionType"]


async def alarm_types(client: Client) -> list[Any]:
    """millsense's two alarm event types, found where Part 9's hierarchy puts them (issue 42): the limit alarms'
    MillsenseAlarmType under ExclusiveLevelAlarmType, the discrete ones' (FeedHeld, the DAQ link) under
    OffNormalAlarmType. Subscribe to both for every alarm event."""
    ms = await client.get_namespace_index(MS_NS)
    limit = await client.nodes.root.get_child([*_ALARM_CONDITION, "0:LimitAlarmType", "0:ExclusiveLimitAlarmType",
                                               "0:ExclusiveLevelAlarmType", f"{ms}:MillsenseAlarmType"])
    discrete = await client.nodes.root.get_child([*_ALARM_CONDITION, "0:DiscreteAlarmType", "0:OffNormalAlarmType",
                                                  f"{ms}:MillsenseOffNormalAlarmType"])
    return [limit, discrete]


def in_process_options(tmp_path: Path, pki: Any, *, operators: bool = False) -> tuple[int, Any]:
    """(port, Options) of an in-process server (`server.build_server`): `pki`'s identity and trust list on a free
    port; `operators`: the client's certificate is an operator's too (Acknowledge, Confirm)."""
    from millsense.daemon.opcua.security import TrustList, load_server_identity
    from millsense.daemon.opcua.server import Options
    from tests.conftest import free_tcp_port

    extra: dict[str, Any] = {}
    if operators:
        folder = tmp_path / "operators"
        folder.mkdir(exist_ok=True)
        shutil.copyfile(pki.client_cert, folder / "client.der")
        extra["operators"] = TrustList(folder)
    port = free_tcp_port()
    return port, Options(endpoint=f"opc.tcp://127.0.0.1:{port}",
                         identity=load_server_identity(pki.server_cert, pki.server_key),
                         trust=TrustList(pki.trust_dir), **extra)
