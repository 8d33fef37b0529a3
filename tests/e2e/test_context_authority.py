"""Issue 36, finding 2, live: a peer without the adapter key cannot make the applied override exceed 100 %.

A real daemon (`millsense run`, AFC on at start, `[context] source = "zenoh"`, an adapter key file) reads
the real emulator over TCP (`millsense sim --protocol 2`: a DAQ with the feed-override output, whose CNC
applies what the daemon commands and reports it back, `feed_override_pct`). A Zenoh peer on loopback plays
both the outsider and the adapter:

- an unsigned put with `afc_allowed: true`: the cut is labelled with it, AFC stays idle ("context not
  authenticated") and the override the CNC applies stays at 100 % (before issue 36: armed, 124–150 %);
- the same context signed with the adapter key by docs/zenoh.md's reference signer: AFC arms and the CNC
  applies more than 100 %;
- a signed put naming tool 7, whose `[afc.targets."7/*"]` says `allow = false`: idle, back to 100 %;
- the first signed put replayed: refused (counted), the context and AFC stay as they were.
"""

from __future__ import annotations

import json
import os
import signal
from pathlib import Path

from tests.conftest import free_tcp_port
from tests.e2e.helpers import Procs, Subscriber, tcp, wait_for, write_config
from tests.learning.doc_signer import signer

MACHINE = "ctx-e2e"
KEY = "adapter-key-of-at-least-32-characters-0123456789"
SLOW_S = 90.0    # detects a hang; no budget
REVS = 15        # cutting revolutions watched under the unsigned context (the old daemon armed within 3)
CUT = {"program": 1234, "tool": 3, "operation": 1, "cycle": True, "monitor": True, "afc_allowed": True}
UNTRUSTED = "context not authenticated"


def _config(tmp: Path, daq_port: int, z_port: int) -> Path:
    key_file = tmp / "adapter.key"
    key_file.write_text(KEY + "\n")
    os.chmod(key_file, 0o600)
    # arm_pct = 0 and a target far above the step cut's load: allowed to run, the controller goes to its bound
    extra = (f'\n[context]\nsource = "zenoh"\nadapter_key_file = "{key_file}"\n'
             "\n[afc]\nenabled = true\narm_pct = 0\ntarget_torque_nm = 30.0\n"
             '\n[afc.targets."7/*"]\nallow = false\n')
    return write_config(tmp / "d.toml", machine=MACHINE, daq=f'transport = "tcp"\nhost = "127.0.0.1"\ntcp_port = {daq_port}',
                        zenoh_listen=[tcp(z_port)], interlock="enabled = true\nheartbeat_ms = 50\nwatchdog_ms = 1000",
                        extra=extra)


def _under(sub: Subscriber, program: int) -> list[dict]:
    return [e for e in sub.get("estimate") if e.get("program") == program]


def _status(sub: Subscriber) -> dict:
    (status,) = sub.query(f"millsense/{MACHINE}/status")
    return status


def test_only_the_adapter_key_lets_a_zenoh_context_raise_the_applied_override(tmp_path):
    daq_port, z_port = free_tcp_port(), free_tcp_port()
    cfg = _config(tmp_path, daq_port, z_port)
    sign = signer()
    key = f"millsense/{MACHINE}/context"
    with Procs(tmp_path) as procs:
        daemon = procs.start("daemon", ["run", "--config", str(cfg), "--connect-timeout", "60"])
        sub = Subscriber([tcp(z_port)], MACHINE)
        try:
            procs.start("sim", ["sim", "--scenario", "step", "--protocol", "2", "--tcp", f"127.0.0.1:{daq_port}",
                                "--realtime", "--watchdog-ms", "1000"])
            wait_for(lambda: any("afc" in e for e in sub.get("estimate")) or daemon.poll() is not None, SLOW_S,
                     "estimates with the controller's state")
            assert daemon.poll() is None, procs.text("daemon")[-3000:]
            publisher = sub.session.declare_publisher(key)
            wait_for(lambda: publisher.matching_status.matching, SLOW_S, "the daemon's context subscriber")
            status = _status(sub)
            run_id = status["run_id"]
            assert status["context_auth"] == {"key": True, "trust": "none", "seq": 0}, status.get("context_auth")

            # -- an outsider's put: labels the cut, never raises the feed
            publisher.put(json.dumps(CUT).encode())
            wait_for(lambda: len([e for e in _under(sub, 1234) if e.get("cutting")]) >= REVS, SLOW_S,
                     f"{REVS} cutting revolutions under the unsigned context")
            unsigned = _under(sub, 1234)
            assert {e["afc"]["state"] for e in unsigned} == {"idle"}, [e["afc"] for e in unsigned][:5]
            assert max(e["afc"]["override_pct"] for e in unsigned) <= 100.0
            assert max(e["feed_override_pct"] for e in unsigned) <= 100.0, [e["feed_override_pct"] for e in unsigned]
            # `status` answers with the one published last (once a second): wait for one from after the put
            status = wait_for(lambda: (s := _status(sub)).get("context") and s["context"]["program"] == 1234 and s,
                              SLOW_S, "a status under the unsigned context")
            assert status["afc"]["reason"] == UNTRUSTED and status["context"]["authority"] == "none", status["afc"]

            # -- the adapter's, signed as docs/zenoh.md shows: AFC arms and the CNC applies more than 100 %
            first = sign(KEY, MACHINE, run_id, 1, {**CUT, "program": 1235})
            publisher.put(first)
            wait_for(lambda: [e for e in _under(sub, 1235) if e["afc"]["state"] in ("armed", "saturated")
                              and e["feed_override_pct"] > 100.0], SLOW_S,
                     "the CNC applying more than 100 % under the signed context")
            status = wait_for(lambda: (s := _status(sub))["context"]["program"] == 1235 and s, SLOW_S,
                              "a status under the signed context")
            assert status["context"]["authority"] == "mac" and status["context_auth"]["seq"] == 1, status["context"]

            # -- signed, but naming the tool whose target says allow = false: idle, back to 100 %
            publisher.put(sign(KEY, MACHINE, run_id, 2, {**CUT, "program": 1236, "tool": 7}))
            wait_for(lambda: [e for e in _under(sub, 1236) if e["feed_override_pct"] <= 100.0], SLOW_S,
                     "the programmed feed again under tool 7")
            tool7 = _under(sub, 1236)
            assert {e["afc"]["state"] for e in tool7} == {"idle"} and max(e["afc"]["override_pct"] for e in tool7) <= 100.0
            status = wait_for(lambda: (s := _status(sub))["context"]["program"] == 1236 and s, SLOW_S,
                              "a status under tool 7")
            assert status["afc"]["reason"] == "not allowed" and status["context"]["authority"] == "mac", status["afc"]

            # -- the first signed put replayed: refused and counted; nothing changes
            refused = _status(sub)["sink"]["context_refused"]
            publisher.put(first)
            wait_for(lambda: _status(sub)["sink"]["context_refused"] == refused + 1, SLOW_S, "the replay refused")
            n = len(sub.get("estimate"))
            wait_for(lambda: len(sub.get("estimate")) >= n + REVS, SLOW_S, "revolutions after the replay")
            after = sub.get("estimate")[n:]
            assert {e.get("program") for e in after} == {1236}   # the replayed context never came back in force
            assert {e["afc"]["state"] for e in after} == {"idle"} and max(e["feed_override_pct"] for e in after) <= 100.0
            assert "Traceback" not in procs.text("daemon")

            publisher.undeclare()
            daemon.send_signal(signal.SIGTERM)
            assert daemon.wait(SLOW_S) == 0
        finally:
            sub.close()
