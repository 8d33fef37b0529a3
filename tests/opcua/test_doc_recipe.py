"""docs/opcua.md's client recipe, run as written: its asyncua block against `millsense opcua` and a daemon.

The block is taken from the page (the one after the comment naming this test), its endpoint and
machine id pointed at this test's server and daemon, and run as a separate Python process from a
folder holding `client.der`, `client.pem` and `server.der`, as the page says. The client certificate
carries the application URI the block sets (read from the block), and is put in the trust list as
step 2 says. It must print the daemon's torque.
"""

from __future__ import annotations

import asyncio
import re
from datetime import UTC, datetime
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("asyncua", reason="the opcua extra (asyncua) is not installed")

from tests.conftest import free_tcp_port  # noqa: E402
from tests.e2e.helpers import Procs, Subscriber, tcp, wait_for, write_config  # noqa: E402
from tests.opcua.pki import make_app_cert  # noqa: E402
from tests.opcua.rig import MS_NS, SLOW_S, child, connect, make_pki, start_opcua, wait_async  # noqa: E402

DOC = Path(__file__).resolve().parents[2] / "docs" / "opcua.md"
MARKER = "<!-- tests/opcua/test_doc_recipe.py runs this block"
MACHINE = "recipe-01"


def recipe() -> str:
    text = DOC.read_text(encoding="utf-8")
    after = text[text.index(MARKER):]
    return re.search(r"```python\n(.*?)```", after, re.S).group(1)


def test_the_pages_block_is_one_python_program_with_an_endpoint_and_a_machine():
    code = recipe()
    compile(code, "docs/opcua.md", "exec")
    assert re.search(r'^URL = "opc\.tcp://[^"]+"', code, re.M)
    assert re.search(r'^MACHINE = "[^"]+"', code, re.M)
    assert "Basic256Sha256,SignAndEncrypt" in code


def test_the_recipe_reads_the_torque_of_a_live_daemon(tmp_path):
    code = recipe()
    uri = re.search(r'application_uri = "([^"]+)"', code).group(1)
    pki = make_pki(tmp_path / "pki")
    client_dir = tmp_path / "client"
    client_dir.mkdir()
    cert, key = make_app_cert(client_dir, "client", uri, server=False)            # step 1: client.der, client.pem
    shutil.copy(cert, pki.trust_dir / "scada-01.der")                              # step 2: trust it
    shutil.copy(pki.server_cert, client_dir / "server.der")
    z_port, ua_port, sub_port = free_tcp_port(), free_tcp_port(), free_tcp_port()
    cfg = write_config(tmp_path / "d.toml", machine=MACHINE, daq='transport = "sim"\nscenario = "step"',
                       zenoh_listen=[tcp(z_port)], zenoh_connect=[tcp(sub_port)], interlock="enabled = true")
    # every estimate the daemon publishes (it connects to this subscriber: none missed), to check what the recipe read
    sub = Subscriber([], MACHINE, listen=[tcp(sub_port)])
    url = f"opc.tcp://127.0.0.1:{ua_port}"
    code = re.sub(r'^URL = "[^"]+"', f'URL = "{url}"', code, flags=re.M)
    code = re.sub(r'^MACHINE = "[^"]+"', f'MACHINE = "{MACHINE}"', code, flags=re.M)
    with Procs(tmp_path) as procs:
        start_opcua(procs, "opcua", pki, ua_port, z_port)
        procs.start("daemon", ["run", "--config", str(cfg)])

        async def cutting_torque():   # the server has a good torque of a cutting revolution to give
            client = await connect(ua_port, pki.client_cert, pki.client_key)
            try:
                ms = await client.get_namespace_index(MS_NS)

                async def cutting():
                    node = await child(client.nodes.objects, f"{ms}:millsense", f"{ms}:{MACHINE}", f"{ms}:Spindle",
                                       f"{ms}:cutting")
                    return node is not None and (await node.read_data_value(raise_on_bad_status=False)).Value.Value

                await wait_async(cutting, SLOW_S, "a cutting revolution on the server")
            finally:
                await client.disconnect()

        try:
            asyncio.run(cutting_torque())
            out = subprocess.run([sys.executable, "-c", code], cwd=client_dir, capture_output=True, text=True,
                                 timeout=SLOW_S)
            assert out.returncode == 0, out.stderr
            m = re.fullmatch(r"torque_nm (\S+) at (\S+ \S+)\n", out.stdout)
            assert m, out.stdout
            read_t = datetime.fromisoformat(m.group(2))
            read_t = (read_t if read_t.tzinfo else read_t.replace(tzinfo=UTC)).timestamp()
            # the daemon's torque of the revolution at that time, as it published it (not the cut's phase when the
            # recipe ran: on a loaded box the step cut may have reached its overload, the feed held, the tool in air)
            published = wait_for(lambda: [e for e in sub.get("estimate") if abs(e["t"] - read_t) < 1e-3], SLOW_S,
                                 "the estimate the recipe's value came from")
        finally:
            sub.close()
    assert published[0]["torque_nm"] is not None
    assert float(m.group(1)) == pytest.approx(published[0]["torque_nm"], rel=1e-9, abs=1e-9)
