"""Issue 43's acceptance, live and cheap: `millsense router`, three daemons of program 1001 on the in-process
emulator (its CNC's context makes processes) as Zenoh clients of the router, one `millsense historian`, a client of
the router too, and the test's PostgreSQL. Nothing meets but through the router.

Every alarm and process summary each daemon published (the test's own client of the router, subscribed before the
daemons start, is what they published) is in PostgreSQL once, with its values; each machine's load is there per
second, its revolution counts those the test saw; `millsense history --dsn … --machine all` exports the three
machines; and each machine's per-second aggregates in `load_1s` are those its daemon's own SQLite history gives
(`millsense history --config … --what revolutions` after the daemon stopped): the same seconds, the same counts,
min/mean/max within float rounding. The children's CPU time is printed (its budget, 15 CPU s, is
docs/historian.md's, not a test's)."""

from __future__ import annotations

import json
import math
import os
import resource
import signal
import subprocess

import pytest

from tests.conftest import free_tcp_port
from tests.e2e.helpers import CMD, Procs, Subscriber, read_jsonl, tcp, wait_for
from tests.historian.live import historian_config, p1001_daemon
from tests.historian.test_live import has_event, rows

pytestmark = pytest.mark.slow

SLOW_S = 90.0   # detects a hang; no budget
MACHINES = ("plant-a", "plant-b", "plant-c")


def _router_started(procs) -> bool:
    return any(e.get("event") == "router.started" for e in read_jsonl(procs.tmp / "router.out")) or \
        any(e.get("event") == "router.started" for e in read_jsonl(procs.tmp / "router.err"))


LOAD_COLUMNS = ("revolutions", "valid", "invalid", "torque_min_nm", "torque_mean_nm", "torque_max_nm", "force_min_n",
                "force_mean_n", "force_max_n", "power_min_w", "power_mean_w", "power_max_w")


def sqlite_load(config, state_dir) -> dict[int, tuple]:
    """The daemon's revolutions (its SQLite history, through `millsense history`), aggregated per second of `t` as
    the historian's `load_1s` is: counts, and min/mean/max of torque, force and input power over the valid ones."""
    p = subprocess.run(CMD + ["history", "--config", str(config), "--what", "revolutions", "--format", "jsonl"],
                       capture_output=True, text=True, timeout=60,
                       env={**os.environ, "STATE_DIRECTORY": str(state_dir)})
    assert p.returncode == 0, p.stderr
    seconds: dict[int, list[dict]] = {}
    for line in p.stdout.splitlines():
        r = json.loads(line)
        seconds.setdefault(math.floor(r["t"]), []).append(r)
    out = {}
    for s, revs in seconds.items():
        valid = [r for r in revs if r["valid"]]
        row: list = [len(revs), len(valid), len(revs) - len(valid)]
        for field in ("torque_nm", "force_n", "p_in_w"):
            v = [r[field] for r in valid if r[field] is not None]
            row += [min(v), math.fsum(v) / len(v), max(v)] if v else [None, None, None]
        out[s] = tuple(row)
    return out


def _agree(a, b) -> bool:
    return all(x == y if x is None or y is None or isinstance(x, int)
               else math.isclose(x, y, rel_tol=1e-12, abs_tol=1e-12) for x, y in zip(a, b, strict=True))


def assert_load_matches_sqlite(server, db, machine, config, state_dir) -> None:
    mine = sqlite_load(config, state_dir)
    cols = ", ".join(LOAD_COLUMNS)
    plant = {s: tuple(r) for s, *r in rows(server, db, f"SELECT extract(epoch FROM time)::bigint, {cols} FROM load_1s "
                                                         "WHERE machine = %s ORDER BY 1", (machine,))}
    assert len(mine) >= 3, (machine, mine)
    assert sorted(plant) == sorted(mine), (machine, sorted(set(plant) ^ set(mine)))
    wrong = {s: (plant[s], mine[s]) for s in mine if not _agree(plant[s], mine[s])}
    assert not wrong, (machine, wrong)


def test_three_daemons_through_the_router_into_one_database(pg_db, tmp_path):
    server, db, passfile = pg_db
    cpu0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    r_port = free_tcp_port()
    router_at = [tcp(r_port)]
    client = {"mode": "client", "connect": router_at}
    hist = historian_config(tmp_path / "historian.toml", server, db, passfile, connect=router_at, mode="client")
    with Procs(tmp_path) as procs:
        router = procs.start("router", ["router", "--log-format", "json", "--listen", tcp(r_port)])
        wait_for(lambda: _router_started(procs) or router.poll() is not None, SLOW_S, "router.started")
        assert router.poll() is None, procs.text("router")[-2000:]
        historian = procs.start("historian", ["historian", "--config", str(hist)])
        wait_for(lambda: has_event(procs, "historian.subscribed"), SLOW_S, "the historian subscribed")
        sub = Subscriber(router_at, "*", mode="client")
        try:
            daemons = {}
            for m in MACHINES:
                # a warning on every cut (the heaviest is 12.5 N·m): alarms from each machine's first operation
                cfg = p1001_daemon(tmp_path / f"{m}.toml", m, zenoh=client, alarms={"torque_warn_nm": 3.0})
                daemons[m] = procs.start(m, ["run", "--config", str(cfg)], env_extra={"STATE_DIRECTORY": str(tmp_path / m)})

            def each_has(kind, pred=lambda p: True):
                got = {p["machine"] for p in sub.get(kind) if pred(p)}
                return all(m in got for m in MACHINES)

            wait_for(lambda: each_has("process") and each_has("alarm", lambda a: a["level"] == "warning")
                     or any(d.poll() is not None for d in daemons.values()), SLOW_S,
                     "a process summary and a warning from every machine")
            for m, d in daemons.items():
                assert d.poll() is None, procs.text(m)[-3000:]
            for m, d in daemons.items():
                d.send_signal(signal.SIGTERM)
            for m, d in daemons.items():
                assert d.wait(SLOW_S) == 0, procs.text(m)[-3000:]
            historian.send_signal(signal.SIGTERM)
            assert historian.wait(SLOW_S) == 0, procs.text("historian")[-3000:]
            router.send_signal(signal.SIGTERM)
            assert router.wait(SLOW_S) == 0
            published = {k: sub.get(k) for k in ("estimate", "alarm", "process")}
        finally:
            sub.close()
    stopped = has_event(procs, "historian.stopped")[-1]
    assert stopped["db"] == "up" and stopped["spooled_rows"] == 0 and stopped["rejected"] == 0, stopped

    # every alarm and process summary each daemon published: once, with its values
    alarms = sorted((a["machine"], a["run_id"], a["alarm_seq"], a["level"], a["quantity"], a["value"], a["limit"])
                    for a in published["alarm"])
    assert rows(server, db, "SELECT machine, run_id, alarm_seq, level, quantity, value, limit_value FROM alarms "
                            "ORDER BY 1, 2, 3, 4, 5") == alarms
    procs_pub = sorted((p["machine"], p["process"], p["key"], p["verdict"], p["revolutions"], p["energy_j"])
                       for p in published["process"])
    assert rows(server, db, "SELECT machine, process, key, verdict, revolutions, energy_j FROM processes "
                            "ORDER BY 1, 2") == procs_pub
    assert {m for m, *_ in procs_pub} == set(MACHINES)

    # the load: each machine's seconds, their revolution counts those the test saw (the first and last second of a
    # machine may hold revolutions one of the two missed: the historian subscribed first, the test a moment later)
    for m in MACHINES:
        seen: dict[int, int] = {}
        for e in published["estimate"]:
            if e["machine"] == m:
                seen[math.floor(e["t"])] = seen.get(math.floor(e["t"]), 0) + 1
        load = dict(rows(server, db, "SELECT extract(epoch FROM time)::bigint, revolutions FROM load_1s "
                                     "WHERE machine = %s", (m,)))
        inner = sorted(seen)[1:-1]
        assert len(inner) >= 3, (m, seen)
        assert {s: load.get(s) for s in inner} == {s: seen[s] for s in inner}, m

    # the per-second aggregates agree with each daemon's own SQLite history
    for m in MACHINES:
        assert_load_matches_sqlite(server, db, m, tmp_path / f"{m}.toml", tmp_path / m)

    # the plant's export across machines
    base = CMD + ["history", "--dsn", server.dsn(db), "--passfile", str(passfile), "--machine", "all",
                  "--format", "jsonl"]
    for what in ("alarms", "processes", "load", "status"):
        p = subprocess.run(base + ["--what", what], capture_output=True, text=True, timeout=60)
        assert p.returncode == 0, p.stderr
        assert {json.loads(line)["machine"] for line in p.stdout.splitlines()} == set(MACHINES), what
    cpu1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    print(f"children's CPU: {cpu1.ru_utime + cpu1.ru_stime - cpu0.ru_utime - cpu0.ru_stime:.1f} s")
