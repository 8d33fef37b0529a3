"""`millsense router` for real: a subprocess that routes between a daemon and its readers.

Every node here is a Zenoh *client* of the router with only the router's
endpoint, so nothing reaches anyone unless `millsense router` relays it. With
the shipped config/zenoh-router.json5 (mutual TLS, access control) a spoofer
holding a viewer's certificate puts estimates under the daemon's keys and the
router drops them while the daemon's own go through. SIGTERM stops it with
exit 0 and a log line; a configuration that cannot work exits 78 naming the key.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import zenoh

from tests.conftest import free_tcp_port
from tests.e2e.helpers import Procs, Subscriber, tcp, write_config

from .helpers import wait_for
from .pki import Pki
from .test_acl_router import MACHINE, Seen, _client, _example

REPO = Path(__file__).resolve().parents[2]


def _events(procs: Procs, name: str) -> list[dict]:
    out = []
    for line in procs.text(name, "out").splitlines():
        try:
            out.append(json.loads(line))
        except ValueError:
            pass
    return out


def _event(procs: Procs, name: str, event: str) -> dict | None:
    return next((e for e in _events(procs, name) if e.get("event") == event), None)


def _start_router(procs: Procs, args: list[str]) -> subprocess.Popen:
    router = procs.start("router", ["router", "--log-format", "json", *args])
    wait_for(lambda: _event(procs, "router", "router.started") or router.poll() is not None, 30.0, "router.started")
    assert router.poll() is None, procs.text("router", "err")[-2000:] + procs.text("router", "out")[-2000:]
    return router


def _stop_cleanly(procs: Procs, router: subprocess.Popen) -> None:
    router.send_signal(signal.SIGTERM)
    assert router.wait(20) == 0, procs.text("router", "err")[-2000:]
    assert _event(procs, "router", "router.stopped") is not None
    assert "Traceback" not in procs.text("router", "err") + procs.text("router", "out")


def test_daemon_and_subscriber_meet_only_through_the_router(tmp_path):
    port = free_tcp_port()
    cfg = write_config(tmp_path / "d.toml", machine="m-routed", daq='transport = "sim"\nscenario = "step"',
                       zenoh_mode="client", zenoh_connect=[tcp(port)])
    with Procs(tmp_path) as procs:
        router = _start_router(procs, ["--listen", tcp(port)])
        started = _event(procs, "router", "router.started")
        assert started["listen"] == [tcp(port)] and started["access_control"] is False
        assert _event(procs, "router", "router.no_access_control") is not None  # a bench router says so
        daemon = procs.start("daemon", ["run", "--config", str(cfg)])
        sub = Subscriber([tcp(port)], machine="m-routed", mode="client")
        try:
            wait_for(lambda: len(sub.get("estimate")) >= 3 or daemon.poll() is not None, 60.0,
                     "estimates relayed by the router")
            assert daemon.poll() is None, procs.text("daemon", "out")[-3000:]
            assert all(e["machine"] == "m-routed" for e in sub.get("estimate"))
            _stop_cleanly(procs, router)
            # with the router gone, the relay stops: the estimates above crossed it and nothing else
            time.sleep(0.5)
            n = len(sub.get("estimate"))
            time.sleep(1.0)
            assert len(sub.get("estimate")) == n
        finally:
            sub.close()


def test_router_with_the_shipped_acl_drops_a_spoofers_puts(tmp_path):
    pki_dir = tmp_path / "pki"
    pki_dir.mkdir()
    pki = Pki(pki_dir)
    for stem, cn in {"router": "cell-router", "daemon": MACHINE, "viewer": "hmi-01", "spoofer": "hmi-02"}.items():
        pki.issue(stem, cn)
    port = free_tcp_port()
    router_json5 = _example("zenoh-router.json5", pki_dir, port)
    cfg = write_config(tmp_path / "d.toml", machine=MACHINE, daq='transport = "sim"\nscenario = "step"',
                       zenoh_mode="client", interlock='enabled = true\nreset = "off"')
    daemon_json5 = _example("zenoh-daemon.json5", pki_dir, port)
    cfg.write_text(cfg.read_text().replace("[zenoh]\n", f'[zenoh]\nconfig_file = "{daemon_json5}"\n'))
    sessions: list[zenoh.Session] = []
    with Procs(tmp_path) as procs:
        try:
            router = _start_router(procs, ["--config", str(router_json5)])
            started = _event(procs, "router", "router.started")
            assert started["encrypted"] is True and started["access_control"] is True
            daemon = procs.start("daemon", ["run", "--config", str(cfg)])
            viewer = _client(pki_dir, port, "zenoh-viewer.json5", "viewer")
            spoofer = _client(pki_dir, port, "zenoh-viewer.json5", "spoofer")  # a real viewer's certificate
            sessions += [viewer, spoofer]
            seen = Seen()
            sub = viewer.declare_subscriber("millsense/**", seen)
            wait_for(lambda: len(seen.keys("/estimate")) >= 3 or daemon.poll() is not None, 60.0,
                     "the daemon's estimates at the viewer, through the router")
            assert daemon.poll() is None, procs.text("daemon", "out")[-3000:]
            n0 = len(seen.keys("/estimate"))
            spoof = {"rev": 10**9, "torque_nm": 1234.5, "valid": True, "spoof": True}
            for _ in range(20):
                spoofer.put(f"millsense/{MACHINE}/estimate", json.dumps(spoof).encode())
                time.sleep(0.05)
            # the viewer's link stayed up all along: more real estimates arrived after the spoofing
            wait_for(lambda: len(seen.keys("/estimate")) >= n0 + 10, 30.0, "real estimates after the spoofing")
            sub.undeclare()
            assert seen.spoofed() == [], seen.spoofed()[:3]
            _stop_cleanly(procs, router)
        finally:
            for s in sessions:
                s.close()


BAD_ACL = """{
  mode: "router",
  scouting: { multicast: { enabled: false } },
  access_control: {
    enabled: true, default_permission: "deny",
    rules: [{ id: "r", permission: "allow", flows: ["ingress"], messages: ["put"], key_exprs: ["millsense/**"] }],
    subjects: [{ id: "s", cert_common_names: ["hmi-01"] }],
    policies: [{ rules: ["no-such-rule"], subjects: ["s"] }],
  },
}"""


@pytest.mark.parametrize("case, text, named", [
    ("missing", None, "does not exist"),
    ("syntax", '{ mode: "router", listen: { endpoints: [ }', "not a Zenoh configuration"),
    ("unknown key", '{ mode: "router", lisen: { endpoints: [] } }', "lisen"),
    ("client file", '{ mode: "client" }', "mode: 'client'"),
    ("certificate path", "shipped", "transport.link.tls.root_ca_certificate"),
    ("acl", BAD_ACL, "access_control"),
])
def test_a_config_that_cannot_work_exits_78_naming_it(tmp_path, case, text, named):
    path = tmp_path / "router.json5"
    if text == "shipped":  # the shipped file, its /etc/millsense/tls certificates absent here
        port = free_tcp_port()
        text = (REPO / "config" / "zenoh-router.json5").read_text().replace("tls/0.0.0.0:7447", f"tls/127.0.0.1:{port}")
        text = text.replace("/etc/millsense/tls/", f"{tmp_path}/no-tls/")
    if text is not None:
        path.write_text(text)
    args = ["--config", str(path)]
    if case == "acl":
        args += ["--listen", tcp(free_tcp_port())]
    with Procs(tmp_path) as procs:
        p = procs.start("router", ["router", "--log-format", "json", *args])
        assert p.wait(30) == 78, procs.text("router", "err")
        err = procs.text("router", "err")
    assert named in err and str(path) in err, err
    assert "Traceback" not in err and ".rs:" not in err, err


UNIT = REPO / "systemd" / "millsense-router.service"


def test_unit_verifies_clean(tmp_path):
    from tests.ops.test_systemd import INSTALLED, SYSTEMD_ANALYZE

    if SYSTEMD_ANALYZE is None:
        pytest.skip("systemd-analyze not installed")
    script = Path(sys.executable).with_name("millsense")  # the venv's console script (pip install -e .)
    text = UNIT.read_text()
    assert f"{INSTALLED} router --config " in text and "RestartPreventExitStatus=78" in text
    (tmp_path / UNIT.name).write_text(text.replace(INSTALLED, str(script)))
    p = subprocess.run([SYSTEMD_ANALYZE, "verify", UNIT.name], capture_output=True, text=True, timeout=60, cwd=tmp_path)
    assert (p.returncode, p.stdout, p.stderr) == (0, "", "")


def test_the_router_relays_tls_under_mdwe(tmp_path):
    """The unit's MemoryDenyWriteExecute=yes, for real: the router (Zenoh, rustls) relays over mTLS with W+X refused."""
    from tests.ops.test_systemd import MDWE_EXEC, _mdwe_supported

    if not _mdwe_supported():
        pytest.skip("kernel without PR_SET_MDWE (Linux < 6.3)")
    pki_dir = tmp_path / "pki"
    pki_dir.mkdir()
    pki = Pki(pki_dir)
    for stem, cn in {"router": "cell-router", "daemon": MACHINE, "viewer": "hmi-01"}.items():
        pki.issue(stem, cn)
    port = free_tcp_port()
    router_json5 = _example("zenoh-router.json5", pki_dir, port)
    with Procs(tmp_path) as procs:
        # MDWE_EXEC turns W+X off for itself, then runs `python -m millsense.daemon router` in that process
        p = subprocess.Popen([sys.executable, "-c", MDWE_EXEC, "-m", "millsense.daemon", "router", "--log-format", "json",
                              "--config", str(router_json5)], stdout=open(tmp_path / "mdwe.out", "wb"),  # noqa: SIM115
                             stderr=open(tmp_path / "mdwe.err", "wb"))  # noqa: SIM115
        procs.procs.append(p)
        wait_for(lambda: "router.started" in (tmp_path / "mdwe.out").read_text() or p.poll() is not None, 30.0,
                 "router.started under MDWE")
        assert p.poll() is None, (tmp_path / "mdwe.err").read_text()
        daemon_side = zenoh.Config.from_json5(_example("zenoh-daemon.json5", pki_dir, port).read_text())
        daemon_side.insert_json5("transport/shared_memory/enabled", "false")
        publisher = zenoh.open(daemon_side)
        viewer = _client(pki_dir, port, "zenoh-viewer.json5", "viewer")
        try:
            seen = Seen()
            sub = viewer.declare_subscriber("millsense/**", seen)
            pub = publisher.declare_publisher(f"millsense/{MACHINE}/estimate")
            wait_for(lambda: pub.matching_status.matching, 30.0, "the viewer's subscription, through the router")
            pub.put(json.dumps({"rev": 1}).encode())
            wait_for(lambda: seen.keys("/estimate"), 30.0, "a put relayed over mTLS under MDWE")
            sub.undeclare()
            pub.undeclare()
        finally:
            viewer.close()
            publisher.close()
        p.send_signal(signal.SIGTERM)
        assert p.wait(20) == 0
    assert "Traceback" not in (tmp_path / "mdwe.err").read_text()
