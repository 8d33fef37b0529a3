"""Daemon RSS with the process issue's features on: context, learned limits, the SQLite history.

Runs `millsense sim --scenario part-program --tcp --realtime` and `millsense run
--config config/part-program.toml` (learning from 2 parts, interlock on, history
in a temporary state directory) for `--seconds`, and prints the daemon's peak RSS
(VmHWM) beside two baselines measured in the same run: the same daemon on the same
stream with `[learning]` and `[history]` off, and the floor of the stack the daemon
stands on: a bare interpreter that imports numpy, pydantic (and builds one model),
structlog, sqlite3 and hmac and opens a Zenoh peer session configured as the
daemon's, and nothing of millsense.
The difference to the floor is what the daemon's own code and data cost.
Every process runs with the environment the systemd unit gives the daemon
(`Environment=` of systemd/millsense@.service: Python with -OO), as deployed; the
same daemon under a plain interpreter is printed beside it.
Budget (issue 13): ≤ 70 MB.

    .venv/bin/python bench/daemon_rss_learning.py [--seconds 100]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
import tomllib
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from tests.conftest import free_tcp_port  # noqa: E402
from tests.config.helpers import dumps  # noqa: E402
from tests.ops.unit_file import unit_environment  # noqa: E402

CMD = [sys.executable, "-m", "millsense.daemon"]
RSS_BUDGET_MB = 70.0

# The floor: the daemon's third-party stack loaded and a Zenoh peer session open, as `millsense run`
# opens it (shared memory off, scouting off, one loopback listener), with the same OpenBLAS thread
# count the daemon sets for itself; then it idles as long as the daemon runs.
_FLOOR = r"""
import json, os, sys, time
os.environ["OPENBLAS_NUM_THREADS"] = "1"
import hmac, numpy, pydantic, sqlite3, structlog, zenoh
class Section(pydantic.BaseModel, extra="forbid"):  # one model built: pydantic's schema machinery loaded
    name: str = pydantic.Field(min_length=1)
Section(name="x")
conf = zenoh.Config()
conf.insert_json5("mode", '"peer"')
conf.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{sys.argv[1]}"]))
conf.insert_json5("scouting/multicast/enabled", "false")
conf.insert_json5("transport/shared_memory/enabled", "false")
with zenoh.open(conf):
    time.sleep(float(sys.argv[2]))
    print(next(int(l.split()[1]) for l in open("/proc/self/status") if l.startswith("VmHWM")))
"""


def peak_rss_mb(learning: bool, seconds: float, as_unit: bool = True) -> tuple[float, int]:
    """(the daemon's VmHWM in MB, the processes it logged) after `seconds` on the part program; with the
    unit's environment, or (as_unit False) under a plain interpreter."""
    tmp = Path(tempfile.mkdtemp(prefix="millsense-rss-"))
    port, zport = free_tcp_port(), free_tcp_port()
    doc = tomllib.loads((REPO / "config" / "part-program.toml").read_text())
    doc["daq"].update(host="127.0.0.1", tcp_port=port)
    doc["learning"] = {"processes": 2, "enabled": learning}
    doc["history"] = {"enabled": learning}
    doc["interlock"] = {"enabled": True, "heartbeat_ms": 100, "watchdog_ms": 1000, "reset": "open"}
    doc["zenoh"] = {"mode": "peer", "listen": [f"tcp/127.0.0.1:{zport}"], "connect": [], "multicast_scouting": False}
    doc["log"] = {"level": "info", "format": "json"}
    cfg = tmp / "d.toml"
    cfg.write_text(dumps(doc))
    env = dict(os.environ, XDG_STATE_HOME=str(tmp / "state"), **(unit_environment() if as_unit else {}))
    sim = subprocess.Popen(CMD + ["sim", "--scenario", "part-program", "--parts", "30", "--tcp", f"127.0.0.1:{port}",
                                  "--realtime", "--watchdog-ms", "1000"],
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    log = open(tmp / "daemon.log", "w")  # noqa: SIM115
    try:
        time.sleep(2.0)
        # a loaded box may take the emulator longer than the default 10 s start window to come up
        daemon = subprocess.Popen(CMD + ["run", "--config", str(cfg), "--connect-timeout", "60"], stdout=log,
                                  stderr=subprocess.STDOUT, env=env)
        time.sleep(seconds)
        if daemon.poll() is not None:
            raise SystemExit(f"the daemon exited ({daemon.returncode}) before it was measured; its log: {tmp / 'daemon.log'}")
        hwm_kb = next(int(line.split()[1]) for line in open(f"/proc/{daemon.pid}/status") if line.startswith("VmHWM"))
        daemon.terminate()
        daemon.wait(10)
    finally:
        sim.terminate()
        sim.wait(10)
        log.close()
    processes = (tmp / "daemon.log").read_text().count('"event": "process"')
    return hwm_kb / 1000.0, processes


def floor_rss_mb(seconds: float) -> float:
    """Peak RSS in MB of the bare stack (`_FLOOR`) after `seconds`."""
    out = subprocess.run([sys.executable, "-c", _FLOOR, str(free_tcp_port()), str(seconds)],
                         capture_output=True, text=True, timeout=seconds + 60, check=True,
                         env=dict(os.environ, **unit_environment()))
    return int(out.stdout) / 1000.0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=100.0)
    args = parser.parse_args()
    floor = floor_rss_mb(min(args.seconds, 10.0))
    on, n_on = peak_rss_mb(True, args.seconds)
    off, _ = peak_rss_mb(False, args.seconds)
    plain, _ = peak_rss_mb(True, args.seconds, as_unit=False)
    verdict = "met" if on <= RSS_BUDGET_MB else "missed"
    env = " ".join(f"{k}={v}" for k, v in unit_environment().items())
    print(f"daemon peak RSS (VmHWM), learned limits + history on, as the unit runs it ({env}): {on:.1f} MB "
          f"({n_on} processes in {args.seconds:g} s)")
    print(f"the same daemon under a plain interpreter: {plain:.1f} MB (the unit's environment saves {plain - on:.1f} MB)")
    print(f"baseline, the same daemon and stream with both off: {off:.1f} MB (learning + history cost {on - off:+.1f} MB)")
    print(f"baseline, the bare stack (numpy, pydantic, structlog, sqlite3, hmac, a Zenoh peer session): {floor:.1f} MB "
          f"(the daemon's own share: {on - floor:.1f} MB)")
    print(f"budget: <= {RSS_BUDGET_MB:g} MB: {verdict} ({on - RSS_BUDGET_MB:+.1f} MB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
