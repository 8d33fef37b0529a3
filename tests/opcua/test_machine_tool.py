"""`millsense opcua` with the companion specifications loaded (issue 42): one real server, configured only by
the daemon's `[opcua]` section (`--config`), the real NodeSet2 files from the npm registry
(tests/opcua/nodesets.py), a real daemon on the simulator, asyncua's client.

The machine's MachineToolType object under Objects/Machines, its Identification from the configuration,
a Monitoring value that the daemon's estimates fill (its source timestamp one the daemon published), and
the three security policies: each connects, and an untrusted certificate is refused under each.
"""

from __future__ import annotations

import asyncio

import pytest

pytest.importorskip("asyncua", reason="the opcua extra (asyncua) is not installed")
from asyncua import ua  # noqa: E402
from asyncua.crypto.security_policies import (  # noqa: E402
    SecurityPolicyAes128Sha256RsaOaep,
    SecurityPolicyAes256Sha256RsaPss,
    SecurityPolicyBasic256Sha256,
)

from tests.conftest import free_tcp_port  # noqa: E402
from tests.e2e.helpers import Procs, Subscriber, tcp, wait_for, write_config  # noqa: E402
from tests.opcua import nodesets as fetched  # noqa: E402
from tests.opcua.rig import MS_NS, MT_NS, SLOW_S, child, connect, make_pki, wait_async  # noqa: E402

MACHINE = "mt-01"
MACHINERY_NS = "http://opcfoundation.org/UA/Machinery/"
DI_NS = "http://opcfoundation.org/UA/DI/"
MACHINE_TOOL_TYPE = 13  # OPC 40501 NodeIds.csv
IDENTITY = {"manufacturer": "Hermle AG", "serial_number": "C42-0815", "product_instance_uri": "urn:hermle:c42:0815"}
POLICIES = {"Basic256Sha256": SecurityPolicyBasic256Sha256, "Aes128_Sha256_RsaOaep": SecurityPolicyAes128Sha256RsaOaep,
            "Aes256_Sha256_RsaPss": SecurityPolicyAes256Sha256RsaPss}


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    six = fetched.folder()
    tmp = tmp_path_factory.mktemp("opcua-mt")
    pki = make_pki(tmp / "pki")
    z_port, ua_port, sub_port = free_tcp_port(), free_tcp_port(), free_tcp_port()
    # Everything the server needs from the [opcua] section, its certificate paths relative to the file's folder.
    opcua = "\n".join([f'endpoint = "opc.tcp://127.0.0.1:{ua_port}"', 'cert = "pki/server.der"',
                       'key = "pki/server.pem"', 'trust_dir = "pki/trusted"', f'nodesets_dir = "{six}"',
                       *(f'{k} = "{v}"' for k, v in IDENTITY.items())])
    cfg = write_config(tmp / "d.toml", machine=MACHINE, daq='transport = "sim"\nscenario = "step"',
                       zenoh_listen=[tcp(z_port)], zenoh_connect=[tcp(sub_port)])
    cfg.write_text(cfg.read_text() + f"\n[opcua]\n{opcua}\n\n[tools.12]\ndiameter_mm = 10.0\nflutes = 4\n")
    with Procs(tmp) as procs:
        server = procs.start("opcua", ["opcua", "--config", str(cfg), "--connect", tcp(z_port), "--no-scouting",
                                       "--log-format", "json"])
        wait_for(lambda: "opcua.listening" in procs.text("opcua") or server.poll() is not None, SLOW_S, "listening")
        assert server.poll() is None, procs.text("opcua")
        yield {"procs": procs, "pki": pki, "cfg": cfg, "z_port": z_port, "port": ua_port, "sub_port": sub_port}


@pytest.mark.slow
def test_the_machine_is_a_machine_tool_with_its_identification_and_live_monitoring(rig):
    pki, procs = rig["pki"], rig["procs"]
    # What the daemon really published, from its first estimate on: the daemon connects to this subscriber (a
    # subscriber connecting to the daemon could join after the estimate that turned IsRotating true: seen once).
    sub = Subscriber([], MACHINE, listen=[tcp(rig["sub_port"])])

    async def scenario():
        client = await connect(rig["port"], pki.client_cert, pki.client_key)
        try:
            mt, ms = await client.get_namespace_index(MT_NS), await client.get_namespace_index(MS_NS)
            di, machinery = await client.get_namespace_index(DI_NS), await client.get_namespace_index(MACHINERY_NS)
            changes = []

            class Handler:
                def datachange_notification(self, node, value, data):
                    changes.append(data.monitored_item.Value)

            subscription = await client.create_subscription(50, Handler())
            procs.start("daemon", ["run", "--config", str(rig["cfg"])])
            # Objects/Machines → the machine, found by browsing (as umati's clients do), typed MachineToolType.
            machines = await client.nodes.objects.get_child([f"{machinery}:Machines"])

            async def instance():
                for node in await machines.get_children():
                    if await node.read_type_definition() == ua.NodeId(MACHINE_TOOL_TYPE, mt):
                        return node
                return None
            machine = await wait_async(instance, SLOW_S, "a MachineToolType object under Objects/Machines")
            assert (await machine.read_browse_name()).Name == MACHINE
            ident = await machine.get_child([f"{di}:Identification"])
            assert (await (await ident.get_child([f"{di}:Manufacturer"])).read_value()).Text == IDENTITY["manufacturer"]
            assert await (await ident.get_child([f"{di}:SerialNumber"])).read_value() == IDENTITY["serial_number"]
            uri = await (await ident.get_child([f"{di}:ProductInstanceUri"])).read_value()
            assert uri == IDENTITY["product_instance_uri"]
            # Read only, the typed nodes too: a trusted client's write is refused.
            serial = await ident.get_child([f"{di}:SerialNumber"])
            with pytest.raises(ua.UaStatusCodeError) as refused:
                await serial.write_value("forged")
            assert refused.value.code in (ua.StatusCodes.BadUserAccessDenied, ua.StatusCodes.BadNotWritable), refused
            assert await serial.read_value() == IDENTITY["serial_number"]
            # millsense's own values, one reference away from the instance.
            torque = await child(machine, f"{ms}:{MACHINE}", f"{ms}:Spindle", f"{ms}:torque_nm")
            assert torque is not None
            # The configured tool, typed ToolType, its number its ControlIdentifier1.
            tool = await machine.get_child([f"{mt}:Equipment", f"{mt}:Tools", f"{ms}:T12"])
            assert await (await tool.get_child([f"{mt}:ControlIdentifier1"])).read_value() == 12
            # A mandatory node millsense cannot know says so.
            mode = await machine.get_child([f"{mt}:Monitoring", f"{mt}:MachineTool", f"{mt}:OperationMode"])
            assert (await mode.read_data_value(raise_on_bad_status=False)).StatusCode.value == ua.StatusCodes.BadNoData

            # Monitoring, live: the spindle turns in the daemon's estimates; the value's source time is the
            # time of an estimate the daemon published.
            rotating = await machine.get_child([f"{mt}:Monitoring", f"{ms}:Spindle", f"{mt}:IsRotating"])
            await subscription.subscribe_data_change(rotating)

            async def turning():
                return next((v for v in changes if v.StatusCode.is_good() and v.Value.Value is True), None)
            value = await wait_async(turning, SLOW_S, "Monitoring/Spindle/IsRotating true from the daemon")
            published = wait_for(lambda: [e for e in sub.get("estimate")
                                          if abs(e["t"] - value.SourceTimestamp.timestamp()) < 1e-3], SLOW_S,
                                 "the estimate the value came from, on Zenoh")
            assert published[0]["spindle_rpm"] > 0
        finally:
            await client.disconnect()

    try:
        asyncio.run(scenario())
    finally:
        sub.close()
    assert "opcua.nodesets_loaded" in procs.text("opcua") and "Traceback" not in procs.text("opcua")


def test_each_security_policy_connects_and_refuses_an_untrusted_certificate(rig):
    pki = rig["pki"]

    async def attempt(cert, key, policy):
        client = None
        try:
            client = await connect(rig["port"], cert, key, policy=policy)
            return await client.nodes.server.read_browse_name()
        except Exception as exc:  # noqa: BLE001 - what a refusal looks like to a client
            return exc
        finally:
            if client is not None and client.uaclient.protocol is not None:
                await client.disconnect()

    async def scenario():
        endpoints = await _endpoints(rig["port"])
        assert endpoints == {(p.URI, ua.MessageSecurityMode.SignAndEncrypt) for p in POLICIES.values()}, endpoints
        for name, policy in POLICIES.items():
            trusted = await attempt(pki.client_cert, pki.client_key, policy)
            assert getattr(trusted, "Name", None) == "Server", (name, trusted)
            refused = await attempt(pki.stranger_cert, pki.stranger_key, policy)
            assert isinstance(refused, ua.UaStatusCodeError), (name, refused)
            assert refused.code == ua.StatusCodes.BadCertificateUntrusted, (name, refused)

    asyncio.run(scenario())


async def _endpoints(port: int) -> set[tuple[str, ua.MessageSecurityMode]]:
    from asyncua import Client

    client = Client(f"opc.tcp://127.0.0.1:{port}", timeout=10)
    return {(e.SecurityPolicyUri, e.SecurityMode) for e in await client.connect_and_get_server_endpoints()}
