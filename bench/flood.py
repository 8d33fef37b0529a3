"""Flood: does a query-and-put flood on the shop network touch what matters? (issue 11, findings 4 and 5)

Runs the emulator (`millsense sim --scenario step --loop --tcp --realtime`,
DAQ watchdog 500 ms, `--status-log`) and `millsense run` against it with the
interlock armed (heartbeat 100 ms, watchdog 500 ms, reset = "token"),
Zenoh on loopback only. A subscriber in this process times each estimate's
delivery (receipt − the estimate's `t`, the daemon's time of the revolution's
last sample). Phases:

1. baseline, `--phase-s` seconds, no flood;
2. flood, `--phase-s` seconds: flooder processes (tests/faults/flood.py) send
   `--qps` queries a second in all to every queryable, payloads uniform up to
   `--max-payload` bytes, plus 1 MB puts under the machine's keys at
   `--put-hz`; bounded in count and time;
3. 20 local peer sessions, one after another, each 20 queries of 64 KB, with
   shared memory on at their side.

Prints, against the budgets of issue 11: the largest heartbeat gap the
emulator saw during the flood (budget: half the watchdog), feed holds raised
(budget: none), estimate delivery p99 with and without the flood (budget:
< 50 ms under flood), daemon CPU in each phase, RSS growth through the 20
peer sessions (budget: < 10 MB), and the daemon's thread count. The machine's
other load shows in every figure: say so when quoting them.

Run: .venv/bin/python bench/flood.py [--phase-s 20] [--qps 900] [--max-payload 100000] [--put-hz 10]
"""

from __future__ import annotations

import argparse
import json
import os
import secrets
import signal
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from tests.conftest import free_tcp_port  # noqa: E402
from tests.e2e.helpers import Procs, Subscriber, read_jsonl, tcp, wait_for, write_config  # noqa: E402
from tests.faults.flood import Flooder, heartbeat_gaps_ms, holds, rss_growth_through_local_peers  # noqa: E402
from tests.procstat import proc_cpu_s, proc_kb  # noqa: E402

MACHINE = "flood"
WATCHDOG_MS = 500
FLOODERS = 2


class Delivery:
    """(receipt monotonic, delivery ms, rev) of every estimate; the flood's garbage is counted, not parsed."""

    def __init__(self) -> None:
        self.items: list[tuple[float, float, int]] = []
        self.garbage = 0
        self.lock = threading.Lock()

    def __call__(self, sample) -> None:
        now_wall, now_mono = time.time(), time.monotonic()
        raw = sample.payload.to_bytes()
        body = None
        if len(raw) < 65536:
            try:
                body = json.loads(raw)
            except ValueError:
                pass
        with self.lock:
            if isinstance(body, dict) and body.get("t") is not None:
                self.items.append((now_mono, (now_wall - float(body["t"])) * 1e3, int(body.get("rev") or -1)))
            else:
                self.garbage += 1

    def between(self, a: float, b: float) -> list[float]:
        with self.lock:
            return [ms for m, ms, _ in self.items if a <= m < b]


def p(values: list[float], q: float) -> float:
    return float(np.percentile(values, q)) if values else float("nan")


def verdict(ok: bool) -> str:
    return "PASS" if ok else "MISS"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--phase-s", type=float, default=20.0, help="length of the baseline and of the flood (default 20)")
    ap.add_argument("--qps", type=float, default=900.0, help="queries a second, all flooders together (default 900)")
    ap.add_argument("--max-payload", type=int, default=100_000, help="largest query payload, bytes (default 100000)")
    ap.add_argument("--put-hz", type=float, default=10.0, help="1 MB puts a second (default 10)")
    ap.add_argument("--keep", action="store_true", help="keep the run directory")
    args = ap.parse_args()

    tmp = Path(tempfile.mkdtemp(prefix="millsense-flood-"))
    daq_port, z_port = free_tcp_port(), free_tcp_port()
    token_file = tmp / "reset-token"
    token_file.write_text(secrets.token_urlsafe(32) + "\n")
    token_file.chmod(0o600)
    cfg = write_config(
        tmp / "flood.toml", machine=MACHINE,
        daq=f'transport = "tcp"\nhost = "127.0.0.1"\ntcp_port = {daq_port}',
        zenoh_listen=[tcp(z_port)],
        interlock=(f'enabled = true\nheartbeat_ms = 100\nwatchdog_ms = {WATCHDOG_MS}\nreset = "token"\n'
                   f'reset_token_file = "{token_file}"'),
    )
    status_log = tmp / "sim-status.jsonl"
    delivery = Delivery()
    flooders: list[Flooder] = []
    with Procs(tmp) as procs:
        procs.start("sim", ["sim", "--scenario", "step", "--loop", "--tcp", f"127.0.0.1:{daq_port}", "--realtime",
                            "--status-log", str(status_log), "--watchdog-ms", str(WATCHDOG_MS)])
        wait_for(lambda: "serving" in procs.text("sim"), 60.0, "emulator serving")
        daemon = procs.start("daemon", ["run", "--config", str(cfg)])
        sub = Subscriber([tcp(z_port)], MACHINE, read=False)
        est_sub = sub.session.declare_subscriber(f"millsense/{MACHINE}/estimate", delivery)
        try:
            wait_for(lambda: len(delivery.items) >= 5 or daemon.poll() is not None, 60.0, "first estimates")
            if daemon.poll() is not None:
                print(procs.text("daemon", "out")[-2000:])
                return 1
            print(f"flood bench: baseline {args.phase_s:g} s, then {args.qps:g} queries/s (payload 0-{args.max_payload} B) "
                  f"+ 1 MB puts at {args.put_hz:g}/s for {args.phase_s:g} s, from {FLOODERS} processes; loopback; "
                  f"run dir {tmp}", flush=True)
            t_base = time.monotonic()
            cpu0 = proc_cpu_s(daemon.pid)
            time.sleep(args.phase_s)
            for i in range(FLOODERS):
                flooders.append(Flooder(tmp / f"flooder{i}.jsonl", tcp(z_port), MACHINE, qps=args.qps / FLOODERS,
                                        max_payload=args.max_payload, put_hz=args.put_hz if i == 0 else 0.0,
                                        duration_s=args.phase_s, max_queries=int(args.qps / FLOODERS * args.phase_s) + 1,
                                        seed=i))
            wait_for(lambda: all(f.started() for f in flooders), 30.0, "flooders running")
            t_flood = time.monotonic()
            cpu1 = proc_cpu_s(daemon.pid)
            threads = []
            while time.monotonic() < t_flood + args.phase_s:
                time.sleep(1.0)
                threads.append(len(os.listdir(f"/proc/{daemon.pid}/task")))
            t_end = time.monotonic()
            cpu2 = proc_cpu_s(daemon.pid)
            wait_for(lambda: all(f.result() is not None for f in flooders), 60.0, "flooders done")
            sent = [f.result() for f in flooders]
            rss_before = proc_kb(daemon.pid)
            growth_kb, replies = rss_growth_through_local_peers(daemon.pid, tcp(z_port), f"millsense/{MACHINE}/status")
            (st,) = sub.query(f"millsense/{MACHINE}/status", timeout=3.0)
            t_stop = time.monotonic()
            daemon.send_signal(signal.SIGTERM)
            daemon.wait(15)
        finally:
            for f in flooders:
                f.stop()
            try:
                est_sub.undeclare()
            except Exception:  # noqa: BLE001
                pass
            sub.close()
    log = read_jsonl(status_log)
    gaps_flood = heartbeat_gaps_ms(log, t_flood, t_end)
    gaps_base = heartbeat_gaps_ms(log, t_base, t_flood)
    raised = [e for e in holds(log) if e["mono"] < t_stop]
    base = delivery.between(t_base, t_flood)
    flood = delivery.between(t_flood, t_end)
    revs = [r for _, _, r in delivery.items]
    lost_revs = sum(b - a - 1 for a, b in zip(revs, revs[1:]) if b > a + 1)
    q = sum(s["queries"] for s in sent)
    r = sum(s["replies"] for s in sent)
    puts = sum(s["puts"] for s in sent)
    half = WATCHDOG_MS / 2
    print()
    print(f"flood sent: {q} queries ({q / args.phase_s:.0f}/s), {r} answered, {puts} puts of 1 MB; "
          f"{delivery.garbage} garbage samples reached the subscriber")
    print(f"heartbeat gap max: {max(gaps_flood, default=float('nan')):.0f} ms under flood, "
          f"{max(gaps_base, default=float('nan')):.0f} ms baseline; budget {half:.0f} ms -> "
          f"{verdict(max(gaps_flood, default=0) <= half)}")
    print(f"feed holds raised while the daemon ran: {len(raised)} -> {verdict(not raised)}; daemon interlock "
          f"{st.get('interlock')}, lost samples {st.get('lost_samples')}, revolutions missing at the subscriber {lost_revs}")
    print(f"estimate delivery p50/p99/max: baseline {p(base, 50):.1f}/{p(base, 99):.1f}/{max(base, default=float('nan')):.1f} ms "
          f"(n={len(base)}); flood {p(flood, 50):.1f}/{p(flood, 99):.1f}/{max(flood, default=float('nan')):.1f} ms "
          f"(n={len(flood)}); budget p99 < 50 ms -> {verdict(p(flood, 99) < 50)}")
    print(f"daemon CPU: baseline {100 * (cpu1 - cpu0) / (t_flood - t_base):.1f} %, flood "
          f"{100 * (cpu2 - cpu1) / (t_end - t_flood):.1f} % of one core; threads under flood max {max(threads, default=0)}")
    print(f"RSS: {rss_before / 1024:.1f} MB before the peer sessions; growth through 20 local peer sessions x 20 queries "
          f"of 64 KB: {growth_kb / 1024:.1f} MB ({replies} answers); budget < 10 MB -> {verdict(growth_kb < 10 * 1024)}")
    events = [json.loads(line) for line in procs.text("daemon", "out").splitlines() if line.startswith("{")]
    refused_lines = sum(1 for e in events if e.get("event") == "zenoh.query_refused")
    print(f"daemon log: {len(events)} lines, {refused_lines} of them zenoh.query_refused")
    if not args.keep:
        import shutil

        shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
