"""`Objects/millsense` lists each machine once (issue 39).

A new user browsing the address space in a client saw every machine twice under `Objects/millsense`:
the folder held two hierarchical references to each machine's object (the folder's Organizes, from
asyncua's `add_object`, and the HasNotifier of the event-notifier hierarchy). A real daemon on the
simulator, `millsense opcua` as a subprocess and a real asyncua client browsing as a generic client
does (hierarchical references with their subtypes, the default of a Browse).
"""

from __future__ import annotations

import asyncio
from collections import Counter

import pytest

asyncua = pytest.importorskip("asyncua", reason="the opcua extra (asyncua) is not installed")
from asyncua import ua  # noqa: E402

from tests.conftest import free_tcp_port  # noqa: E402
from tests.e2e.helpers import Procs, tcp, write_config  # noqa: E402
from tests.opcua.rig import MS_NS, SLOW_S, child, connect, make_pki, start_opcua, wait_async  # noqa: E402

MACHINE = "browse-01"


async def hierarchical_targets(node) -> list[ua.NodeId]:
    """Every target of a Browse of `node` as a generic client does it (UaExpert's tree, asyncua's
    get_children): forward hierarchical references, subtypes included. One entry per reference."""
    refs = await node.get_references(refs=ua.ObjectIds.HierarchicalReferences, direction=ua.BrowseDirection.Forward,
                                     includesubtypes=True)
    return [ref.NodeId for ref in refs]


def test_objects_millsense_lists_each_machine_once(tmp_path):
    pki = make_pki(tmp_path / "pki")
    z_port, ua_port = free_tcp_port(), free_tcp_port()
    cfg = write_config(tmp_path / "d.toml", machine=MACHINE, daq='transport = "sim"\nscenario = "step"',
                       zenoh_listen=[tcp(z_port)])
    with Procs(tmp_path) as procs:
        start_opcua(procs, "opcua", pki, ua_port, z_port)
        procs.start("daemon", ["run", "--config", str(cfg)])

        async def scenario():
            client = await connect(ua_port, pki.client_cert, pki.client_key)
            try:
                ms = await client.get_namespace_index(MS_NS)
                machine = await wait_async(lambda: child(client.nodes.objects, f"{ms}:millsense", f"{ms}:{MACHINE}"),
                                           SLOW_S, "the machine's object")
                rev = await machine.get_child([f"{ms}:Spindle", f"{ms}:rev"])

                async def estimated():  # its liveliness, then its first estimate and status, are all in
                    return (await rev.read_data_value(raise_on_bad_status=False)).StatusCode.is_good()
                await wait_async(estimated, SLOW_S, "the machine's first estimate")

                folder = await client.nodes.objects.get_child([f"{ms}:millsense"])
                listed = await hierarchical_targets(folder)
                assert listed == [machine.nodeid], [n.to_string() for n in listed]
                assert [(await n.read_browse_name()).Name for n in await folder.get_children()] == [MACHINE]
                # Nothing under the machine is listed twice either.
                twice = {n.to_string(): c for n, c in Counter(await hierarchical_targets(machine)).items() if c > 1}
                assert not twice, twice
                # The path a client is told to browse still leads there (docs/opcua.md).
                assert await child(client.nodes.objects, f"{ms}:millsense", f"{ms}:{MACHINE}", f"{ms}:alive")
            finally:
                await client.disconnect()

        asyncio.run(scenario())
