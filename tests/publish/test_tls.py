"""config/zenoh-tls.json5 for real: mutual TLS on loopback and access control by certificate CN.

Certificates come from the `cryptography` package (a throw-away CA per test
run, tests/publish/pki.py): no openssl binary, so these tests never skip.
"""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import pytest
import zenoh

from millsense.daemon.publish.command_auth import CommandError, send_command
from millsense.daemon.publish.session import open_session
from millsense.daemon.publish.sink import ZenohSink

from .helpers import Collector, FakeInterlock, wait_for
from .pki import Pki

EXAMPLE = Path(__file__).resolve().parents[2] / "config" / "zenoh-tls.json5"
EXAMPLES = sorted(EXAMPLE.parent.glob("zenoh-*.json5"))


@pytest.fixture(scope="module")
def pki(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("pki")
    ca = Pki(d)
    for stem, cn in {"daemon": "mch10-01", "hmi": "hmi-01", "operator": "operator-01",
                     "intruder": "intruder"}.items():  # intruder: signed by the same CA, but in no policy
        ca.issue(stem, cn)
    return d


@pytest.mark.parametrize("path", EXAMPLES, ids=lambda p: p.name)
def test_every_shipped_zenoh_file_loads_in_the_installed_zenoh(path):
    conf = zenoh.Config.from_file(str(path))  # zenoh rejects any unknown key
    tls = json.loads(conf.get_json("transport/link/tls"))
    assert tls["enable_mtls"] is True
    assert json.loads(conf.get_json("transport/link/protocols")) == ["tls"]


def test_no_rule_lets_a_client_send_what_it_may_only_receive():
    # finding 2: a rule for both flows let viewers put and declare queryables on millsense/**
    for path in EXAMPLES:
        conf = zenoh.Config.from_file(str(path))
        acl = json.loads(conf.get_json("access_control"))
        if not acl["enabled"]:
            continue
        assert acl["default_permission"] == "deny", path.name
        for rule in acl["rules"]:
            assert len(rule["flows"]) == 1, (path.name, rule["id"])


def test_example_is_valid_for_the_installed_zenoh():
    conf = zenoh.Config.from_file(str(EXAMPLE))  # zenoh rejects any unknown key
    tls = json.loads(conf.get_json("transport/link/tls"))
    assert tls["enable_mtls"] is True
    assert json.loads(conf.get_json("access_control/default_permission")) == "deny"


def _daemon_config(pki: Path, port: int) -> Path:
    text = EXAMPLE.read_text().replace("/etc/millsense/tls/", f"{pki}/").replace("tls/0.0.0.0:7447", f"tls/127.0.0.1:{port}")
    f = pki / f"daemon-{port}.json5"
    f.write_text(text)
    return f


def _from_file(path: Path) -> SimpleNamespace:
    """[zenoh] settings with only `config_file` written: everything else comes from the file."""
    return SimpleNamespace(mode="peer", connect=[], listen=[], multicast_scouting=True,
                           config_file=str(path), model_fields_set={"config_file"})


def _client(pki: Path, port: int, stem: str | None) -> zenoh.Session:
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([f"tls/localhost:{port}"]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(f"{pki}/ca.pem"))
    if stem is not None:
        conf.insert_json5("transport/link/tls/enable_mtls", "true")
        conf.insert_json5("transport/link/tls/connect_private_key", json.dumps(f"{pki}/{stem}.key"))
        conf.insert_json5("transport/link/tls/connect_certificate", json.dumps(f"{pki}/{stem}.pem"))
    return zenoh.open(conf)


def _replies(session: zenoh.Session, key: str, payload: bytes | None = None) -> list:
    return [r for r in session.get(key, payload=payload, timeout=1.0)]


def test_mutual_tls_and_access_control_by_common_name(pki, port):
    # The daemon side goes through millsense's own session helper, with the example as config_file.
    daemon = open_session(_from_file(_daemon_config(pki, port)), retry_for_s=0)
    controls = FakeInterlock()  # reset = "token": the challenge–response of docs/zenoh.md, over TLS
    sink = ZenohSink(daemon, "mch10-01", controls)
    sessions = []
    try:
        hmi, operator, intruder = (_client(pki, port, s) for s in ("hmi", "operator", "intruder"))
        sessions += [hmi, operator, intruder]
        seen_hmi, seen_intruder = Collector(), Collector()
        hmi.declare_subscriber("millsense/**", seen_hmi)
        intruder.declare_subscriber("millsense/**", seen_intruder)

        wait_for(lambda: (sink.estimate({"rev": 1}), seen_hmi.payloads("/estimate"))[1], 10.0, "hmi-01 receives estimates over TLS")
        sink.alarm({"level": "overload"})
        wait_for(lambda: seen_hmi.payloads("/alarm"), 5.0, "hmi-01 receives the alarm")
        # A certificate from the right CA is not enough: "intruder" is in no policy.
        assert seen_intruder.items == []

        assert _replies(intruder, "millsense/mch10-01/cmd/reset", b"{}") == []
        assert _replies(hmi, "millsense/mch10-01/cmd/reset", b"{}") == []  # viewers cannot reach commands
        with pytest.raises(CommandError):
            send_command(hmi, "mch10-01", "reset", controls.token, timeout_s=1.0)  # not even with the token
        assert controls.requesters == [] and controls.latched
        status = _replies(hmi, "millsense/mch10-01/status")
        assert json.loads(status[0].ok.payload.to_bytes())["interlock"] == "feed_hold"

        assert send_command(operator, "mch10-01", "reset", controls.token) == {"ok": True, "interlock": "clear"}
        assert not controls.latched
        assert seen_intruder.items == []
    finally:
        sink.close()
        for s in sessions:
            s.close()
        daemon.close()


def test_no_client_certificate_no_session(pki, port):
    daemon = open_session(_from_file(_daemon_config(pki, port)), retry_for_s=0)
    try:
        with pytest.raises(zenoh.ZError, match="Unable to connect"):
            _client(pki, port, None)  # TLS without a client certificate: refused by mTLS
        plain = zenoh.Config()
        plain.insert_json5("mode", '"client"')
        plain.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
        with pytest.raises(zenoh.ZError, match="Unable to connect"):
            zenoh.open(plain)  # plain TCP on the TLS port
    finally:
        daemon.close()
