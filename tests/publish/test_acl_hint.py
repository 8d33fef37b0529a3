"""A command the router's access control drops says the ACL may be why (issue 39).

Through a router with mutual TLS and an ACL (config/zenoh-router.json5, the shop-network example that
tests/publish/test_acl_router.py runs for real), a query the ACL denies is dropped at the router: the
CLI hears nothing, and said only "no daemon answered" with its `try:` line, which sends a user
looking for a stopped daemon. `millsense reset` as a real subprocess with a viewer's certificate (its
policy may not query `cmd/*`) says the router's access control may deny this identity; the same
command with an operator's certificate reaches the daemon (it is there); on a plain loopback session
with no router, no ACL is suggested.
"""

from __future__ import annotations

import subprocess

from millsense.daemon.publish.session import open_session
from tests.conftest import free_tcp_port
from tests.e2e.helpers import CMD, Procs, tcp, write_config

from .helpers import wait_for
from .pki import Pki
from .test_acl_router import MACHINE, _example, _from_file

ACL_HINT = "access control"


def reset(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(CMD + ["reset", *args], capture_output=True, text=True, timeout=120)


def test_a_command_the_routers_acl_drops_names_the_acl(tmp_path):
    pki_dir = tmp_path / "pki"
    pki_dir.mkdir()
    pki = Pki(pki_dir)
    for stem, cn in {"router": "cell-router", "daemon": MACHINE, "viewer": "hmi-01", "operator": "operator-01"}.items():
        pki.issue(stem, cn)
    port = free_tcp_port()
    router = open_session(_from_file(_example("zenoh-router.json5", pki_dir, port)), retry_for_s=0)
    cfg = write_config(tmp_path / "d.toml", machine=MACHINE, daq='transport = "sim"\nscenario = "step"',
                       zenoh_mode="client", interlock='enabled = true\nreset = "off"')
    cfg.write_text(cfg.read_text().replace(
        "[zenoh]\n", f'[zenoh]\nconfig_file = "{_example("zenoh-daemon.json5", pki_dir, port)}"\n'))
    viewer = _example("zenoh-viewer.json5", pki_dir, port)
    operator = _example("zenoh-operator.json5", pki_dir, port)
    try:
        with Procs(tmp_path) as procs:
            daemon = procs.start("daemon", ["run", "--config", str(cfg)])

            def operator_answered():
                # The operator's certificate may send commands: the daemon answers (reset = "off": its refusal).
                # Asked again while the daemon is still starting and its queryables not yet at the router.
                assert daemon.poll() is None, procs.text("daemon")[-2000:]
                p = reset("--machine", MACHINE, "--zenoh-config", str(operator), "--timeout", "5")
                return p if "no daemon answered" not in p.stderr else None
            answered = wait_for(operator_answered, 90.0, "the daemon answers the operator's reset")
            assert answered.returncode == 1 and "off" in answered.stderr, answered.stderr
            assert ACL_HINT not in answered.stderr

            # A viewer's may not: the router drops the query, nothing answers.
            denied = reset("--machine", MACHINE, "--zenoh-config", str(viewer), "--timeout", "3")
            assert daemon.poll() is None, procs.text("daemon")[-2000:]
    finally:
        router.close()
    assert denied.returncode == 1, denied.stderr
    assert f"no daemon answered on millsense/{MACHINE}/cmd/reset within 3 s" in denied.stderr, denied.stderr
    acl_lines = [line for line in denied.stderr.splitlines() if ACL_HINT in line]
    assert acl_lines and "may deny this identity" in acl_lines[0], denied.stderr
    assert "Traceback" not in denied.stderr


def test_a_plain_loopback_session_suggests_no_acl(tmp_path):
    # The demo's case: a peer on loopback, no router, no Zenoh file; nobody listening on the endpoint.
    p = reset("--machine", "nobody-01", "--connect", tcp(free_tcp_port()), "--no-scouting", "--timeout", "1")
    assert p.returncode == 1
    assert "no daemon answered on millsense/nobody-01/cmd/reset within 1 s" in p.stderr, p.stderr
    assert ACL_HINT not in p.stderr, p.stderr
