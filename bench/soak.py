"""Soak: emulator + daemon + subscriber for a long time; does anything grow, stall or go missing?

Runs `millsense sim --scenario step --loop --tcp --realtime` (1 kHz, the plant
looping its 32.5-s step cut), `millsense run` against it with the interlock
armed (heartbeats every 50 ms, DAQ watchdog 500 ms: any stall of the daemon
would show as a watchdog trip) and warning levels that the scenario crosses
four times a loop, and a Zenoh subscriber in this process. Every `--interval-s`
it samples the daemon's and the emulator's RSS and CPU from /proc and the
daemon's `status` queryable. At the end (SIGTERM to both) it reads the
emulator's truth and status log and prints:

- a line per minute: RSS, CPU, estimates received;
- the daemon's RSS slope after warm-up, in KB/min, from a least-squares fit
  (with its standard error), and the verdict against `--max-slope-kb-min`;
- CPU of the daemon and the emulator (mean, p95) in % of one core;
- estimates received against revolutions simulated (truth revolutions that
  ended while the daemon was publishing), invalid estimates, lost samples,
  bad frames, sink drops, faults;
- alarm latency: alarm received here − the daemon's `t` of the last sample of
  the revolution that raised it (when that sample reached the daemon, late
  only by the smallest transport delay);
- feed-hold writes and watchdog trips seen by the emulator (both must be 0).

Run: .venv/bin/python bench/soak.py [--minutes 10] [--interval-s 5] [--warmup-min 2]
Concurrent load on the machine shows in the CPU figures; say so when quoting them.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from tests.conftest import free_tcp_port  # noqa: E402
from tests.e2e.helpers import Procs, Subscriber, read_jsonl, tcp, wait_for, write_config  # noqa: E402
from tests.e2e.truth import Timebase, truth_revs  # noqa: E402
from tests.procstat import proc_cpu_s, proc_kb  # noqa: E402

MACHINE = "soak"
# Crossed by the step scenario (torque plateaus ~2.0 / ~3.8 / ~5.9 N·m, force ~210 / ~400 / ~630 N):
# a torque warning from the second plateau on, a force warning on the third, each cleared on the way out.
ALARMS = "torque_warn_nm = 3.0\nforce_warn_n = 500.0\nbreakage_drop_pct = 0"
INTERLOCK = 'enabled = true\nheartbeat_ms = 50\nwatchdog_ms = 500\nreset = "off"'
WATCHDOG_MS = 500


def slope_kb_per_min(t_min: np.ndarray, kb: np.ndarray) -> tuple[float, float]:
    """Least-squares slope of RSS against time and its standard error."""
    if len(t_min) < 3:
        return float("nan"), float("nan")
    a = np.vstack([t_min, np.ones_like(t_min)]).T
    coef, res, *_ = np.linalg.lstsq(a, kb, rcond=None)
    resid = kb - a @ coef
    s2 = float(resid @ resid) / (len(kb) - 2)
    se = float(np.sqrt(s2 / np.sum((t_min - t_min.mean()) ** 2)))
    return float(coef[0]), se


def pct(values, q) -> float:
    return float(np.percentile(values, q)) if len(values) else float("nan")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--minutes", type=float, default=10.0, help="how long to run (default 10)")
    ap.add_argument("--interval-s", type=float, default=5.0, help="sampling interval of RSS/CPU/status (default 5)")
    ap.add_argument("--warmup-min", type=float, default=None,
                    help="excluded from the RSS fit (default: 2 min, or until the daemon's latency window is full if later)")
    ap.add_argument("--max-slope-kb-min", type=float, default=10.0,
                    help="RSS slope above which the verdict is 'grows' (default 10 KB/min = 14 MB/day)")
    ap.add_argument("--scenario", default="step")
    ap.add_argument("--keep", action="store_true", help="keep the run directory (logs, truth, status log)")
    args = ap.parse_args()
    warmup_min = args.warmup_min

    tmp = Path(tempfile.mkdtemp(prefix="millsense-soak-"))
    daq_port, z_port = free_tcp_port(), free_tcp_port()
    cfg = write_config(
        tmp / "soak.toml",
        machine=MACHINE,
        daq=f'transport = "tcp"\nhost = "127.0.0.1"\ntcp_port = {daq_port}',
        zenoh_listen=[tcp(z_port)],
        alarms=ALARMS,
        interlock=INTERLOCK,
    )
    truth_path, status_log = tmp / "truth.jsonl", tmp / "sim-status.jsonl"
    samples: list[dict] = []
    alarms_rx: list[tuple[float, float, dict]] = []  # (monotonic, wall, payload) at receipt
    with Procs(tmp) as procs:
        sim = procs.start("sim", ["sim", "--scenario", args.scenario, "--loop", "--tcp", f"127.0.0.1:{daq_port}",
                                  "--realtime", "--truth", str(truth_path), "--status-log", str(status_log),
                                  "--watchdog-ms", str(WATCHDOG_MS)])
        wait_for(lambda: "serving" in procs.text("sim") or sim.poll() is not None, 60.0, "emulator serving")
        daemon = procs.start("daemon", ["run", "--config", str(cfg)])
        sub = Subscriber([tcp(z_port)], MACHINE)
        alarm_sub = sub.session.declare_subscriber(
            f"millsense/{MACHINE}/alarm",
            lambda s: alarms_rx.append((time.monotonic(), time.time(), json.loads(s.payload.to_bytes()))),
        )
        try:
            wait_for(lambda: len(sub.get("estimate")) >= 5 or daemon.poll() is not None, 60.0, "first estimates")
            if daemon.poll() is not None:
                print(procs.text("daemon", "out")[-2000:], procs.text("daemon")[-2000:])
                return 1
            t0 = time.monotonic()
            end = t0 + args.minutes * 60.0
            print(f"soak: {args.minutes:g} min, scenario {args.scenario} looped at 1 kHz, interlock armed "
                  f"(heartbeat 50 ms, DAQ watchdog {WATCHDOG_MS} ms), run dir {tmp}", flush=True)
            print(f"{'min':>5} {'RSS MB':>7} {'CPU %':>6} {'sim CPU %':>9} {'est/s':>6} {'lost':>5} {'p99 ms':>7} state", flush=True)
            last = {"t": t0, "cpu": proc_cpu_s(daemon.pid), "sim_cpu": proc_cpu_s(sim.pid), "n": len(sub.get("estimate"))}
            next_print = t0 + 60.0
            while time.monotonic() < end:
                time.sleep(max(0.0, min(args.interval_s, end - time.monotonic())))
                if daemon.poll() is not None or sim.poll() is not None:
                    print(f"soak: a process exited early: daemon rc={daemon.poll()} sim rc={sim.poll()}")
                    break
                now = time.monotonic()
                cpu, sim_cpu = proc_cpu_s(daemon.pid), proc_cpu_s(sim.pid)
                n = len(sub.get("estimate"))
                try:
                    (st,) = sub.query(f"millsense/{MACHINE}/status", timeout=2.0)
                except ValueError:
                    st = {}
                dt = now - last["t"]
                rec = {
                    "t_min": (now - t0) / 60.0,
                    "rss_kb": proc_kb(daemon.pid, "VmRSS"),
                    "sim_rss_kb": proc_kb(sim.pid, "VmRSS"),
                    "cpu_pct": 100.0 * (cpu - last["cpu"]) / dt,
                    "sim_cpu_pct": 100.0 * (sim_cpu - last["sim_cpu"]) / dt,
                    "est_per_s": (n - last["n"]) / dt,
                    "status": st,
                }
                samples.append(rec)
                last = {"t": now, "cpu": cpu, "sim_cpu": sim_cpu, "n": n}
                if now >= next_print or now >= end - 0.01:
                    next_print += 60.0
                    recent = [s for s in samples if s["t_min"] > rec["t_min"] - 1.0]
                    lat = (st.get("latency_ms") or {}).get("p99")
                    print(f"{rec['t_min']:5.1f} {rec['rss_kb'] / 1024:7.1f} {np.mean([s['cpu_pct'] for s in recent]):6.2f} "
                          f"{np.mean([s['sim_cpu_pct'] for s in recent]):9.2f} {np.mean([s['est_per_s'] for s in recent]):6.2f} "
                          f"{st.get('lost_samples', '?')!s:>5} {lat!s:>7} {st.get('state', '?')}", flush=True)
            (final,) = sub.query(f"millsense/{MACHINE}/status", timeout=3.0)
            estimates = sub.get("estimate")
            hwm_kb = proc_kb(daemon.pid, "VmHWM")
            daemon.send_signal(signal.SIGTERM)
            rc_daemon = daemon.wait(10)
        finally:
            try:
                alarm_sub.undeclare()
            except Exception:  # noqa: BLE001
                pass
            sub.close()
        sim.send_signal(signal.SIGTERM)
        rc_sim = sim.wait(60)
    truth = read_jsonl(truth_path)
    sim_log = read_jsonl(status_log)
    daemon_log = procs.text("daemon", "out")
    report(args, warmup_min, samples, final, estimates, alarms_rx, truth, sim_log, daemon_log, hwm_kb, rc_daemon, rc_sim)
    if not args.keep:
        import shutil

        shutil.rmtree(tmp, ignore_errors=True)
    return 0


def window_full_min(samples: list[dict]) -> float | None:
    """When the daemon's latency window (its last N revolutions, status `latency_ms.n`) stopped growing."""
    ns = [((s["status"].get("latency_ms") or {}).get("n") or 0, s["t_min"]) for s in samples]
    for (n0, _), (n1, t1) in zip(ns, ns[1:]):
        if n1 and n1 == n0:
            return t1
    return None


def report(args, warmup_min, samples, final, estimates, alarms_rx, truth, sim_log, daemon_log, hwm_kb, rc_daemon, rc_sim) -> None:
    t = np.array([s["t_min"] for s in samples])
    rss = np.array([s["rss_kb"] for s in samples], dtype=float)
    full = window_full_min(samples)
    if warmup_min is None:
        # Warm means the bounded buffers are full: the latency window holds the last 4096
        # revolutions, ~7 min at 600 rpm; before that the daemon grows by design.
        warmup_min = max(min(2.0, 0.2 * args.minutes), full if full is not None else 0.0)
    early = (t >= min(2.0, 0.2 * args.minutes)) & (t < warmup_min)
    after = t >= warmup_min
    slope, se = slope_kb_per_min(t[after], rss[after])
    sim_slope, sim_se = slope_kb_per_min(t[after], np.array([s["sim_rss_kb"] for s in samples], dtype=float)[after])
    cpu = np.array([s["cpu_pct"] for s in samples])
    sim_cpu = np.array([s["sim_cpu_pct"] for s in samples])
    print()
    print(f"== soak summary: {t[-1] if len(t) else 0:.1f} min measured, {len(samples)} samples every {args.interval_s:g} s")
    grows = slope > args.max_slope_kb_min
    print(f"daemon RSS: {rss[0] / 1024 if len(rss) else 0:.1f} MB at start, {rss[after][0] / 1024 if after.any() else 0:.1f} MB "
          f"after {warmup_min:.1f} min warm-up, {rss[-1] / 1024 if len(rss) else 0:.1f} MB at end, peak (VmHWM) {hwm_kb / 1024:.1f} MB")
    if early.sum() >= 3:
        e_slope, e_se = slope_kb_per_min(t[early], rss[early])
        print(f"daemon RSS slope while its latency window filled ({t[early][0]:.1f}-{warmup_min:.1f} min): "
              f"{e_slope:+.1f} ± {e_se:.1f} KB/min (bounded by design: the window keeps the last 4096 revolutions)")
    print(f"daemon RSS slope after warm-up ({warmup_min:.1f} min): {slope:+.1f} ± {se:.1f} KB/min (least squares over "
          f"{int(after.sum())} points) -> {'GROWS' if grows else 'no growth'} (threshold {args.max_slope_kb_min:g} KB/min)")
    print(f"emulator RSS slope after warm-up: {sim_slope:+.1f} ± {sim_se:.1f} KB/min (it keeps the truth of every revolution in memory)")
    print(f"daemon CPU: mean {np.mean(cpu):.2f} %, p95 {pct(cpu, 95):.2f} %, max {np.max(cpu):.2f} % of one core; "
          f"emulator CPU: mean {np.mean(sim_cpu):.2f} %, p95 {pct(sim_cpu, 95):.2f} %")

    # estimates against the truth
    tb = Timebase.from_status_log(sim_log)
    revs = truth_revs(truth)
    valid = [e for e in estimates if e.get("valid", True)]
    if estimates and revs:
        t_first, t_last = float(estimates[0]["t"]), float(estimates[-1]["t"])
        period = 60.0 / 600.0
        simulated = sum(1 for r in revs if t_first - period / 2 <= tb.nominal_wall(int(r["index_end"])) <= t_last + period / 2)
        rev_numbers = [e["rev"] for e in estimates]
        gaps = sum(1 for a, b in zip(rev_numbers, rev_numbers[1:]) if b != a + 1)
        print(f"estimates: {len(estimates)} received, {simulated} revolutions simulated while the daemon published "
              f"({len(estimates) - simulated:+d}); {len(estimates) - len(valid)} invalid; {gaps} gaps in rev numbers; "
              f"daemon counted {final.get('revolutions')} revolutions")
    print(f"samples: {final.get('samples_received')} received, {final.get('lost_samples')} lost, {final.get('bad_frames')} bad frames; "
          f"processing latency {final.get('latency_ms')}")
    sink = final.get("sink") or {}
    print(f"sink: {sink.get('published')} published, {sink.get('alarms_published')} alarms, {sink.get('dropped')} dropped, "
          f"{sink.get('publish_errors')} errors; daemon state {final.get('state')}, faults {final.get('faults')}")

    # alarm latency: receipt here − the daemon's `t` of the revolution's last sample (SeqClock: the arrival of
    # that sample at the daemon, late only by the smallest transport delay, ~1 ms on loopback)
    lat_t = [(wall - float(a["t"])) * 1e3 for _, wall, a in alarms_rx if a.get("t") is not None]
    levels: dict[str, int] = {}
    for _, _, a in alarms_rx:
        levels[a["level"]] = levels.get(a["level"], 0) + 1
    print(f"alarms: {len(alarms_rx)} received {levels}")
    if lat_t:
        print(f"alarm latency, last sample of the revolution at the daemon -> subscriber: p50 {pct(lat_t, 50):.1f} ms, "
              f"p99 {pct(lat_t, 99):.1f} ms, max {max(lat_t):.1f} ms")
    holds = [e for e in sim_log if e.get("event") == "outputs"]
    trips = [e for e in holds if e.get("cause") == "watchdog"]
    heartbeats = sum(1 for e in sim_log if e.get("event") == "heartbeat")
    print(f"emulator: {heartbeats} heartbeats, {len(holds)} output changes, {len(trips)} watchdog trips")
    errors = sum(1 for line in daemon_log.splitlines() if '"level": "error"' in line)
    print(f"daemon log: {errors} error lines, {'a' if 'Traceback' in daemon_log else 'no'} traceback; "
          f"exit codes daemon {rc_daemon}, emulator {rc_sim}")


if __name__ == "__main__":
    sys.exit(main())
