"""A foreign client from another stack, node-opcua, against `millsense opcua` (issue 42's acceptance).

Everything real: a daemon on the simulator (the step scenario; a torque limit it crosses at its depth step, the
interlock on), `millsense opcua` configured by the daemon's `[opcua]` section with the OPC Foundation's nodesets
(tests/opcua/nodesets.py) and an operators' folder, and node-opcua's client (tests/opcua/foreign.py, our script
tests/opcua/node_client/client.js) in one Node process. It

- connects under each of the three security policies (node-opcua 2.186 has all three: its SecurityPolicy enum
  and its crypto for Aes128_Sha256_RsaOaep and Aes256_Sha256_RsaPss), and is refused with a certificate the
  server does not trust;
- finds the machine by browsing Objects/Machines for a TypeDefinition of MachineToolType in the MachineTool
  namespace, reads its Identification;
- reads live torque values whose source timestamps are those of estimates the daemon published on Zenoh;
- receives the overload as a condition event, and the held feed's; once the overload's condition has cleared it
  calls ConditionRefresh: the stopped, held machine shows an active condition (FeedHeld) to a client that keeps
  only the active ones, and to one that watches only active conditions (a second event item whose where clause is
  `OfType(AlarmConditionType) AND ActiveState/Id = true`: issue 42's last acceptance line), which never gets an
  inactive one;
- acknowledges the overload's condition with an operator's certificate and reads AckedState true, then confirms
  it and reads ConfirmedState true.
"""

from __future__ import annotations

import shutil

import pytest

pytest.importorskip("asyncua", reason="the opcua extra (asyncua) is not installed")

from tests.conftest import free_tcp_port  # noqa: E402
from tests.e2e.helpers import Procs, Subscriber, tcp, wait_for, write_config  # noqa: E402
from tests.opcua import nodesets as fetched  # noqa: E402
from tests.opcua.foreign import NodeClient  # noqa: E402
from tests.opcua.rig import CLIENT_URI, MT_NS, SLOW_S, make_pki  # noqa: E402

MACHINE = "node-01"
TORQUE_LIMIT_NM = 2.6  # between the step scenario's torque at 1 mm and at 2 mm (test_opcua_server.py)
IDENTITY = {"manufacturer": "DMG MORI", "serial_number": "DMU50-4711", "product_instance_uri": "urn:dmgmori:dmu50:4711"}
POLICIES = ["Basic256Sha256", "Aes128_Sha256_RsaOaep", "Aes256_Sha256_RsaPss"]
TORQUE_VALUES = 5
COMMENT = "seen from node-opcua"


@pytest.mark.slow
def test_node_opcua_finds_the_machine_by_type_reads_live_values_and_acknowledges_the_overload(tmp_path):
    six = fetched.folder()
    pki = make_pki(tmp_path / "pki")
    operators = tmp_path / "pki" / "operators"
    operators.mkdir()
    shutil.copyfile(pki.client_cert, operators / "client.der")
    z_port, ua_port, sub_port = free_tcp_port(), free_tcp_port(), free_tcp_port()
    opcua = "\n".join([f'endpoint = "opc.tcp://127.0.0.1:{ua_port}"', 'cert = "pki/server.der"',
                       'key = "pki/server.pem"', 'trust_dir = "pki/trusted"', 'operators_dir = "pki/operators"',
                       f'nodesets_dir = "{six}"', *(f'{k} = "{v}"' for k, v in IDENTITY.items())])
    cfg = write_config(tmp_path / "d.toml", machine=MACHINE, daq='transport = "sim"\nscenario = "step"',
                       zenoh_listen=[tcp(z_port)], zenoh_connect=[tcp(sub_port)],
                       alarms=f"torque_limit_nm = {TORQUE_LIMIT_NM}\nrevolutions = 2", interlock="enabled = true")
    cfg.write_text(cfg.read_text() + f"\n[opcua]\n{opcua}\n")
    # What the daemon really published, from its first estimate on (the daemon connects to this subscriber).
    sub = Subscriber([], MACHINE, listen=[tcp(sub_port)])
    client = None
    try:
        with Procs(tmp_path) as procs:
            server = procs.start("opcua", ["opcua", "--config", str(cfg), "--connect", tcp(z_port), "--no-scouting",
                                           "--log-format", "json"])
            wait_for(lambda: "opcua.listening" in procs.text("opcua") or server.poll() is not None, SLOW_S,
                     "listening")
            assert server.poll() is None, procs.text("opcua")
            client = NodeClient({
                "endpoint": f"opc.tcp://127.0.0.1:{ua_port}", "application_uri": CLIENT_URI,
                "pki_dir": str(tmp_path / "node-pki"), "server_cert": str(pki.server_cert),
                "client_cert": str(pki.client_cert), "client_key": str(pki.client_key),
                "stranger_cert": str(pki.stranger_cert), "stranger_key": str(pki.stranger_key),
                "policies": POLICIES, "main_policy": "Aes256_Sha256_RsaPss", "machine": MACHINE,
                "overload_condition": "torque_nm", "torque_values": TORQUE_VALUES, "comment": COMMENT,
                "timeout_s": SLOW_S})
            wait_for(lambda: client.steps("subscribed") or client.ended(), SLOW_S, "node-opcua subscribed")
            assert client.steps("subscribed"), client.transcript()
            procs.start("daemon", ["run", "--config", str(cfg)])
            wait_for(lambda: client.ended(), 3 * SLOW_S, "node-opcua's scenario")
            said = client.transcript()
            assert client.proc.returncode == 0 and client.steps("done"), said

            # Each policy connects; an untrusted certificate is refused.
            assert [(p["policy"], p["ok"]) for p in client.steps("policy")] == [(p, True) for p in POLICIES], said
            assert all(p["server"] == "Server" for p in client.steps("policy")), said
            (stranger,) = client.steps("stranger")
            assert stranger["ok"] is False and "BadCertificateUntrusted" in stranger["error"], stranger

            # Found by type, Identification from the configuration.
            (machine,) = client.steps("machine")
            assert machine["browse_name"] == MACHINE and machine["type_namespace"] == MT_NS, machine
            assert machine["type_definition"].endswith(";i=13"), machine
            (ident,) = client.steps("identification")
            assert ident == {"step": "identification", "Manufacturer": IDENTITY["manufacturer"],
                             "SerialNumber": IDENTITY["serial_number"],
                             "ProductInstanceUri": IDENTITY["product_instance_uri"]}, ident

            # Live torque: each value's source timestamp and value is an estimate's on Zenoh.
            torque = client.steps("torque")
            assert len(torque) == TORQUE_VALUES, said
            for value in torque:
                published = wait_for(lambda v=value: [e for e in sub.get("estimate")
                                                      if abs(e["t"] - v["source_t"]) < 1e-3], SLOW_S,
                                     f"the estimate of {value} on Zenoh")
                assert published[0]["torque_nm"] == pytest.approx(value["value"], rel=1e-12), (value, published[0])

            # The overload as a condition event, with its ConditionId; the held feed's.
            events = client.steps("event")
            overload = next(e for e in events if e["condition"] == "torque_nm" and e["active"])
            assert overload["severity"] == 800 and overload["acked"] is False and overload["retain"] is True
            assert overload["condition_id"].endswith(f"{MACHINE}/Notification/Messages/torque_nm"), overload
            held = next(e for e in events if e["condition"] == "FeedHeld" and e["active"])
            assert held["severity"] >= 900, held

            # ConditionRefresh on the stopped, held machine: a client that keeps only the active conditions shows
            # FeedHeld (the overload's own condition has cleared).
            (refresh_called,) = client.steps("refresh_called")
            assert refresh_called["status"] == "Good", refresh_called
            (refreshed,) = client.steps("refreshed")
            active = [c["condition"] for c in refreshed["conditions"] if c["active"]]
            assert active == ["FeedHeld"], refreshed
            # The cleared overload nobody acknowledged yet is replayed too, inactive and retained (Part 9).
            (unacked,) = [c for c in refreshed["conditions"] if c["condition"] == "torque_nm"]
            assert unacked["active"] is False and unacked["acked"] is False and unacked["retain"] is True, unacked
            # The client that watches only active conditions (its where clause, evaluated by the server): FeedHeld
            # from the refresh, the overload and the held feed live, never an inactive condition (the overload's
            # clear came before the refresh; the acknowledgements after it are of an inactive condition).
            (active_refreshed,) = client.steps("active_refreshed")
            assert [(c["condition"], c["active"]) for c in active_refreshed["conditions"]] == [("FeedHeld", True)], \
                active_refreshed
            watched = client.steps("active_event")
            assert {"torque_nm", "FeedHeld"} <= {e["condition"] for e in watched}, said
            assert all(e["active"] is True for e in watched), said

            # Part 9's types: the overload's condition a limit alarm (its limit the HighLimit), the held feed discrete.
            (types,) = client.steps("types")
            assert "ns=0;i=9482" in types["types"]["torque_nm"], types  # ExclusiveLevelAlarmType
            assert "ns=0;i=10637" in types["types"]["FeedHeld"], types  # OffNormalAlarmType
            assert types["high_limit"] == TORQUE_LIMIT_NM, types

            # The operator's Acknowledge: Good, AckedState true, one event saying so; the feed is still held.
            (acked,) = client.steps("acknowledged")
            assert acked["status"] == "Good" and acked["condition_id"] == overload["condition_id"], acked
            assert client.steps("acked_state") == [{"step": "acked_state", "acked": True}], said
            assert client.steps("confirmed") == [{"step": "confirmed", "status": "Good", "confirmed": True}], said
            assert not any(e["condition"] == "FeedHeld" and not e["active"] for e in client.steps("event")), said
            assert "opcua.audit" in procs.text("opcua") and "Traceback" not in procs.text("opcua")
    finally:
        if client is not None:
            client.close()
        sub.close()
