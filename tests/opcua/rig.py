"""What the OPC UA tests run: `millsense opcua` as a subprocess, and a real asyncua client.

The server connects over loopback Zenoh (scouting off) to daemons that run the simulator; the
client speaks Basic256Sha256 Sign & Encrypt with throw-away certificates (tests/opcua/pki.py).
"""

from __future__ import annotations

import asyncio
import shutil
import time
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
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


ACKNOWLEDGE = ua.NodeId(ua.ObjectIds.AcknowledgeableConditionType_Acknowledge)
CONFIRM = ua.NodeId(ua.ObjectIds.AcknowledgeableConditionType_Confirm)
REFRESH_END = ua.NodeId(ua.ObjectIds.RefreshEndEventType)


@dataclass
class Rig:
    """An in-process server (`server.build_server`), its feeder, and a client connected to it whose subscription's
    events land in `events`, in the order they came. `opcua_rig` makes one."""
    pki: Pki
    port: int
    server: Any
    ns: Any
    root: Any
    feeder: Any
    client: Client
    ms: int                     # the millsense namespace's index, as the client knows it
    events: list[Any]
    _arrived: asyncio.Event     # set by every event: a waiter looks again
    _clients: list[Client]
    subscription: Any = None

    async def subscribe(self, types: list[Any] | None = None, *, evfilter: Any = None) -> Any:
        """The client's subscription to the Server object's events: of `types` (nodes, or the server's "alarm" and
        "discrete" types and "refresh_end" by name), or through `evfilter`; each event appended to `events`."""
        rig = self

        class Handler:
            def event_notification(self, event: Any) -> None:
                rig.events.append(event)
                rig._arrived.set()

        named = {"alarm": self.ns.alarm_type.nodeid, "discrete": self.ns.discrete_type.nodeid,
                 "refresh_end": REFRESH_END}
        self.subscription = await self.client.create_subscription(20, Handler())
        if evfilter is not None:
            await self.subscription.subscribe_events(ua.ObjectIds.Server, evfilter=evfilter)
        else:
            nodes = [self.client.get_node(named[t]) if isinstance(t, str) else t for t in types or []]
            await self.subscription.subscribe_events(ua.ObjectIds.Server, nodes)
        return self.subscription

    async def machine(self, name: str = "m1") -> Any:
        """The machine's nodes (made by the feeder the first time), to `apply` the daemon's payloads to."""
        return await self.feeder.machine(name)

    def condition(self, name: str, machine: str = "m1") -> Any:
        """The client's node of a machine's condition (its ConditionId)."""
        return self.client.get_node(ua.NodeId(f"{machine}/Notification/Messages/{name}", self.ms))

    async def connect(self, cert: Path, key: Path) -> Client:
        """Another client, disconnected with the rig."""
        client = await connect(self.port, cert, key)
        self._clients.append(client)
        return client

    async def until(self, predicate: Any, what: str, timeout_s: float = SLOW_S) -> Any:
        """`predicate(events)`'s first truthy value, looked at again each time an event arrives (no polling)."""
        async def look() -> Any:
            while True:
                value = predicate(self.events)
                if value:
                    return value
                self._arrived.clear()   # no await since the look: an event cannot have come in between
                await self._arrived.wait()
        try:
            return await asyncio.wait_for(look(), timeout_s)
        except TimeoutError:
            raise AssertionError(f"timed out after {timeout_s} s: {what}; {len(self.events)} events came") from None

    async def named(self, name: str, n: int = 1) -> list[Any]:
        """The events of condition `name` so far, once there are at least `n`."""
        def enough(events: list[Any]) -> list[Any] | None:
            got = [e for e in events if getattr(e, "ConditionName", None) == name]
            return got if len(got) >= n else None
        return await self.until(enough, f"{n} events of {name}")

    async def first(self, name: str, **fields: Any) -> Any:
        """The first event of condition `name` whose fields (`**{"AckedState/Id": True}`) are these."""
        return await self.until(lambda events: next((e for e in events if getattr(e, "ConditionName", None) == name
                                                     and all(getattr(e, k) == v for k, v in fields.items())), None),
                                f"an event of {name} with {fields}")

    async def refresh(self) -> list[Any]:
        """ConditionRefresh on the subscription: the events from the call up to RefreshEnd (Part 9 5.5.7), which
        closes the replay."""
        mark = len(self.events)
        await self.client.get_node(ua.ObjectIds.ConditionType).call_method(
            ua.NodeId(ua.ObjectIds.ConditionType_ConditionRefresh),
            ua.Variant(self.subscription.subscription_id, ua.VariantType.UInt32))
        await self.until(lambda events: any(e.EventType == REFRESH_END for e in events[mark:]), "RefreshEnd")
        return self.events[mark:]


async def acknowledge(condition: Any, event_id: bytes, comment: str = "seen") -> None:
    """Acknowledge (Part 9) called on `condition` for the event `event_id`, with `comment`."""
    await condition.call_method(ACKNOWLEDGE, ua.Variant(event_id, ua.VariantType.ByteString),
                                ua.Variant(ua.LocalizedText(comment), ua.VariantType.LocalizedText))


async def value(node: Any, *path: str) -> Any:
    """The value of the variable at the browse path `path` (e.g. "0:ActiveState", "0:Id") under `node`."""
    return await (await node.get_child(list(path))).read_value()


@asynccontextmanager
async def opcua_rig(tmp_path: Path, *, operators: bool = False, trust_stranger: bool = False,
                    subscribe: list[Any] | None = None) -> AsyncIterator[Rig]:
    """The server object of `millsense opcua` on loopback (`in_process_options`: fresh certificates under
    `tmp_path`, a free port), a client connected with the trusted certificate, and, with `subscribe` (see
    `Rig.subscribe`), its subscription. `operators`: that client is an operator (Acknowledge, Confirm);
    `trust_stranger`: the stranger's certificate is trusted too, but no operator's. Stops all on the way out."""
    from millsense.daemon.opcua.server import Feeder, build_server

    pki = make_pki(tmp_path / "pki")
    if trust_stranger:
        shutil.copyfile(pki.stranger_cert, pki.trust_dir / "stranger.der")
    port, options = in_process_options(tmp_path, pki, operators=operators)
    server, ns, root = await build_server(options)
    await server.start()
    clients: list[Client] = []
    try:
        client = await connect(port, pki.client_cert, pki.client_key)
        clients.append(client)
        rig = Rig(pki, port, server, ns, root, Feeder(server, ns, root), client,
                  await client.get_namespace_index(MS_NS), [], asyncio.Event(), clients)
        if subscribe is not None:
            await rig.subscribe(subscribe)
        yield rig
    finally:
        for client in clients:
            await client.disconnect()
        await server.stop()
