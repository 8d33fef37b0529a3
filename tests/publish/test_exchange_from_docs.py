"""The command exchange written from docs/zenoh.md alone, against a real daemon.

This file implements the requester side with nothing but zenoh, hmac, hashlib,
json and secrets, the way a third-party HMI would from the docs: it imports no
millsense module (checked below; the daemon runs as a subprocess). The worked
example's MACs in the docs are recomputed here too, so the docs cannot drift
from what a daemon accepts without this test failing.
"""

from __future__ import annotations

import ast
import hashlib
import hmac
import json
import re
import secrets
import time
from pathlib import Path

import pytest
import zenoh

from tests.conftest import REPO, free_tcp_port
from tests.e2e.helpers import Procs, tcp, write_config

DOCS = REPO / "docs" / "zenoh.md"


# ---- the exchange, from the docs ----------------------------------------------------------
def canonical(args: dict) -> str:
    return json.dumps(args, sort_keys=True, separators=(",", ":"), ensure_ascii=True)


def hmac_hex(token: str, *fields: str) -> str:
    return hmac.new(token.encode("utf-8"), "\n".join(fields).encode("utf-8"), hashlib.sha256).hexdigest()


def ask(session: zenoh.Session, key: str, body: dict, timeout_s: float) -> list[tuple[bool, dict]]:
    replies = session.get(key, payload=json.dumps(body).encode(), encoding="application/json", timeout=timeout_s)
    return [(r.ok is not None, json.loads((r.ok or r.err).payload.to_bytes())) for r in replies]


def run_command(session: zenoh.Session, machine: str, command: str, token: str, args: dict) -> dict:
    key = f"millsense/{machine}/cmd/{command}"
    cn = secrets.token_hex(32)
    [(ok, challenge)] = ask(session, key, {"step": "challenge", "client_nonce": cn}, 5.0)
    assert ok and challenge["machine"] == machine and challenge["command"] == command, challenge
    assert challenge["policy"] == "token" and "paused_s" not in challenge, challenge
    sn = challenge["server_nonce"]
    mac = hmac_hex(token, "millsense-cmd-v1", command, machine, sn, cn, canonical(args))
    [(ok, reply)] = ask(session, key, {"step": "prove", "client_nonce": cn, "server_nonce": sn, "args": args,
                                       "mac": mac}, 5.0)
    expected = hmac_hex(token, "millsense-reply-v1", command, machine, sn, cn, reply["result"])
    assert hmac.compare_digest(reply["server_mac"], expected), "the daemon's reply failed its MAC"
    result = json.loads(reply["result"])
    assert ok, result
    return result


# ---- the tests ------------------------------------------------------------------------------
def test_this_file_imports_no_millsense():
    tree = ast.parse(Path(__file__).read_text())
    names = [a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names]
    names += [n.module or "" for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)]
    assert not [n for n in names if n.split(".")[0] == "millsense"], names


def test_the_docs_worked_example_reproduces():
    text = DOCS.read_text()
    example = text[text.index("### Worked example"):text.index("### Why it holds")]
    token = re.search(r"token\s+`([A-Za-z0-9_-]{43})`", example).group(1)
    cn = re.search(r'"client_nonce": "([0-9a-f]+)"', example).group(1)
    sn = re.search(r"server nonce\s+`([0-9a-f]{64})`", example).group(1)
    mac = re.search(r"mac = `([0-9a-f]{64})`", example).group(1)
    server_mac = re.search(r"server_mac = `([0-9a-f]{64})`", example).group(1)
    assert hmac_hex(token, "millsense-cmd-v1", "reset", "mch10-01", sn, cn, canonical({})) == mac
    assert hmac_hex(token, "millsense-reply-v1", "reset", "mch10-01", sn, cn, '{"ok":true,"interlock":"armed"}') \
        == server_mac


@pytest.mark.quick
def test_a_third_party_requester_resets_a_real_daemon(tmp_path):
    z_port = free_tcp_port()
    machine = "docs-01"
    token = secrets.token_urlsafe(32)
    token_file = tmp_path / "reset.token"
    token_file.write_text(token + "\n")
    token_file.chmod(0o600)
    cfg = write_config(
        tmp_path / "d.toml", machine=machine, daq='transport = "sim"\nscenario = "step"',
        zenoh_listen=[tcp(z_port)],
        interlock=f'enabled = true\nheartbeat_ms = 50\nwatchdog_ms = 500\nreset = "token"\n'
                  f'reset_token_file = "{token_file}"',
    )
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("connect/endpoints", json.dumps([tcp(z_port)]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    with Procs(tmp_path) as procs:
        daemon = procs.start("daemon", ["run", "--config", str(cfg)], env_extra={"STATE_DIRECTORY": str(tmp_path / "state")})
        session = zenoh.open(conf)
        try:
            deadline = time.monotonic() + 60
            while not list(session.liveliness().get(f"millsense/{machine}/alive", timeout=0.5)):
                assert daemon.poll() is None, procs.text("daemon", "out")[-2000:] + procs.text("daemon")[-2000:]
                assert time.monotonic() < deadline, "the daemon never came up"
                time.sleep(0.2)
            while not any(ok and body.get("revolutions", 0) >= 1 and body.get("daq_link") == "up"
                          for ok, body in ask(session, f"millsense/{machine}/status", {}, 1.0)):
                assert time.monotonic() < deadline, "the daemon never estimated"
                time.sleep(0.2)
            querier = session.declare_querier(f"millsense/{machine}/cmd/reset")
            while not querier.matching_status.matching:
                assert time.monotonic() < deadline, "cmd/reset never matched"
                time.sleep(0.05)
            querier.undeclare()
            result = run_command(session, machine, "reset", token, {})
            assert result["ok"] is True, result
        finally:
            session.close()
    audit = (tmp_path / "state" / "audit.log").read_text()
    assert '"granted":true' in audit and token not in audit
