"""The plant's historian under a plant's load: N machines' real payloads through `millsense router` into one
`millsense historian` and one PostgreSQL, on this box (issue 43, "Performance"). Not a timed test.

The payloads are the daemon's own: `millsense sim` records a capture of the part program (program 1001, so the
CNC's context makes process summaries), `millsense replay` turns it into estimate, alarm and process JSON lines
(the replay's machine warns at 3 N·m, so alarms come with every cut). Publisher processes (`--publishers`, each a
slice of the machines, Zenoh clients of the router like a daemon) send them in the replay's order, every machine
at `--rev-hz` estimates a second (an alarm or a process summary goes out with the estimate it followed in the
replay), each re-stamped: `machine`, `t` = the publication's wall-clock time, `rev` (and a summary's `process`)
counting on. Congestion control BLOCK: a publisher that cannot keep its schedule says so (its achieved rate is
printed); none of its payloads is dropped on its side, so every one the database misses is the historian's.

Figures, each beside its budget or floor:
- **steady** (`--machines`, `--rev-hz`, `--seconds`): nothing lost (per machine, `load_1s`'s revolution count
  summed = estimates published; alarm and process rows = those published); publication → committed row p99 ≤ 2 s;
  the historian's RSS ≤ 150 MB and flat. The latency is the row's commit time minus the payload's publication
  time: PostgreSQL runs with `track_commit_timestamp = on` and `pg_xact_commit_timestamp(xmin)` is the commit
  time of the transaction that wrote the row (the same clock: one box). For `revolutions` rows (the machines in
  `revolutions_for`: the first `--revolution-machines`), alarms and processes, the publication time is the row's
  `time` (the payload's `t`); for a `load_1s` row it is the end of its second (`time` + 1 s: the second's last
  revolution was published then). RSS: /proc/<pid>/status VmRSS every second, each minute's median, and the
  least-squares slope over the run's second half (the first half is the warm-up): "flat" is a slope of at most
  `RSS_FLAT_MB_PER_H` (1 MB an hour), printed with its standard error.
- **saturation** (`--saturate`, rates `--rev-hz` × each factor, `--step-s` each, a fresh database with every
  machine in `revolutions_for`, so that every revolution is a row): rows committed a second while the publishers
  run, the p99 latency of each step, and whether the historian kept up (p99 ≤ 2 s and every row in the database
  within 30 s after the publishers stopped). Beside it the COPY floor of the same run: psycopg COPY of rows of the
  same tables and shape (bench/historian.py's `batches` and `write_copy`: no Zenoh, no staging), into a fresh
  database of the same server.
- **outage** (`--pg-outage-s`): a fresh stack, `pg_ctl stop -m fast` a third into `--outage-run-s`, started again
  `--pg-outage-s` later: every row afterwards once (counts as in steady, and no key twice).
- **profile** (`--profile`): no Zenoh, no router, no publishers: `--profile-s` seconds of the same payloads for
  `--machines` at `--rev-hz` fed through the historian's own callbacks, loop and writer (into a fresh database of
  the same server), and the CPU µs a payload each took (`time.process_time`: the work, not the box's load);
  `--cprofile` adds cProfile's top functions, `--profile-memory` a first round under tracemalloc (the Python
  objects the path holds as payloads go through). Issue 43's before/after figure.

Beside each run's figures, the CPU (in cores, while the publishers run) of the historian (and of each of its
threads: `main` is the loop that parses, makes rows and writes them, `python` Zenoh's callbacks keeping the
bytes), the router, this PostgreSQL and the publishers: the profile that says who is short of what; the
historian's CPU a payload (its cores over the payloads a second, Zenoh's threads in it: what it spends, which the
box's load moves far less than a rate); and the historian's RSS each minute.

`os.nice(19)` first: every process it starts (PostgreSQL, the router, the historian, the publishers) inherits it.

Run: python bench/historian_plant.py --machines 500 --rev-hz 10 --seconds 600 --saturate 1,2,3,4 --pg-outage-s 60
     python bench/historian_plant.py --profile --machines 500 --rev-hz 10 [--cprofile]
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import math
import os
import resource
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))   # tests/ from a checkout

CMD = [sys.executable, "-m", "millsense.daemon"]
P99_BUDGET_S = 2.0
RSS_BUDGET_MB = 150.0
KINDS = ("estimate", "alarm", "process")


# --------------------------------------------------------------------------- the payloads
def replay_payloads(folder: Path) -> list[dict]:
    """The daemon's payloads of 60 s of the part program, in publication order (`type` says the kind)."""
    from tests.historian.live import p1001_daemon

    cap, cfg = folder / "capture.bin", folder / "replay.toml"
    subprocess.run(CMD + ["sim", "--scenario", "part-program", "--duration-s", "60", "--capture", str(cap), "--fast"],
                   check=True, capture_output=True, timeout=300)
    p1001_daemon(cfg, "bench", zenoh={}, alarms={"torque_warn_nm": 3.0})
    out = subprocess.run(CMD + ["replay", "--config", str(cfg), str(cap)], check=True, capture_output=True,
                         text=True, timeout=300).stdout
    return [json.loads(line) for line in out.splitlines() if line.strip()]


# --------------------------------------------------------------------------- one publisher process
def publisher(args: argparse.Namespace) -> int:
    """Machines [first, last) at `rate_hz` estimates a second each for `seconds`, from `start_at` (wall clock)."""
    import zenoh

    payloads = json.loads(Path(args.payloads).read_text())
    names = [f"plant-{m:04d}" for m in range(args.first, args.last)]
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([args.router]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    session = zenoh.open(conf)
    # each machine starts at its own place in the replay: the plant is not one machine 500 times in step
    est_at = [i for i, p in enumerate(payloads) if p["type"] == "estimate"]
    pos = {n: est_at[(k * 37) % len(est_at)] for k, n in enumerate(names)}
    rev = dict.fromkeys(names, 0)
    proc = dict.fromkeys(names, 0)
    sent = {n: dict.fromkeys(KINDS, 0) for n in names}
    # each payload's JSON but for what is re-stamped, made once: a publication only writes `machine`, `t` and the
    # counter in front of it (the publishers must not be what limits the rate the historian is measured at)
    counter = {"estimate": "rev", "alarm": "rev", "process": "process"}
    bodies = []
    for p in payloads:
        rest = {k: v for k, v in p.items() if k not in ("type", "machine", "t", counter[p["type"]])}
        bodies.append((p["type"], counter[p["type"]], ("," + json.dumps(rest)[1:-1]) if rest else ""))
    block = zenoh.CongestionControl.BLOCK
    period = 1.0 / args.rate_hz
    slots = 10   # a tick's machines spread over 10 slots: no burst of every machine at once
    per_slot = math.ceil(len(names) / slots)
    while time.time() < args.start_at:
        time.sleep(min(0.05, args.start_at - time.time()))
    late_max = 0.0
    tick = 0
    end = args.start_at + args.seconds
    while True:
        tick_at = args.start_at + tick * period
        if tick_at >= end:
            break
        for s in range(slots):
            due = tick_at + s * period / slots
            wait = due - time.time()
            if wait > 0:
                time.sleep(wait)
            else:
                late_max = max(late_max, -wait)
            for n in names[s * per_slot:(s + 1) * per_slot]:
                i = pos[n]
                first = True
                sent_n = sent[n]
                while True:   # this machine's next estimate, and the alarms and summaries after it
                    kind, field, body = bodies[i]
                    if kind == "estimate" and not first:
                        break
                    first = False
                    if kind == "estimate":
                        rev[n] += 1
                        count = rev[n]
                    elif kind == "alarm":
                        count = rev[n]
                    else:
                        proc[n] += 1
                        count = proc[n]
                    text = f'{{"machine":"{n}","t":{time.time()!r},"{field}":{count}{body}}}'
                    session.put(f"millsense/{n}/{kind}", text, congestion_control=block)
                    sent_n[kind] += 1
                    i = (i + 1) % len(payloads)
                pos[n] = i
        tick += 1
    session.close()
    Path(args.report).write_text(json.dumps({"sent": sent, "late_max_s": late_max,
                                             "elapsed_s": time.time() - args.start_at}))
    return 0


# --------------------------------------------------------------------------- the stack
def pg_server():
    from tests.historian.pg import PgServer

    class CommitTimes(PgServer):
        """tests/historian/pg.py's server, with every transaction's commit time kept (the latency's end)."""

        def start(self) -> None:
            self._run("pg_ctl", "start", "-w", "-D", str(self.data), "-l", str(self.folder / "log"), "-o",
                      f"-p {self.port} -c listen_addresses=127.0.0.1 -c unix_socket_directories='' -c fsync=off "
                      "-c full_page_writes=off -c max_connections=40 -c track_commit_timestamp=on")

    return CommitTimes()


class Stack:
    """A router, one historian (its own database), the RSS sampler; the publishers per run."""

    def __init__(self, server, work: Path, name: str, machines: int, revolution_machines: int) -> None:
        from tests.conftest import free_tcp_port
        from tests.historian.live import historian_config

        self.server, self.work, self.machines = server, work / name, machines
        self.work.mkdir()
        self.db = server.new_database()
        passfile = server.passfile(self.work)
        port = free_tcp_port()
        self.router_at = f"tcp/127.0.0.1:{port}"
        self.logs = []
        self.router = self._start("router", ["router", "--log-format", "json", "--listen", self.router_at])
        _wait_port(port)
        names = tuple(f"plant-{m:04d}" for m in range(revolution_machines))
        cfg = historian_config(self.work / "historian.toml", server, self.db, passfile, connect=[self.router_at],
                               mode="client", revolutions_for=names)
        self.historian = self._start("historian", ["historian", "--config", str(cfg)])
        _wait_for(lambda: "historian.subscribed" in (self.work / "historian.err").read_text(errors="replace"), 60,
                  "the historian subscribed")
        self.rss: list[tuple[float, float]] = []
        self._stop = threading.Event()
        self._sampler = threading.Thread(target=self._sample, daemon=True)
        self._sampler.start()

    def _start(self, name: str, args: list[str]) -> subprocess.Popen:
        out = open(self.work / f"{name}.err", "wb")  # noqa: SIM115 - closed at the end
        self.logs.append(out)
        return subprocess.Popen(CMD + args, stdout=out, stderr=out, cwd=self.work)

    def _sample(self) -> None:
        path = Path(f"/proc/{self.historian.pid}/status")
        while not self._stop.wait(1.0):
            try:
                kb = next(int(line.split()[1]) for line in path.read_text().splitlines() if line.startswith("VmRSS"))
            except (OSError, StopIteration):
                return
            self.rss.append((time.time(), kb / 1024))

    def cpu(self) -> dict[str, float]:
        """CPU seconds so far: the historian, the router, this server's PostgreSQL (its processes alive now)."""
        out = {"historian": cpu_s(self.historian.pid), "router": cpu_s(self.router.pid),
               "postgres": sum(cpu_s(p) for p in postgres_pids(self.server))}
        out.update({f"  historian thread {k}": v for k, v in threads_cpu_s(self.historian.pid).items()})
        return out

    def publish(self, payload_file: Path, rate_hz: float, seconds: float, publishers: int,
                during=None) -> dict:
        """Every machine at `rate_hz` for `seconds`; `during(start_at)` runs meanwhile. The publishers' reports."""
        start_at = time.time() + 3.0
        procs, reports = [], []
        children0 = resource.getrusage(resource.RUSAGE_CHILDREN)
        bounds = [round(i * self.machines / publishers) for i in range(publishers + 1)]
        for i in range(publishers):
            report = self.work / f"publisher-{i}-{rate_hz:g}.json"
            reports.append(report)
            procs.append(subprocess.Popen([sys.executable, __file__, "--_publisher", "--payloads", str(payload_file),
                                           "--router", self.router_at, "--first", str(bounds[i]),
                                           "--last", str(bounds[i + 1]), "--rate-hz", str(rate_hz),
                                           "--seconds", str(seconds), "--start-at", str(start_at),
                                           "--report", str(report)]))
        time.sleep(max(0.0, start_at - time.time()))
        cpu0, at0 = self.cpu(), time.time()   # from the publishers' start (an outage's `during` is in it)
        if during is not None:
            during(start_at)
        for p in procs:
            if p.wait(seconds + 600) != 0:
                raise SystemExit(f"a publisher failed ({p.returncode})")
        cpu1, wall = self.cpu(), time.time() - at0
        children1 = resource.getrusage(resource.RUSAGE_CHILDREN)
        share = {k: (cpu1[k] - cpu0.get(k, 0.0)) / wall for k in cpu1}
        share["publishers"] = (children1.ru_utime + children1.ru_stime - children0.ru_utime - children0.ru_stime) / wall
        sent: dict[str, dict[str, int]] = {}
        late = elapsed = 0.0
        for r in reports:
            data = json.loads(r.read_text())
            sent.update(data["sent"])
            late, elapsed = max(late, data["late_max_s"]), max(elapsed, data["elapsed_s"])
        return {"sent": sent, "late_max_s": late, "elapsed_s": elapsed, "start_at": start_at,
                "end_at": start_at + seconds, "cpu": share}

    def stop(self) -> dict:
        self._stop.set()
        self.historian.send_signal(signal.SIGTERM)
        self.historian.wait(120)
        self.router.send_signal(signal.SIGTERM)
        self.router.wait(60)
        for f in self.logs:
            f.close()
        lines = [json.loads(x) for x in (self.work / "historian.err").read_text(errors="replace").splitlines()
                 if x.startswith("{")]
        return next((e for e in reversed(lines) if e.get("event") == "historian.stopped"), {})

    def query(self, statement: str, params=()) -> list[tuple]:
        import psycopg

        with psycopg.connect(self.server.dsn(self.db).replace("user=historian", "user=postgres")) as conn:
            return conn.execute(statement, params).fetchall()


def cpu_s(pid: int) -> float:
    """utime + stime of a process so far (/proc/<pid>/stat), seconds; 0 when it is gone."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def threads_cpu_s(pid: int) -> dict[str, float]:
    """CPU seconds so far of a process's threads, summed by thread name (/proc/<pid>/task/*/stat)."""
    out: dict[str, float] = {}
    for stat in Path(f"/proc/{pid}/task").glob("*/stat"):
        try:
            text = stat.read_text()
        except OSError:
            continue
        name = text[text.index("(") + 1:text.rindex(")")]
        fields = text.rsplit(")", 1)[1].split()
        name = "main (the loop: rows, writes)" if stat.parent.name == str(pid) else name.rstrip("0123456789-")
        out[name] = out.get(name, 0.0) + (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    return out


def postgres_pids(server) -> list[int]:
    """The postmaster and its children (this server's only: other PostgreSQL servers may run on the box)."""
    try:
        master = int((server.data / "postmaster.pid").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return []
    out = [master]
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            if int(stat.read_text().rsplit(")", 1)[1].split()[1]) == master:
                out.append(int(stat.parent.name))
        except (OSError, ValueError, IndexError):
            pass
    return out


def _wait_port(port: int, timeout_s: float = 60) -> None:
    import socket

    def up() -> bool:
        try:
            socket.create_connection(("127.0.0.1", port), 0.5).close()
            return True
        except OSError:
            return False
    _wait_for(up, timeout_s, f"the router on port {port}")


def _wait_for(predicate, timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            raise SystemExit(f"timed out waiting for {what}")
        time.sleep(0.1)


# --------------------------------------------------------------------------- the figures
def totals(sent: dict[str, dict[str, int]]) -> dict[str, int]:
    return {k: sum(s[k] for s in sent.values()) for k in KINDS}


def in_db(stack: Stack) -> dict[str, dict[str, int]]:
    """Per machine: the revolutions load_1s counts, the alarm and process rows."""
    out: dict[str, dict[str, int]] = {}
    for kind, statement in (("estimate", "SELECT machine, sum(revolutions) FROM load_1s GROUP BY 1"),
                            ("alarm", "SELECT machine, count(*) FROM alarms GROUP BY 1"),
                            ("process", "SELECT machine, count(*) FROM processes GROUP BY 1")):
        for machine, n in stack.query(statement):
            out.setdefault(machine, dict.fromkeys(KINDS, 0))[kind] = int(n)
    return out


def losses(sent: dict[str, dict[str, int]], got: dict[str, dict[str, int]]) -> dict[str, int]:
    """Per kind: published minus in the database (negative: more in it than published)."""
    return {k: sum(s[k] - got.get(m, {}).get(k, 0) for m, s in sent.items()) for k in KINDS}


def duplicates(stack: Stack) -> int:
    n = 0
    for statement in ("SELECT count(*) - count(DISTINCT (machine, time)) FROM load_1s",
                      "SELECT count(*) - count(DISTINCT (machine, time, level, quantity)) FROM alarms",
                      "SELECT count(*) - count(DISTINCT (machine, time, process)) FROM processes",
                      "SELECT count(*) - count(DISTINCT (machine, time, rev)) FROM revolutions"):
        n += int(stack.query(statement)[0][0])
    return n


def wait_all_in(stack: Stack, sent: dict, timeout_s: float) -> float | None:
    """Seconds until every published payload is in the database (None: not within `timeout_s`). A load_1s second
    is closed by the machine's next revolution or 2 s after its last: the last ones only by the latter."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout_s:
        if not any(losses(sent, in_db(stack)).values()):
            return time.monotonic() - t0
        time.sleep(1.0)
    return None


LATENCY = {
    "revolutions": "time",
    "alarms": "time",
    "processes": "time",
    "load_1s": "time + interval '1 second'",
}


TAIL_S = 3.0   # the run's last seconds: a machine's last second closes by the 2 s idle rule, not by its next revolution


def latencies(stack: Stack, t_from: float, t_to: float) -> dict[str, list[float]]:
    """Per table: commit time − publication time of the rows published in [t_from, t_to − TAIL_S)."""
    t_to -= TAIL_S
    out = {}
    for table, published in LATENCY.items():
        rows = stack.query(f"SELECT extract(epoch FROM pg_xact_commit_timestamp(xmin) - ({published})) FROM {table} "
                           "WHERE time >= to_timestamp(%s) AND time < to_timestamp(%s)", (t_from, t_to))
        out[table] = sorted(float(r[0]) for r in rows if r[0] is not None)
    return out


def _after(drained: float | None, limit_s: float) -> str:
    return f"{drained:.1f} s after the publishers stopped" if drained is not None else f"NOT within {limit_s:g} s"


def pct(values: list[float], q: float) -> float:
    return values[min(len(values) - 1, int(q * len(values)))] if values else float("nan")


def print_latency(lat: dict[str, list[float]]) -> float:
    worst = 0.0
    for table, v in lat.items():
        if not v:
            continue
        print(f"    {table:12s} {len(v):9,d} rows: p50 {pct(v, 0.5):6.3f} s, p99 {pct(v, 0.99):6.3f} s, "
              f"max {v[-1]:6.3f} s   (budget p99 ≤ {P99_BUDGET_S:g} s)")
        worst = max(worst, pct(v, 0.99))
    return worst


def committed_rows_per_s(stack: Stack, t_from: float, t_to: float) -> float:
    n = 0
    for table in LATENCY:
        n += int(stack.query(f"SELECT count(*) FROM {table} WHERE pg_xact_commit_timestamp(xmin) >= to_timestamp(%s) "
                             "AND pg_xact_commit_timestamp(xmin) < to_timestamp(%s)", (t_from, t_to))[0][0])
    return n / (t_to - t_from)


def cores(share: dict[str, float]) -> str:
    return ", ".join(f"{k.strip()} {v:.2f}" for k, v in share.items() if v >= 0.01)


def cpu_a_payload(run: dict) -> str:
    """The historian's CPU a payload published (Zenoh's threads included): its cores over the payloads a second.
    Less dependent on the box's load than any rate is: what the historian spends, not what it was given."""
    n = sum(sum(s.values()) for s in run["sent"].values())
    us = run["cpu"]["historian"] / (n / run["elapsed_s"]) * 1e6 if n else float("nan")
    return f"historian CPU {us:.1f} µs a payload (Zenoh's threads in it): {1e6 / us:,.0f} payloads/s on a whole core"


RSS_FLAT_MB_PER_H = 1.0   # "flat": the second half's least-squares slope at most this (below)


def rss_slope(rss: list[tuple[float, float]], t0: float, t1: float) -> tuple[float, float, int]:
    """The least-squares slope of the RSS over the second half of [t0, t1) in MB an hour, its standard error,
    and the samples in it. The first half is the warm-up (the partitions, the keys, the arenas filling); a leak
    is what still grows after it. Flat: slope ≤ RSS_FLAT_MB_PER_H, a rate at which the historian would take more
    than 40 hours to grow from 105 MB to its 150 MB budget, and a 5-minute half can still tell from noise
    (its standard error, printed beside it, is a few tenths of a MB an hour)."""
    half = [(t, mb) for t, mb in rss if (t0 + t1) / 2 <= t < t1]
    n = len(half)
    if n < 3:
        return float("nan"), float("nan"), n
    mt = sum(t for t, _ in half) / n
    mm = sum(mb for _, mb in half) / n
    sxx = sum((t - mt) ** 2 for t, _ in half)
    slope = sum((t - mt) * (mb - mm) for t, mb in half) / sxx
    resid = sum((mb - mm - slope * (t - mt)) ** 2 for t, mb in half)
    stderr = math.sqrt(resid / (n - 2) / sxx)
    return slope * 3600, stderr * 3600, n


def rss_figures(rss: list[tuple[float, float]], t0: float, t1: float) -> tuple[float, float, float]:
    """Max, the second minute's median, the last minute's median (MB) of the publishing window."""
    window = [(t, mb) for t, mb in rss if t0 <= t < t1]
    if not window:
        return float("nan"), float("nan"), float("nan")
    second = [mb for t, mb in window if t0 + 60 <= t < t0 + 120] or [mb for _, mb in window]
    last = [mb for t, mb in window if t >= t1 - 60]
    return max(mb for _, mb in window), statistics.median(second), statistics.median(last)


# --------------------------------------------------------------------------- the three runs
def steady(server, work: Path, payload_file: Path, args) -> None:
    print(f"\n== steady: {args.machines} machines × {args.rev_hz:g} rev/s = {args.machines * args.rev_hz:,.0f} rev/s, "
          f"{args.seconds} s; full revolutions for {args.revolution_machines} machines")
    stack = Stack(server, work, "steady", args.machines, args.revolution_machines)
    try:
        run = stack.publish(payload_file, args.rev_hz, args.seconds, args.publishers)
        drained = wait_all_in(stack, run["sent"], 60)
        sent, lost = totals(run["sent"]), losses(run["sent"], in_db(stack))
        lat = latencies(stack, run["start_at"], run["end_at"])
        rss_max, rss_2, rss_last = rss_figures(stack.rss, run["start_at"], run["end_at"])
    finally:
        stopped = stack.stop()
    print(f"  published {sent['estimate']:,} estimates, {sent['alarm']:,} alarms, {sent['process']:,} summaries in "
          f"{run['elapsed_s']:.0f} s (the publishers' worst lateness {run['late_max_s']:.2f} s)")
    print(f"  lost: {lost}   (budget: 0 each); all in {_after(drained, 60)}")
    print("  publication → committed row:")
    print_latency(lat)
    print(f"  historian RSS: max {rss_max:.1f} MB (budget ≤ {RSS_BUDGET_MB:g}); median second minute {rss_2:.1f} MB, "
          f"last minute {rss_last:.1f} MB (flat: {rss_last - rss_2:+.1f} MB)")
    slope, stderr, n = rss_slope(stack.rss, run["start_at"], run["end_at"])
    verdict = "flat" if slope <= RSS_FLAT_MB_PER_H else "NOT flat"
    print(f"  historian RSS over the run's second half ({n} samples): {slope:+.2f} ± {stderr:.2f} MB/h "
          f"(least squares ± its standard error); {verdict} (criterion: ≤ {RSS_FLAT_MB_PER_H:g} MB/h)")
    print(f"  CPU (cores, while publishing): {cores(run['cpu'])}; load {os.getloadavg()[0]:.2f}")
    print(f"  {cpu_a_payload(run)}")
    minutes = {}
    for t, mb in stack.rss:
        if run["start_at"] <= t < run["end_at"]:
            minutes.setdefault(int((t - run["start_at"]) // 60), []).append(mb)
    print("  historian RSS, each minute's median (MB): " +
          " ".join(f"{statistics.median(v):.1f}" for _, v in sorted(minutes.items())))
    print(f"  historian at stop: db {stopped.get('db')}, written {stopped.get('written')}, overflow "
          f"{stopped.get('overflow')}, spooled {stopped.get('spooled_rows')}, rejected {stopped.get('rejected')}")


def saturation(server, work: Path, payload_file: Path, args) -> None:
    factors = [float(f) for f in args.saturate.split(",")]
    print(f"\n== saturation: {args.machines} machines, every revolution a row, {args.step_s} s a step")
    stack = Stack(server, work, "saturation", args.machines, args.machines)
    best = 0.0
    so_far: dict[str, dict[str, int]] = {}   # every step's payloads: the database holds them all
    try:
        for f in factors:
            hz = args.rev_hz * f
            run = stack.publish(payload_file, hz, args.step_s, args.publishers)
            for m, s in run["sent"].items():
                for k, n in s.items():
                    so_far.setdefault(m, dict.fromkeys(KINDS, 0))[k] += n
            drained = wait_all_in(stack, so_far, 30)
            rate = committed_rows_per_s(stack, run["start_at"] + 5, run["end_at"])
            lat = latencies(stack, run["start_at"], run["end_at"])
            sent = totals(run["sent"])
            p99 = max((pct(v, 0.99) for v in lat.values() if v), default=float("nan"))
            kept_up = drained is not None and p99 <= P99_BUDGET_S
            print(f"  {hz:5.1f} rev/s a machine: {sent['estimate'] / run['elapsed_s']:8,.0f} estimates/s published "
                  f"(publishers' worst lateness {run['late_max_s']:.2f} s), {rate:8,.0f} rows/s committed, "
                  f"p99 {p99:.2f} s, {'kept up' if kept_up else 'BEHIND'}"
                  f"{'' if drained is not None else ' (not all in 30 s after)'}")
            print(f"      CPU (cores): {cores(run['cpu'])}; load {os.getloadavg()[0]:.2f}")
            print(f"      {cpu_a_payload(run)}")
            if kept_up:
                best = max(best, rate)
            else:
                late = drained if drained is not None else wait_all_in(stack, so_far, 300)
                if late is not None and drained is None:
                    late += 30.0
                lost = losses(so_far, in_db(stack))
                print("      behind: " + (f"nothing lost, all in {_after(late, 330)}" if late is not None
                                          else f"after 330 s still missing {lost}"))
                break
    finally:
        stack.stop()
    floor = copy_floor(server, work, args.machines, int(args.rev_hz))
    none = " (no step kept up)" if not best else ""
    print(f"  sustained {best:,.0f} rows/s through Zenoh and the historian{none}; the COPY floor of the same rows "
          f"(psycopg COPY, no Zenoh, no staging) {floor:,.0f} rows/s ({best / floor:.2f} × the floor); "
          f"budget: ≥ 3 × {args.machines * args.rev_hz:,.0f} rev/s")


def copy_floor(server, work: Path, machines: int, revs: int, seconds: int = 4) -> float:
    spec = importlib.util.spec_from_file_location("bench_historian_writer", ROOT / "bench" / "historian.py")
    writer_bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(writer_bench)
    folder = work / "floor"
    folder.mkdir(exist_ok=True)
    passfile = server.passfile(folder)
    data = writer_bench.batches(machines, revs, seconds, time.time() - seconds - 5)
    return writer_bench.measure(server, passfile, writer_bench.write_copy, data)


def outage(server, work: Path, payload_file: Path, args) -> None:
    print(f"\n== PostgreSQL stopped for {args.pg_outage_s} s: {args.machines} machines × {args.rev_hz:g} rev/s, "
          f"{args.outage_run_s} s")
    stack = Stack(server, work, "outage", args.machines, args.revolution_machines)
    times = {}

    def cut(start_at: float) -> None:
        time.sleep(max(0.0, start_at + args.outage_run_s / 3 - time.time()))
        times["stop"] = time.time()
        server.stop("fast")
        time.sleep(args.pg_outage_s)
        server.start()
        times["start"] = time.time()

    try:
        run = stack.publish(payload_file, args.rev_hz, args.outage_run_s, args.publishers, during=cut)
        drained = wait_all_in(stack, run["sent"], 300)
        sent, lost, dup = totals(run["sent"]), losses(run["sent"], in_db(stack)), duplicates(stack)
    finally:
        stopped = stack.stop()
    print(f"  down {times['start'] - times['stop']:.0f} s; published {sent}; lost {lost} (budget 0), rows twice "
          f"{dup} (budget 0); all in {_after(drained, 300)}")
    print(f"  historian at stop: spooled {stopped.get('spooled_rows')}, spool dropped {stopped.get('spool_dropped')}, "
          f"duplicates skipped {stopped.get('duplicates')}")


# --------------------------------------------------------------------------- the per-payload CPU (no Zenoh)
class _Payload:
    __slots__ = ("data",)

    def __init__(self, data: bytes) -> None:
        self.data = data

    def to_bytes(self) -> bytes:
        return self.data


class _Sample:
    """What the historian's callback reads of a Zenoh sample: `key_expr` and `payload.to_bytes()`."""
    __slots__ = ("key_expr", "payload")

    def __init__(self, key: str, data: bytes) -> None:
        self.key_expr, self.payload = key, _Payload(data)


def plant_seconds(payloads: list[dict], machines: int, rev_hz: float, seconds: int, t0: float) -> list[list]:
    """`seconds` one-second lists of (kind, key, bytes) as the publishers send them (same order, same re-stamping,
    the same `json.dumps`), `t` spread over each second."""
    est_at = [i for i, p in enumerate(payloads) if p["type"] == "estimate"]
    names = [f"plant-{m:04d}" for m in range(machines)]
    pos = {n: est_at[(k * 37) % len(est_at)] for k, n in enumerate(names)}
    rev, proc = dict.fromkeys(names, 0), dict.fromkeys(names, 0)
    ticks = max(1, round(rev_hz))
    out = []
    for s in range(seconds):
        second = []
        for tick in range(ticks):
            t = t0 + s + tick / ticks
            for n in names:
                i, first = pos[n], True
                while True:
                    p = payloads[i]
                    kind = p["type"]
                    if kind == "estimate" and not first:
                        break
                    first = False
                    msg = {k: v for k, v in p.items() if k != "type"}
                    msg["machine"], msg["t"] = n, t
                    if kind == "estimate":
                        rev[n] += 1
                        msg["rev"] = rev[n]
                    elif kind == "alarm":
                        msg["rev"] = rev[n]
                    else:
                        proc[n] += 1
                        msg["process"] = proc[n]
                    second.append((kind, f"millsense/{n}/{kind}", json.dumps(msg).encode()))
                    i = (i + 1) % len(payloads)
                pos[n] = i
        out.append(second)
    return out


class _NullLog:
    def _say(self, event: str, **fields) -> None:
        pass

    info = warning = error = _say


def profile(server, work: Path, payloads: list[dict], args) -> None:
    """CPU µs a payload (this process's `time.process_time`: it does not depend on the box's load, the way the
    wall clock does) of the historian's own path with no Zenoh: the callbacks (`Inbox.callback`), the loop's
    rows (`_drain_all` then `Rows`), the writes (`Writer.flush` into a fresh database of the throw-away server;
    PostgreSQL's own CPU is another process's, not in it). Once with every machine's revolutions kept (the
    saturation's case), once with those of `--revolution-machines` (the steady run's)."""
    import cProfile
    import pstats
    import tracemalloc

    from millsense.daemon.historian import schema, service
    from millsense.daemon.historian.spool import Spool
    from millsense.daemon.historian.writer import Writer

    seconds = plant_seconds(payloads, args.machines, args.rev_hz, args.profile_s, time.time() - args.profile_s - 10)
    n = sum(len(s) for s in seconds)
    n_est = sum(k == "estimate" for s in seconds for k, _, _ in s)
    print(f"\n== CPU a payload, no Zenoh: {args.machines} machines × {args.rev_hz:g} rev/s, {args.profile_s} s "
          f"({n:,} payloads, {n_est:,} estimates), best of {args.profile_rounds}")
    for label, kept in (("every revolution a row", args.machines), (f"revolutions of {args.revolution_machines} "
                                                                   "machines", args.revolution_machines)):
        best: dict[str, float] = {}
        for r in range(args.profile_rounds + bool(args.profile_memory)):   # the memory round first
            folder = work / f"profile-{kept}-{r}"
            folder.mkdir()
            db = server.new_database()
            writer = Writer(server.dsn(db), str(server.passfile(folder)), Spool(folder / "spool", 10**9),
                            {t: 30.0 for t in schema.TABLES}, _NullLog())
            rows = service.Rows(writer, {f"plant-{m:04d}" for m in range(kept)})
            inbox = service.Inbox()
            callbacks = {k: inbox.callback(k) for k in service.KINDS}
            samples = [[(callbacks[k], _Sample(key, data)) for k, key, data in s] for s in seconds]
            writer.flush()   # connected, partitions made: not in the figures
            took = dict.fromkeys(("receive", "rows", "write"), 0.0)
            memory = []   # --profile-memory: (Python's traced MiB, RSS MiB) after each second
            if args.profile_memory and r == 0:
                tracemalloc.start()
            prof = cProfile.Profile() if args.cprofile and r == int(args.profile_memory) else None
            for second in samples:
                c0 = time.process_time()
                if prof:
                    prof.enable()
                for cb, sample in second:
                    cb(sample)
                c1 = time.process_time()
                service._drain_all(inbox, rows)
                c2 = time.process_time()
                writer.flush()
                c3 = time.process_time()
                if prof:
                    prof.disable()
                took["receive"] += c1 - c0
                took["rows"] += c2 - c1
                took["write"] += c3 - c2
                if tracemalloc.is_tracing():
                    memory.append((tracemalloc.get_traced_memory()[0] / 2**20, _rss_mib()))
            c0 = time.process_time()
            rows.close_all()
            writer.flush()
            took["write"] += time.process_time() - c0
            (counted,), = _query(server, db, "SELECT coalesce(sum(revolutions), 0) FROM load_1s")
            missing = n_est - int(counted)   # every estimate aggregated and written, or the figure means nothing
            writer.close()
            if missing:
                raise SystemExit(f"profile: {missing} estimates not in load_1s")
            if memory:
                tracemalloc.stop()
                q = len(memory) // 4
                print(f"  {label}, memory (tracemalloc on: its CPU figures not taken): Python's traced "
                      f"{memory[q][0]:.2f} MiB after a quarter of the seconds, {memory[-1][0]:.2f} MiB at the end "
                      f"(max {max(m[0] for m in memory):.2f}); RSS {memory[q][1]:.1f} → {memory[-1][1]:.1f} MiB")
                continue
            total = sum(took.values())
            for k, v in dict(took, total=total).items():
                best[k] = min(best.get(k, math.inf), v)
            if prof:
                print(f"  cProfile, {label}, round 1 (the top 25 by own time):")
                stats = pstats.Stats(prof)
                stats.sort_stats("tottime").print_stats(25)
        per = {k: v / n * 1e6 for k, v in best.items()}
        print(f"  {label}: receive {per['receive']:.1f} µs, rows {per['rows']:.1f} µs, write {per['write']:.1f} µs; "
              f"total {per['total']:.1f} µs a payload = {1e6 / per['total']:,.0f} payloads/s on one whole core")


def _rss_mib() -> float:
    return next(int(line.split()[1]) for line in Path("/proc/self/status").read_text().splitlines()
                if line.startswith("VmRSS")) / 1024


def _query(server, db: str, statement: str) -> list[tuple]:
    import psycopg

    with psycopg.connect(server.dsn(db).replace("user=historian", "user=postgres")) as conn:
        return conn.execute(statement).fetchall()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    ap.add_argument("--machines", type=int, default=50)
    ap.add_argument("--rev-hz", type=float, default=10.0, help="estimates a second per machine")
    ap.add_argument("--seconds", type=int, default=60, help="the steady run (0: none)")
    ap.add_argument("--revolution-machines", type=int, default=10, help="machines in revolutions_for (steady)")
    ap.add_argument("--publishers", type=int, default=2, help="publisher processes")
    ap.add_argument("--saturate", default="", help="rate factors of the saturation steps, e.g. 1,2,3,4")
    ap.add_argument("--step-s", type=int, default=30)
    ap.add_argument("--pg-outage-s", type=float, default=0.0)
    ap.add_argument("--outage-run-s", type=int, default=180)
    ap.add_argument("--profile", action="store_true", help="the historian's CPU a payload, no Zenoh (and no other "
                    "run unless asked)")
    ap.add_argument("--profile-s", type=int, default=10, help="seconds of the plant's payloads the profile feeds")
    ap.add_argument("--profile-rounds", type=int, default=3)
    ap.add_argument("--cprofile", action="store_true", help="with --profile: cProfile's top functions")
    ap.add_argument("--profile-memory", action="store_true", help="with --profile: a first round more, under "
                    "tracemalloc: does the historian's own path keep Python objects as payloads go through?")
    ap.add_argument("--payloads-file", help="the replay's payloads from a file (JSON list) instead of a new replay")
    ap.add_argument("--_publisher", action="store_true", help=argparse.SUPPRESS)
    for name in ("payloads", "router", "report"):
        ap.add_argument(f"--{name}", help=argparse.SUPPRESS)
    for name in ("first", "last"):
        ap.add_argument(f"--{name}", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--rate-hz", type=float, help=argparse.SUPPRESS)
    ap.add_argument("--start-at", type=float, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args._publisher:
        return publisher(args)

    os.nice(19)   # the lead's suite runs beside: everything started from here inherits it
    print(f"uptime: {subprocess.run(['uptime'], capture_output=True, text=True).stdout.strip()}")
    print(f"{os.cpu_count()} CPUs; {' '.join(sys.argv)}")
    work = Path(tempfile.mkdtemp(prefix="millsense-plant-bench-"))
    server = pg_server()
    try:
        payloads = (json.loads(Path(args.payloads_file).read_text()) if args.payloads_file
                    else replay_payloads(work))
        payload_file = work / "payloads.json"
        payload_file.write_text(json.dumps(payloads))
        kinds = {k: sum(p["type"] == k for p in payloads) for k in KINDS}
        print(f"replay: {kinds} in 60 s of program 1001")
        if args.profile:
            profile(server, work, payloads, args)
        if args.seconds and not (args.profile and "--seconds" not in sys.argv):
            steady(server, work, payload_file, args)
        if args.saturate:
            saturation(server, work, payload_file, args)
        if args.pg_outage_s:
            outage(server, work, payload_file, args)
    finally:
        server.remove()
        shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
