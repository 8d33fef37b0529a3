"""The shop-network example for real: a router with mutual TLS and access control, a real daemon behind it.

config/zenoh-router.json5 runs in a Zenoh session in mode "router" (a working
router, shared/notes/libraries.md); `millsense run` is a client of it with
config/zenoh-daemon.json5; viewers and operators are clients with
zenoh-viewer.json5 / zenoh-operator.json5. Certificates come from the
`cryptography` package (tests/publish/pki.py). A node holding a viewer's
certificate tries what the issue's attacker did (finding 2): spoofed
estimates, alarms and an alive token under a machine's keys, and a fake
`cmd/reset` queryable. None of it may reach anyone, while the real daemon's
publications reach the viewer. Issue 14: the same viewer certificate can
neither tell the daemon a context (`millsense/<m>/context`) nor reach
`cmd/limits`, while a CNC adapter's certificate (zenoh-adapter.json5) tells
it the context its estimates then carry, and an operator reaches `cmd/limits`.
"""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import zenoh

from millsense.daemon.publish.session import open_session
from tests.conftest import free_tcp_port
from tests.e2e.helpers import Procs, write_config

from .helpers import wait_for
from .pki import Pki

CONFIG = Path(__file__).resolve().parents[2] / "config"
MACHINE = "mch10-01"  # the daemon certificate's CN, as in the examples


def _example(name: str, pki: Path, port: int) -> Path:
    """A shipped JSON5 example with the test's certificate folder and port; nothing else changed."""
    text = (CONFIG / name).read_text()
    text = text.replace("/etc/millsense/tls/", f"{pki}/")
    text = text.replace("tls/0.0.0.0:7447", f"tls/127.0.0.1:{port}")
    text = text.replace("tls/cell-router.plant.lan:7447", f"tls/localhost:{port}")
    out = pki / f"{port}-{name}"
    out.write_text(text)
    return out


def _client(pki: Path, port: int, example: str, stem: str) -> zenoh.Session:
    """A client from a shipped example, presenting certificate `stem` (a viewer file with another CN...)."""
    text = _example(example, pki, port).read_text()
    for kind in ("viewer", "operator", "adapter"):
        text = text.replace(f"/{kind}.key", f"/{stem}.key").replace(f"/{kind}.pem", f"/{stem}.pem")
    conf = zenoh.Config.from_json5(text)
    conf.insert_json5("transport/shared_memory/enabled", "false")
    return zenoh.open(conf)


def _from_file(path: Path) -> SimpleNamespace:
    return SimpleNamespace(mode="peer", connect=[], listen=[], multicast_scouting=True,
                           config_file=str(path), model_fields_set={"config_file"})


class Seen:
    """Every sample a subscriber gets, decoded if it can be."""

    def __init__(self) -> None:
        self.items: list[tuple[str, object]] = []
        self.lock = threading.Lock()

    def __call__(self, sample) -> None:
        try:
            body = json.loads(sample.payload.to_bytes())
        except ValueError:
            body = sample.payload.to_bytes()
        with self.lock:
            self.items.append((str(sample.key_expr), body))

    def keys(self, suffix: str) -> list[object]:
        with self.lock:
            return [b for k, b in self.items if k.endswith(suffix)]

    def spoofed(self) -> list[tuple[str, object]]:
        with self.lock:
            return [(k, b) for k, b in self.items if "ghost" in k or (isinstance(b, dict) and b.get("spoof"))]


def test_router_acl_stops_spoofing_and_lets_the_daemon_through(tmp_path):
    pki_dir = tmp_path / "pki"
    pki_dir.mkdir()
    pki = Pki(pki_dir)
    for stem, cn in {"router": "cell-router", "daemon": MACHINE, "viewer": "hmi-01", "spoofer": "hmi-02",
                     "operator": "operator-01", "stranger": "laptop-17", "adapter": "cnc-adapter-01"}.items():
        pki.issue(stem, cn)
    port = free_tcp_port()
    router = open_session(_from_file(_example("zenoh-router.json5", pki_dir, port)), retry_for_s=0)
    cfg = write_config(tmp_path / "d.toml", machine=MACHINE, daq='transport = "sim"\nscenario = "step"',
                       zenoh_mode="client", interlock='enabled = true\nreset = "off"')
    daemon_json5 = _example("zenoh-daemon.json5", pki_dir, port)
    cfg.write_text(cfg.read_text().replace("[zenoh]\n", f'[zenoh]\nconfig_file = "{daemon_json5}"\n'))
    sessions: list[zenoh.Session] = []
    entities = []
    with Procs(tmp_path) as procs:
        try:
            daemon = procs.start("daemon", ["run", "--config", str(cfg)])
            viewer = _client(pki_dir, port, "zenoh-viewer.json5", "viewer")
            operator = _client(pki_dir, port, "zenoh-operator.json5", "operator")
            spoofer = _client(pki_dir, port, "zenoh-viewer.json5", "spoofer")  # a real viewer's certificate
            stranger = _client(pki_dir, port, "zenoh-viewer.json5", "stranger")  # the plant CA's, in no subject
            adapter = _client(pki_dir, port, "zenoh-adapter.json5", "adapter")
            sessions += [viewer, operator, spoofer, stranger, adapter]
            seen_viewer, seen_operator, seen_stranger = Seen(), Seen(), Seen()
            alive: list[str] = []
            alive_kinds: list[str] = []   # with PUT / DELETE, for the message
            entities += [
                viewer.declare_subscriber("millsense/**", seen_viewer),
                operator.declare_subscriber("millsense/**", seen_operator),
                stranger.declare_subscriber("millsense/**", seen_stranger),
                viewer.liveliness().declare_subscriber("millsense/*/alive", lambda s: (
                    alive.append(str(s.key_expr)), alive_kinds.append(f"{s.kind}: {s.key_expr}")), history=True),
            ]

            # -- the daemon's publications reach the viewer through the router
            wait_for(lambda: len(seen_viewer.keys("/estimate")) >= 3 or daemon.poll() is not None, 60.0,
                     "estimates from the daemon at the viewer")
            assert daemon.poll() is None, procs.text("daemon", "out")[-3000:]
            assert f"millsense/{MACHINE}/alive" in alive

            # -- the attacker, with a viewer's certificate: a fake command queryable and a fake machine
            fake_queries: list[str] = []

            def fake_reset(query) -> None:
                fake_queries.append(str(query.key_expr))
                query.reply(query.key_expr, json.dumps({"ok": True, "spoof": True}).encode())

            entities += [
                spoofer.declare_queryable(f"millsense/{MACHINE}/cmd/reset", fake_reset),
                spoofer.declare_queryable("millsense/ghost-01/cmd/reset", fake_reset),
                spoofer.declare_queryable(f"millsense/{MACHINE}/status", fake_reset),
                spoofer.liveliness().declare_token("millsense/ghost-01/alive"),
            ]
            spoof_estimate = {"rev": 10**9, "torque_nm": 1234.5, "valid": True, "spoof": True}
            spoof_alarm = {"level": "crash", "spoof": True}
            # Spoof while real estimates keep coming: the viewer's link is up all along (positive control).
            n0 = len(seen_viewer.keys("/estimate"))
            for _ in range(20):
                for key, body in ((f"millsense/{MACHINE}/estimate", spoof_estimate),
                                  (f"millsense/{MACHINE}/alarm", spoof_alarm),
                                  ("millsense/ghost-01/estimate", spoof_estimate)):
                    spoofer.put(key, json.dumps(body).encode())
                time.sleep(0.05)
            wait_for(lambda: len(seen_viewer.keys("/estimate")) >= n0 + 10, 30.0, "more real estimates after the spoofing")

            # -- context (issue 14): the viewer's certificate may not tell the daemon what the machine does ...
            spoof_context = {"program": 6666, "tool": 66, "operation": 6, "cycle": True, "monitor": True}
            for _ in range(10):
                spoofer.put(f"millsense/{MACHINE}/context", json.dumps(spoof_context).encode())
                spoofer.put(f"millsense/{MACHINE}/context", json.dumps(dict(spoof_context, spoof=True)).encode())
                time.sleep(0.05)
            # ... the adapter's may: the router tells it the daemon listens, and the daemon's estimates carry it
            context_pub = adapter.declare_publisher(f"millsense/{MACHINE}/context")
            entities.append(context_pub)
            wait_for(lambda: context_pub.matching_status.matching, 30.0, "the daemon's context subscriber, seen by the adapter")
            good_context = {"program": 4321, "tool": 7, "operation": 2, "cycle": True, "monitor": True}
            context_pub.put(json.dumps(good_context).encode())
            wait_for(lambda: [e for e in seen_viewer.keys("/estimate") if isinstance(e, dict) and e.get("program") == 4321],
                     30.0, "estimates carrying the adapter's context")
            estimates_with_context = [e for e in seen_viewer.keys("/estimate") if isinstance(e, dict)]

            # -- the operator asks for a reset: only the real daemon answers (reset = "off" here: a refusal)
            status_replies = [r for r in operator.get(f"millsense/{MACHINE}/status", timeout=3.0)]
            reset_replies = [r for r in operator.get(f"millsense/{MACHINE}/cmd/reset", payload=b"{}", timeout=3.0)]
            ghost_replies = [r for r in operator.get("millsense/ghost-01/cmd/reset", payload=b"{}", timeout=1.0)]
            viewer_cmd = [r for r in viewer.get(f"millsense/{MACHINE}/cmd/reset", payload=b"{}", timeout=1.0)]
            viewer_limits_cmd = [r for r in viewer.get(f"millsense/{MACHINE}/cmd/limits", payload=b"{}", timeout=1.0)]
            operator_limits_cmd = [r for r in operator.get(f"millsense/{MACHINE}/cmd/limits", payload=b"{}", timeout=3.0)]
            viewer_limits = [r for r in viewer.get(f"millsense/{MACHINE}/limits", timeout=3.0)]
            stranger_status = [r for r in stranger.get(f"millsense/{MACHINE}/status", timeout=1.0)]
            viewer_status = [r for r in viewer.get(f"millsense/{MACHINE}/status", timeout=3.0)]
            # the tokens the router holds: asked until the daemon's is among them (the positive control: a get on a
            # loaded box came back without it once, CI), then the spoofer's must not be
            ghost_alive = wait_for(lambda: (lambda keys: keys if f"millsense/{MACHINE}/alive" in keys else None)(
                [str(r.ok.key_expr) for r in viewer.liveliness().get("millsense/*/alive", timeout=2.0)
                 if r.ok is not None]), 30.0, f"the daemon's alive token at the router ({alive_kinds})")
            assert daemon.poll() is None
        finally:
            for e in entities:
                try:
                    e.undeclare()
                except Exception:  # noqa: BLE001
                    pass
            for s in sessions:
                s.close()
            router.close()

    # nobody received a spoofed sample, alive token or reply
    assert seen_viewer.spoofed() == [] and seen_operator.spoofed() == [], (seen_viewer.spoofed() + seen_operator.spoofed())[:3]
    assert not [a for a in alive if "ghost" in a] and ghost_alive == [f"millsense/{MACHINE}/alive"], (alive_kinds, ghost_alive)
    assert fake_queries == [], "a query reached the fake queryable"
    assert ghost_replies == []
    # the real daemon answered the operator, once per query, and it was not the impostor
    assert len(status_replies) == 1 and json.loads(status_replies[0].ok.payload.to_bytes())["state"] == "running"
    assert len(reset_replies) == 1
    body = json.loads((reset_replies[0].ok or reset_replies[0].err).payload.to_bytes())
    assert isinstance(body, dict) and not body.get("spoof"), body  # the daemon's own answer, whatever it says
    # viewers may ask status but not commands; a certificate in no subject gets nothing at all
    assert viewer_cmd == []
    assert len(viewer_status) == 1 and not json.loads(viewer_status[0].ok.payload.to_bytes()).get("spoof")
    assert stranger_status == [] and seen_stranger.items == []
    # context: only the adapter's reached the daemon; the viewer certificate's never reached anyone
    assert not [e for e in estimates_with_context if e.get("program") == 6666]
    assert not [b for b in seen_viewer.keys("/context") + seen_operator.keys("/context")
                if isinstance(b, dict) and b.get("program") == 6666]
    # cmd/limits: operators reach the daemon (reset = "off" here: its refusal), viewers nothing; limits reads
    assert viewer_limits_cmd == []
    assert len(operator_limits_cmd) == 1
    body = json.loads((operator_limits_cmd[0].ok or operator_limits_cmd[0].err).payload.to_bytes())
    assert body.get("policy") == "off" and not body.get("spoof"), body
    assert len(viewer_limits) == 1 and json.loads(viewer_limits[0].ok.payload.to_bytes())["machine"] == MACHINE
