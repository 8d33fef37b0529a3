"""`[opcua]` (issue 42): checked by the configuration's own validation (what `check-config` and the daemon
run), read by `millsense opcua --config`, its keys overridden by the command line, an error naming the key."""

from __future__ import annotations

import subprocess

import pytest

from millsense.daemon.config.errors import ConfigError
from millsense.daemon.config.load import load_config
from tests.conftest import free_tcp_port
from tests.e2e.helpers import CMD, tcp, write_config


def _config(tmp_path, opcua: str):
    cfg = write_config(tmp_path / "d.toml", machine="m1", daq='transport = "sim"\nscenario = "step"')
    cfg.write_text(cfg.read_text() + f"\n[opcua]\n{opcua}\n")
    return cfg


def _problems(tmp_path, opcua: str) -> list[str]:
    with pytest.raises(ConfigError) as refused:
        load_config(_config(tmp_path, opcua))
    return refused.value.problems


@pytest.mark.quick
def test_nodesets_need_the_machines_identification_and_a_bad_key_is_named(tmp_path):
    problems = _problems(tmp_path, 'nodesets_dir = "/srv/nodesets"\nmanufacturer = "ACME"\n'
                                   'product_instance_uri = "not a uri"')
    assert any(p.startswith("opcua.serial_number: missing") for p in problems), problems
    assert any(p.startswith("opcua.product_instance_uri: 'not a uri' is not a URI") for p in problems), problems
    assert not any(p.startswith("opcua.manufacturer") for p in problems), problems
    problems = _problems(tmp_path, 'endpoint = "http://10.0.0.5:4840"\nendpont = "x"')
    assert any(p.startswith("opcua.endpoint: 'http://10.0.0.5:4840' is not opc.tcp://HOST:PORT") for p in problems), problems
    assert any(p.startswith("opcua.endpont: unknown key") for p in problems), problems
    ok = load_config(_config(tmp_path, 'nodesets_dir = "/srv/nodesets"\nmanufacturer = "ACME"\n'
                                       'serial_number = "42"\nproduct_instance_uri = "urn:acme:42"'))
    assert ok.opcua.serial_number == "42" and ok.opcua.allow_anonymous is False
    assert load_config(_config(tmp_path, "")).opcua.nodesets_dir == ""  # an empty section: the defaults


def test_opcua_takes_the_section_and_the_command_line_overrides_it(tmp_path):
    cfg = _config(tmp_path, f'endpoint = "opc.tcp://127.0.0.1:{free_tcp_port()}"\ncert = "pki/none.der"\n'
                            'key = "pki/none.pem"\ntrust_dir = "pki"')
    base = CMD + ["opcua", "--config", str(cfg), "--connect", tcp(free_tcp_port()), "--no-scouting"]
    from_file = subprocess.run(base, capture_output=True, text=True, timeout=60)
    assert from_file.returncode == 78, from_file.stderr
    # The section's relative path, from the file's folder, and the error names the key it came from.
    assert f"opcua.cert ({cfg}) {tmp_path / 'pki' / 'none.der'}: does not exist" in from_file.stderr, from_file.stderr
    given = subprocess.run(base + ["--cert", str(tmp_path / "other.der")], capture_output=True, text=True, timeout=60)
    assert given.returncode == 78 and f"--cert {tmp_path / 'other.der'}: does not exist" in given.stderr, given.stderr
    (cfg.parent / "bad.toml").write_text(cfg.read_text().replace('trust_dir = "pki"', 'allow_anonymous = "yes"'))
    bad = subprocess.run(CMD + ["opcua", "--config", str(cfg.parent / "bad.toml")], capture_output=True, text=True,
                         timeout=60)
    assert bad.returncode == 78 and "opcua.allow_anonymous" in bad.stderr and "Traceback" not in bad.stderr, bad.stderr
    # --nodesets with no machine whose identification is configured: nothing could be typed, said at once.
    untyped = subprocess.run(base + ["--nodesets", str(tmp_path)], capture_output=True, text=True, timeout=60)
    assert untyped.returncode == 78 and "--nodesets: no machine to show as a MachineToolType" in untyped.stderr, \
        untyped.stderr
    # The operators' folder (who may acknowledge alarms), from the section, named by its key when it is wrong.
    from tests.opcua.rig import make_pki  # asyncua's client: only here (the test above needs no extra)

    pki = make_pki(tmp_path / "real")
    (cfg.parent / "ops.toml").write_text(cfg.read_text().replace(
        'cert = "pki/none.der"\nkey = "pki/none.pem"\ntrust_dir = "pki"',
        f'cert = "{pki.server_cert}"\nkey = "{pki.server_key}"\ntrust_dir = "{pki.trust_dir}"\n'
        'operators_dir = "no-such-folder"'))
    ops = subprocess.run(CMD + ["opcua", "--config", str(cfg.parent / "ops.toml"), "--connect", tcp(free_tcp_port()),
                                "--no-scouting"], capture_output=True, text=True, timeout=60)
    assert ops.returncode == 78, ops.stderr
    assert f"opcua.operators_dir ({cfg.parent / 'ops.toml'}) {tmp_path / 'no-such-folder'}: not a directory" in ops.stderr, \
        ops.stderr
