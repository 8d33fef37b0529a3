"""The asyncua server of `millsense opcua` and the loop that feeds it from Zenoh.

One asyncio loop owns the address space. Zenoh's callbacks fill `Inbox` and wake the loop; the
loop drains it at most every `MIN_UPDATE_S`, so however fast the daemons publish, each machine's
variables are written at most 1 / MIN_UPDATE_S times a second and the loop never falls behind
(an estimate newer than the last drain replaces the older one in the inbox).
"""

from __future__ import annotations

import asyncio
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import urlparse

import structlog
from asyncua import Server, ua

from millsense.daemon.opcua.acknowledge import CallerRuleset
from millsense.daemon.opcua.acknowledge import bind as bind_acknowledge
from millsense.daemon.opcua.inbox import Inbox, subscribe
from millsense.daemon.opcua.machine_nodes import MachineNodes, Namespaces
from millsense.daemon.opcua.machine_tool import MachineToolInstance
from millsense.daemon.opcua.nodesets import NodesetError, import_nodesets
from millsense.daemon.opcua.settings import Identification
from millsense.daemon.opcua.security import (
    OpcuaSetupError,
    ServerIdentity,
    SessionUsers,
    TrustList,
    client_validator,
    identity_tokens,
)
from millsense.daemon.opcua.where_clause import install as install_where_clause

log = structlog.get_logger("millsense.opcua")

MIN_UPDATE_S = 0.05
MAX_MACHINES = 256
DEFAULT_PORT = 4840
REFRESH_EVENT_SEVERITY = 100
# Sign & Encrypt only, each of the three RSA policies of OPC UA 1.04/1.05 that asyncua serves (issue 42):
# no None endpoint, no Sign-only one, none of the deprecated Basic128Rsa15/Basic256.
SECURITY_POLICIES = ("Basic256Sha256_SignAndEncrypt", "Aes128Sha256RsaOaep_SignAndEncrypt",
                     "Aes256Sha256RsaPss_SignAndEncrypt")


@dataclass
class Options:
    endpoint: str
    identity: ServerIdentity
    trust: TrustList
    allow_anonymous: bool = False
    machine: str = "*"
    nodesets: Path | None = None  # the folder of the companion specifications' NodeSet2 files (nodesets.py)
    identities: dict[str, Identification] = field(default_factory=dict)  # [opcua] of --config, by machine id
    tools: list[int] = field(default_factory=list)  # its [tools.N] numbers
    operators: TrustList | None = None  # who may acknowledge and confirm alarms (acknowledge.py); none: nobody
    refused: list[str] = field(default_factory=list)  # client refusals, newest last (tests and the status line)


def parse_endpoint(text: str) -> tuple[str, int]:
    """(host, port) of `opc.tcp://HOST:PORT`; ValueError with the reason otherwise."""
    url = urlparse(text)
    if url.scheme != "opc.tcp":
        raise ValueError(f"{text!r} is not opc.tcp://HOST:PORT")
    try:
        port = url.port
    except ValueError:
        raise ValueError(f"{text!r}: the port is not a number 1-65535") from None
    if not url.hostname:
        raise ValueError(f"{text!r} names no host (opc.tcp://127.0.0.1:{DEFAULT_PORT})")
    if url.path not in ("", "/") or url.query:
        raise ValueError(f"{text!r}: give only opc.tcp://HOST:PORT")
    return url.hostname, port or DEFAULT_PORT


async def build_server(options: Options) -> tuple[Server, Namespaces, Any]:
    # a where clause as Part 4 reads it (OfType with subtypes, ActiveState/Id): a client that watches only active
    # conditions gets them (where_clause.py; on another asyncua version it patches nothing and says so)
    install_where_clause()
    server = Server(user_manager=SessionUsers(options.trust, options.operators))
    # ConditionRefresh (and Refresh2): a client that connects while a condition is active (a held feed)
    # asks for the retained conditions. asyncua binds the methods only when told; the value is the
    # severity of its RefreshStart/RefreshEnd events (an int: True would make it 1).
    server.iserver.bind_condition_methods = REFRESH_EVENT_SEVERITY
    await server.init()
    server.set_endpoint(options.endpoint)
    server.set_server_name("millsense")
    await server.set_application_uri(options.identity.application_uri)
    # CallerRuleset: asyncua's own rules, noting each request's user for Acknowledge and Confirm (acknowledge.py)
    server.set_security_policy([getattr(ua.SecurityPolicyType, p) for p in SECURITY_POLICIES],
                               permission_ruleset=CallerRuleset())
    server.set_identity_tokens(identity_tokens(options.allow_anonymous))
    await server.load_certificate(options.identity.certificate_der, format="der")
    await server.load_private_key(options.identity.private_key_pem, format="pem")
    server.set_certificate_validator(client_validator(options.trust, options.refused))
    if options.nodesets is not None:
        try:
            await import_nodesets(server, options.nodesets)
        except NodesetError as exc:  # never a silent fallback to the own model: the operator asked for these
            raise OpcuaSetupError(f"--nodesets {exc}") from None
    else:
        log.info("opcua.own_model", detail="no --nodesets folder: millsense's own model only, no MachineToolType "
                 "instances (docs/opcua.md)")
    ns = await Namespaces.register(server)
    bind_acknowledge(server, ns.conditions, ns.ack_methods)
    root = await server.nodes.objects.add_folder(ua.NodeId("millsense", ns.ms), ua.QualifiedName("millsense", ns.ms))
    await root.set_event_notifier([ua.EventNotifier.SubscribeToEvents])
    await server.nodes.server.add_reference(root.nodeid, ua.ObjectIds.HasNotifier)
    return server, ns, root


class Feeder:
    """Drains the inbox into the address space; one MachineNodes per machine seen (at most MAX_MACHINES), and
    with the nodesets loaded one MachineToolType object per machine whose identification is configured."""

    def __init__(self, server: Server, ns: Namespaces, root: Any, options: Options | None = None) -> None:
        self.server, self.ns, self.root = server, ns, root
        self.options = options
        self.machines: dict[str, MachineNodes] = {}
        self.typed: dict[str, MachineToolInstance] = {}
        self.errors = 0
        self._full_logged = False

    async def machine(self, name: str) -> MachineNodes | None:
        if name in self.machines:
            return self.machines[name]
        if len(self.machines) >= MAX_MACHINES:
            if not self._full_logged:
                self._full_logged = True
                log.warning("opcua.machines_full", max_machines=MAX_MACHINES, refused=name)
            return None
        nodes = await MachineNodes(self.server, self.ns, name).create(self.root)
        self.machines[name] = nodes
        log.info("opcua.machine_added", machine=name)
        options = self.options
        if options is not None and options.nodesets is not None:
            identification = options.identities.get(name)
            if identification is None:  # 40001-1's Identification is mandatory, and only the configuration knows it
                log.warning("opcua.machine_untyped", machine=name,
                            reason="no [opcua] manufacturer, serial_number and product_instance_uri for this machine "
                                   "in --config: no MachineToolType object, only Objects/millsense/" + name)
            else:
                try:
                    self.typed[name] = await MachineToolInstance(self.server, name, self.ns.ms).create(
                        identification, options.tools, nodes.obj)
                except Exception as exc:  # noqa: BLE001 - its own nodes still serve; the log says what is missing
                    log.error("opcua.machine_tool_failed", machine=name, error=f"{type(exc).__name__}: {exc}",
                              detail="no MachineToolType object for this machine; Objects/millsense/" + name + " serves")
        return nodes

    async def flush(self) -> None:
        """Fire the held-back events of flapping conditions whose rate allows it now (flapping.py)."""
        for machine, nodes in self.machines.items():
            try:
                await nodes.flush()
            except Exception as exc:  # noqa: BLE001 - one machine's event must not stop the others
                log.warning("opcua.flush_error", machine=machine, error=f"{type(exc).__name__}: {exc}")

    async def apply(self, items: list[tuple[str, str, dict[str, Any]]]) -> None:
        for machine, kind, payload in items:
            try:
                nodes = await self.machine(machine)
                if nodes is None:
                    continue
                if kind in ("alive", "gone"):
                    await nodes.set_alive(kind == "alive")
                    if kind == "gone" and machine in self.typed:
                        await self.typed[machine].gone()
                    log.info("opcua.machine_" + kind, machine=machine)
                else:
                    await nodes.apply(kind, payload)
                    if machine in self.typed:
                        await self.typed[machine].apply(kind, payload)
            except Exception as exc:  # noqa: BLE001 - one bad payload must not stop the others
                self.errors += 1
                if self.errors <= 10 or self.errors % 1000 == 0:
                    log.warning("opcua.payload_error", machine=machine, kind=kind, error=f"{type(exc).__name__}: {exc}",
                                count=self.errors)


async def serve(options: Options, session: Any, stop: asyncio.Event, on_ready: Any = None) -> None:
    """Run until `stop` is set. Raises OpcuaSetupError when the endpoint cannot be served."""
    host, port = parse_endpoint(options.endpoint)
    # asyncua logs a traceback for every refused client and chats at INFO: our own lines say what matters.
    logging.getLogger("asyncua").setLevel(logging.CRITICAL)
    server, ns, root = await build_server(options)
    try:
        await server.start()
    except OSError as exc:
        raise OpcuaSetupError(f"--endpoint {options.endpoint}: cannot listen on {host}:{port}: "
                              f"{exc.strerror or exc}") from None
    loop = asyncio.get_running_loop()
    wake = asyncio.Event()

    def wake_soon() -> None:
        try:
            loop.call_soon_threadsafe(wake.set)
        except RuntimeError:
            pass  # the loop closed while Zenoh still delivered: nothing left to feed

    inbox = Inbox(wake_soon)
    feeder = Feeder(server, ns, root, options)
    entities = subscribe(session, inbox, options.machine)
    log.info("opcua.listening", endpoint=options.endpoint, application_uri=options.identity.application_uri,
             trusted_clients=len(options.trust.trusted()), allow_anonymous=options.allow_anonymous)
    if on_ready is not None:
        on_ready()
    try:
        while not stop.is_set():
            stopper = asyncio.ensure_future(stop.wait())
            waker = asyncio.ensure_future(wake.wait())
            await asyncio.wait({stopper, waker}, timeout=1.0, return_when=asyncio.FIRST_COMPLETED)
            stopper.cancel()
            waker.cancel()
            wake.clear()
            await feeder.apply(inbox.take())
            await feeder.flush()
            await asyncio.sleep(MIN_UPDATE_S)
    finally:
        for e in entities:
            try:
                e.undeclare()
            except Exception:  # noqa: BLE001 - closing anyway
                pass
        await server.stop()
