"""systemd/millsense-opcua.service, checked by systemd's own tool, and its MemoryDenyWriteExecute=yes
checked for real: the server (asyncua, cryptography, Zenoh) serving an encrypted session under the
kernel's MDWE (the same check tests/ops/test_systemd.py makes for the daemon)."""

from __future__ import annotations

import asyncio
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.conftest import REPO, free_tcp_port
from tests.e2e.helpers import tcp
from tests.ops.test_systemd import INSTALLED, MDWE_EXEC, SYSTEMD_ANALYZE, _mdwe_supported

UNIT = REPO / "systemd" / "millsense-opcua.service"


@pytest.mark.skipif(SYSTEMD_ANALYZE is None, reason="systemd-analyze not installed")
def test_unit_verifies_clean(tmp_path):
    script = Path(sys.executable).with_name("millsense")  # the venv's console script (pip install -e .)
    text = UNIT.read_text()
    assert f"{INSTALLED} opcua " in text and "RestartPreventExitStatus=78" in text
    (tmp_path / UNIT.name).write_text(text.replace(INSTALLED, str(script)))
    p = subprocess.run([SYSTEMD_ANALYZE, "verify", UNIT.name], capture_output=True, text=True, timeout=60, cwd=tmp_path)
    assert (p.returncode, p.stdout, p.stderr) == (0, "", "")


@pytest.mark.skipif(not _mdwe_supported(), reason="kernel without PR_SET_MDWE (Linux < 6.3)")
def test_the_opcua_server_serves_an_encrypted_session_under_mdwe(tmp_path):
    pytest.importorskip("asyncua", reason="the opcua extra (asyncua) is not installed")
    from tests.opcua.rig import connect, make_pki

    pki = make_pki(tmp_path / "pki")
    port = free_tcp_port()
    err = tmp_path / "opcua.err"
    args = ["-m", "millsense.daemon", "opcua", "--endpoint", f"opc.tcp://127.0.0.1:{port}", "--cert",
            str(pki.server_cert), "--key", str(pki.server_key), "--trust-dir", str(pki.trust_dir),
            "--connect", tcp(free_tcp_port()), "--no-scouting", "--log-format", "json"]
    with open(err, "wb") as stderr:
        p = subprocess.Popen([sys.executable, "-c", MDWE_EXEC, *args], stderr=stderr)
    try:
        deadline = time.monotonic() + 60
        while "opcua.listening" not in err.read_text(errors="replace"):
            assert p.poll() is None, err.read_text(errors="replace")
            assert time.monotonic() < deadline, err.read_text(errors="replace")
            time.sleep(0.05)

        async def session():
            client = await connect(port, pki.client_cert, pki.client_key)
            try:
                return (await client.nodes.server.read_browse_name()).Name
            finally:
                await client.disconnect()

        assert asyncio.run(session()) == "Server"
    finally:
        p.kill()
        p.wait(10)
    assert "Traceback" not in err.read_text(errors="replace")
