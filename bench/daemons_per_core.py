"""How many live daemons one core carries: N `millsense run` at 1 kHz, 10-sample frames over TCP.

The DAQs are a cheap stream source, not the plant: one feeder process
(`--feed`, this file) replays a recorded capture (`millsense sim --capture`,
scenario `step`, made once at the start) to N TCP ports, paced at 1 kHz in
10-sample frames with indices that go on across the capture's loops, and reads
and drops what the daemons send back (heartbeats). The feeder shares the box
but its CPU is not counted.

How the DAQs' streams line up (`--clocks`, both by default, one run each):

- `independent`: each DAQ starts at its own place in the capture (the N + 1
  streams spread evenly over it) and sends on its own millisecond of the
  10 ms frame (ten groups). Machines that run apart close their revolutions
  at different moments, and DAQ clocks are not aligned to each other.
- `lockstep`: every DAQ sends the same frame at the same instant, so all N
  daemons close the same revolution within the same millisecond and queue
  for the two cores together. No plant runs so; it is the worst case, kept
  beside the other (before stop 21 it was the only one).

Each daemon is a real `millsense run` subprocess (its own config, state
directory, Zenoh listen endpoint; the environment its systemd unit gives it).
After a warm-up the bench measures, over a window, the daemons' CPU (user +
system from /proc) and asks every daemon for its status on its local control
socket: none may have lost a sample or fallen
behind (samples received within 2 % of the feeder's pace, the driver's queue
nearly empty), and the per-revolution processing latency p99 must be ≤ 5 ms.

Figure: the mean daemon CPU in % of one core and the daemons per core it
implies (100 / mean); baseline in the same run: a bare blocking `recv` loop on
one more feeder port. Budget (issue 13): ≥ 30 daemons per core, every daemon
keeping up, latency p99 ≤ 5 ms.

Run: .venv/bin/python bench/daemons_per_core.py [--daemons 30] [--seconds 20] [--clocks independent lockstep]
"""

from __future__ import annotations

import argparse
import asyncio
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from tests.conftest import free_tcp_port  # noqa: E402
from tests.procstat import proc_cpu_s  # noqa: E402

CLOCKS = {
    "independent": "each DAQ at its own place in the capture and its own millisecond of the 10 ms frame, "
                   "as machines that run apart",
    "lockstep": "every DAQ the same frame at the same instant: every daemon closes the same revolution together "
                "(the worst case)",
}
BUDGET_PER_CORE = 30
BUDGET_P99_MS = 5.0
PER_FRAME = 10
CAPTURE_S = 30


# ---------------------------------------------------------------- the feeder (its own process)


def feed(capture: str, clocks: str, ports: list[int]) -> None:
    from millsense.daemon.commands.capture_reader import iter_capture_blocks
    from millsense.drivers.protocol import encode_descriptor, encode_sample_frames

    desc, parts = None, []
    for d, block in iter_capture_blocks(capture):
        desc = d
        parts.append(block.counts)
    counts = np.concatenate(parts)
    head = encode_descriptor(desc)
    clients: dict[int, list] = {p: [] for p in ports}

    async def serve(port: int) -> None:
        async def client(reader, writer):
            writer.write(head)
            clients[port].append(writer)
            try:
                while await reader.read(4096):  # heartbeats, descriptor requests: dropped
                    pass
            except (ConnectionError, OSError):
                pass
            finally:
                clients[port].remove(writer)

        await asyncio.start_server(client, "127.0.0.1", port)

    async def main() -> None:
        for p in ports:
            await serve(p)
        print("ready", flush=True)
        usable = len(counts) - PER_FRAME
        if clocks == "lockstep":   # every DAQ the same frame at the same instant
            offsets, slots = [0] * len(ports), 1
        else:                      # each DAQ its own place in the capture and its own millisecond of the frame
            offsets = [k * usable // len(ports) // PER_FRAME * PER_FRAME for k in range(len(ports))]
            slots = PER_FRAME
        t0, tick = time.monotonic(), 0
        while True:
            first = tick * PER_FRAME
            for slot in range(slots):
                await asyncio.sleep(max(0.0, t0 + (first + slot) / 1000.0 - time.monotonic()))
                frame, last = None, None
                for k, port in enumerate(ports):
                    if k % slots != slot or not clients[port]:
                        continue
                    a = (first + offsets[k]) % usable
                    if a != last:
                        frame, last = encode_sample_frames(first, counts[a : a + PER_FRAME], PER_FRAME), a
                    for w in clients[port]:
                        w.write(frame)
            tick += 1

    asyncio.run(main())


_BARE_RECV = r"""
import socket, sys, time
for _ in range(200):
    try:
        s = socket.create_connection(("127.0.0.1", int(sys.argv[1])))
        break
    except OSError:
        time.sleep(0.05)
while s.recv(65536):
    pass
"""


# ---------------------------------------------------------------- the bench


def run(n: int, seconds: float, clocks: str) -> int:
    from tests.e2e.helpers import Procs, tcp, write_config
    from tests.ops.unit_file import unit_environment  # the daemons as their unit runs them

    from millsense.daemon.state_dir import state_dir
    from millsense.daemon.local_socket import LocalControlError, local_command

    tmp = Path(tempfile.mkdtemp(prefix="millsense-per-core-"))
    capture = tmp / "step.cap"
    subprocess.run([sys.executable, "-m", "millsense.daemon", "sim", "--scenario", "step", "--loop",
                    "--capture", str(capture), "--duration-s", str(CAPTURE_S)], check=True,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    ports = [free_tcp_port() for _ in range(n + 1)]
    feeder = subprocess.Popen([sys.executable, __file__, "--feed", str(capture), clocks, *map(str, ports)],
                              stdout=subprocess.PIPE, text=True)
    try:
        assert feeder.stdout.readline().strip() == "ready", "the feeder did not start"
        with Procs(tmp) as procs:
            daemons = []
            for k in range(n):
                cfg = write_config(tmp / f"d{k}.toml", machine=f"m{k}",
                                   daq=f'transport = "tcp"\nhost = "127.0.0.1"\ntcp_port = {ports[k]}',
                                   zenoh_listen=[tcp(free_tcp_port())], interlock="enabled = true")
                daemons.append(procs.start(f"d{k}", ["run", "--config", str(cfg)], env_extra=unit_environment()))
                time.sleep(0.3)  # imports take a CPU-second each: a staggered start
            bare = subprocess.Popen([sys.executable, "-c", _BARE_RECV, str(ports[n])])
            sdirs = [state_dir(f"m{k}", {"XDG_STATE_HOME": str(tmp / "state")}) for k in range(n)]

            def status(k: int) -> dict:
                try:
                    return local_command(sdirs[k], "status")
                except (LocalControlError, OSError, ValueError):
                    return {}

            deadline = time.monotonic() + 60 + n
            while time.monotonic() < deadline and not all(status(k).get("revolutions", 0) > 5 for k in range(n)):
                time.sleep(0.5)
            time.sleep(3.0)  # warm-up
            before = [status(k) for k in range(n)]
            cpu0 = [proc_cpu_s(d.pid) for d in daemons]
            bare0, t0 = proc_cpu_s(bare.pid), time.monotonic()
            time.sleep(seconds)
            cpu1 = [proc_cpu_s(d.pid) for d in daemons]
            bare1, t1 = proc_cpu_s(bare.pid), time.monotonic()
            after = [status(k) for k in range(n)]
            bare.kill()
            bare.wait(5)
    finally:
        feeder.kill()
        feeder.wait(5)

    window = t1 - t0
    cpu_pct = np.array([100.0 * (b - a) / window for a, b in zip(cpu0, cpu1)])
    problems = []
    p99s = []
    for k, (s0, s1) in enumerate(zip(before, after)):
        if not s1:
            problems.append(f"m{k}: no status")
            continue
        got = s1.get("samples_received", 0) - s0.get("samples_received", 0)
        if s1.get("lost_samples"):
            problems.append(f"m{k}: {s1['lost_samples']} samples lost")
        if got < 0.98 * window * 1000:
            problems.append(f"m{k}: behind: {got} samples in {window:.1f} s")
        if (s1.get("daq") or {}).get("queue_len", 0) > 20:
            problems.append(f"m{k}: {s1['daq']['queue_len']} blocks waiting in its queue")
        p99 = (s1.get("latency_ms") or {}).get("p99")
        p99s.append(p99 if p99 is not None else float("nan"))
        if p99 is None or p99 > BUDGET_P99_MS:
            problems.append(f"m{k}: per-revolution latency p99 {p99} ms")
    mean = float(cpu_pct.mean())
    per_core = 100.0 / mean if mean > 0 else float("inf")
    print(f"daemons per core: {n} daemons at 1 kHz, 10-sample frames over TCP, {window:.0f} s window, "
          f"DAQ clocks {clocks}: {CLOCKS[clocks]}")
    print(f"  daemon CPU     mean {mean:.2f} %  max {cpu_pct.max():.2f} %  total {cpu_pct.sum():.1f} % of one core"
          f"   baseline: bare recv loop {100.0 * (bare1 - bare0) / window:.2f} %")
    print(f"  daemons/core   {per_core:.1f} (100 / mean CPU)   budget >= {BUDGET_PER_CORE}")
    print(f"  latency p99    worst {np.nanmax(p99s) if p99s else float('nan'):.2f} ms over the daemons   budget <= {BUDGET_P99_MS:g} ms")
    print(f"  kept up        {n - len({p.split(':')[0] for p in problems})}/{n}" + ("" if not problems else
          "   " + "; ".join(problems[:8])))
    return 0 if not problems and per_core >= BUDGET_PER_CORE else 1


def main() -> int:
    if len(sys.argv) > 3 and sys.argv[1] == "--feed":
        feed(sys.argv[2], sys.argv[3], [int(p) for p in sys.argv[4:]])
        return 0
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--daemons", type=int, default=30)
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--clocks", nargs="+", choices=sorted(CLOCKS), default=["independent", "lockstep"],
                    help="how the DAQs' streams line up (default: both, one run each)")
    args = ap.parse_args()
    return max(run(args.daemons, args.seconds, clocks) for clocks in args.clocks)


if __name__ == "__main__":
    sys.exit(main())
