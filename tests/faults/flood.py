"""The network flood of issue 11 (finding 4), shared by tests/faults/test_flood.py and bench/flood.py.

A flooder is its own process (so its work competes with the daemon for the
CPU as a real attacker's would, and does not slow this process's subscriber):
a zenoh-python peer connected to the daemon on loopback that sends queries
to the daemon's queryables at a set rate, with random payloads up to a set
size, and 1 MB puts under the machine's keys at a set rate, for a bounded
count and time. It prints one JSON line at the end: what it sent, what came back.

Also here: heartbeat gaps from the emulator's `--status-log`, and the RSS
growth of a process through a number of local peer sessions (finding 5).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import zenoh

from tests.procstat import proc_kb

FLOODER = r"""
import json, os, random, sys, time, zenoh
endpoint, machine, qps, max_payload, put_hz, duration_s, max_queries, seed = sys.argv[1:9]
qps, max_payload, put_hz, duration_s, max_queries = float(qps), int(max_payload), float(put_hz), float(duration_s), int(max_queries)
rng = random.Random(int(seed))
conf = zenoh.Config()
conf.insert_json5("mode", '"peer"')
conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
conf.insert_json5("scouting/multicast/enabled", "false")
s = zenoh.open(conf)
time.sleep(0.5)
keys = [f"millsense/{machine}/{k}" for k in ("cmd/reset", "cmd/test-trip", "status", "config", "cmd/reset")]
blob = os.urandom(max(max_payload, 1))
big = os.urandom(1_000_000)
got = {"replies": 0}
def on_reply(reply):
    got["replies"] += 1
sent = puts = 0
t0 = time.monotonic()
next_put = t0
tick = 0.01
print(json.dumps({"event": "flooding"}), flush=True)
while sent < max_queries and time.monotonic() - t0 < duration_s:
    now = time.monotonic()
    due = int((now - t0) * qps) - sent
    for _ in range(max(0, min(due, max_queries - sent))):
        n = rng.randint(0, max_payload)
        start = rng.randint(0, max(0, len(blob) - n))
        s.get(keys[sent % len(keys)], on_reply, payload=blob[start:start + n], timeout=2.0)
        sent += 1
    if put_hz > 0 and now >= next_put:
        s.put(f"millsense/{machine}/estimate", big)  # under the machine's keys, where subscribers listen
        puts += 1
        next_put += 1.0 / put_hz
    time.sleep(tick)
elapsed = time.monotonic() - t0
time.sleep(2.5)  # the last replies (or timeouts)
print(json.dumps({"event": "done", "queries": sent, "replies": got["replies"], "puts": puts,
                  "elapsed_s": elapsed}), flush=True)
s.close()
"""


class Flooder:
    """One flooder process; `result()` waits for its summary line."""

    def __init__(self, out: Path, endpoint: str, machine: str, *, qps: float, max_payload: int, put_hz: float,
                 duration_s: float, max_queries: int, seed: int) -> None:
        self.out = out
        self._fh = open(out, "w")  # noqa: SIM115 - closed in stop()
        self.proc = subprocess.Popen(
            [sys.executable, "-c", FLOODER, endpoint, machine, str(qps), str(max_payload), str(put_hz), str(duration_s),
             str(max_queries), str(seed)],
            stdout=self._fh, stderr=subprocess.DEVNULL)

    def lines(self) -> list[dict]:
        out = []
        for line in self.out.read_text().splitlines():
            try:
                out.append(json.loads(line))
            except ValueError:
                pass
        return out

    def started(self) -> bool:
        return any(e.get("event") == "flooding" for e in self.lines())

    def result(self) -> dict | None:
        return next((e for e in self.lines() if e.get("event") == "done"), None)

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait(5)
        self._fh.close()


def heartbeat_gaps_ms(status_log: list[dict], after: float = float("-inf"), before: float = float("inf")) -> list[float]:
    """Gaps between heartbeats the emulator heard (monotonic, ms), for heartbeats in [after, before]."""
    t = [e["mono"] for e in status_log if e.get("event") == "heartbeat" and after <= e["mono"] <= before]
    return [(b - a) * 1e3 for a, b in zip(t, t[1:])]


def holds(status_log: list[dict]) -> list[dict]:
    """Output changes that set feed hold (a watchdog trip or a commanded hold)."""
    return [e for e in status_log if e.get("event") == "outputs" and e.get("feed_hold")]


def rss_growth_through_local_peers(pid: int, endpoint: str, key: str, sessions: int = 20, queries: int = 20,
                                   payload_bytes: int = 65536) -> tuple[int, int]:
    """(RSS growth of `pid` in kB, replies received) while `sessions` local peers, one after another,
    each send `queries` queries of `payload_bytes` to `key`. The peers enable shared memory on their
    side, as an attacker's would."""
    blob = os.urandom(payload_bytes)

    def peer() -> zenoh.Session:
        conf = zenoh.Config()
        conf.insert_json5("mode", '"peer"')
        conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
        conf.insert_json5("scouting/multicast/enabled", "false")
        conf.insert_json5("transport/shared_memory/enabled", "true")
        return zenoh.open(conf)

    # one session first: the growth counts sessions, not the daemon's first large query
    with peer() as s:
        list(s.get(key, payload=blob, timeout=5.0))
    rss0 = proc_kb(pid)
    replies = 0
    for _ in range(sessions):
        with peer() as s:
            deadline = time.monotonic() + 5.0
            while not list(s.info.peers_zid()) and time.monotonic() < deadline:
                time.sleep(0.01)
            for _ in range(queries):
                replies += len(list(s.get(key, payload=blob, timeout=5.0)))
    time.sleep(0.5)
    return proc_kb(pid) - rss0, replies
