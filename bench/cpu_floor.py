"""Where the live daemon's CPU floor lies: the parts any such daemon must run, each alone, in one window.

Issue 13 asks for the daemon's CPU at 1 kHz (10-sample frames over TCP) to be at most 3 × a bare
blocking `recv` loop. This measures, beside that loop and in the same window, processes that each do
only part of the daemon's work on the same emulator stream (each its own process, so each is timed
alone, from /proc):

- `recv`      the bare loop (the baseline);
- `decode`    recv + the project's decoder (`StreamDecoder.feed`) on each read, the frames dropped;
- `driver`    the project's TCP driver as the daemon runs it (reader thread: read, decode, index
              tracking, the queue), and a consumer thread that drains the queue every 100 ms doing
              nothing with it;
- `checked`   the same, with the reader's per-frame crash check (`FrameCheck`) as its sample hook;
- `publish`   no DAQ: a Zenoh peer session publishing what the daemon publishes at 600 rpm (an
              estimate each 100 ms, the status each second) to a subscriber in this process;
- `daemon`    `millsense run` as its systemd unit runs it.

`driver` + `publish` is what a daemon built on this driver and this publisher costs before any
physics, check or alarm: if that alone is near 3 × `recv`, the budget leaves the estimator nothing.

Run: .venv/bin/python bench/cpu_floor.py [--seconds 30] [--scenario step]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from tests.conftest import free_tcp_port  # noqa: E402
from tests.e2e.helpers import Procs, Subscriber, tcp, wait_for, write_config  # noqa: E402
from tests.ops.unit_file import unit_environment  # noqa: E402
from tests.procstat import proc_cpu_s  # noqa: E402

ROLES = ("recv", "decode", "driver", "checked", "publish")


def _connect(port: int):
    import socket

    for _ in range(200):  # the emulator may still be starting
        try:
            s = socket.create_connection(("127.0.0.1", port))
            break
        except OSError:
            time.sleep(0.05)
    s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    return s


def role_recv(port: int) -> None:
    s = _connect(port)
    while s.recv(65536):
        pass


def role_decode(port: int) -> None:
    from millsense.drivers.protocol import StreamDecoder

    s, decoder = _connect(port), StreamDecoder()
    while data := s.recv(65536):
        decoder.feed(data)


def role_driver(port: int, check: bool) -> None:
    from millsense.daemon.config.load import load_config
    from millsense.daemon.pipeline.safety_check import FrameCheck
    from millsense.drivers.tcp_driver import TcpDriver

    settings = load_config(REPO / "daemon" / "demo.toml")
    driver = TcpDriver("127.0.0.1", port)
    frame_check: list = []

    def hook(seq, counts, lost, disc):
        if check:
            if not frame_check or frame_check[0][0] is not driver.descriptor:
                frame_check[:] = [(driver.descriptor, FrameCheck(settings, driver.descriptor))]
            frame_check[0][1].check(seq, counts, lost, disc, 1.0)
            return True, False
        return False, False   # no wake-up: the consumer drains on its own timer, as the estimator's

    driver.sample_hook = hook
    driver.start()
    while True:
        driver.wake.wait(0.1)
        driver.wake.clear()
        driver.drain()


def role_publish(port: int) -> None:
    from types import SimpleNamespace

    from millsense.daemon.publish.session import open_session
    from millsense.daemon.publish.sink import ZenohSink

    zs = SimpleNamespace(mode="peer", listen=[tcp(port)], connect=[], multicast_scouting=False, config_file="")
    sink = ZenohSink(open_session(zs, retry_for_s=0), "floor")
    estimate = {"machine": "floor", "rev": 0, "t": 0.0, "spindle_rpm": 600.0, "gear": "low-speed", "p_in_w": 612.4,
                "p_gap_w": 598.1, "torque_nm": 4.21, "torque_sigma_nm": 0.05, "force_n": 452.6,
                "force_tangential_n": 421.0, "force_feed_n": None, "feed_per_tooth_mm": 0.1667,
                "radial_depth_mm": 20.0, "axial_depth_mm": 2.03, "depth_status": "ok", "cutting": True,
                "samples": 100, "lost_samples": 0, "valid": True}
    status = {"machine": "floor", "state": "running", "lost_samples": 0, "faults": [], "daq": {"link": "up"}}
    next_t = time.monotonic()
    while True:
        estimate["rev"] += 1
        sink.estimate(dict(estimate))
        if estimate["rev"] % 10 == 0:
            sink.status(dict(status))
        next_t += 0.1
        time.sleep(max(0.0, next_t - time.monotonic()))


def _spawn(role: str, port: int) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-OO", __file__, "--role", role, "--port", str(port)],
                            env=unit_environment() | {"PYTHONPATH": str(REPO)})


def measure(seconds: float, scenario: str) -> dict[str, float]:
    tmp = Path(tempfile.mkdtemp(prefix="millsense-floor-"))
    daq_port, z_port, pub_port = free_tcp_port(), free_tcp_port(), free_tcp_port()
    cfg = write_config(tmp / "floor.toml", machine="bench",
                       daq=f'transport = "tcp"\nhost = "127.0.0.1"\ntcp_port = {daq_port}',
                       zenoh_listen=[tcp(z_port)], extra="")
    with Procs(tmp) as procs:
        procs.start("sim", ["sim", "--scenario", scenario, "--loop", "--tcp", f"127.0.0.1:{daq_port}", "--realtime"])
        time.sleep(0.5)
        pids = {"daemon": procs.start("daemon", ["run", "--config", str(cfg)], env_extra=unit_environment())}
        parts = {role: _spawn(role, pub_port if role == "publish" else daq_port) for role in ROLES}
        pids.update(parts)
        sub, pub_sub = Subscriber([tcp(z_port)], "bench"), Subscriber([tcp(pub_port)], "floor")
        try:
            wait_for(lambda: len(sub.get("estimate")) >= 5, 30.0, "estimates from the daemon")
            wait_for(lambda: len(pub_sub.get("estimate")) >= 5, 30.0, "estimates from the publisher")
            time.sleep(2.0)   # warm-up: imports, first descriptor, caches
            for name, proc in pids.items():
                if proc.poll() is not None:
                    raise SystemExit(f"{name} ended early (exit {proc.returncode})")
            cpu0, t0 = {name: proc_cpu_s(p.pid) for name, p in pids.items()}, time.monotonic()
            threading.Event().wait(seconds)
            cpu1, t1 = {name: proc_cpu_s(p.pid) for name, p in pids.items()}, time.monotonic()
        finally:
            sub.close()
            pub_sub.close()
            for proc in parts.values():
                proc.kill()
                proc.wait(5)
    return {name: 100.0 * (cpu1[name] - cpu0[name]) / (t1 - t0) for name in pids}


def main() -> int:
    parser = argparse.ArgumentParser(description="the live daemon's CPU floor, part by part")  # -OO: no __doc__
    parser.add_argument("--seconds", type=float, default=30.0)
    parser.add_argument("--scenario", default="step")
    parser.add_argument("--role", choices=ROLES, help=argparse.SUPPRESS)
    parser.add_argument("--port", type=int, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.role:
        {"recv": role_recv, "decode": role_decode, "publish": role_publish,
         "driver": lambda p: role_driver(p, False), "checked": lambda p: role_driver(p, True)}[args.role](args.port)
        return 0
    pct = measure(args.seconds, args.scenario)
    base = pct["recv"]
    print(f"CPU at 1 kHz, 10-sample frames over TCP ({args.scenario}), {args.seconds:.0f} s, one window, % of one core:")
    for name, what in (("recv", "bare blocking recv loop (baseline)"),
                       ("decode", "recv + the project's decoder"),
                       ("driver", "the TCP driver: reader thread + a consumer draining every 100 ms"),
                       ("checked", "the same + the per-frame crash check"),
                       ("publish", "Zenoh: an estimate each 100 ms, the status each second (no DAQ)"),
                       ("daemon", "millsense run, as its unit runs it")):
        print(f"  {name:8s} {pct[name]:6.2f} %   {pct[name] / base:5.1f} x recv   {what}")
    floor = pct["driver"] + pct["publish"]
    print(f"  driver + publish (no physics, no check): {floor:.2f} % = {floor / base:.1f} x recv; "
          f"the budget: 3 x recv = {3 * base:.2f} %")
    return 0


if __name__ == "__main__":
    sys.exit(main())
