"""The companion specifications' nodesets (issue 42): the real NodeSet2 files from the npm registry
(tests/opcua/nodesets.py), imported by daemon/opcua/nodesets.py into a real asyncua server; a folder that
cannot be imported stops `millsense opcua` with exit 78, naming the file and the node."""

from __future__ import annotations

import asyncio
import shutil
import subprocess

import pytest

pytest.importorskip("asyncua", reason="the opcua extra (asyncua) is not installed")
from asyncua import Server, ua  # noqa: E402

from millsense.daemon.opcua.nodesets import (  # noqa: E402
    DI_NS,
    MACHINE_TOOL_NS,
    REQUIRED_MODELS,
    NodesetError,
    find_nodesets,
    import_nodesets,
)
from millsense.daemon.opcua.machine_nodes import MachineNodes, Namespaces  # noqa: E402
from millsense.daemon.opcua.machine_tool import MachineToolInstance  # noqa: E402
from millsense.daemon.opcua.settings import Identification  # noqa: E402
from tests.conftest import free_tcp_port  # noqa: E402
from tests.e2e.helpers import CMD, tcp, write_config  # noqa: E402
from tests.opcua import nodesets as fetched  # noqa: E402
from tests.opcua.rig import make_pki  # noqa: E402

DI_DESIGN_TOOL_ONLY = "ns=1;i=73"  # DI's parentless `Configuration` template (DesignToolOnly="true")
MACHINE_TOOL_TYPE = 13             # MachineToolType in OPC 40501's NodeIds.csv


@pytest.fixture(scope="module")
def six():
    return fetched.folder()


def _copy(six, tmp_path):
    """A writable copy of the six files (the shared folder is read-only)."""
    folder = tmp_path / "nodesets"
    folder.mkdir()
    for name in fetched.FILES:
        shutil.copyfile(six / name, folder / name)
    return folder


def test_the_six_models_are_found_in_dependency_order_by_what_each_file_declares(six, tmp_path):
    order = [n.model_uri for n in find_nodesets(six)]
    assert sorted(order) == sorted(REQUIRED_MODELS)
    for n in find_nodesets(six):
        for required in n.requires:  # each after every model it requires
            assert required not in REQUIRED_MODELS or order.index(required) < order.index(n.model_uri), (n, order)
    # A model missing: named, with its URI.
    folder = _copy(six, tmp_path)
    (folder / "Opc.Ua.Machinery.Jobs.Nodeset2.xml").unlink()
    with pytest.raises(NodesetError, match=r"no NodeSet2 file for Machinery Jobs \(http://opcfoundation.org/UA/Machinery/Jobs/\)"):
        find_nodesets(folder)


def test_the_official_nodesets_import_into_asyncua_with_their_types_and_a_machine_tool_fills_from_payloads(six):
    async def scenario():
        server = Server()
        await server.init()
        loaded = await import_nodesets(server, six)
        assert [n.name for n in loaded][-1] == "MachineTool (OPC 40501)"
        mt = await server.get_namespace_index(MACHINE_TOOL_NS)
        machine_tool_type = server.get_node(ua.NodeId(MACHINE_TOOL_TYPE, mt))
        assert (await machine_tool_type.read_browse_name()) == ua.QualifiedName("MachineToolType", mt)
        # The DesignToolOnly templates are left out, as the UANodeSet schema says (and their import failed).
        di = await server.get_namespace_index(DI_NS)
        template = server.get_node(ua.NodeId.from_string(DI_DESIGN_TOOL_ONLY.replace("ns=1", f"ns={di}")))
        with pytest.raises(ua.UaStatusCodeError):
            await template.read_browse_name()
        # The data types were loaded after the last file: Machinery Jobs' OptionSet structure among them.
        assert hasattr(ua, "OutputInformationDataType")

        # A MachineToolType object on that server: what an estimate writes, and a null that says BadNoData.
        ns = await Namespaces.register(server)
        own = await MachineNodes(server, ns, "m1").create(server.nodes.objects)
        machine = await MachineToolInstance(server, "m1", ns.ms).create(
            Identification("ACME", "42", "urn:acme:42"), [7], own.obj)
        assert await machine.obj.read_type_definition() == ua.NodeId(MACHINE_TOOL_TYPE, mt)
        rotating = machine.nodes["IsRotating"]
        assert (await rotating.read_data_value(raise_on_bad_status=False)).StatusCode.value == \
            ua.StatusCodes.BadWaitingForInitialData
        await machine.apply("estimate", {"t": 1.7e9, "spindle_rpm": 3000.0, "feed_override_pct": 80.0, "program": 12})
        assert await rotating.read_value() is True
        assert await machine.nodes["FeedOverride"].read_value() == 80.0
        assert await machine.nodes["ProgramName"].read_value() == "12"
        await machine.apply("estimate", {"t": 1.7e9 + 0.1, "spindle_rpm": None, "feed_override_pct": 80.0,
                                         "program": None})
        for name in ("IsRotating", "ProgramName"):
            dv = await machine.nodes[name].read_data_value(raise_on_bad_status=False)
            assert dv.StatusCode.value == ua.StatusCodes.BadNoData, (name, dv)
        assert await machine.nodes["FeedOverride"].read_value() == 80.0
        # A stopped spindle sends no estimate: the status, once a second, says no revolution closed since the last.
        await machine.apply("estimate", {"t": 1.7e9 + 0.2, "spindle_rpm": 3000.0})
        await machine.apply("status", {"t": 1.7e9 + 1, "revolutions": 50, "daq_link": "up"})
        await machine.apply("status", {"t": 1.7e9 + 2, "revolutions": 99, "daq_link": "up"})
        assert await rotating.read_value() is True
        await machine.apply("status", {"t": 1.7e9 + 3, "revolutions": 99, "daq_link": "up"})
        assert await rotating.read_value() is False
        await machine.apply("status", {"t": 1.7e9 + 4, "revolutions": 99, "daq_link": "down"})
        assert (await rotating.read_data_value(raise_on_bad_status=False)).StatusCode.value == ua.StatusCodes.BadNoData
        await machine.apply("estimate", {"t": 1.7e9 + 5, "spindle_rpm": 3000.0})
        assert await rotating.read_value() is True
        await machine.gone()
        assert (await rotating.read_data_value(raise_on_bad_status=False)).StatusCode.value == ua.StatusCodes.BadNoData
        await machine.apply("process", {"tool": 7, "tool_processes": 3, "tool_wear_pct": 2.5})
        assert [await n.read_value() for n in machine.tools[7]] == [3, 2.5]

    asyncio.run(scenario())


def test_a_nodeset_folder_that_fails_to_import_exits_78_naming_the_file_and_the_node(six, tmp_path):
    folder = _copy(six, tmp_path)
    broken = folder / "Opc.Ua.Di.NodeSet2.xml"  # the first imported: the test stops early (CPU)
    text = broken.read_text(encoding="utf-8")
    # An object whose parent is in no nodeset: asyncua refuses it (BadParentNodeIdInvalid).
    bad = ('<UAObject NodeId="ns=1;i=990001" BrowseName="1:Orphan" ParentNodeId="ns=1;i=990000">'
           '<DisplayName>Orphan</DisplayName><References>'
           '<Reference ReferenceType="HasComponent" IsForward="false">ns=1;i=990000</Reference>'
           '<Reference ReferenceType="HasTypeDefinition">i=58</Reference></References></UAObject>')
    broken.write_text(text.replace("</UANodeSet>", bad + "</UANodeSet>"), encoding="utf-8")
    pki = make_pki(tmp_path / "pki")
    cfg = write_config(tmp_path / "d.toml", machine="m1", daq='transport = "sim"\nscenario = "step"')
    cfg.write_text(cfg.read_text() + '\n[opcua]\nmanufacturer = "ACME"\nserial_number = "42"\n'
                                     'product_instance_uri = "urn:acme:42"\n')
    done = subprocess.run(CMD + ["opcua", "--endpoint", f"opc.tcp://127.0.0.1:{free_tcp_port()}", "--cert",
                                 str(pki.server_cert), "--key", str(pki.server_key), "--trust-dir", str(pki.trust_dir),
                                 "--config", str(cfg), "--connect", tcp(free_tcp_port()), "--no-scouting",
                                 "--nodesets", str(folder)],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 78, done.stderr
    assert "--nodesets" in done.stderr and str(broken) in done.stderr and "ns=1;i=990001" in done.stderr, done.stderr
    assert "BadParentNodeIdInvalid" in done.stderr and "Traceback" not in done.stderr, done.stderr
    assert "opcua.listening" not in done.stderr  # never served with a model it could not load
