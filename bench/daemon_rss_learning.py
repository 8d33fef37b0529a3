"""Daemon RSS with the process issue's features on: context, learned limits, the SQLite history.

Runs `millsense sim --scenario part-program --tcp --realtime` and `millsense run
--config config/part-program.toml` (learning from 2 parts, interlock on, history
in a temporary state directory) for `--seconds`, and prints the daemon's peak RSS
(VmHWM) beside the baseline measured in the same run: the same daemon on the same
stream with `[learning]` and `[history]` off. Budget (issue 13): ≤ 70 MB.

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

CMD = [sys.executable, "-m", "millsense.daemon"]


def peak_rss_mb(learning: bool, seconds: float) -> tuple[float, int]:
    """(the daemon's VmHWM in MB, the processes it logged) after `seconds` on the part program."""
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
    env = dict(os.environ, XDG_STATE_HOME=str(tmp / "state"))
    sim = subprocess.Popen(CMD + ["sim", "--scenario", "part-program", "--parts", "30", "--tcp", f"127.0.0.1:{port}",
                                  "--realtime", "--watchdog-ms", "1000"],
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    log = open(tmp / "daemon.log", "w")  # noqa: SIM115
    try:
        time.sleep(2.0)
        daemon = subprocess.Popen(CMD + ["run", "--config", str(cfg)], stdout=log, stderr=subprocess.STDOUT, env=env)
        time.sleep(seconds)
        hwm_kb = next(int(line.split()[1]) for line in open(f"/proc/{daemon.pid}/status") if line.startswith("VmHWM"))
        daemon.terminate()
        daemon.wait(10)
    finally:
        sim.terminate()
        sim.wait(10)
        log.close()
    processes = (tmp / "daemon.log").read_text().count('"event": "process"')
    return hwm_kb / 1000.0, processes


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=100.0)
    args = parser.parse_args()
    on, n_on = peak_rss_mb(True, args.seconds)
    off, _ = peak_rss_mb(False, args.seconds)
    verdict = "met" if on <= 70.0 else "missed"
    print(f"daemon peak RSS, learned limits + history on: {on:.1f} MB ({n_on} processes in {args.seconds:g} s); "
          f"baseline, both off, same stream: {off:.1f} MB; budget <= 70 MB: {verdict}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
