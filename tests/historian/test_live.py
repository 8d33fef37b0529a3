"""The historian live: a real daemon on the simulator publishing on a loopback Zenoh, a real `millsense historian`
subprocess, a real PostgreSQL killed mid-run (`pg_ctl stop -m immediate`) and started again.

While the server is down the historian spools and says so (its log); once it is back the spool is replayed in
order: every revolution, alarm and status change the daemon published while the historian listened is in the
database once, with the same values, and the per-second aggregates agree with the revolutions themselves. SIGTERM
flushes and exits 0. The test's own Zenoh subscriber, subscribed before the daemon starts, is what the daemon
published; the window compared starts at the first revolution both saw (the historian subscribes a moment later).

Its own PostgreSQL (not the worker's shared one): the test stops its server.
"""

from __future__ import annotations

import json
import math
import signal

import psycopg
import pytest

from tests.conftest import free_tcp_port
from tests.e2e.helpers import Procs, Subscriber, read_jsonl, tcp, wait_for, write_config
from tests.historian.pg import PgServer

pytestmark = pytest.mark.slow

SLOW_S = 60.0
MACHINE = "hist-live"
STATUS_FIELDS = ("state", "daq_link", "interlock", "alarm", "faults", "run_id")


def events(procs, name="historian") -> list[dict]:
    return read_jsonl(procs.tmp / f"{name}.err")


def has_event(procs, event: str, after: int = 0) -> list[dict]:
    return [e for e in events(procs)[after:] if e.get("event") == event]


def test_postgres_killed_mid_run_the_historian_spools_says_so_and_replays_in_order_once(tmp_path):
    server = PgServer()
    try:
        run(server, tmp_path)
    finally:
        server.remove()


def run(server, tmp_path):
    db = server.new_database()
    passfile = server.passfile(tmp_path)
    z_port = free_tcp_port()
    daemon_cfg = write_config(tmp_path / "d.toml", machine=MACHINE, daq='transport = "sim"\nscenario = "step"',
                              zenoh_listen=[tcp(z_port)], alarms="power_warn_w = 450.0\nrevolutions = 1")
    hist_cfg = tmp_path / "historian.toml"
    hist_cfg.write_text(f'[historian]\ndsn = "{server.dsn(db)}"\npassfile = "{passfile.name}"\nspool_dir = "spool"\n'
                        f'revolutions_for = ["{MACHINE}"]\n[zenoh]\nconnect = ["{tcp(z_port)}"]\n'
                        'multicast_scouting = false\n[log]\nformat = "json"\n')
    with Procs(tmp_path) as procs:
        daemon = procs.start("daemon", ["run", "--config", str(daemon_cfg)])
        sub = Subscriber([tcp(z_port)], MACHINE)
        try:
            historian = procs.start("historian", ["historian", "--config", str(hist_cfg)])
            wait_for(lambda: has_event(procs, "historian.subscribed"), SLOW_S, "the historian subscribed")
            first = wait_for(lambda: rows(server, db, "SELECT min(rev) FROM revolutions")[0][0], SLOW_S,
                             "revolutions written")
            wait_for(lambda: [a for a in sub.get("alarm") if a["level"] == "warning"], SLOW_S, "a warning alarm")

            mark = len(events(procs))
            server.stop("immediate")
            down = wait_for(lambda: has_event(procs, "historian.db_down", mark), SLOW_S, "db_down said")[0]
            assert down["level"] == "error" and down["error"]
            wait_for(lambda: has_event(procs, "historian.spooling", mark), SLOW_S, "spooling said")
            n = len(sub.get("estimate"))
            wait_for(lambda: len(sub.get("estimate")) >= n + 30, SLOW_S, "revolutions while PostgreSQL is down")
            status = wait_for(lambda: [e for e in has_event(procs, "historian.status", mark) if e["spooled_rows"]],
                              SLOW_S, "the status line saying what is spooled")[0]
            assert status["db"] == "down" and status["level"] == "warning", status
            assert list((tmp_path / "spool").glob("spool-*.jsonl"))

            server.start()
            wait_for(lambda: has_event(procs, "historian.spool_replayed", mark), SLOW_S, "the spool replayed")
            n = len(sub.get("estimate"))
            wait_for(lambda: len(sub.get("estimate")) >= n + 10, SLOW_S, "revolutions after the replay")
            daemon.send_signal(signal.SIGTERM)
            assert daemon.wait(30) == 0, procs.text("daemon")
            historian.send_signal(signal.SIGTERM)
            assert historian.wait(30) == 0, procs.text("historian")[-3000:]
            published = {k: sub.get(k) for k in ("estimate", "alarm", "status")}
        finally:
            sub.close()
    stopped = has_event(procs, "historian.stopped")[-1]
    assert stopped["db"] == "up" and stopped["spooled_rows"] == 0 and stopped["spool_dropped"] == 0, stopped
    assert not list((tmp_path / "spool").glob("spool-*.jsonl"))

    # from the first revolution both saw: the historian's first written, or the test's subscriber's first received
    # (declared beside the daemon, it can miss the daemon's first estimate; the historian then holds one more)
    first = max(first, min(e["rev"] for e in published["estimate"]))
    estimates = [e for e in published["estimate"] if e["rev"] >= first]
    t0 = estimates[0]["t"]
    # every revolution once, in the window, with its values
    got = {r[0]: r[1:] for r in rows(server, db, "SELECT rev, valid, torque_nm, force_n, p_in_w, "
                                                 "extract(epoch FROM time)::float8 FROM revolutions WHERE rev >= %s",
                                     (first,))}
    assert rows(server, db, "SELECT count(*), count(DISTINCT rev) FROM revolutions")[0][0] == \
        rows(server, db, "SELECT count(DISTINCT rev) FROM revolutions")[0][0]
    assert sorted(got) == [e["rev"] for e in estimates], "a revolution lost or one the daemon never published"
    for e in estimates:
        valid, torque, force, power, t = got[e["rev"]]
        assert (valid, torque, force, power) == (e["valid"], e.get("torque_nm"), e.get("force_n"), e.get("p_in_w"))
        assert math.isclose(t, e["t"], abs_tol=1e-5)
    assert len(estimates) > 60

    # the per-second aggregates: each whole second of the window against its revolutions
    seconds: dict[int, list[dict]] = {}
    for e in estimates:
        seconds.setdefault(math.floor(e["t"]), []).append(e)
    load = {int(r[0]): r[1:] for r in rows(server, db, "SELECT extract(epoch FROM time)::bigint, revolutions, valid, "
                                                       "invalid, torque_min_nm, torque_mean_nm, torque_max_nm "
                                                       "FROM load_1s")}
    whole = sorted(seconds)[1:]   # the first second of the window may hold revolutions before it
    assert len(whole) >= 5
    for s in whole:
        revs = seconds[s]
        valid = [e["torque_nm"] for e in revs if e["valid"] and e.get("torque_nm") is not None]
        want = (len(revs), sum(1 for e in revs if e["valid"]), sum(1 for e in revs if not e["valid"]))
        assert load[s][:3] == want, s
        if valid:
            assert load[s][3] == min(valid) and load[s][5] == max(valid)
            assert math.isclose(load[s][4], math.fsum(valid) / len(valid), rel_tol=1e-12)

    # every alarm of the window once, with its values
    alarms = [a for a in published["alarm"] if a["t"] >= t0]
    assert alarms, "no alarm in the window"
    got_alarms = rows(server, db, "SELECT alarm_seq, level, value, limit_value, run_id FROM alarms "
                                  "WHERE time >= to_timestamp(%s) ORDER BY alarm_seq", (t0,))
    assert got_alarms == [(a["alarm_seq"], a["level"], a["value"], a["limit"], a["run_id"]) for a in alarms]

    # every status change of the window (against the status before it, as the daemon published them)
    statuses = published["status"]
    changes = [s["t"] for prev, s in zip(statuses, statuses[1:])
               if s["t"] >= t0 and any(json.dumps(prev.get(f)) != json.dumps(s.get(f)) for f in STATUS_FIELDS)]
    stored = [r[0] for r in rows(server, db, "SELECT extract(epoch FROM time)::float8 FROM status_changes "
                                             "WHERE time >= to_timestamp(%s) ORDER BY time", (t0,))]
    def seen(t, among):
        return any(math.isclose(t, x, abs_tol=1e-5) for x in among)

    assert changes and all(seen(t, stored) for t in changes), (changes, stored)
    # besides the changes, only the first status the historian saw after its start (nothing before it to differ)
    extra = [t for t in stored if not seen(t, changes)]
    assert extra in ([], stored[:1]), (extra, stored)
    assert all(seen(t, [s["t"] for s in statuses]) for t in stored)


def rows(server, db, query, params=()):
    try:
        with psycopg.connect(server.dsn(db).replace("user=historian", "user=postgres"), connect_timeout=5) as conn:
            return conn.execute(query, params).fetchall()
    except psycopg.errors.UndefinedTable:
        return [(None,)]
